//! `--arch grid`: a local, grid-based surrogate with Lagrangian memory (docs/design.md,
//! "Models"; docs/grid.md). One step, for every particle i of every scene in a batch:
//!
//! 1. P2G ([`transfer`]): the particle's mass (1), its last T velocities and its material
//!    one-hot are splatted onto an `n x n` grid with MPM's quadratic B-spline weights;
//!    channels `m / 4`, `sum w v / m` per frame (normalised), `sum w onehot / m`, plus two
//!    wall masks (nodes with index < 3 or > n - 3 on each axis, where `sim` enforces its
//!    walls). NeuralMPM (Rochman-Sharabi et al. 2024, arXiv 2408.15753) builds its grid the
//!    same way. With [`GridConfig::reference`], two more channels after the walls: the
//!    displacement `(x - X) n` from each particle's reference position X (its position in the
//!    first frame of its stream; MPM's reference configuration), mass-weighted.
//! 2. A [`unet::UNet`] on the grid; with temporal bundling ([`GridConfig::bundle`] = K) it
//!    returns K latent fields, one per predicted frame.
//! 3. G2P: the U-Net's output gathered back at the particle, `g_i` (field k at the
//!    particle's position after k - 1 predicted frames).
//! 4. Memory ([`memory`]): `u_i = [g_i, own_i]` (own = normalised velocities, material
//!    one-hot, position) drives a per-particle minGRU | minLSTM | GRU | LSTM, or nothing.
//!    With [`GridConfig::rest_shape`] each solid particle also measures its deformation from
//!    its rest neighbours ([`rest`]: Green strain, `J - 1`, shape matching's restoring offset,
//!    6 values): splatted as 6 more P2G channels (after the reference ones) and fed to the head.
//!    With [`Deformation::Advect`] the features' F is instead carried per particle and
//!    advected with the predicted velocities' APIC gradient after every frame
//!    ([`rest::advect`]; started from the fit where a rollout starts).
//! 5. Head: an MLP on `[u_i, memory output]` predicts the normalised velocity change;
//!    `dv = dv_mean + dv_scale * out` (physical), `v' = v + dv`, and the trapezoid
//!    `x' = x + dt (v + v') / 2` (its floor against MPM frames is 1.5e-6 / 1.3e-6 MSE, the
//!    explicit `x + v' dt` 8e-6 / 2e-5: docs/design.md, "Models"), clamped into the box MPM
//!    keeps its particles in. With [`GridConfig::update`] = [`Update::Grid`] the velocity
//!    change is instead the G2P of a grid velocity-change field the U-Net predicts (two more
//!    output channels per frame): neighbours of one body read one smooth field and move as a
//!    body, as MPM's G2P moves them (PIC; NeuralMPM, Rochman-Sharabi et al. 2024, section 3,
//!    predicts grid velocities the same way); [`Update::GridHead`] adds the head's output to
//!    it as a per-particle correction.
//!
//! With [`GridConfig::interaction`] = R rounds, R rounds of message passing between each
//! particle and its nearest neighbours within a radius run between steps 3 and 4
//! ([`interact`], GNS's processor), their output added to `u_i`.
//!
//! With [`GridConfig::substeps`] = S the call runs steps 1 to 5 S times at `dt / S`, each on
//! the positions and velocities the last left (`substeps.rs`): the grid is built again
//! halfway through a fast particle's move, and only the frame at the end is predicted.
//!
//! Any N, any particle order: every per-particle operation is row-wise and the grid sums are
//! order-free. The normalisation constants are fitted on the training split and saved in
//! [`GridConfig`]. Used by [`crate::model::store::Surrogate`] and [`crate::train::grid`].
//!
//! Files: this one holds the network, its input and output and their helpers; `step.rs` one
//! network call ([`GridModel::step_bundle`]) as tensors, `host_pass.rs` its per-particle part
//! as host passes on the CPU; `config.rs` the configuration, `grow.rs` growing a trained
//! model into a larger one; `substeps.rs` the network substeps; `interact.rs` the message
//! passing.

mod config;
mod grow;
mod host_pass;
pub mod interact;
pub mod memory;
pub mod rest;
mod step;
mod substeps;
pub mod transfer;
pub mod unet;

pub use config::{Deformation, GridConfig, GridConfigError, Update};
/// The ranges of [`GridConfig`]'s settings that have flags, shared with their clap parsers.
pub use config::{
    BOX_GRID, BUNDLE, INTERACTION_NEIGHBOURS, INTERACTION_RADIUS_MAX, INTERACTION_ROUNDS, SUBSTEPS,
};
pub use memory::{Memory, MemoryKind, MemoryState};
pub use rest::{NeighbourTensors, Neighbourhood, REST_FEATURES};
pub use unet::{ConvKernel, UNet, UNetConfig};

use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

use crate::ops::NetOps;

/// The network (see the module doc).
#[derive(Module, Debug)]
pub struct GridModel<B: Backend> {
    unet: UNet<B>,
    memory: Memory<B>,
    /// Message passing between neighbouring particles ([`GridConfig::interaction`]).
    interaction: Option<interact::Interaction<B>>,
    head_a: Linear<B>,
    head_b: Linear<B>,
    head_out: Linear<B>,
    /// The rest-shape features' own first head layer ([`GridConfig::rest_shape`]).
    rest_in: Option<Linear<B>>,
    n: usize,
    window: usize,
    bundle: usize,
    /// Network substeps per frame ([`GridConfig::substeps`]; `substeps.rs`).
    #[module(skip)]
    substeps: usize,
    /// The grid whose MPM box the integration clamps into ([`GridConfig::box_grid`]; 0: the
    /// network's `n`, whichever grid it is on).
    #[module(skip)]
    box_grid: usize,
    reference: bool,
    #[module(skip)]
    update: Update,
    #[module(skip)]
    deformation: Deformation,
    /// Whether CPU inference takes the per-particle host passes ([`host_pass`]; true unless a
    /// test asks for the tensor path with [`GridModel::with_host_pass`]).
    #[module(skip)]
    host_pass: bool,
    /// The particle-grid transfers' form when a test or bench fixes it ([`transfer::stencil`]'s
    /// `dense`; [`GridModel::with_dense_transfers`]); the backend's choice,
    /// [`NetOps::dense_stencil`], otherwise.
    #[module(skip)]
    dense_transfers: Option<bool>,
    vel_scale: [f32; 2],
    dv_mean: [f32; 2],
    dv_scale: [f32; 2],
}

/// One scene batch's input to a step, physical units.
#[derive(Clone, Debug)]
pub struct StepInput<B: Backend> {
    /// `[B, N, 2]` positions, domain units.
    pub pos: Tensor<B, 3>,
    /// `[B, N, 2 T]` velocities of the last T frames, oldest first, domain units per time unit.
    pub vel: Tensor<B, 3>,
    /// `[B, N, M]` material one-hot ([`one_hot`], M = [`GridConfig::materials`]).
    pub material: Tensor<B, 3>,
    /// `[B]` frame spacing, time units.
    pub dt: Tensor<B, 1>,
    /// `[B, N, 2]` reference positions X (each particle's position in the first frame of
    /// its stream), domain units; read only by a model with [`GridConfig::reference`], which
    /// takes `pos` (no displacement) when it is `None`.
    pub reference: Option<Tensor<B, 3>>,
    /// The rest neighbourhoods of the `B N` particles (built from the reference positions,
    /// [`Neighbourhood::build`]); read only by a model with [`GridConfig::rest_shape`], whose
    /// rest-shape features are 0 when it is `None`.
    pub rest: Option<NeighbourTensors<B>>,
    /// `[B, N, 4]` each particle's carried deformation gradient (row-major), read only by a
    /// model with [`Deformation::Advect`]: a [`StepOutput::deformation`] of the step before,
    /// or `None` at a rollout's start (then the fit to `rest`, [`NeighbourTensors::fitted`]).
    pub deformation: Option<Tensor<B, 3>>,
}

/// A step's prediction, physical units.
#[derive(Clone, Debug)]
pub struct StepOutput<B: Backend> {
    /// `[B, N, 2]` next positions.
    pub pos: Tensor<B, 3>,
    /// `[B, N, 2]` next velocities.
    pub vel: Tensor<B, 3>,
    /// `[B, N, 4]` the advected deformation gradient at the next frame (a model with
    /// [`Deformation::Advect`]; `None` otherwise).
    pub deformation: Option<Tensor<B, 3>>,
}

/// `[1, 1, 2k]`: `v` repeated k times (per-component constants for interleaved x, y).
fn pairs<B: Backend>(v: [f32; 2], k: usize, device: &B::Device) -> Tensor<B, 3> {
    let data: Vec<f32> = (0..k).flat_map(|_| v).collect();
    Tensor::from_data(TensorData::new(data, [1, 1, 2 * k]), device)
}

/// `[B, N, width]` one-hot of material ids `[B N]` (ids above `width - 1` count as
/// `width - 1`); `width` is the model's [`GridConfig::materials`].
pub fn one_hot<B: Backend>(
    material: &[u8],
    width: usize,
    b: usize,
    n: usize,
    device: &B::Device,
) -> Tensor<B, 3> {
    let mut data = vec![0.0f32; b * n * width];
    for (row, &m) in data.chunks_exact_mut(width).zip(material) {
        row[usize::from(m).min(width - 1)] = 1.0;
    }
    Tensor::from_data(TensorData::new(data, [b, n, width]), device)
}

impl<B: NetOps> GridModel<B> {
    /// Velocity frames per particle the step reads (T).
    pub fn window(&self) -> usize {
        self.window
    }

    /// Frames predicted per call (K, [`GridConfig::bundle`]).
    pub fn bundle(&self) -> usize {
        self.bundle
    }

    /// Network calls per predicted frame (S, [`GridConfig::substeps`]).
    pub fn substeps(&self) -> usize {
        self.substeps
    }

    /// Whether the step reads reference positions ([`GridConfig::reference`]).
    pub fn uses_reference(&self) -> bool {
        self.reference
    }

    /// Whether the model reads rest-shape features ([`GridConfig::rest_shape`]).
    pub fn uses_rest_shape(&self) -> bool {
        self.rest_in.is_some()
    }

    /// The particle update ([`GridConfig::update`]).
    pub fn update(&self) -> Update {
        self.update
    }

    /// Whether the model carries an advected F ([`Deformation::Advect`] with rest shape).
    pub fn advects(&self) -> bool {
        self.rest_in.is_some() && self.deformation == Deformation::Advect
    }

    /// The box `(lo, hi)` (domain units, both axes) the integration clamps predicted
    /// positions into: MPM's `[0.5 dx, 1 - 1.5 dx]` (`sim::mpm`'s G2P) on the grid of
    /// [`GridConfig::box_grid`], the network's own where that is 0.
    pub fn integration_box(&self) -> (f32, f32) {
        let grid = if self.box_grid == 0 {
            self.n
        } else {
            self.box_grid
        };
        let dx = 1.0 / grid as f32;
        (0.5 * dx, 1.0 - 1.5 * dx)
    }

    /// One step for a batch of scenes: the next frame and the new memory state. For a
    /// bundled model (K > 1) this is the first frame of [`GridModel::step_bundle`].
    ///
    /// # Shapes
    /// See [`StepInput`] and [`StepOutput`]; `state` holds `[B N, H]` rows.
    pub fn step(
        &self,
        input: StepInput<B>,
        state: MemoryState<B>,
    ) -> (StepOutput<B>, MemoryState<B>) {
        let (mut frames, state) = self.step_bundle(input, state);
        (frames.swap_remove(0), state)
    }
}

/// Mirrors physical particle rows of `width` values (x, y[, vx, vy]) about the box's
/// vertical midline in place: `x -> 1 - x`, `vx -> -vx`. MPM's unit box, its walls (grid
/// nodes `< 3` or `> n - 3`, free from 2.5 to n - 2.5 cells) and gravity are symmetric under
/// it, so a mirrored trajectory is one MPM could have produced: `train --mirror` doubles the
/// scenes a model sees (data augmentation by a symmetry of the physics), and
/// [`crate::model::store::Surrogate::with_mirror`] uses the same symmetry at inference.
pub fn mirror_rows(rows: &mut [f32], width: usize) {
    for r in rows.chunks_exact_mut(width) {
        r[0] = 1.0 - r[0];
        if width >= 4 {
            r[2] = -r[2];
        }
    }
}

/// `parts` (`[B, N, C_i]` each) concatenated along the channels: `[B, N, sum C_i]`. As rows
/// `[B N, C_i]`, so the CPU backend copies rows (its concatenation along the last of three
/// axes goes element by element once B > 1: a batch of scenes cost 2-7x a scene alone).
fn cat_rows<B: Backend>(parts: Vec<Tensor<B, 3>>) -> Tensor<B, 3> {
    let [b, n, _] = parts[0].dims();
    let rows = parts
        .into_iter()
        .map(|p| {
            let c = p.dims()[2];
            p.reshape([b * n, c])
        })
        .collect();
    let out = Tensor::cat(rows, 1);
    let c = out.dims()[1];
    out.reshape([b, n, c])
}
