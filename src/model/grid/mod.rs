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
//! Any N, any particle order: every per-particle operation is row-wise and the grid sums are
//! order-free. The normalisation constants are fitted on the training split and saved in
//! [`GridConfig`]. Used by [`crate::model::store::Surrogate`] and [`crate::train::grid`].

mod config;
mod fused;
mod grow;
pub mod memory;
pub mod rest;
pub mod transfer;
pub mod unet;

pub use config::{Deformation, GridConfig, GridConfigError, Update};
pub use memory::{Memory, MemoryKind, MemoryState};
pub use rest::{NeighbourTensors, Neighbourhood, REST_FEATURES};
pub use unet::{ConvKernel, UNet, UNetConfig};

use burn::module::Module;
use burn::nn::Linear;
use burn::tensor::backend::Backend;
use burn::tensor::{Tensor, TensorData};

use crate::ops::{grid_channels, host_values, linear, silu, NetOps};

/// The network (see the module doc).
#[derive(Module, Debug)]
pub struct GridModel<B: Backend> {
    unet: UNet<B>,
    memory: Memory<B>,
    head_a: Linear<B>,
    head_b: Linear<B>,
    head_out: Linear<B>,
    /// The rest-shape features' own first head layer ([`GridConfig::rest_shape`]).
    rest_in: Option<Linear<B>>,
    n: usize,
    window: usize,
    bundle: usize,
    reference: bool,
    #[module(skip)]
    update: Update,
    #[module(skip)]
    deformation: Deformation,
    /// Whether CPU inference takes the per-particle host passes ([`fused`]; true unless a
    /// test asks for the tensor path with [`GridModel::with_host_pass`]).
    #[module(skip)]
    host_pass: bool,
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
        let rest = |pos: &Tensor<B, 3>| self.rest_features(input.rest.as_ref(), pos);
        // Variant (a): F carried, advected after every frame; its features replace the fit's.
        let mut carried = self.advects().then(|| self.carried(&input, [b, n_p]));

        // P2G: the separable dense transfers where the backend has no sparse ones.
        let s = transfer::stencil(input.pos.clone(), self.n, B::dense_stencil());
        let ones = Tensor::ones([b, n_p, 1], &device);
        let mut values = vec![ones, vel.clone(), input.material.clone()];
        if self.reference {
            // Displacement from the reference position, in grid cells.
            let x0 = input.reference.clone().unwrap_or_else(|| input.pos.clone());
            values.push((input.pos.clone() - x0).mul_scalar(self.n as f32));
        }
        let mut features = match &carried {
            Some((f, _)) => Some(rest::advect::features_of(f.clone())),
            None => rest(&input.pos),
        };
        if let Some(r) = &features {
            values.push(r.clone());
        }
        // [B, n^2, 1 + 2T + M (+ 2) (+ 6)], then the channels [m / 4, velocities and materials
        // per mass, walls, displacement per mass, rest shape per mass]: the grown channels
        // after the walls, so a model grown by `with_reference` / `with_rest_shape` keeps its
        // channel order.
        let splat = transfer::p2g(&s, cat_rows(values));
        let grid = grid_channels(splat, self.n, 2 * t + input.material.dims()[2]); // [B, n^2, C]
        let cells = self.n * self.n;
        let c = grid.dims()[2];
        let grid = grid.reshape([b, self.n, self.n, c]); // channels last, node (i, j) at [i, j]

        // U-Net: K latent fields of L channels each (and K velocity-change fields).
        let out = self.unet.forward(grid);
        let channels = out.dims()[3];
        let out = out.reshape([b, cells, channels]); // [B, n^2, K L (+ 2 K)]
        let (fields, dv_fields) = self.fields(out, [b, cells]);
        if self.takes_host_pass(&input) {
            return self.host_frames(&input, vel, &fields, features, state);
        }
        let field = |k: usize| fields[k].clone();

        // Memory, once per call, on the first frame's inputs (not in the output of the grid
        // update: left as it is).
        let u = self.particle_inputs(
            transfer::g2p(&s, field(0)),
            &vel,
            &input.material,
            &input.pos,
        );
        let (memory, state) = match self.update {
            Update::Grid => (None, state),
            _ => self.memory.step(u.clone(), state),
        };
        let dt = input.dt.clone().reshape([b, 1, 1]);
        let (mut pos, mut vel, mut u, mut s) = (input.pos.clone(), vel, u, s);
        let mut frames = Vec::with_capacity(self.bundle);
        for k in 0..self.bundle {
            if k > 0 {
                s = transfer::stencil(pos.clone(), self.n, B::dense_stencil());
                u = self.particle_inputs(transfer::g2p(&s, field(k)), &vel, &input.material, &pos);
                features = match &carried {
                    Some((f, _)) => Some(rest::advect::features_of(f.clone())),
                    None => rest(&pos),
                };
            }
            let head_in = match &memory {
                Some(m) => Tensor::cat(vec![u.clone(), m.clone()], 1),
                None => u.clone(),
            };
            let grid_dv = dv_fields.get(k).map(|f| transfer::g2p(&s, f.clone()));
            let rest_rows = features
                .clone()
                .map(|r| r.reshape([b * n_p, REST_FEATURES]));
            let out = self.head_out(head_in, rest_rows, grid_dv, [b, n_p]);
            let mut next = self.integrate(out, &vel, pos.clone(), dt.clone());
            if let Some((f, has)) = carried.as_mut() {
                // APIC's gradient at the frame's start positions (the stencil `s`).
                let c = rest::advect::velocity_gradient(&s, &pos, next.vel.clone());
                *f = rest::advect::advect(f.clone(), c, dt.clone(), has.clone());
                next.deformation = Some(f.clone());
            }
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

    /// Whether this call's per-particle part runs as host passes ([`fused`]): on the CPU
    /// where nothing needs a gradient (inference, and the push-forward calls of CPU
    /// training), with the free head and no advected F.
    fn takes_host_pass(&self, input: &StepInput<B>) -> bool {
        self.host_pass
            && B::SEQUENTIAL_SCAN
            && self.update == Update::Free
            && !self.advects()
            && !input.pos.is_require_grad()
            && !input.vel.is_require_grad()
            && !self.head_a.weight.val().is_require_grad()
            && !self.head_out.weight.val().is_require_grad()
    }

    /// [`GridModel::step_bundle`]'s frames from the U-Net's latent `fields` on, through the
    /// host passes of [`fused`]: the input rows, the memory (as tensors, on the first frame's
    /// rows), then per frame the head and the integration. `vel` is the normalised window;
    /// `features` the rest-shape features at the call's positions (`[B, N, 6]`, as P2G read
    /// them; `None` for a model without rest shape).
    fn host_frames(
        &self,
        input: &StepInput<B>,
        vel: Tensor<B, 3>,
        fields: &[Tensor<B, 3>],
        features: Option<Tensor<B, 3>>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let [b, n_p, _] = input.pos.dims();
        let device = input.pos.device();
        let c = fused::Constants {
            n: self.n,
            window: self.window,
            vel_scale: self.vel_scale,
            dv_mean: self.dv_mean,
            dv_scale: self.dv_scale,
        };
        let mut particles = fused::Particles {
            pos: host_values(input.pos.clone()),
            vel: host_values(vel),
            material: host_values(input.material.clone()),
            dt: host_values(input.dt.clone()),
            particles: n_p,
        };
        let head = fused::Head::of(
            &self.head_a,
            self.rest_in.as_ref(),
            &self.head_b,
            &self.head_out,
        );
        let rest = input
            .rest
            .as_ref()
            .filter(|r| r.dims() == [b, n_p] && self.rest_in.is_some());
        // Without neighbourhoods a rest-shape model reads zero features (its first layer's
        // bias still counts), as the tensor path does.
        let rest_rows = |pos: &[f32]| {
            let rows = rest.and_then(|r| r.features_rows(pos));
            let zeros = || vec![0.0; b * n_p * REST_FEATURES];
            rows.or_else(|| self.rest_in.as_ref().map(|_| zeros()))
        };
        let latent = fields[0].dims()[2];
        let mut u = particles.inputs(&host_values(fields[0].clone()), latent, c);
        let width = latent + 2 * self.window + input.material.dims()[2] + 2;
        let (memory, state) = self.memory.step(
            crate::model::upload(u.clone(), [b * n_p, width], &device),
            state,
        );
        let memory = memory.map(host_values);
        let mut features = features.map(host_values);
        let mut frames = Vec::with_capacity(self.bundle);
        for (k, field) in fields.iter().enumerate().take(self.bundle) {
            if k > 0 {
                u = particles.inputs(&host_values(field.clone()), latent, c);
                features = rest_rows(&particles.pos);
            }
            let v = particles.advance(&head, &u, memory.as_deref(), features.as_deref(), c);
            frames.push(StepOutput {
                pos: crate::model::upload(particles.pos.clone(), [b, n_p, 2], &device),
                vel: crate::model::upload(v, [b, n_p, 2], &device),
                deformation: None,
            });
        }
        (frames, state)
    }

    /// The carried F of `input` (`[B, N, 4]`; the fit to its rest neighbourhoods, the
    /// identity without them, where it carries none of this shape) and the `[B, N, 1]` mask of
    /// particles with rest neighbours (the others carry only J).
    fn carried(&self, input: &StepInput<B>, [b, n_p]: [usize; 2]) -> (Tensor<B, 3>, Tensor<B, 3>) {
        let device = input.pos.device();
        let rest = input.rest.as_ref().filter(|r| r.dims() == [b, n_p]);
        let has = match rest {
            Some(r) => r.has_neighbours(),
            None => Tensor::zeros([b, n_p, 1], &device),
        };
        let f = match (input.deformation.clone(), rest) {
            (Some(f), _) if f.dims() == [b, n_p, 4] => f,
            (_, Some(r)) => r.fitted(input.pos.clone()),
            _ => rest::advect::identity([b, n_p], &device),
        };
        (f, has)
    }

    /// `[B, N, REST_FEATURES]`: the rest-shape features of positions `pos` from the
    /// neighbourhoods `rest` (0 without them), or `None` for a model without rest shape.
    fn rest_features(
        &self,
        rest: Option<&NeighbourTensors<B>>,
        pos: &Tensor<B, 3>,
    ) -> Option<Tensor<B, 3>> {
        self.rest_in.as_ref()?;
        let [b, n_p, _] = pos.dims();
        Some(match rest.filter(|r| r.dims() == [b, n_p]) {
            // Inference on the CPU: one host pass (the same values; no gradient needed).
            Some(r) if B::SEQUENTIAL_SCAN && !pos.is_require_grad() => r.features_host(pos.clone()),
            Some(r) => r.features(pos.clone()),
            None => Tensor::zeros([b, n_p, REST_FEATURES], &pos.device()),
        })
    }

    /// The U-Net's output `[B, n^2, K L (+ 2 K)]` as K latent fields of `[B, n^2, L]` and, for
    /// a grid update, K velocity-change fields of `[B, n^2, 2]`, each its own contiguous
    /// tensor: the CPU's one-pass gather reads only dense inputs (a strided view would take
    /// the composed path).
    fn fields(
        &self,
        out: Tensor<B, 3>,
        [b, cells]: [usize; 2],
    ) -> (Vec<Tensor<B, 3>>, Vec<Tensor<B, 3>>) {
        let k = self.bundle;
        let dv_channels = if self.update == Update::Free {
            0
        } else {
            2 * k
        };
        if k == 1 && dv_channels == 0 {
            return (vec![out], Vec::new());
        }
        let latent = (out.dims()[2] - dv_channels) / k;
        let part = |at: usize, width: usize| {
            let view = out.clone().narrow(2, at, width);
            view.reshape([b * cells * width]).reshape([b, cells, width])
        };
        let fields = (0..k).map(|i| part(i * latent, latent)).collect();
        let dv = match dv_channels {
            0 => Vec::new(),
            _ => (0..k).map(|i| part(k * latent + 2 * i, 2)).collect(),
        };
        (fields, dv)
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

    /// `[B, N, 2]`: the normalised velocity change of one frame: the head on `features`
    /// (`[B N, D]` rows; the rest-shape rows `rest`, `[B N, 6]`, through their own first
    /// layer), the gathered grid field `grid_dv` (`[B, N, 2]`), or their sum, as
    /// [`GridConfig::update`] says.
    fn head_out(
        &self,
        features: Tensor<B, 2>,
        rest: Option<Tensor<B, 2>>,
        grid_dv: Option<Tensor<B, 3>>,
        [b, n_p]: [usize; 2],
    ) -> Tensor<B, 3> {
        let head = (self.update != Update::Grid).then(|| {
            // Through the backend-ops dense layer, as every per-particle layer: its weight
            // gradient sums over all B N rows, which burn's `Linear` leaves to one matmul with
            // a handful of output tiles on a GPU (`bench train --arch grid --stages`, H100,
            // batch 64: 62 ms of a 110 ms step outside the timed stages).
            let mut pre = linear(&self.head_a, features);
            if let (Some(layer), Some(rest)) = (&self.rest_in, rest) {
                pre = pre + linear(layer, rest);
            }
            let h = silu(linear(&self.head_b, silu(pre)));
            linear(&self.head_out, h).reshape([b, n_p, 2])
        });
        match (head, grid_dv) {
            (Some(h), Some(g)) => h + g,
            (Some(h), None) => h,
            (None, Some(g)) => g,
            (None, None) => Tensor::zeros([b, n_p, 2], &self.head_out.weight.device()),
        }
    }

    /// One frame integrated from the normalised velocity change `dv` (`[B, N, 2]`), the
    /// normalised velocity window `vel` and positions `pos`, physical units: `dv = dv_mean +
    /// dv_scale * out`, `v' = v + dv`, the trapezoid `x' = x + dt (v + v') / 2`, clamped into
    /// the box MPM keeps its particles in.
    fn integrate(
        &self,
        dv: Tensor<B, 3>,
        vel: &Tensor<B, 3>,
        pos: Tensor<B, 3>,
        dt: Tensor<B, 3>,
    ) -> StepOutput<B> {
        let device = pos.device();
        let t = self.window;
        let dv = dv * pairs(self.dv_scale, 1, &device) + pairs(self.dv_mean, 1, &device);
        let v = vel.clone().narrow(2, 2 * (t - 1), 2) * pairs(self.vel_scale, 1, &device);
        let v_next = v.clone() + dv;
        let pos = pos + (v + v_next.clone()) * dt.mul_scalar(0.5);
        let dx = 1.0 / self.n as f32;
        let pos = pos.clamp(0.5 * dx, 1.0 - 1.5 * dx);
        StepOutput {
            pos,
            vel: v_next,
            deformation: None,
        }
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
