//! Adam as one fused pass per parameter: [`FusedAdam`] is a `burn::optim::SimpleOptimizer`
//! (used through burn's `OptimizerAdaptor`, like `burn::optim::Adam`) whose step calls the
//! backend's [`NetOps::adam_step`]. Same arithmetic as burn's Adam (Kingma & Ba 2015,
//! Algorithm 1, epsilon scaled by `sqrt(1 - b2^t)` as in PyTorch), but burn composes it from
//! about 13 tensor ops that each read and write the whole parameter; at the paper's sizes
//! (11-33 M parameters) that was half of a CPU training step with the cheap encoder.

use crate::ops::{AdamStep, NetOps};
use burn::module::AutodiffModule;
use burn::optim::adaptor::OptimizerAdaptor;
use burn::optim::{LearningRate, SimpleOptimizer};
use burn::record::Record;
use burn::tensor::backend::{AutodiffBackend, Backend};
use burn::tensor::{Tensor, TensorPrimitive};

/// Adam's hyper-parameters (burn's defaults for the betas; epsilon 1e-8, PyTorch's default,
/// not burn's 1e-5).
#[derive(Clone, Copy, Debug)]
pub struct FusedAdam {
    /// First-moment decay (0.9).
    pub beta_1: f32,
    /// Second-moment decay (0.999).
    pub beta_2: f32,
    /// Denominator epsilon (1e-8).
    pub epsilon: f32,
}

impl Default for FusedAdam {
    fn default() -> Self {
        Self {
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
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
}

/// Per-parameter state: step count and the two moments (shaped like the parameter). Saved in
/// checkpoints.
#[derive(Record, Clone)]
pub struct FusedAdamState<B: Backend, const D: usize> {
    /// Steps taken.
    pub time: usize,
    /// First moment.
    pub moment_1: Tensor<B, D>,
    /// Second moment.
    pub moment_2: Tensor<B, D>,
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
        // The composed default (what CUDA uses) equals the fused CPU pass too.
        let g = Tensor::<C, 2>::random([37, 301], Distribution::Normal(0.0, 1.0), &device);
        let s = s2.unwrap();
        let c = AdamStep {
            lr: 1e-2,
            beta_1: 0.9,
            beta_2: 0.999,
            epsilon: 1e-8,
            time: s.time + 1,
        };
        let prim = |t: Tensor<C, 2>| t.into_primitive().tensor();
        let wrap = |t| Tensor::<C, 2>::from_primitive(TensorPrimitive::Float(t));
        let (pa, ma, va) = crate::ops::adam_step::composed_adam::<C>(
            prim(p2.clone()),
            prim(g.clone()),
            Some(prim(s.moment_1.clone())),
            Some(prim(s.moment_2.clone())),
            &c,
        );
        let (pb, mb, vb) = C::adam_step(
            prim(p2),
            prim(g),
            Some(prim(s.moment_1)),
            Some(prim(s.moment_2)),
            &c,
        );
        for (x, y) in [(pa, pb), (ma, mb), (va, vb)] {
            let d: f32 = (wrap(x) - wrap(y)).abs().max().into_scalar();
            assert!(d <= 1e-6, "composed and fused differ by {d}");
        }
    }
}
