//! The per-particle part of a grid step on the CPU in host passes over the particles, where
//! nothing needs a gradient: after P2G and the U-Net (tensors, as everywhere), each frame k
//! of a call is
//! - one pass building every particle's input row `u = [G2P of latent field k, normalised
//!   velocities, material one-hot, position]` (its quadratic B-spline stencil taken on the
//!   spot, [`crate::ops::bspline_axis`]),
//! - one pass over blocks of [`BLOCK`] particles on the rayon pool: the head MLP on
//!   `[u, memory output]` (the rest-shape features through their own first layer) as small
//!   products on the cache-resident block, and SiLU, and
//! - the trapezoid integration with the clamp into MPM's box, writing the next positions,
//!   velocities and velocity window (a serial pass over the particles: a few flops each).
//!
//! The same arithmetic as [`super::GridModel::step_bundle`]'s tensor path (the module doc of
//! [`super`], steps 3 to 5) with the CPU backend's own product and SiLU
//! ([`crate::ops::host`]), equal to rounding (the products sum in another order); a test
//! holds the two to 1e-5. The tensor path makes about twenty tensors a frame here (stencil,
//! gather, concatenations, each layer's output, each integration term), each a fresh buffer
//! and a pass of its own: on 2 cores they cost the small bundled model more than its
//! products. The memory cell still runs as tensors, once per call, on the rows of the first
//! pass. Taken by [`super::GridModel::step_bundle`] on the CPU for inference and for CPU
//! training's push-forward calls, with the free head ([`super::Update::Free`]) and the
//! fitted or no rest shape (not the advected F), through `GridModel::host_frames` (here).

use burn::nn::Linear;
use burn::tensor::Tensor;
use rayon::prelude::*;

use crate::ops::{bspline_axis, host, host_values, NetOps};

use super::{GridModel, MemoryState, StepInput, StepOutput, REST_FEATURES};

/// Particles per task of the head pass: a block's rows of every layer stay in L1/L2.
pub const BLOCK: usize = 128;

impl<B: NetOps> GridModel<B> {
    /// [`GridModel::step_bundle`]'s frames from the U-Net's latent `fields` on, through the
    /// host passes of this file: the input rows, the memory (as tensors, on the first frame's
    /// rows), then per frame the head and the integration. `vel` is the normalised window;
    /// `features` the rest-shape features at the call's positions (`[B, N, 6]`, as P2G read
    /// them; `None` for a model without rest shape).
    pub(super) fn host_frames(
        &self,
        input: &StepInput<B>,
        vel: Tensor<B, 3>,
        fields: &[Tensor<B, 3>],
        features: Option<Tensor<B, 3>>,
        state: MemoryState<B>,
    ) -> (Vec<StepOutput<B>>, MemoryState<B>) {
        let [b, n_p, _] = input.pos.dims();
        let device = input.pos.device();
        let (dv_mean, dv_scale) = self.dv_affine();
        let c = Constants {
            n: self.n,
            window: self.window,
            vel_scale: self.vel_scale,
            dv_mean,
            dv_scale,
            bounds: self.integration_box(),
        };
        let mut particles = Particles {
            pos: host_values(input.pos.clone()),
            vel: host_values(vel),
            material: host_values(input.material.clone()),
            dt: host_values(input.dt.clone()),
            particles: n_p,
        };
        let head = Head::of(
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
}

/// A dense layer's weights on the host: `w` `[in, out]` row-major (burn's `Linear` layout),
/// `b` `[out]` (zeros without a bias).
struct Dense {
    w: Vec<f32>,
    b: Vec<f32>,
    inputs: usize,
    outputs: usize,
}

impl Dense {
    fn of<B: NetOps>(layer: &Linear<B>) -> Self {
        let [inputs, outputs] = layer.weight.dims();
        let w = host_values(layer.weight.val());
        let b = match &layer.bias {
            Some(b) => host_values(b.val()),
            None => vec![0.0; outputs],
        };
        Self {
            w,
            b,
            inputs,
            outputs,
        }
    }

    /// `dst = x @ w[rows at..at + width] (+ b)` for the `m` rows of `x` (`[m, width]`), or `+=`
    /// with `accumulate` (then without the bias).
    fn apply(&self, dst: &mut [f32], x: &[f32], [m, at, width]: [usize; 3], accumulate: bool) {
        let w = &self.w[at * self.outputs..(at + width) * self.outputs];
        host::matmul(dst, x, w, [m, width, self.outputs], accumulate);
        if !accumulate {
            for row in dst.chunks_exact_mut(self.outputs) {
                row.iter_mut().zip(&self.b).for_each(|(v, b)| *v += b);
            }
        }
    }
}

/// The head's weights on the host ([`super::GridModel`]'s `head_a`, `rest_in`, `head_b`,
/// `head_out`).
pub struct Head {
    a: Dense,
    rest: Option<Dense>,
    b: Dense,
    out: Dense,
}

impl Head {
    /// Host copies of the four layers (`rest` with rest-shape features).
    pub fn of<B: NetOps>(
        a: &Linear<B>,
        rest: Option<&Linear<B>>,
        b: &Linear<B>,
        out: &Linear<B>,
    ) -> Self {
        Self {
            a: Dense::of(a),
            rest: rest.map(Dense::of),
            b: Dense::of(b),
            out: Dense::of(out),
        }
    }
}

/// A call's particles on the host, physical units where not said otherwise; rows are the
/// `B N` particles, scene-major.
pub struct Particles {
    /// `[B N, 2]` positions.
    pub pos: Vec<f32>,
    /// `[B N, 2 T]` velocity window, normalised by `vel_scale`, oldest first.
    pub vel: Vec<f32>,
    /// `[B N, M]` material one-hot.
    pub material: Vec<f32>,
    /// `[B]` frame spacing.
    pub dt: Vec<f32>,
    /// Particles per scene, N.
    pub particles: usize,
}

/// The model's constants the pass reads.
#[derive(Clone, Copy)]
pub struct Constants {
    /// Grid size n.
    pub n: usize,
    /// Velocity frames per particle, T.
    pub window: usize,
    /// Velocity normalisation (domain units per time unit), per component.
    pub vel_scale: [f32; 2],
    /// Mean velocity change, physical, per component.
    pub dv_mean: [f32; 2],
    /// Velocity-change scale the head's output is in, per component.
    pub dv_scale: [f32; 2],
    /// The box `(lo, hi)` the integration clamps into ([`GridModel::integration_box`]).
    pub bounds: (f32, f32),
}

impl Particles {
    /// Rows of the particles' `B N` input rows `u` (`[B N, L + 2T + M + 2]`): the G2P of
    /// `field` (`[B, n^2, L]`, node `i n + j`) at each position, then the velocity window,
    /// the one-hot and the position.
    pub fn inputs(&self, field: &[f32], latent: usize, c: Constants) -> Vec<f32> {
        let (t2, m) = (2 * c.window, self.material.len() / self.rows().max(1));
        let width = latent + t2 + m + 2;
        let cells = c.n * c.n;
        let mut u = vec![0.0f32; self.rows() * width];
        u.par_chunks_mut(BLOCK * width)
            .enumerate()
            .for_each(|(block, rows)| {
                for (r, row) in rows.chunks_exact_mut(width).enumerate() {
                    let p = block * BLOCK + r;
                    let (x, y) = (self.pos[2 * p], self.pos[2 * p + 1]);
                    let ((bx, wx), (by, wy)) = (bspline_axis(x, c.n), bspline_axis(y, c.n));
                    let grid = &field[(p / self.particles) * cells * latent..];
                    let (gathered, own) = row.split_at_mut(latent);
                    for (i, wx) in wx.iter().enumerate() {
                        for (j, wy) in wy.iter().enumerate() {
                            let w = wx * wy;
                            let node = ((bx + i) * c.n + by + j) * latent;
                            gathered
                                .iter_mut()
                                .zip(&grid[node..node + latent])
                                .for_each(|(g, v)| *g += w * v);
                        }
                    }
                    own[..t2].copy_from_slice(&self.vel[p * t2..(p + 1) * t2]);
                    own[t2..t2 + m].copy_from_slice(&self.material[p * m..(p + 1) * m]);
                    own[t2 + m..].copy_from_slice(&self.pos[2 * p..2 * p + 2]);
                }
            });
        u
    }

    /// Particles `B N`.
    pub fn rows(&self) -> usize {
        self.pos.len() / 2
    }

    /// One frame: the head on the input rows `u` (from [`Particles::inputs`]), the memory
    /// output `memory` (`[B N, H]`) and the rest-shape features `rest` (`[B N, 6]`), and the
    /// integration; the particles move on to the next frame (positions, velocity window).
    /// Returns the `[B N, 2]` next velocities, physical.
    pub fn advance(
        &mut self,
        head: &Head,
        u: &[f32],
        memory: Option<&[f32]>,
        rest: Option<&[f32]>,
        c: Constants,
    ) -> Vec<f32> {
        let rows = self.rows();
        let width = u.len() / rows.max(1);
        let hidden = memory.map_or(0, |m| m.len() / rows.max(1));
        let mut dv = vec![0.0f32; rows * 2];
        dv.par_chunks_mut(BLOCK * 2)
            .enumerate()
            .for_each(|(block, out)| {
                let (at, m) = (block * BLOCK, out.len() / 2);
                let mut pre = vec![0.0f32; m * head.a.outputs];
                head.a.apply(
                    &mut pre,
                    &u[at * width..(at + m) * width],
                    [m, 0, width],
                    false,
                );
                if let Some(mem) = memory {
                    let x = &mem[at * hidden..(at + m) * hidden];
                    head.a.apply(&mut pre, x, [m, width, hidden], true);
                }
                if let (Some(layer), Some(r)) = (&head.rest, rest) {
                    let mut extra = vec![0.0f32; m * layer.outputs];
                    let k = layer.inputs;
                    layer.apply(&mut extra, &r[at * k..(at + m) * k], [m, 0, k], false);
                    pre.iter_mut().zip(&extra).for_each(|(p, e)| *p += e);
                }
                pre.iter_mut().for_each(|v| *v = host::silu(*v));
                let mut h = vec![0.0f32; m * head.b.outputs];
                head.b.apply(&mut h, &pre, [m, 0, head.a.outputs], false);
                h.iter_mut().for_each(|v| *v = host::silu(*v));
                head.out.apply(out, &h, [m, 0, head.b.outputs], false);
            });
        self.integrate(&dv, c)
    }

    /// `dv = dv_mean + dv_scale out`, `v' = v + dv`, `x' = x + dt (v + v') / 2` clamped into
    /// `c.bounds`, as `GridModel::integrate`; the window moves on by `v'`.
    fn integrate(&mut self, out: &[f32], c: Constants) -> Vec<f32> {
        let t2 = 2 * c.window;
        let (lo, hi) = c.bounds;
        let mut next = vec![0.0f32; out.len()];
        for (p, v_next) in next.chunks_exact_mut(2).enumerate() {
            let dt = self.dt[p / self.particles];
            let window = &mut self.vel[p * t2..(p + 1) * t2];
            for a in 0..2 {
                let dv = out[2 * p + a] * c.dv_scale[a] + c.dv_mean[a];
                let v = window[t2 - 2 + a] * c.vel_scale[a];
                v_next[a] = v + dv;
                let x = self.pos[2 * p + a] + (v + v_next[a]) * (dt * 0.5);
                self.pos[2 * p + a] = x.clamp(lo, hi);
            }
            window.copy_within(2.., 0);
            window[t2 - 2] = v_next[0] / c.vel_scale[0];
            window[t2 - 1] = v_next[1] / c.vel_scale[1];
        }
        next
    }
}
