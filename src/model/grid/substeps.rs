//! Network substeps ([`super::GridConfig::substeps`], `train --substeps S`; issue 81's lever
//! "the call advances half a frame twice"): [`GridModel::step_bundle`] runs the whole network
//! ([`GridModel::network_call`]) S times at `dt / S`, each call reading the grid where the last
//! left the particles. A thrown column moves about 1.6 cells of a 32^2 network grid a frame;
//! at S = 2 each call sees half that move. Only the frame at the end is returned.
//!
//! The velocity window keeps its meaning, the particle's last T velocities one frame apart:
//! substep s (at `t + s / S`, frames) reads its newest velocity from substep s - 1 and the
//! older ones interpolated linearly between the window's frames. The head's output is a
//! velocity change over `dt / S`, so its normalisation (`dv_mean`, `dv_scale`, fitted on
//! whole frames) is divided by S: an untrained model, constant velocity plus the mean
//! acceleration, predicts the same frame at every S (the trapezoid integrates a constant
//! acceleration exactly). The memory steps once a substep.

use burn::tensor::Tensor;

use super::{GridModel, MemoryState, StepInput, StepOutput};
use crate::ops::NetOps;

impl<B: NetOps> GridModel<B> {
    /// One network call for a batch of scenes: the next K frames (K = [`GridModel::bundle`])
    /// and the new memory state. P2G, the U-Net and the memory run once; then for k = 1..K
    /// each particle gathers latent field k at its current position (G2P), the head predicts
    /// its velocity change and the frame is integrated, so frame k + 1 reads the grid where
    /// frame k left the particle. K = 1 is the single-frame step. A model with substeps
    /// (S > 1, K = 1) runs all of that S times at `dt / S` (the module doc) and returns the
    /// last.
    ///
    /// # Shapes
    /// See [`StepInput`]; returns K [`StepOutput`]s, oldest first; `state` holds `[B N, H]`
    /// rows.
    pub fn step_bundle(
        &self,
        input: StepInput<B>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let substeps = self.substeps;
        if substeps <= 1 {
            return self.network_call(input, state);
        }
        let window = input.vel.clone();
        let mut sub = StepInput {
            dt: input.dt.clone().div_scalar(substeps as f32),
            ..input
        };
        let (mut frames, mut state) = self.network_call(sub.clone(), state);
        for s in 1..substeps {
            let last = frames.swap_remove(0);
            sub.vel = substep_window(&window, last.vel, s as f32 / substeps as f32);
            sub.pos = last.pos;
            if last.deformation.is_some() {
                sub.deformation = last.deformation;
            }
            (frames, state) = self.network_call(sub.clone(), state);
        }
        (frames, state)
    }

    /// `(dv_mean, dv_scale)` of one network call: the fitted per-frame normalisation over the
    /// substeps (the module doc).
    pub(super) fn dv_affine(&self) -> ([f32; 2], [f32; 2]) {
        let s = self.substeps.max(1) as f32;
        (self.dv_mean.map(|v| v / s), self.dv_scale.map(|v| v / s))
    }
}

/// The velocity window `[B, N, 2 T]` (physical, oldest first, one frame apart) of substep s,
/// at `f = s / S` of the frame past `window`'s newest: entry j of T - 1 older ones
/// interpolated, `(1 - f) window[j] + f window[j + 1]`, and `newest` (`[B, N, 2]`, the last
/// substep's velocity) last.
fn substep_window<B: NetOps>(window: &Tensor<B, 3>, newest: Tensor<B, 3>, f: f32) -> Tensor<B, 3> {
    let t = window.dims()[2] / 2;
    let entry = |j: usize| window.clone().narrow(2, 2 * j, 2);
    let mut parts: Vec<Tensor<B, 3>> = (0..t - 1)
        .map(|j| entry(j).mul_scalar(1.0 - f) + entry(j + 1).mul_scalar(f))
        .collect();
    parts.push(newest);
    Tensor::cat(parts, 2)
}

#[cfg(test)]
mod tests {
    use burn::backend::NdArray;
    use burn::tensor::{Tensor, TensorData};

    use super::super::{GridConfig, MemoryKind, MemoryState, StepInput};
    use super::substep_window;

    type B = NdArray<f32>;

    fn input(b: usize, n: usize, t: usize) -> StepInput<B> {
        let device = Default::default();
        let value = |i: usize, scale: f32| ((i * 7919 % 1000) as f32 / 1000.0) * scale;
        let tensor = |c: usize, lo: f32, scale: f32| {
            let data: Vec<f32> = (0..b * n * c).map(|i| lo + value(i, scale)).collect();
            Tensor::<B, 3>::from_data(TensorData::new(data, [b, n, c]), &device)
        };
        StepInput {
            pos: tensor(2, 0.3, 0.4),
            vel: tensor(2 * t, -0.5, 1.0),
            material: super::super::one_hot(&vec![0u8; b * n], 4, b, n, &device),
            dt: Tensor::from_data(TensorData::new(vec![0.02f32; b], [b]), &device),
            reference: None,
            rest: None,
            deformation: None,
        }
    }

    fn config(substeps: usize) -> GridConfig {
        GridConfig::new(MemoryKind::MinGru)
            .with_grid(16)
            .with_unet_width(4)
            .with_levels(2)
            .with_latent(4)
            .with_hidden(4)
            .with_head_hidden(8)
            .with_head_zero_init(false)
            .with_substeps(substeps)
    }

    fn close(a: Tensor<B, 3>, b: Tensor<B, 3>) -> f32 {
        (a - b).abs().max().into_scalar()
    }

    /// Two substeps are two calls of the single-substep network at half the frame spacing,
    /// its velocity change halved, the second reading the interpolated window.
    #[test]
    fn two_substeps_are_two_half_frame_calls() {
        let device = Default::default();
        let two = config(2)
            .with_dv_mean([0.1, -0.3])
            .with_dv_scale([0.2, 0.4]);
        let model = two.init::<B>(&device);
        let x = input(2, 30, 2);
        // burn initialises parameters lazily: a first call makes them, so the clone below
        // shares them.
        let _ = model.step_bundle(x.clone(), MemoryState::Empty);
        let half_model = {
            let mut m = model.clone();
            m.substeps = 1;
            m.dv_mean = [0.05, -0.15];
            m.dv_scale = [0.1, 0.2];
            m
        };
        let state = MemoryState::Empty;
        let (got, _) = model.step_bundle(x.clone(), state.clone());
        let mut first_in = x.clone();
        first_in.dt = x.dt.clone().div_scalar(2.0);
        let (first, s1) = half_model.step_bundle(first_in.clone(), state);
        let mut second_in = first_in;
        second_in.pos = first[0].pos.clone();
        second_in.vel = substep_window(&x.vel, first[0].vel.clone(), 0.5);
        let (want, _) = half_model.step_bundle(second_in, s1);
        assert_eq!(got.len(), 1);
        let d = close(got[0].pos.clone(), want[0].pos.clone());
        assert!(d < 1e-6, "positions {d}");
        let d = close(got[0].vel.clone(), want[0].vel.clone());
        assert!(d < 1e-6, "velocities {d}");
        // And they are not one whole-frame call of the same weights.
        let mut whole = model.clone();
        whole.substeps = 1;
        let (one, _) = whole.step_bundle(x, MemoryState::Empty);
        assert!(close(got[0].vel.clone(), one[0].vel.clone()) > 1e-4);
    }

    /// An untrained model (the head's last layer at zero: constant velocity plus the mean
    /// acceleration) predicts the same frame with and without substeps.
    #[test]
    fn an_untrained_model_predicts_the_same_frame_at_any_substeps() {
        let device = Default::default();
        let x = input(1, 40, 2);
        let frame = |s: usize| {
            let model = config(s)
                .with_head_zero_init(true)
                .with_dv_mean([0.0, -0.4])
                .init::<B>(&device);
            let (out, _) = model.step_bundle(x.clone(), MemoryState::Empty);
            out.into_iter().next().expect("a frame")
        };
        let (one, three) = (frame(1), frame(3));
        assert!(close(one.pos, three.pos) < 1e-6);
        assert!(close(one.vel, three.vel) < 1e-6);
    }

    #[test]
    fn the_window_is_interpolated_one_frame_apart() {
        let device = Default::default();
        let data = vec![0.0f32, 10.0, 2.0, 20.0, 4.0, 40.0];
        let window = Tensor::<B, 3>::from_data(TensorData::new(data, [1, 1, 6]), &device);
        let newest =
            Tensor::<B, 3>::from_data(TensorData::new(vec![9.0f32, 90.0], [1, 1, 2]), &device);
        let got: Vec<f32> = substep_window(&window, newest, 0.25)
            .into_data()
            .to_vec()
            .unwrap();
        assert_eq!(got, vec![0.5, 12.5, 2.5, 25.0, 9.0, 90.0]);
    }
}
