//! Adam as one fused pass per parameter: [`FusedAdam`] is a `burn::optim::SimpleOptimizer`
//! (used through burn's `OptimizerAdaptor`, like `burn::optim::Adam`) whose step calls the
//! backend's [`NetOps::adam_step`]. Same arithmetic as burn's Adam (Kingma & Ba 2015,
//! Algorithm 1, epsilon scaled by `sqrt(1 - b2^t)` as in PyTorch), but burn composes it from
//! about 13 tensor ops that each read and write the whole parameter; at the paper's sizes
//! (11-33 M parameters) that was half of a CPU training step with the cheap encoder. Both
//! architectures train with it; its checkpointed state ([`FusedAdamState`]) also reads the
//! layout of burn's `AdamState`, which grid checkpoints held before.

use crate::ops::{AdamStep, NetOps};
use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{LearningRate, SimpleOptimizer};
use burn::record::{PrecisionSettings, Record};
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Tensor, TensorPrimitive};
use serde::{Deserialize, Serialize};

/// Adam's hyper-parameters (burn's defaults for the betas; epsilon 1e-8, PyTorch's default,
/// not burn's 1e-5) and the gradient's norm clipping, which the step does itself (in the
/// same pass on the CPU, in the same kernel on CUDA) instead of burn's optimizer adaptor.
#[derive(Clone, Copy, Debug)]
pub struct FusedAdam {
    /// First-moment decay (0.9).
    pub beta_1: f32,
    /// Second-moment decay (0.999).
    pub beta_2: f32,
    /// Denominator epsilon (1e-8).
    pub epsilon: f32,
    /// Each parameter's gradient clipped to this L2 norm first (burn's
    /// `GradientClipping::Norm`, per parameter tensor); None (the default): not clipped.
    pub max_norm: Option<f32>,
}

impl Default for FusedAdam {
    fn default() -> Self {
        Self {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
            max_norm: None,
        }
    }
}

impl FusedAdam {
    /// The optimizer for module `M` on autodiff backend `B`.
    pub fn init<B: AutodiffBackend, M: AutodiffModule<B>>(self) -> OptimizerAdaptor<Self, M, B>
    where
        B::InnerBackend: NetOps,
    {
        OptimizerAdaptor::from(self)
    }

    /// [`Self::init`] with each parameter's gradient clipped to L2 norm `max_norm` first
    /// (burn's `GradientClipping::Norm`, per parameter tensor, done by the step itself:
    /// [`AdamStep::max_norm`]); no clipping for `None`.
    pub fn init_clipped<B: AutodiffBackend, M: AutodiffModule<B>>(
        self,
        max_norm: Option<f32>,
    ) -> OptimizerAdaptor<Self, M, B>
    where
        B::InnerBackend: NetOps,
    {
        OptimizerAdaptor::from(Self { max_norm, ..self })
    }
}

/// Per-parameter state: step count and the two moments (shaped like the parameter). Saved in
/// checkpoints in its own layout (`time`, `moment_1`, `moment_2`); read from that layout or
/// from burn's `AdamState` (`momentum: {time, moment_1, moment_2, max_moment_2}`), so a grid
/// run checkpointed when it trained with burn's Adam resumes with this one.
#[derive(Clone)]
pub struct FusedAdamState<B: Backend, const D: usize> {
    /// Steps taken.
    pub time: usize,
    /// First moment.
    pub moment_1: Tensor<B, D>,
    /// Second moment.
    pub moment_2: Tensor<B, D>,
}

/// [`FusedAdamState`]'s own record layout.
#[derive(Record)]
pub struct FlatState<B: Backend, const D: usize> {
    time: usize,
    moment_1: Tensor<B, D>,
    moment_2: Tensor<B, D>,
}

/// burn's `AdaptiveMomentumState` layout (AMSGrad's `max_moment_2` is never set here).
#[derive(Record)]
pub struct BurnMomentum<B: Backend, const D: usize> {
    time: usize,
    moment_1: Tensor<B, D>,
    moment_2: Tensor<B, D>,
    max_moment_2: Option<Tensor<B, D>>,
}

/// burn's `AdamState` layout.
#[derive(Record)]
pub struct BurnState<B: Backend, const D: usize> {
    momentum: BurnMomentum<B, D>,
}

/// A saved [`FusedAdamState`]: written flat, read flat or as burn's `AdamState` (the recorder
/// is self-describing: named MessagePack).
#[derive(Serialize, Deserialize, Clone)]
#[serde(untagged, bound = "")]
pub enum FusedAdamStateItem<B: Backend, const D: usize, S: PrecisionSettings> {
    /// This optimizer's layout.
    Flat(<FlatState<B, D> as Record<B>>::Item<S>),
    /// burn's `AdamState`.
    Burn(<BurnState<B, D> as Record<B>>::Item<S>),
}

impl<B: Backend, const D: usize> Record<B> for FusedAdamState<B, D> {
    type Item<S: PrecisionSettings> = FusedAdamStateItem<B, D, S>;

    fn into_item<S: PrecisionSettings>(self) -> Self::Item<S> {
        let flat = FlatState {
            time: self.time,
            moment_1: self.moment_1,
            moment_2: self.moment_2,
        };
        FusedAdamStateItem::Flat(flat.into_item())
    }

    fn from_item<S: PrecisionSettings>(item: Self::Item<S>, device: &B::Device) -> Self {
        let (time, moment_1, moment_2) = match item {
            FusedAdamStateItem::Flat(item) => {
                let s = FlatState::<B, D>::from_item::<S>(item, device);
                (s.time, s.moment_1, s.moment_2)
            }
            FusedAdamStateItem::Burn(item) => {
                let s = BurnState::<B, D>::from_item::<S>(item, device).momentum;
                (s.time, s.moment_1, s.moment_2)
            }
        };
        Self {
            time,
            moment_1,
            moment_2,
        }
    }
}

impl<B: NetOps> SimpleOptimizer<B> for FusedAdam {
    type State<const D: usize> = FusedAdamState<B, D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<B, D>,
        grad: Tensor<B, D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<B, D>, Option<Self::State<D>>) {
        let time = state.as_ref().map_or(0, |s| s.time) + 1;
        let c = AdamStep {
            lr: lr as f32,
            beta_1: self.beta_1,
            beta_2: self.beta_2,
            epsilon: self.epsilon,
            time,
            max_norm: self.max_norm,
        };
        let prim = |t: Tensor<B, D>| t.into_primitive().tensor();
        let (m, v) = match state {
            Some(s) => (Some(prim(s.moment_1)), Some(prim(s.moment_2))),
            None => (None, None),
        };
        let (p, m, v) = B::adam_step(prim(tensor), prim(grad), m, v, &c);
        let wrap = |t| Tensor::<B, D>::from_primitive(TensorPrimitive::Float(t));
        let state = FusedAdamState {
            time,
            moment_1: wrap(m),
            moment_2: wrap(v),
        };
        (wrap(p), Some(state))
    }

    fn to_device<const D: usize>(mut state: Self::State<D>, device: &B::Device) -> Self::State<D> {
        state.moment_1 = state.moment_1.to_device(device);
        state.moment_2 = state.moment_2.to_device(device);
        state
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::NdArray;
    use burn::tensor::Distribution;

    /// burn Adam's checkpointed state (what grid runs saved before they used [`FusedAdam`])
    /// loads into [`FusedAdam`] and the next clipped step equals burn's; its own layout
    /// round-trips too.
    #[test]
    fn burns_adam_checkpoint_resumes_with_fused_adam() {
        use burn::backend::Autodiff;
        use burn::grad_clipping::GradientClippingConfig;
        use burn::nn::{Linear, LinearConfig};
        use burn::optim::{AdamConfig, GradientsParams, Optimizer};
        use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder, Recorder};
        type A = Autodiff<NdArray<f32>>;
        let device = Default::default();
        let x = Tensor::<A, 2>::random([5, 8], Distribution::Normal(0.0, 1.0), &device);
        let grads = |m: &Linear<A>| {
            let loss = m.forward(x.clone()).powf_scalar(2.0).sum();
            GradientsParams::from_grads(loss.backward(), m)
        };
        let weights = |m: &Linear<A>| m.weight.val().inner().into_data().to_vec::<f32>().unwrap();
        let mut model: Linear<A> = LinearConfig::new(8, 4).init(&device);
        let mut burn_adam = AdamConfig::new()
            .with_epsilon(1e-8)
            .with_grad_clipping(Some(GradientClippingConfig::Norm(0.5)))
            .init::<A, Linear<A>>();
        for _ in 0..3 {
            model = burn_adam.step(1e-2, model.clone(), grads(&model));
        }
        let dir = tempfile::tempdir().unwrap();
        let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
        let path = dir.path().join("optim");
        recorder
            .record(burn_adam.to_record(), path.clone())
            .unwrap();
        let fused = FusedAdam::default().init_clipped::<A, Linear<A>>(Some(0.5));
        let mut fused = fused.load_record(recorder.load(path.clone(), &device).unwrap());
        let mut fresh = FusedAdam::default().init_clipped::<A, Linear<A>>(Some(0.5));
        let want = weights(&burn_adam.step(1e-2, model.clone(), grads(&model)));
        let got = fused.step(1e-2, model.clone(), grads(&model));
        let unloaded = weights(&fresh.step(1e-2, model.clone(), grads(&model)));
        let diff = |a: &[f32], b: &[f32]| {
            (a.iter().zip(b))
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max)
        };
        assert!(
            diff(&want, &weights(&got)) <= 1e-6,
            "{}",
            diff(&want, &weights(&got))
        );
        // Without the loaded moments the step is another one: the check can fail.
        assert!(diff(&want, &unloaded) > 1e-4, "{}", diff(&want, &unloaded));
        // FusedAdam's own layout: saved, loaded, the same next step.
        recorder.record(fused.to_record(), path.clone()).unwrap();
        let again = FusedAdam::default().init_clipped::<A, Linear<A>>(Some(0.5));
        let mut again = again.load_record(recorder.load(path, &device).unwrap());
        let a = weights(&fused.step(1e-2, got.clone(), grads(&got)));
        let b = weights(&again.step(1e-2, got.clone(), grads(&got)));
        assert_eq!(a, b);
    }

    /// The fused CPU step equals burn's `Adam` (epsilon 1e-8) over three steps.
    #[test]
    fn fused_adam_equals_burns_adam() {
        type C = NdArray<f32>;
        let device = Default::default();
        let burn_adam = burn::optim::AdamConfig::new().with_epsilon(1e-8).build();
        let fused = FusedAdam::default();
        let mut p1 = Tensor::<C, 2>::random([37, 301], Distribution::Normal(0.0, 1.0), &device);
        let mut p2 = p1.clone();
        let (mut s1, mut s2) = (None, None);
        for k in 0..3 {
            let g = Tensor::<C, 2>::random(
                [37, 301],
                Distribution::Normal(0.0, 0.1 + k as f64),
                &device,
            );
            let (a, sa) = SimpleOptimizer::<C>::step(&burn_adam, 1e-2, p1, g.clone(), s1);
            let (b, sb) = SimpleOptimizer::<C>::step(&fused, 1e-2, p2, g, s2);
            let d: f32 = (a.clone() - b.clone()).abs().max().into_scalar();
            assert!(d <= 1e-6, "step {k}: parameters differ by {d}");
            (p1, s1, p2, s2) = (a, sa, b, sb);
        }
        // The composed default equals the fused CPU pass too, with and without clipping (a
        // gradient of norm ~190: clipped to 0.5 it is another step).
        let g = Tensor::<C, 2>::random([37, 301], Distribution::Normal(0.0, 1.0), &device);
        let s = s2.unwrap();
        let prim = |t: Tensor<C, 2>| t.into_primitive().tensor();
        let wrap = |t| Tensor::<C, 2>::from_primitive(TensorPrimitive::Float(t));
        let mut params = Vec::new();
        for max_norm in [None, Some(0.5)] {
            let c = AdamStep {
                lr: 1e-2,
                beta_1: 0.9,
                beta_2: 0.999,
                epsilon: 1e-8,
                time: s.time + 1,
                max_norm,
            };
            let (pa, ma, va) = crate::ops::adam_step::composed_adam::<C>(
                prim(p2.clone()),
                prim(g.clone()),
                Some(prim(s.moment_1.clone())),
                Some(prim(s.moment_2.clone())),
                &c,
            );
            let (pb, mb, vb) = C::adam_step(
                prim(p2.clone()),
                prim(g.clone()),
                Some(prim(s.moment_1.clone())),
                Some(prim(s.moment_2.clone())),
                &c,
            );
            params.push(wrap(pb.clone()));
            for (x, y) in [(pa, pb), (ma, mb), (va, vb)] {
                let d: f32 = (wrap(x) - wrap(y)).abs().max().into_scalar();
                assert!(d <= 1e-6, "{max_norm:?}: composed and fused differ by {d}");
            }
        }
        let d: f32 = (params[0].clone() - params[1].clone())
            .abs()
            .max()
            .into_scalar();
        assert!(d > 1e-4, "clipping changed the step by only {d}");
    }
}
