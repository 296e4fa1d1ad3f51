//! One network call of [`GridModel`] (the module doc of [`super`], steps 1 to 5):
//! [`GridModel::network_call`] splats the particles onto the grid and runs the U-Net
//! ([`GridModel::latent_fields`]), then predicts the call's K frames either as tensors
//! ([`GridModel::tensor_frames`]: memory, G2P, head, integration) or, on the CPU where
//! nothing needs a gradient, through the host passes of [`super::host_pass`]. The head, the
//! integration, the carried F and the rest-shape features are this file's helpers.

use burn::tensor::Tensor;

use super::rest::{self, NeighbourTensors, REST_FEATURES};
use super::{cat_rows, pairs, transfer, GridModel, MemoryState, StepInput, StepOutput, Update};
use crate::model::roofline::{self, Part};
use crate::ops::{grid_channels, linear, silu, NetOps};

/// The U-Net's output for one call, `[B, n^2, K L (+ 2 K)]`: K latent fields of L channels
/// and, for a grid update, K velocity-change fields of 2 ([`Latent::field`], [`Latent::dv`]),
/// each cut out where it is read.
pub(super) struct Latent<B: burn::tensor::backend::Backend> {
    out: Tensor<B, 3>,
    /// L, a latent field's channels.
    width: usize,
    /// K, the fields of each kind.
    bundle: usize,
    /// Whether the velocity-change fields follow the latent ones.
    dv: bool,
}

impl<B: burn::tensor::backend::Backend> Latent<B> {
    /// Latent field k, `[B, n^2, L]`, to be gathered by frame k's particles.
    pub(super) fn field(&self, k: usize) -> Tensor<B, 3> {
        self.part(k * self.width, self.width)
    }

    /// Velocity-change field k, `[B, n^2, 2]` ([`Update::Grid`], [`Update::GridHead`]).
    fn dv(&self, k: usize) -> Option<Tensor<B, 3>> {
        (self.dv && k < self.bundle).then(|| self.part(self.bundle * self.width + 2 * k, 2))
    }

    /// Channels `at..at + width` as their own contiguous tensor: the CPU's one-pass gather
    /// reads only dense inputs (a strided view would take the composed path).
    fn part(&self, at: usize, width: usize) -> Tensor<B, 3> {
        let [b, cells, channels] = self.out.dims();
        if at == 0 && width == channels {
            return self.out.clone();
        }
        let view = self.out.clone().narrow(2, at, width);
        view.reshape([b * cells * width]).reshape([b, cells, width])
    }
}

/// A carried deformation gradient (`[B, N, 4]`) and the `[B, N, 1]` mask of particles
/// with rest neighbours ([`GridModel::carried`]).
type Carried<B> = (Tensor<B, 3>, Tensor<B, 3>);

impl<B: NetOps> GridModel<B> {
    /// One network call at the frame spacing `input.dt`: [`GridModel::step_bundle`] when the
    /// model takes no substeps, each of its substeps otherwise (`substeps.rs`).
    pub(super) fn network_call(
        &self,
        input: StepInput<B>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let [b, n_p, _] = input.pos.dims();
        let device = input.pos.device();
        let vel = input.vel.clone() / pairs(self.vel_scale, self.window, &device); // [B, N, 2T], normalised
                                                                                   // Variant (a): F carried, advected after every frame; its features replace the fit's.
        let carried = self.advects().then(|| self.carried(&input, [b, n_p]));
        roofline::mark::<B>(&device, Part::Input);
        // P2G: the separable dense transfers where the backend has no sparse ones.
        let s = transfer::stencil(input.pos.clone(), self.n, self.dense_transfers());
        let features = match &carried {
            Some((f, _)) => Some(rest::advect::features_of(f.clone())),
            None => self.rest_features(input.rest.as_ref(), &input.pos),
        };
        let latent = self.latent_fields(&input, &s, &vel, features.as_ref());
        if self.takes_host_pass(&input) {
            let fields: Vec<_> = (0..self.bundle).map(|k| latent.field(k)).collect();
            let frames = self.host_frames(&input, vel, &fields, features, state);
            roofline::mark::<B>(&device, Part::Head);
            return frames;
        }
        self.tensor_frames(&input, (s, vel), latent, features, carried, state)
    }

    /// P2G of the particles (stencil `s`, normalised velocity window `vel`, the rest-shape
    /// `features` where the model reads them) and the U-Net on the grid: the call's
    /// [`Latent`] fields.
    fn latent_fields(
        &self,
        input: &StepInput<B>,
        s: &transfer::Stencil<B>,
        vel: &Tensor<B, 3>,
        features: Option<&Tensor<B, 3>>,
    ) -> Latent<B> {
        let [b, n_p, _] = input.pos.dims();
        let t = self.window;
        let ones = Tensor::ones([b, n_p, 1], &input.pos.device());
        let mut values = vec![ones, vel.clone(), input.material.clone()];
        if self.reference {
            // Displacement from the reference position, in grid cells.
            let x0 = input.reference.clone().unwrap_or_else(|| input.pos.clone());
            values.push((input.pos.clone() - x0).mul_scalar(self.n as f32));
        }
        if let Some(r) = features {
            values.push(r.clone());
        }
        // [B, n^2, 1 + 2T + M (+ 2) (+ 6)], then the channels [m / 4, velocities and materials
        // per mass, walls, displacement per mass, rest shape per mass]: the grown channels
        // after the walls, so a model grown by `with_reference` / `with_rest_shape` keeps its
        // channel order.
        let values = cat_rows(values);
        let (c, cells) = (values.dims()[2], self.n * self.n);
        // The stencil (positions in, 9 nodes and weights out) and the splat.
        let (rows, nodes) = ((b * n_p) as f64, (b * cells) as f64);
        roofline::count(
            18.0 * rows * c as f64,
            4.0 * (rows * (2.0 + 36.0 + c as f64) + nodes * c as f64),
        );
        let splat = transfer::p2g(s, values);
        let grid = grid_channels(splat, self.n, 2 * t + input.material.dims()[2]); // [B, n^2, C]
        let c = grid.dims()[2];
        let grid = grid.reshape([b, self.n, self.n, c]); // channels last, node (i, j) at [i, j]
        roofline::mark::<B>(&input.pos.device(), Part::P2g);

        // U-Net: K latent fields of L channels each (and K velocity-change fields).
        roofline::count_unet::<B, _>(&self.unet, b, self.n);
        let out = self.unet.forward(grid);
        let channels = out.dims()[3];
        let out = out.reshape([b, cells, channels]); // [B, n^2, K L (+ 2 K)]
        roofline::mark::<B>(&input.pos.device(), Part::UNet);
        let dv = self.update != Update::Free;
        let width = (channels - if dv { 2 * self.bundle } else { 0 }) / self.bundle;
        Latent {
            out,
            width,
            bundle: self.bundle,
            dv,
        }
    }

    /// [`GridModel::step_bundle`]'s frames from the U-Net's `latent` fields on, as tensors:
    /// the memory once per call on the first frame's inputs, then per frame G2P at the
    /// particles' current positions, the head and the integration (the carried F advected
    /// after each). `s` and `vel` are the call's stencil and normalised velocity window,
    /// `features` the rest-shape features at the call's positions.
    fn tensor_frames(
        &self,
        input: &StepInput<B>,
        (mut s, mut vel): (transfer::Stencil<B>, Tensor<B, 3>),
        latent: Latent<B>,
        mut features: Option<Tensor<B, 3>>,
        mut carried: Option<Carried<B>>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let [b, n_p, _] = input.pos.dims();
        let (t, device) = (self.window, input.pos.device());
        let field = |k: usize| latent.field(k);
        // Memory, once per call, on the first frame's inputs (not in the output of the grid
        // update: left as it is).
        let gathered = gather(&s, field(0));
        roofline::mark::<B>(&device, Part::G2p);
        let u = self.particle_inputs(gathered, &vel, &input.material, &input.pos);
        // Message passing on the call's input positions, its output added to every frame's rows.
        let messages =
            (self.interaction.as_ref()).map(|i| i.forward(u.clone(), &i.graph(&input.pos)));
        let mut u = messaged(u, &messages);
        let (memory, state) = self.memory_step(&u, state);
        roofline::mark::<B>(&device, Part::Memory);
        if carried.is_none() && features.is_none() && messages.is_none() {
            if let Some(frames) = self.fused_frames(input, &vel, &latent, memory.as_ref()) {
                roofline::mark::<B>(&device, Part::Head);
                return (frames, state);
            }
        }
        let dt = input.dt.clone().reshape([b, 1, 1]);
        let mut pos = input.pos.clone();
        let mut frames = Vec::with_capacity(self.bundle);
        for k in 0..self.bundle {
            if k > 0 {
                s = transfer::stencil(pos.clone(), self.n, self.dense_transfers());
                u = self.particle_inputs(gather(&s, field(k)), &vel, &input.material, &pos);
                u = messaged(u, &messages);
                features = match &carried {
                    Some((f, _)) => Some(rest::advect::features_of(f.clone())),
                    None => self.rest_features(input.rest.as_ref(), &pos),
                };
            }
            let head_in = match &memory {
                Some(m) => Tensor::cat(vec![u.clone(), m.clone()], 1),
                None => u.clone(),
            };
            let grid_dv = latent.dv(k).map(|f| transfer::g2p(&s, f));
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
        roofline::mark::<B>(&device, Part::Head);
        (frames, state)
    }

    /// The memory's step on the particle rows `u` (`[B N, D]`): its output (`[B N, H]`; `None`
    /// for the grid update, whose output it does not reach) and the new state.
    fn memory_step(
        &self,
        u: &Tensor<B, 2>,
        state: MemoryState<B>,
    ) -> (Option<Tensor<B, 2>>, MemoryState<B>) {
        let (memory, state) = match self.update {
            Update::Grid => (None, state),
            _ => self.memory.step(u.clone(), state),
        };
        if let Some(m) = &memory {
            // minGRU: the gate and the candidate from the input, then h' = (1 - z) h + z h~.
            let [rows, hidden] = m.dims();
            roofline::count_dense(rows, u.dims()[1], 2 * hidden);
            roofline::count(4.0 * (rows * hidden) as f64, 12.0 * (rows * hidden) as f64);
        }
        (memory, state)
    }

    /// [`GridModel::tensor_frames`]'s frames in one operation, [`NetOps::particle_frames`],
    /// where the backend has it and the per-particle part is the plain one: the free head
    /// (no rest-shape layer, no advected F), sparse transfers, nothing that needs a gradient;
    /// `None` otherwise. `vel` is the call's normalised velocity window, `memory` the
    /// memory's output (`[B N, H]`).
    fn fused_frames(
        &self,
        input: &StepInput<B>,
        vel: &Tensor<B, 3>,
        latent: &Latent<B>,
        memory: Option<&Tensor<B, 2>>,
    ) -> Option<Vec<StepOutput<B>>> {
        let plain = self.update == Update::Free && self.rest_in.is_none() && !self.advects();
        let grad = input.pos.is_require_grad()
            || vel.is_require_grad()
            || self.head_a.weight.val().is_require_grad();
        if !plain || grad || self.dense_transfers() {
            return None;
        }
        let [b, n_p, _] = input.pos.dims();
        let layer = |l: &burn::nn::Linear<B>| {
            let bias = l.bias.as_ref()?.val().into_primitive().tensor();
            Some((l.weight.val().into_primitive().tensor(), bias))
        };
        let layers = [&self.head_a, &self.head_b, &self.head_out];
        let [a, h, o] = layers.map(layer);
        let (dv_mean, dv_scale) = self.dv_affine();
        let frames = crate::ops::ParticleFrames {
            fields: latent.out.clone().into_primitive().tensor(),
            latent: latent.width,
            bundle: self.bundle,
            n: self.n,
            memory: memory.map(|m| m.clone().into_primitive().tensor()),
            vel: vel.clone().into_primitive().tensor(),
            material: input.material.clone().into_primitive().tensor(),
            pos: input.pos.clone().into_primitive().tensor(),
            dt: input.dt.clone().into_primitive().tensor(),
            layers: [a?, h?, o?],
            vel_scale: self.vel_scale,
            dv_scale,
            dv_mean,
            bounds: self.integration_box(),
        };
        let out = B::particle_frames(frames)?;
        if roofline::on() {
            let rows = (b * n_p * self.bundle) as f64;
            let [w_a, w_b, w_o] = layers.map(|l| l.weight.dims());
            let macs = w_a[0] * w_a[1] + w_b[0] * w_b[1] + w_o[0] * w_o[1] + 9 * latent.width;
            // Each field read once, each particle's inputs once, each frame written once.
            let field = latent.out.dims().iter().product::<usize>() as f64;
            let own = (b * n_p * (w_a[0] - latent.width)) as f64;
            roofline::count(2.0 * rows * macs as f64, 4.0 * (field + own + 4.0 * rows));
        }
        let out: Tensor<B, 3> = Tensor::from_primitive(burn::tensor::TensorPrimitive::Float(out));
        let frame = |k: usize| {
            let f = out.clone().narrow(0, k * b, b);
            StepOutput {
                pos: f.clone().narrow(2, 0, 2),
                vel: f.narrow(2, 2, 2),
                deformation: None,
            }
        };
        Some((0..self.bundle).map(frame).collect())
    }

    /// Whether this call's per-particle part runs as host passes ([`super::host_pass`]): on the CPU
    /// where nothing needs a gradient (inference, and the push-forward calls of CPU
    /// training), with the free head, no advected F and no message passing.
    fn takes_host_pass(&self, input: &StepInput<B>) -> bool {
        // A call with the transfers fixed dense runs as tensors, so that it uses them.
        if self.dense_transfers == Some(true) {
            return false;
        }
        self.host_pass
            && B::ON_HOST
            && self.update == Update::Free
            && !self.advects()
            && self.interaction.is_none()
            && !input.pos.is_require_grad()
            && !input.vel.is_require_grad()
            && !self.head_a.weight.val().is_require_grad()
            && !self.head_out.weight.val().is_require_grad()
    }

    /// Whether this call's transfers take the separable dense form: as fixed by
    /// [`GridModel::with_dense_transfers`], else the backend's [`NetOps::dense_stencil`].
    fn dense_transfers(&self) -> bool {
        self.dense_transfers.unwrap_or_else(B::dense_stencil)
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
            Some(r) if B::ON_HOST && !pos.is_require_grad() => r.features_host(pos.clone()),
            Some(r) => r.features(pos.clone()),
            None => Tensor::zeros([b, n_p, REST_FEATURES], &pos.device()),
        })
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
            if roofline::on() {
                let layers = [&self.head_a, &self.head_b, &self.head_out];
                for layer in layers.into_iter().chain(self.rest_in.as_ref()) {
                    let [i, o] = layer.weight.dims();
                    roofline::count_dense(b * n_p, i, o);
                }
            }
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
    /// the box MPM keeps its particles in ([`GridModel::integration_box`]).
    fn integrate(
        &self,
        dv: Tensor<B, 3>,
        vel: &Tensor<B, 3>,
        pos: Tensor<B, 3>,
        dt: Tensor<B, 3>,
    ) -> StepOutput<B> {
        let device = pos.device();
        let t = self.window;
        let (dv_mean, dv_scale) = self.dv_affine();
        let dv = dv * pairs(dv_scale, 1, &device) + pairs(dv_mean, 1, &device);
        let v = vel.clone().narrow(2, 2 * (t - 1), 2) * pairs(self.vel_scale, 1, &device);
        let v_next = v.clone() + dv;
        let pos = pos + (v + v_next.clone()) * dt.mul_scalar(0.5);
        let (lo, hi) = self.integration_box();
        let pos = pos.clamp(lo, hi);
        StepOutput {
            pos,
            vel: v_next,
            deformation: None,
        }
    }
}

/// The particle rows `u` (`[B N, D]`) plus the call's `messages` (the same shape) where the
/// model passes any ([`super::GridConfig::interaction`]).
fn messaged<B: NetOps>(u: Tensor<B, 2>, messages: &Option<Tensor<B, 2>>) -> Tensor<B, 2> {
    match messages {
        Some(m) => u + m.clone(),
        None => u,
    }
}

/// [`transfer::g2p`] of `field` (`[B, n^2, L]`) at the stencil `s`, its needs counted for
/// the roofline: 9 multiply-adds a channel a particle; the field, the stencil and the
/// gathered rows read or written once.
fn gather<B: NetOps>(s: &transfer::Stencil<B>, field: Tensor<B, 3>) -> Tensor<B, 3> {
    if roofline::on() {
        let [b, cells, l] = field.dims();
        let rows = (b * s.particles) as f64;
        let l = l as f64;
        roofline::count(
            18.0 * rows * l,
            4.0 * ((b * cells) as f64 * l + rows * (36.0 + l)),
        );
    }
    transfer::g2p(s, field)
}
