//! The grid architecture's training loss (see [`super`]): a batch of windows uploaded as
//! physical frames (mirrored where drawn so), and the loss of P network calls of K frames
//! each over it (after M push-forward calls without gradient or loss, when asked), from the
//! true frame `T - 1`, teacher-forced for the first calls, then on the
//! model's own predictions, the memory state carried through. Used by
//! [`super::GridTrainer`].
//!
//! Beside the velocity and position MSE, two structure terms ([`crate::model::grid::rest`]):
//! - strain (`strain_weight`): for every solid rest-neighbour pair (8 nearest of the same
//!   material in the scene's first frame), the squared difference of the pair's length
//!   `|x_i - x_j| / d0_i` (`d0_i` the particle's rest neighbour distance), prediction
//!   against truth, averaged over the pairs: a body torn apart or crumpled pays for it even
//!   where each particle's own error is small;
//! - volume (`volume_weight`): for every liquid particle with liquid neighbours in the
//!   sample's first input frame, the squared difference of its fitted `J = det F` relative to
//!   that frame (clamped to `[0, 2]`), prediction against truth: liquid pressed together
//!   (J < 1 where the truth keeps 1) pays for it. MPM's liquid keeps its volume through J (docs/mpm.md); the paper
//!   adds a density-map loss for the same reason (section 3).

use burn::module::Module;
use burn::tensor::backend::Backend;
use burn::tensor::{Distribution, Tensor};

use super::GridTrainOptions;
use crate::data::Batch;
use crate::model::grid::{
    mirror_rows, one_hot, GridConfig, GridModel, MemoryState, NeighbourTensors, Neighbourhood,
    StepInput,
};
use crate::model::upload;
use crate::ops::NetOps;

/// What [`sequence_loss`] reads of one batch, on the device, physical units.
pub(super) struct BatchTensors<B: Backend> {
    /// `[B, S, N, 4]`: the window's frames and its target frame.
    frames: Tensor<B, 4>,
    /// `[B, N, 4]`: material one-hot.
    material: Tensor<B, 3>,
    /// `[B]`: frame spacing.
    dt: Tensor<B, 1>,
    /// `[B, N, 2]`: positions in the trajectory's first frame (the reference positions).
    first_pos: Tensor<B, 3>,
    /// The solids' rest neighbourhoods in `first_pos`, when a model or the strain loss needs
    /// them, with the number of rest-neighbour pairs.
    rest: Option<(NeighbourTensors<B>, f32)>,
    /// The liquid's neighbourhoods in the first input frame, for the volume loss, with the
    /// number of liquid particles that have neighbours.
    liquid: Option<(NeighbourTensors<B>, f32)>,
}

/// Which neighbourhoods [`upload_batch`] builds.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Needs {
    /// The solids' rest neighbourhoods (rest-shape features, strain loss).
    pub rest: bool,
    /// The liquid's neighbourhoods in this frame of the window (volume loss): `T - 1`.
    pub liquid_at: Option<usize>,
    /// The model's material one-hot width ([`GridConfig::materials`]).
    pub materials: usize,
}

/// The tensors of a batch of windows built with the identity scaler (inputs then hold
/// physical values); the windows `w` with `mirror[w]` are mirrored ([`mirror_rows`]);
/// `needs` says which neighbourhoods to build and the model's one-hot width.
pub(super) fn upload_batch<B: Backend>(
    batch: Batch,
    mirror: &[bool],
    needs: Needs,
    device: &B::Device,
) -> BatchTensors<B> {
    let (b, t, n) = (batch.b, batch.t, batch.n);
    let mut frames = Vec::with_capacity(b * (t + 1) * n * 4);
    let mut first_pos = batch.first_pos;
    for w in 0..b {
        let start = frames.len();
        for k in 0..t {
            let start = ((w * t + k) * n) * 5;
            for row in batch.inputs[start..start + n * 5].chunks_exact(5) {
                frames.extend_from_slice(&row[..4]);
            }
        }
        frames.extend_from_slice(&batch.target_phys[w * n * 4..(w + 1) * n * 4]);
        if mirror.get(w).copied().unwrap_or(false) {
            mirror_rows(&mut frames[start..], 4);
            mirror_rows(&mut first_pos[w * n * 2..(w + 1) * n * 2], 2);
        }
    }
    let with_count = |nb: Neighbourhood, count: f32| (nb.upload(device), count.max(1.0));
    let rest = needs.rest.then(|| {
        let nb = Neighbourhood::build(&first_pos, &batch.material, [b, n], |m| m != 0);
        let pairs = nb.weight.iter().sum::<f32>();
        with_count(nb, pairs)
    });
    let liquid = needs.liquid_at.map(|k| {
        let pos: Vec<f32> = (0..b)
            .flat_map(|w| {
                let at = (w * (t + 1) + k) * n * 4;
                frames[at..at + n * 4]
                    .chunks_exact(4)
                    .flat_map(|r| [r[0], r[1]])
                    .collect::<Vec<f32>>()
            })
            .collect();
        let nb = Neighbourhood::build(&pos, &batch.material, [b, n], |m| m == 0);
        let particles = nb.inv_d0.iter().filter(|&&v| v > 0.0).count() as f32;
        with_count(nb, particles)
    });
    BatchTensors {
        frames: upload(frames, [b, t + 1, n, 4], device),
        material: one_hot(&batch.material, needs.materials, b, n, device),
        dt: upload(batch.dt, [b], device),
        first_pos: upload(first_pos, [b, n, 2], device),
        rest,
        liquid,
    }
}

/// The training loss of one batch (see the module doc).
pub(super) fn sequence_loss<B: NetOps>(
    model: &GridModel<B>,
    config: &GridConfig,
    opts: &GridTrainOptions,
    batch: BatchTensors<B>,
) -> Tensor<B, 1> {
    let BatchTensors {
        frames,
        material,
        dt,
        first_pos,
        rest,
        liquid,
    } = batch;
    let [b, _, n, _] = frames.dims();
    let t = config.window;
    let device = frames.device();
    let truth = |k: usize| frames.clone().narrow(1, k, 1).reshape([b, n, 4]);
    let dv_scale = Tensor::<B, 1>::from_floats(config.dv_scale, &device).reshape([1, 1, 2]);
    let noisy = |v: Tensor<B, 3>| {
        if opts.noise > 0.0 {
            let e = Tensor::random([b, n, 2], Distribution::Normal(0.0, 1.0), &device);
            v + e * dv_scale.clone().mul_scalar(opts.noise)
        } else {
            v
        }
    };
    let mut history: Vec<Tensor<B, 3>> = (0..t).map(|k| noisy(truth(k).narrow(2, 2, 2))).collect();
    let mut pos = truth(t - 1).narrow(2, 0, 2);
    let mut state = MemoryState::Empty;
    // The advected F ([`crate::model::grid::Deformation::Advect`]): fitted to the true frame
    // T - 1 by the first call, then carried.
    let mut deformation = None;
    let pos_scale = dv_scale.clone() * dt.clone().reshape([b, 1, 1]);
    let bundle = config.bundle.max(1);
    let mut total: Option<Tensor<B, 1>> = None;
    let warm = opts.pushforward;
    // The push-forward calls run on a copy of the model whose parameters track no gradient,
    // so they record no autodiff graph (detaching their outputs alone left every call's
    // activations held until the backward pass: 3x the GPU memory at 24 calls).
    let frozen = (warm > 0).then(|| model.clone().no_grad());
    for p in 0..opts.calls() {
        let vel = Tensor::cat(history[history.len() - t..].to_vec(), 2);
        let input = StepInput {
            pos,
            vel,
            material: material.clone(),
            dt: dt.clone(),
            reference: Some(first_pos.clone()),
            rest: rest.as_ref().map(|(r, _)| r.clone()),
            deformation: deformation.take(),
        };
        let net = match &frozen {
            Some(f) if p < warm => f,
            _ => model,
        };
        let (outs, next_state) = net.step_bundle(input, state);
        state = next_state;
        deformation = outs.last().and_then(|o| o.deformation.clone());
        let mut last_pos = None;
        for (k, out) in outs.into_iter().enumerate() {
            let target = truth(t + p * bundle + k);
            if p < warm {
                // Push-forward: the model's own frames, carried on without gradient or loss.
                last_pos = Some(out.pos.detach());
                history.push(out.vel.detach());
                continue;
            }
            let lv = ((out.vel.clone() - target.clone().narrow(2, 2, 2)) / dv_scale.clone())
                .powi_scalar(2)
                .mean();
            let lx = ((out.pos.clone() - target.clone().narrow(2, 0, 2)) / pos_scale.clone())
                .powi_scalar(2)
                .mean();
            let target_pos = target.clone().narrow(2, 0, 2);
            let step = lv
                + lx
                + structure_loss(opts, rest.as_ref(), liquid.as_ref(), &out.pos, &target_pos);
            total = Some(match total {
                Some(acc) => acc + step,
                None => step,
            });
            // The next call reads the truth (teacher steps) or the bundle's own frames.
            if p + 1 < opts.teacher {
                last_pos = Some(target.clone().narrow(2, 0, 2));
                history.push(noisy(target.narrow(2, 2, 2)));
            } else {
                last_pos = Some(out.pos);
                history.push(out.vel);
            }
        }
        pos = last_pos.expect("a bundle has at least one frame");
        if p < warm {
            state = state.detach();
            deformation = deformation.map(|f| f.detach());
        }
    }
    total
        .expect("at least one step")
        .div_scalar((opts.steps.max(1) * bundle) as f32)
}

/// The strain and volume terms of one predicted frame (see the module doc), weighted; 0
/// when both weights are 0.
fn structure_loss<B: Backend>(
    opts: &GridTrainOptions,
    rest: Option<&(NeighbourTensors<B>, f32)>,
    liquid: Option<&(NeighbourTensors<B>, f32)>,
    pred: &Tensor<B, 3>,
    truth: &Tensor<B, 3>,
) -> Tensor<B, 1> {
    let mut loss = Tensor::zeros([1], &pred.device());
    if let (Some((nb, pairs)), true) = (rest, opts.strain_weight > 0.0) {
        let stretch = |x: &Tensor<B, 3>| nb.lengths(nb.offsets(x.clone()));
        let err = (stretch(pred) - stretch(&truth.clone().detach())).powi_scalar(2);
        loss = loss + err.sum().div_scalar(*pairs).mul_scalar(opts.strain_weight);
    }
    if let (Some((nb, count)), true) = (liquid, opts.volume_weight > 0.0) {
        // J clamped to [0, 2]: a pair of particles sampled next to each other can make a
        // fitted J huge, and one such particle would outweigh the rest.
        let j = |x: &Tensor<B, 3>| nb.det(nb.offsets(x.clone())).clamp(0.0, 2.0);
        let err = (j(pred) - j(&truth.clone().detach())).powi_scalar(2);
        loss = loss + err.sum().div_scalar(*count).mul_scalar(opts.volume_weight);
    }
    loss
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::backend::{Autodiff, NdArray};

    /// Push-forward: the M calls without loss are the model's own rollout (the frozen copy
    /// predicts what the model does) and the loss covers the P calls after them only. So,
    /// from one sample, `(M + P) L(P = M + P) = M L(P = M) + P L(P, push-forward M)`.
    #[test]
    fn pushforward_loss_is_the_tail_of_the_rollout_loss() {
        type B = Autodiff<NdArray<f32>>;
        let (t, n, m, p) = (2, 30, 2, 2);
        let frames = t + m + p; // the inputs and the target
        let row = |f: usize, i: usize| {
            let (x0, y0) = (0.3 + 0.013 * (i % 6) as f32, 0.4 + 0.011 * (i / 6) as f32);
            let (vx, vy) = (0.2 + 0.01 * i as f32, -0.3 * f as f32 * 0.016);
            [
                x0 + vx * 0.016 * f as f32,
                y0 + vy * 0.016 * f as f32,
                vx,
                vy,
            ]
        };
        let batch = Batch {
            b: 1,
            t: frames - 1,
            n,
            inputs: (0..frames - 1)
                .flat_map(|f| (0..n).flat_map(move |i| [row(f, i).as_slice(), &[1.0]].concat()))
                .collect(),
            targets: vec![0.0; n * 4],
            last: vec![0.0; n * 4],
            target_phys: (0..n).flat_map(|i| row(frames - 1, i)).collect(),
            dt: vec![0.016],
            material: (0..n).map(|i| (i % 2) as u8).collect(),
            ids: vec![(0, 0)],
            first_pos: (0..n).flat_map(|i| [row(0, i)[0], row(0, i)[1]]).collect(),
        };
        let config = GridConfig::new(crate::model::grid::MemoryKind::MinGru)
            .with_grid(16)
            .with_levels(2)
            .with_unet_width(4)
            .with_latent(4)
            .with_hidden(4)
            .with_head_hidden(8)
            .with_dv_scale([0.1, 0.1])
            .with_head_zero_init(false);
        let device = Default::default();
        let model = config.init::<B>(&device);
        let loss = |steps: usize, pushforward: usize| {
            let opts = GridTrainOptions {
                steps,
                pushforward,
                ..GridTrainOptions::default()
            };
            let needs = Needs {
                materials: config.materials,
                ..Needs::default()
            };
            let tensors = upload_batch::<B>(batch.clone(), &[false], needs, &device);
            sequence_loss(&model, &config, &opts, tensors).into_scalar()
        };
        let (all, head, tail) = (loss(m + p, 0), loss(m, 0), loss(p, m));
        let (lhs, rhs) = ((m + p) as f32 * all, m as f32 * head + p as f32 * tail);
        assert!((lhs - rhs).abs() <= 1e-4 * lhs.abs(), "{lhs} against {rhs}");
        assert!(
            (tail - all).abs() > 1e-3 * all.abs(),
            "the tail's loss is its own: {tail}, {all}"
        );
    }

    /// `--mirror`: a flagged window's frames and reference positions are mirrored about x =
    /// 1/2 (x -> 1 - x, vx -> -vx, y and vy kept); an unflagged one is uploaded as it is.
    #[test]
    fn mirrored_windows_are_uploaded_mirrored() {
        let (b, t, n) = (2, 2, 3);
        let value = |i: usize| 0.01 * i as f32 + 0.1;
        let batch = Batch {
            b,
            t,
            n,
            inputs: (0..b * t * n * 5).map(value).collect(),
            targets: vec![0.0; b * n * 4],
            last: vec![0.0; b * n * 4],
            target_phys: (0..b * n * 4).map(|i| value(i + 7)).collect(),
            dt: vec![0.016; b],
            material: vec![0; b * n],
            ids: vec![(0, 0); b],
            first_pos: (0..b * n * 2).map(|i| value(i + 3)).collect(),
        };
        let device = Default::default();
        let none = Needs {
            materials: 4,
            ..Needs::default()
        };
        let plain = upload_batch::<NdArray<f32>>(batch.clone(), &[false, false], none, &device);
        let mirrored = upload_batch::<NdArray<f32>>(batch, &[false, true], none, &device);
        let host = |t: Tensor<NdArray<f32>, 4>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host(plain.frames), host(mirrored.frames));
        let per_window = (t + 1) * n * 4;
        assert_eq!(p[..per_window], m[..per_window], "window 0 is not flagged");
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(per_window) {
            let want = match i % 4 {
                0 => 1.0 - x,
                2 => -x,
                _ => *x,
            };
            assert_eq!(*y, want, "value {i}");
        }
        let host3 = |t: Tensor<NdArray<f32>, 3>| t.into_data().to_vec::<f32>().unwrap();
        let (p, m) = (host3(plain.first_pos), host3(mirrored.first_pos));
        assert_eq!(p[..n * 2], m[..n * 2]);
        for (i, (x, y)) in p.iter().zip(&m).enumerate().skip(n * 2) {
            assert_eq!(*y, if i % 2 == 0 { 1.0 - x } else { *x }, "reference {i}");
        }
    }
}
