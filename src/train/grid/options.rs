//! The settings of a grid training run ([`GridTrainOptions`]: batch, learning rate and its
//! decay, the rollout's calls P, push-forward M and chunks C, noise, mirroring, the
//! structure losses' weights, the discount, validation and limits), as `minflow train --arch
//! grid` sets them and `model.json`'s run folder keeps them (fields added later default to
//! what runs saved before them did).

/// Optimisation settings of a grid run.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct GridTrainOptions {
    /// Epochs at most.
    pub epochs: usize,
    /// Samples per optimizer step.
    pub batch_size: usize,
    /// Samples per epoch at most (0: every window of the training split).
    pub samples_per_epoch: usize,
    /// Peak learning rate.
    pub lr: f64,
    /// Learning rate at the end of the cosine decay.
    pub lr_final: f64,
    /// Gradient-norm clipping threshold (0: none).
    pub clip: f32,
    /// Steps per sample P.
    pub steps: usize,
    /// Of those, steps that read the true frame.
    pub teacher: usize,
    /// Calls made before the P, without gradient and without loss (push-forward, Brandstetter
    /// et al. 2022, "Message passing neural PDE solvers", section 2.3): the P calls start
    /// from the model's own rollout of `pushforward` calls, its memory and state carried, so
    /// the loss sees the inputs a long rollout produces. 0 in runs saved before it existed.
    #[serde(default)]
    pub pushforward: usize,
    /// Chunks of P calls per sample (truncated backpropagation through time, Williams &
    /// Peng 1990): the P calls with a loss are made `chunks` times in a row, an optimizer
    /// step after each, the rollout (frames, memory state, F) carried on from one chunk to
    /// the next with its gradient cut there, so training sees `chunks P K` frames of the
    /// model's own rollout at the memory cost of P calls. 0 (runs saved before it existed)
    /// and 1: one chunk.
    #[serde(default)]
    pub chunks: usize,
    /// Input-velocity noise, in units of `dv_scale`.
    pub noise: f32,
    /// Train on each sample or, with probability 1/2, its mirror image about the box's
    /// vertical midline (`x -> 1 - x`, `vx -> -vx`; see
    /// [`crate::model::grid::mirror_rows`]).
    #[serde(default)]
    pub mirror: bool,
    /// Weight of the strain loss (solids' rest-neighbour stretch; `rollout_loss/terms.rs`).
    #[serde(default)]
    pub strain_weight: f32,
    /// Weight of the volume loss (liquid particles' fitted J; `rollout_loss/terms.rs`).
    #[serde(default)]
    pub volume_weight: f32,
    /// Weight of the energy loss (each sample's RMS speed against the truth's;
    /// `rollout_loss/terms.rs`).
    #[serde(default)]
    pub energy_weight: f32,
    /// Weight of the liquid density-map loss (its particles per cell on a coarse grid, the
    /// prediction's against the truth's; `rollout_loss/terms.rs`). When on, the frames past
    /// the first chunk of a sample (`chunks` > 1) are scored by the structure, energy and
    /// density terms alone, not by each particle's place.
    #[serde(default)]
    pub density_weight: f32,
    /// Weight of the fast particles in the velocity and position MSE (`fast_weights` in
    /// `rollout_loss/terms.rs`): each particle's squared error weighs
    /// `1 + fast_weight |v| / (mean |v| + floor)`, `|v|` its true speed and the mean over its
    /// sample, the weights normalised to mean 1 over the batch (so a moving sample also
    /// weighs more than one at rest), so a splash's thrown particles count for more than the
    /// liquid at rest around them. 0 (the default, and runs saved before it existed): every
    /// particle alike.
    #[serde(default)]
    pub fast_weight: f32,
    /// Discount of the loss along a sample's rollout, in `(0, 1]`: frame `j` of the P K
    /// frames (from 0) weighs `discount^j`, the weights normalised to sum to 1, so a long
    /// rollout (large P) keeps its first frames' error in view while the later frames still
    /// teach what only many frames show. 1 (the default, and runs saved before it existed):
    /// every frame alike, the plain mean.
    #[serde(default = "no_discount")]
    pub discount: f32,
    /// Seed of the weights, data order and noise.
    pub seed: u64,
    /// Stop after this many epochs without a better validation rollout (0: never).
    pub patience: usize,
    /// Validation rollouts per scene.
    pub val_starts: usize,
    /// Validation rollout length.
    pub val_horizon: usize,
    /// Stop (after validating) once training has run this many minutes (0: no limit).
    pub max_minutes: f64,
    /// Keep the weights of the last this many epochs as run folders `epochs/NNNN`
    /// ([`crate::train::checkpoint::RunOutput::keep_epoch`]; 0: none).
    #[serde(default)]
    pub keep_epochs: usize,
    /// Project every frame the training rollouts feed on (after the teacher-forced calls)
    /// onto these material constraints ([`crate::model::constraints`]), with a
    /// straight-through gradient: the loss and the next call read the projected frame, the
    /// gradient passes the projection as the identity. The trained model keeps them in its
    /// `model.json`. None: no projection.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constraints: Option<crate::model::constraints::Constraints>,
}

/// [`GridTrainOptions::discount`] of runs saved before it existed: none.
fn no_discount() -> f32 {
    1.0
}

impl Default for GridTrainOptions {
    /// A plain run: one epoch of every window, batch 1, one call per sample from the true
    /// frame, Adam at 1e-3 without decay floor or clipping, no noise, mirror, structure loss,
    /// push-forward or limits (tests and `bench train` override what they measure).
    fn default() -> Self {
        Self {
            epochs: 1,
            batch_size: 1,
            samples_per_epoch: 0,
            lr: 1e-3,
            lr_final: 0.0,
            clip: 0.0,
            steps: 1,
            teacher: 1,
            pushforward: 0,
            chunks: 1,
            noise: 0.0,
            mirror: false,
            strain_weight: 0.0,
            volume_weight: 0.0,
            energy_weight: 0.0,
            density_weight: 0.0,
            fast_weight: 0.0,
            discount: 1.0,
            seed: 0,
            patience: 0,
            val_starts: 1,
            val_horizon: 1,
            max_minutes: 0.0,
            keep_epochs: 0,
            constraints: None,
        }
    }
}

impl GridTrainOptions {
    /// Network calls per training sample: the push-forward ones and the P with a loss in
    /// each chunk.
    pub fn calls(&self) -> usize {
        self.pushforward + self.steps * self.chunks()
    }

    /// Chunks of P calls per sample (at least 1; [`GridTrainOptions::chunks`]).
    pub fn chunks(&self) -> usize {
        self.chunks.max(1)
    }
}
