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
//! 5. Head: an MLP on `[u_i, memory output]` predicts the normalised velocity change;
//!    `dv = dv_mean + dv_scale * out` (physical), `v' = v + dv`, and the trapezoid
//!    `x' = x + dt (v + v') / 2` (its floor against MPM frames is 1.5e-6 / 1.3e-6 MSE, the
//!    explicit `x + v' dt` 8e-6 / 2e-5: docs/design.md, "Models"), clamped into the box MPM
//!    keeps its particles in.
//!
//! Any N, any particle order: every per-particle operation is row-wise and the grid sums are
//! order-free. The normalisation constants are fitted on the training split and saved in
//! [`GridConfig`]. Used by [`crate::model::store::Surrogate`] and [`crate::train::grid`].

pub mod memory;
pub mod transfer;
pub mod unet;

pub use memory::{Memory, MemoryKind, MemoryState};
pub use unet::{ConvKernel, UNet, UNetConfig};

use burn::config::Config;
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

use crate::ops::{grid_channels, linear, silu, NetOps};

/// Materials (one-hot width).
pub const MATERIALS: usize = 4;

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
}

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
    /// `bundle` is 0 or above 16.
    #[error("--bundle must be in 1..=16")]
    Bundle,
}

impl GridConfig {
    /// Grid channels of P2G's output (mass, T velocities, materials, 2 walls, and the
    /// displacement from the reference position when `reference`).
    pub fn grid_channels(&self) -> usize {
        1 + 2 * self.window + MATERIALS + 2 + if self.reference { 2 } else { 0 }
    }

    /// Per-particle own features (T velocities, material one-hot, position).
    pub fn own_features(&self) -> usize {
        2 * self.window + MATERIALS + 2
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
        if !(1..=16).contains(&self.bundle) {
            return Err(GridConfigError::Bundle);
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
        GridModel {
            unet: UNetConfig::new(self.grid_channels(), self.latent * self.bundle.max(1))
                .with_width(self.unet_width)
                .with_levels(self.levels)
                .with_conv(self.conv)
                .init(device),
            memory: Memory::new(self.memory, d_u, self.hidden, device),
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
            reference: self.reference,
            vel_scale: self.vel_scale,
            dv_mean: self.dv_mean,
            dv_scale: self.dv_scale,
        }
    }
}

/// The network (see the module doc).
#[derive(Module, Debug)]
pub struct GridModel<B: Backend> {
    unet: UNet<B>,
    memory: Memory<B>,
    head_a: Linear<B>,
    head_b: Linear<B>,
    head_out: Linear<B>,
    n: usize,
    window: usize,
    bundle: usize,
    reference: bool,
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
    /// `[B, N, 4]` material one-hot.
    pub material: Tensor<B, 3>,
    /// `[B]` frame spacing, time units.
    pub dt: Tensor<B, 1>,
    /// `[B, N, 2]` reference positions X (each particle's position in the first frame of
    /// its stream), domain units; read only by a model with [`GridConfig::reference`], which
    /// takes `pos` (no displacement) when it is `None`.
    pub reference: Option<Tensor<B, 3>>,
}

/// A step's prediction, physical units.
#[derive(Clone, Debug)]
pub struct StepOutput<B: Backend> {
    /// `[B, N, 2]` next positions.
    pub pos: Tensor<B, 3>,
    /// `[B, N, 2]` next velocities.
    pub vel: Tensor<B, 3>,
}

/// `[1, 1, 2k]`: `v` repeated k times (per-component constants for interleaved x, y).
fn pairs<B: Backend>(v: [f32; 2], k: usize, device: &B::Device) -> Tensor<B, 3> {
    let data: Vec<f32> = (0..k).flat_map(|_| v).collect();
    Tensor::from_data(TensorData::new(data, [1, 1, 2 * k]), device)
}

/// `[B, N, 4]` one-hot of material ids `[B N]` (ids above 3 count as 3).
pub fn one_hot<B: Backend>(
    material: &[u8],
    b: usize,
    n: usize,
    device: &B::Device,
) -> Tensor<B, 3> {
    let mut data = vec![0.0f32; b * n * MATERIALS];
    for (row, &m) in data.chunks_exact_mut(MATERIALS).zip(material) {
        row[usize::from(m).min(MATERIALS - 1)] = 1.0;
    }
    Tensor::from_data(TensorData::new(data, [b, n, MATERIALS]), device)
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

    /// Whether the step reads reference positions ([`GridConfig::reference`]).
    pub fn uses_reference(&self) -> bool {
        self.reference
    }

    /// This model with [`GridConfig::reference`] on: the U-Net's first convolution gets two
    /// input channels (the displacement from the reference position) whose weights start at
    /// zero, so the result predicts exactly what `self` does until it is trained further
    /// (`train --init-from` a model without them). A model that has them is returned as is.
    pub fn with_reference(self) -> Self {
        if self.reference {
            return self;
        }
        Self {
            unet: self.unet.widen_input(2),
            reference: true,
            ..self
        }
    }

    /// This single-frame model as a bundled one predicting `k` frames per call
    /// ([`GridConfig::bundle`]): the U-Net's output head is tiled `k` times, so every frame
    /// of a bundle starts out reading the same latent field at the particle's position after
    /// the frames before it (the single-frame model's prediction, applied again where the
    /// particle went). `train --bundle K --init-from` a single-frame model starts from this.
    /// A model that is already bundled, or `k` = 1, is returned as is.
    pub fn with_bundle(self, k: usize) -> Self {
        if self.bundle != 1 || k <= 1 {
            return self;
        }
        Self {
            unet: self.unet.tile_output(k),
            bundle: k,
            ..self
        }
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

    /// One network call for a batch of scenes: the next K frames (K = [`GridModel::bundle`])
    /// and the new memory state. P2G, the U-Net and the memory run once; then for k = 1..K
    /// each particle gathers latent field k at its current position (G2P), the head predicts
    /// its velocity change and the frame is integrated, so frame k + 1 reads the grid where
    /// frame k left the particle. K = 1 is the single-frame step.
    ///
    /// # Shapes
    /// See [`StepInput`]; returns K [`StepOutput`]s, oldest first; `state` holds `[B N, H]`
    /// rows.
    pub fn step_bundle(
        &self,
        input: StepInput<B>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let [b, n_p, _] = input.pos.dims();
        let t = self.window;
        let device = input.pos.device();
        let vel = input.vel.clone() / pairs(self.vel_scale, t, &device); // [B, N, 2T], normalised

        // P2G: the separable dense transfers on accelerators, the sparse ones on the CPU.
        let s = transfer::stencil(input.pos.clone(), self.n, !B::SEQUENTIAL_SCAN);
        let ones = Tensor::ones([b, n_p, 1], &device);
        let mut values = vec![ones, vel.clone(), input.material.clone()];
        if self.reference {
            // Displacement from the reference position, in grid cells.
            let x0 = input.reference.clone().unwrap_or_else(|| input.pos.clone());
            values.push((input.pos.clone() - x0).mul_scalar(self.n as f32));
        }
        // [B, n^2, 1 + 2T + 4 (+ 2)], then the channels [m / 4, velocities and materials per
        // mass, walls, displacement per mass]: the reference channels after the walls, so a
        // model grown by `with_reference` keeps its channel order.
        let splat = transfer::p2g(&s, cat_rows(values));
        let grid = grid_channels(splat, self.n, 2 * t + MATERIALS); // [B, n^2, C]
        let cells = self.n * self.n;
        let c = grid.dims()[2];
        let grid = grid.reshape([b, self.n, self.n, c]); // channels last, node (i, j) at [i, j]

        // U-Net: K latent fields of L channels each.
        let out = self.unet.forward(grid);
        let channels = out.dims()[3];
        let out = out.reshape([b, cells, channels]); // [B, n^2, K L]
        let fields = self.fields(out, [b, cells]);
        let field = |k: usize| fields[k].clone();

        // Memory, once per call, on the first frame's inputs.
        let u = self.particle_inputs(
            transfer::g2p(&s, field(0)),
            &vel,
            &input.material,
            &input.pos,
        );
        let (memory, state) = self.memory.step(u.clone(), state);
        let dt = input.dt.clone().reshape([b, 1, 1]);
        let (mut pos, mut vel, mut u) = (input.pos.clone(), vel, u);
        let mut frames = Vec::with_capacity(self.bundle);
        for k in 0..self.bundle {
            if k > 0 {
                let s = transfer::stencil(pos.clone(), self.n, !B::SEQUENTIAL_SCAN);
                u = self.particle_inputs(transfer::g2p(&s, field(k)), &vel, &input.material, &pos);
            }
            let features = match &memory {
                Some(m) => Tensor::cat(vec![u.clone(), m.clone()], 1),
                None => u.clone(),
            };
            let next = self.head_step(features, &vel, pos, dt.clone(), [b, n_p]);
            if k + 1 < self.bundle {
                // The velocity window moves on by the frame just predicted (normalised).
                let v = next.vel.clone() / pairs(self.vel_scale, 1, &device);
                vel = match t {
                    1 => v,
                    _ => Tensor::cat(vec![vel.narrow(2, 2, 2 * (t - 1)), v], 2),
                };
            }
            pos = next.pos.clone();
            frames.push(next);
        }
        (frames, state)
    }

    /// The U-Net's output `[B, n^2, K L]` as K fields of `[B, n^2, L]`, each its own
    /// contiguous tensor: the CPU's one-pass gather reads only dense inputs (a strided view
    /// would take the composed path).
    fn fields(&self, out: Tensor<B, 3>, [b, cells]: [usize; 2]) -> Vec<Tensor<B, 3>> {
        if self.bundle == 1 {
            return vec![out];
        }
        let latent = out.dims()[2] / self.bundle;
        (0..self.bundle)
            .map(|i| {
                let view = out.clone().narrow(2, i * latent, latent);
                view.reshape([b * cells * latent])
                    .reshape([b, cells, latent])
            })
            .collect()
    }

    /// `[B N, L + 2T + 4 + 2]` rows `u_i = [gathered_i, own_i]`: the gathered latent features,
    /// the normalised velocity window `vel` (`[B, N, 2T]`), the material one-hot `material` and the
    /// position `pos` (`[B, N, 2]`).
    fn particle_inputs(
        &self,
        gathered: Tensor<B, 3>,
        vel: &Tensor<B, 3>,
        material: &Tensor<B, 3>,
        pos: &Tensor<B, 3>,
    ) -> Tensor<B, 2> {
        let [b, n_p, _] = pos.dims();
        let u = cat_rows(vec![gathered, vel.clone(), material.clone(), pos.clone()]);
        let d_u = u.dims()[2];
        u.reshape([b * n_p, d_u])
    }

    /// The head on `features` (`[B N, D]` rows) and the integration of one frame from the
    /// normalised velocity window `vel` and positions `pos`, physical units: `dv = dv_mean +
    /// dv_scale * out`, `v' = v + dv`, the trapezoid `x' = x + dt (v + v') / 2`, clamped into
    /// the box MPM keeps its particles in.
    fn head_step(
        &self,
        features: Tensor<B, 2>,
        vel: &Tensor<B, 3>,
        pos: Tensor<B, 3>,
        dt: Tensor<B, 3>,
        [b, n_p]: [usize; 2],
    ) -> StepOutput<B> {
        let device = pos.device();
        let t = self.window;
        // Through the backend-ops dense layer, as every per-particle layer: its weight
        // gradient sums over all B N rows, which burn's `Linear` leaves to one matmul with a
        // handful of output tiles on a GPU (`bench train --arch grid --stages`, H100, batch
        // 64: 62 ms of a 110 ms step outside the timed stages).
        let h = silu(linear(&self.head_a, features));
        let h = silu(linear(&self.head_b, h));
        let dv = linear(&self.head_out, h).reshape([b, n_p, 2]);
        let dv = dv * pairs(self.dv_scale, 1, &device) + pairs(self.dv_mean, 1, &device);
        // Integrate (trapezoid) in physical units.
        let v = vel.clone().narrow(2, 2 * (t - 1), 2) * pairs(self.vel_scale, 1, &device);
        let v_next = v.clone() + dv;
        let pos = pos + (v + v_next.clone()) * dt.mul_scalar(0.5);
        let dx = 1.0 / self.n as f32;
        let pos = pos.clamp(0.5 * dx, 1.0 - 1.5 * dx);
        StepOutput { pos, vel: v_next }
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
