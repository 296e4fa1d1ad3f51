//! [`ParticleFrames`]: what [`NetOps::particle_frames`](super::NetOps::particle_frames) takes,
//! the per-particle part of a grid model's network call (`model::grid::step`, steps 3 to 5 of
//! `model::grid`'s module doc) as one operation: for each of the call's K frames, G2P of that
//! frame's latent field at the particle, the head on the particle's inputs and memory, and
//! the trapezoid integration.

use burn::tensor::backend::Backend;
use burn::tensor::ops::FloatTensor;

/// The inputs of one call's per-particle frames; `B` scenes of `N` particles, an `n x n`
/// grid, K frames, latent width L, velocity window T, M materials, memory width H.
pub struct ParticleFrames<B: Backend> {
    /// `[B, n^2, C]`: the U-Net's output; frame k's latent field is channels `k L..(k + 1) L`.
    pub fields: FloatTensor<B>,
    /// L, the latent field's channels.
    pub latent: usize,
    /// K, the frames predicted.
    pub bundle: usize,
    /// n, the network grid's side.
    pub n: usize,
    /// `[B N, H]`: the memory's output for the call (read by every frame's head), if any.
    pub memory: Option<FloatTensor<B>>,
    /// `[B, N, 2 T]`: the normalised velocity window, oldest first.
    pub vel: FloatTensor<B>,
    /// `[B, N, M]`: the material one-hot.
    pub material: FloatTensor<B>,
    /// `[B, N, 2]`: the positions of the call's input frame, domain units.
    pub pos: FloatTensor<B>,
    /// `[B]`: the frame spacing, time units.
    pub dt: FloatTensor<B>,
    /// The head's three dense layers, `(weight [in, out], bias [out])`: `[L + 2T + M + 2 +
    /// H, A]`, `[A, A']`, `[A', 2]`.
    pub layers: [(FloatTensor<B>, FloatTensor<B>); 3],
    /// The velocity normalisation, the velocity change's scale and mean, per axis.
    pub vel_scale: [f32; 2],
    /// See `vel_scale`.
    pub dv_scale: [f32; 2],
    /// See `vel_scale`.
    pub dv_mean: [f32; 2],
    /// The box `(lo, hi)` the integrated positions are clamped into, domain units, both
    /// axes ([`GridModel::integration_box`](crate::model::grid::GridModel::integration_box):
    /// MPM's box on the grid of `--box-grid`, not necessarily the network's).
    pub bounds: (f32, f32),
}
