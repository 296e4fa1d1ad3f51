//! [`GridConfig`]: every size, switch and normalisation constant of a grid model (saved in
//! its `model.json`), its checks ([`GridConfigError`]) and fresh weights
//! ([`GridConfig::init`]); [`Update`], how the model turns its outputs into velocity changes;
//! [`Deformation`], where its rest-shape features' deformation gradient comes from.

use std::ops::RangeInclusive;

use burn::config::Config;
use burn::nn::{Initializer, LinearConfig};

use super::interact::Interaction;
use super::memory::{Memory, MemoryKind};
use super::unet::{ConvKernel, UNetConfig};
use super::{GridModel, REST_FEATURES};
use crate::ops::NetOps;

/// How a grid model turns its outputs into each particle's velocity change
/// ([`GridConfig::update`]; the module doc, step 5).
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Update {
    /// The per-particle head alone (every model saved before this existed).
    Free,
    /// The G2P of a grid velocity-change field alone: no head, no memory in the output.
    Grid,
    /// The G2P of the grid field plus the head's per-particle correction.
    GridHead,
}

impl Update {
    /// Every update.
    pub const ALL: [Update; 3] = [Update::Free, Update::Grid, Update::GridHead];

    /// Command-line name: `free`, `grid`, `grid+head`.
    pub fn name(self) -> &'static str {
        match self {
            Update::Free => "free",
            Update::Grid => "grid",
            Update::GridHead => "grid+head",
        }
    }

    /// The update named `name`.
    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|u| u.name() == name)
    }
}

/// Where a rest-shape model's deformation gradient F comes from ([`GridConfig::deformation`];
/// [`super::rest`]).
#[derive(Config, Debug, Copy, PartialEq, Eq)]
pub enum Deformation {
    /// Fitted each frame by least squares to the particle's rest neighbours (variant (b);
    /// every rest-shape model saved before this existed).
    Fit,
    /// Carried per particle and advected with the predicted velocity field,
    /// `F <- (I + dt C) F`, `C` the APIC / MLS-MPM affine velocity gradient gathered from the
    /// P2G of the predicted velocities (variant (a); [`super::rest::advect`]). It starts as
    /// the fit where a rollout starts (the identity in a stream's first frame); the liquid
    /// carries only `J` (`F = sqrt(J) I`, as MPM resets its fluid's F).
    Advect,
}

/// Every size and normalisation constant of a grid model; saved with each checkpoint.
#[derive(Config, Debug)]
pub struct GridConfig {
    /// Per-particle memory.
    pub memory: MemoryKind,
    /// Grid size n (a multiple of `2^(levels - 1)`).
    #[config(default = 64)]
    pub grid: usize,
    /// Velocity frames per particle as input, T (the current one and T - 1 before it).
    #[config(default = 2)]
    pub window: usize,
    /// U-Net first-level width.
    #[config(default = 32)]
    pub unet_width: usize,
    /// U-Net resolutions.
    #[config(default = 4)]
    pub levels: usize,
    /// Channels the U-Net returns to the particles.
    #[config(default = 32)]
    pub latent: usize,
    /// Hidden state values per particle.
    #[config(default = 32)]
    pub hidden: usize,
    /// Head MLP width.
    #[config(default = 64)]
    pub head_hidden: usize,
    /// Velocity normalisation (x, y), domain units per time unit.
    #[config(default = "[1.0, 1.0]")]
    pub vel_scale: [f32; 2],
    /// Mean velocity change per frame (x, y): gravity's share.
    #[config(default = "[0.0, 0.0]")]
    pub dv_mean: [f32; 2],
    /// Standard deviation of the velocity change per frame (x, y).
    #[config(default = "[1.0, 1.0]")]
    pub dv_scale: [f32; 2],
    /// Start the head's last layer at zero (an untrained model is then constant velocity
    /// plus the mean acceleration; Goyal et al. 2017, section 5.1); tests turn it off.
    #[config(default = true)]
    pub head_zero_init: bool,
    /// How the U-Net's convolutions are computed (same weights and results either way).
    #[config(default = "ConvKernel::Auto")]
    pub conv: ConvKernel,
    /// Give the grid each particle's displacement from its reference position X, its
    /// position in the first frame of its stream (`--reference first-frame`): two more P2G
    /// channels, `sum w (x - X) n / m` (grid cells). MPM measures its deformation gradient
    /// `F = dx/dX` from that configuration; the U-Net can read `I - F^-1` as the displacement
    /// field's gradient across cells. Off in models saved before it existed.
    #[config(default = false)]
    pub reference: bool,
    /// Frames predicted per call, K (temporal bundling, `train --bundle K`): the U-Net emits
    /// K latent fields (`K latent` channels) and each particle reads field k at its position
    /// after k - 1 integrated frames (NeuralMPM's multi-step grid velocities, Rochman-Sharabi
    /// et al. 2024, section 3; Brandstetter et al. 2022, "Message passing neural PDE
    /// solvers", section 2.3, temporal bundling). The memory is updated once per call.
    /// 1 (the single-frame model) in models saved before it existed.
    #[config(default = 1)]
    pub bundle: usize,
    /// Material one-hot width: the materials the model tells apart, ids `0..materials`
    /// ([`crate::material::COUNT`] when it was made). 4 in models saved before it existed
    /// (`model::store`'s added fields), so they keep their width when a material is added.
    #[config(default = "crate::material::COUNT")]
    pub materials: usize,
    /// Rest-shape features (`train --rest-shape`): each solid particle's deformation fitted to
    /// its 8 nearest neighbours of the same material in the first frame of its stream
    /// ([`rest`]), 6 values into P2G (6 more channels after the reference ones) and into the
    /// head (through their own layer). Off in models saved before it existed.
    #[config(default = false)]
    pub rest_shape: bool,
    /// The particle update (`train --update`, the module doc's step 5). [`Update::Free`] in
    /// models saved before it existed.
    #[config(default = "Update::Free")]
    pub update: Update,
    /// Where the rest-shape features' F comes from (`train --rest-shape fit | advect`).
    /// [`Deformation::Fit`] in models saved before it existed.
    #[config(default = "Deformation::Fit")]
    pub deformation: Deformation,
    /// Network substeps S (`train --substeps S`, issue 81): a call advances its frame in S
    /// calls of the whole network (P2G, U-Net, memory, G2P, head) at `dt / S`, each reading
    /// the grid where the last left the particles ([`GridModel::step_bundle`]); only the
    /// frame at the end is predicted. Single-frame models only (`bundle` 1). 1 in models
    /// saved before it existed.
    #[config(default = 1)]
    pub substeps: usize,
    /// Rounds of message passing between neighbouring particles after G2P (`train
    /// --interaction ROUNDS`, issue 81; [`super::interact`], GNS's processor): its output is
    /// added to each particle's input row, so it feeds the memory and the head. 0 (none) in
    /// models saved before it existed.
    #[config(default = 0)]
    pub interaction: usize,
    /// The message passing's connectivity radius, domain units (`--interaction-radius`).
    #[config(default = 0.02)]
    pub interaction_radius: f64,
    /// Neighbours per particle in the message passing, the nearest within the radius
    /// (`--interaction-neighbours`).
    #[config(default = 12)]
    pub interaction_neighbours: usize,
    /// The grid whose MPM box `[0.5 / g, 1 - 1.5 / g]` (domain units; `sim::mpm`'s G2P
    /// clamp) the integration clamps each predicted position into (`train --box-grid G`);
    /// 0, in models saved before it existed: the network's own grid. A small network's box
    /// is narrower than the solver's: on 32 cells its right and top edges stand at 0.953,
    /// where the solver's particles reach 0.97 (64 cells, `multi`) and 0.98 (128, `fluid`),
    /// so no predicted front reached the far wall. 256, the finest solver `simulate` makes,
    /// leaves each scene's own walls to what the network learned and to the projection's
    /// walls part ([`crate::model::constraints`], in the scene's solver cells).
    #[config(default = 0)]
    pub box_grid: usize,
}

/// `bundle`'s range (`--bundle`): frames one network call predicts.
pub const BUNDLE: RangeInclusive<usize> = 1..=16;
/// `substeps`' range (`--substeps`): network substeps a frame.
pub const SUBSTEPS: RangeInclusive<usize> = 1..=8;
/// `interaction`'s range (`--interaction`): rounds of message passing.
pub const INTERACTION_ROUNDS: RangeInclusive<usize> = 0..=8;
/// `interaction_neighbours`' range (`--interaction-neighbours`).
pub const INTERACTION_NEIGHBOURS: RangeInclusive<usize> = 1..=64;
/// The largest `interaction_radius` (`--interaction-radius`, above 0), a fraction of the box.
pub const INTERACTION_RADIUS_MAX: f64 = 0.25;
/// `box_grid`'s range (`--box-grid`) besides 0 (the network's grid).
pub const BOX_GRID: RangeInclusive<usize> = 8..=4096;

/// A [`GridConfig`] setting out of range; each message names the command-line flag.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GridConfigError {
    /// `window` is 0.
    #[error("--window must be at least 1")]
    Window,
    /// `grid` is below 8 or not divisible by the coarsest U-Net level's factor.
    #[error("--grid {grid} must be at least 8 and a multiple of 2^(--levels - 1) = {multiple}")]
    Grid {
        /// The grid side asked for.
        grid: usize,
        /// `2^(levels - 1)`, which it must be a multiple of.
        multiple: usize,
    },
    /// One of the layer widths is 0.
    #[error("widths (--unet-width, --latent, --hidden, --head-hidden) must be at least 1")]
    Width,
    /// `bundle` outside [`BUNDLE`].
    #[error("--bundle must be in {BUNDLE:?}")]
    Bundle,
    /// `substeps` outside [`SUBSTEPS`], or above 1 with `bundle` above 1.
    #[error("--substeps must be in {SUBSTEPS:?}, and 1 with --bundle above 1")]
    Substeps,
    /// The message passing's rounds outside [`INTERACTION_ROUNDS`], neighbours outside
    /// [`INTERACTION_NEIGHBOURS`] or radius outside (0, [`INTERACTION_RADIUS_MAX`]], or message
    /// passing with the grid update (whose output it would not reach).
    #[error(
        "--interaction must be in {INTERACTION_ROUNDS:?} (0 with --update grid), \
         --interaction-neighbours in {INTERACTION_NEIGHBOURS:?} and --interaction-radius in \
         (0, {INTERACTION_RADIUS_MAX}]"
    )]
    Interaction,
    /// `box_grid` neither 0 nor in [`BOX_GRID`].
    #[error("--box-grid must be 0 (the network's grid) or in {BOX_GRID:?}")]
    BoxGrid,
}

impl GridConfig {
    /// Grid channels of P2G's output (mass, T velocities, materials, 2 walls, and the
    /// displacement from the reference position when `reference`).
    pub fn grid_channels(&self) -> usize {
        1 + 2 * self.window
            + self.materials
            + 2
            + if self.reference { 2 } else { 0 }
            + if self.rest_shape { REST_FEATURES } else { 0 }
    }

    /// Per-particle own features (T velocities, material one-hot, position).
    pub fn own_features(&self) -> usize {
        2 * self.window + self.materials + 2
    }

    /// Checks the sizes.
    ///
    /// # Errors
    /// The first setting out of range, as a [`GridConfigError`] whose message names its flag.
    pub fn validate(&self) -> Result<(), GridConfigError> {
        let levels = self.levels.max(1);
        if self.window == 0 {
            return Err(GridConfigError::Window);
        }
        let multiple = 1 << (levels - 1);
        if self.grid < 8 || self.grid % multiple != 0 {
            return Err(GridConfigError::Grid {
                grid: self.grid,
                multiple,
            });
        }
        if self.unet_width == 0 || self.latent == 0 || self.hidden == 0 || self.head_hidden == 0 {
            return Err(GridConfigError::Width);
        }
        if !BUNDLE.contains(&self.bundle) {
            return Err(GridConfigError::Bundle);
        }
        if !SUBSTEPS.contains(&self.substeps) || (self.substeps > 1 && self.bundle > 1) {
            return Err(GridConfigError::Substeps);
        }
        let radius = self.interaction_radius;
        if !INTERACTION_ROUNDS.contains(&self.interaction)
            || (self.interaction > 0 && self.update == Update::Grid)
            || !INTERACTION_NEIGHBOURS.contains(&self.interaction_neighbours)
            || !(radius > 0.0 && radius <= INTERACTION_RADIUS_MAX)
        {
            return Err(GridConfigError::Interaction);
        }
        if self.box_grid != 0 && !BOX_GRID.contains(&self.box_grid) {
            return Err(GridConfigError::BoxGrid);
        }
        Ok(())
    }

    /// A model with fresh weights; the head's last layer starts at zero, so an untrained
    /// model predicts `dv = dv_mean` (constant velocity plus the mean acceleration).
    pub fn init<B: NetOps>(&self, device: &B::Device) -> GridModel<B> {
        let own = self.own_features();
        let d_u = self.latent + own;
        let d_head = d_u
            + if self.memory == MemoryKind::None {
                0
            } else {
                self.hidden
            };
        let k = self.bundle.max(1);
        let unet = UNetConfig::new(self.grid_channels(), self.latent * k)
            .with_width(self.unet_width)
            .with_levels(self.levels)
            .with_conv(self.conv)
            .init(device);
        GridModel {
            // The velocity-change fields start at zero, like the head's last layer.
            unet: match self.update {
                Update::Free => unet,
                _ => unet.widen_output(2 * k),
            },
            rest_in: self
                .rest_shape
                .then(|| LinearConfig::new(REST_FEATURES, self.head_hidden).init(device)),
            memory: Memory::new(self.memory, d_u, self.hidden, device),
            interaction: self.interaction(d_u, device),
            head_a: LinearConfig::new(d_head, self.head_hidden).init(device),
            head_b: LinearConfig::new(self.head_hidden, self.head_hidden).init(device),
            head_out: if self.head_zero_init {
                LinearConfig::new(self.head_hidden, 2)
                    .with_initializer(Initializer::Zeros)
                    .init(device)
            } else {
                LinearConfig::new(self.head_hidden, 2).init(device)
            },
            n: self.grid,
            window: self.window,
            bundle: self.bundle.max(1),
            substeps: self.substeps.max(1),
            box_grid: self.box_grid,
            reference: self.reference,
            update: self.update,
            deformation: self.deformation,
            host_pass: true,
            dense_transfers: None,
            vel_scale: self.vel_scale,
            dv_mean: self.dv_mean,
            dv_scale: self.dv_scale,
        }
    }

    /// The message passing of a model whose particle rows hold `d_u` values (`None` without
    /// rounds), fresh weights, its output layer at zero ([`Interaction::new`]).
    pub(super) fn interaction<B: NetOps>(
        &self,
        d_u: usize,
        device: &B::Device,
    ) -> Option<Interaction<B>> {
        let [rounds, k] = [self.interaction, self.interaction_neighbours];
        (rounds > 0).then(|| {
            Interaction::new(
                d_u,
                self.hidden,
                [rounds, k],
                self.interaction_radius as f32,
                device,
            )
        })
    }
}
