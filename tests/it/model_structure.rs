//! The physical state and the structured update of the grid model (`train --rest-shape fit`,
//! `--update grid|grid+head`; `model::grid::rest`, `model::grid::grow`): a model grown with
//! them at zero weights predicts exactly what its parent did; the rest neighbourhoods are the
//! scene's state, built from its first frame and kept across a restart; the features see a
//! deformation of the body and not a rigid motion; with the grid update two particles at one
//! place get one velocity change; the features keep the model's independence of the
//! particle order; and an advected F (`--rest-shape advect`) is state the scene carries.

use burn::backend::NdArray;
use burn::tensor::{Tensor, TensorData};
use minflow::model::grid::{
    one_hot, Deformation, GridConfig, MemoryKind, MemoryState, Neighbourhood, StepInput, Update,
};
use minflow::model::store::{self, Surrogate};
use minflow::train::grid::initial_grid_model;

use crate::model_support::{meta, surrogate, tiny_grid};

type B = NdArray<f32>;

fn config(rest_shape: bool, update: Update) -> GridConfig {
    (tiny_grid(MemoryKind::MinGru))
        .with_rest_shape(rest_shape)
        .with_update(update)
}

/// A jelly block of 12 x 12 particles 0.01 apart (slightly jittered, so no two distances
/// tie) beside 60 liquid particles, all moving slowly.
fn scene() -> (Vec<f32>, Vec<u8>) {
    let jitter = |i: usize| 1e-3 * ((i * 7919 % 101) as f32 / 101.0 - 0.5);
    let mut state = Vec::new();
    let mut material = Vec::new();
    for i in 0..144 {
        let (a, b) = ((i % 12) as f32, (i / 12) as f32);
        state.extend([
            0.3 + 0.01 * a + jitter(i),
            0.4 + 0.01 * b + jitter(i + 1),
            0.1,
            -0.2,
        ]);
        material.push(1);
    }
    for i in 0..60 {
        let (a, b) = ((i % 10) as f32, (i / 10) as f32);
        state.extend([0.6 + 0.01 * a + jitter(i + 2), 0.3 + 0.01 * b, -0.1, 0.0]);
        material.push(0);
    }
    (state, material)
}

/// `state` (`[N, 4]` rows) stretched 1.2x along x about x = 0.355 (the block's middle).
fn stretched(state: &[f32]) -> Vec<f32> {
    state
        .chunks(4)
        .flat_map(|r| [0.355 + 1.2 * (r[0] - 0.355), r[1], r[2], r[3]])
        .collect()
}

fn max_abs_diff(a: &[Vec<f32>], b: &[Vec<f32>]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Growing the rest-shape features and then the grid+head update, both at zero weights,
/// leaves a trained model's rollout as it was.
#[test]
fn grown_rest_shape_and_grid_head_predict_what_the_parent_did() {
    let device = Default::default();
    let parent = initial_grid_model::<B>(&config(false, Update::Free), 5, &device).unwrap();
    let grown = parent
        .clone()
        .with_rest_shape()
        .with_update(Update::GridHead);
    assert!(grown.uses_rest_shape() && grown.update() == Update::GridHead);
    let parent = Surrogate::from_net(
        store::Net::Grid(parent),
        meta(config(false, Update::Free)),
        &device,
    );
    let grown = Surrogate::from_net(
        store::Net::Grid(grown),
        meta(config(true, Update::GridHead)),
        &device,
    );
    let (state, material) = scene();
    let a = parent
        .rollout(None, &[state.clone()], &material, 0.016, 4)
        .unwrap();
    let b = grown.rollout(None, &[state], &material, 0.016, 4).unwrap();
    assert!(max_abs_diff(&a, &b) < 1e-6, "{}", max_abs_diff(&a, &b));
}

/// A model with rest-shape features predicts another frame when the body it is given has
/// been stretched since its reference frame than when it has only been moved rigidly; a
/// rigid motion of the reference changes nothing the features see (the prediction differs
/// only through the velocities and positions themselves, which are the same here).
#[test]
fn rest_shape_features_see_a_stretch_not_a_rigid_motion() {
    let model = surrogate(config(true, Update::Free), 9);
    let (state, material) = scene();
    // The same current frame, with three references: itself, itself shifted, itself
    // squeezed by 20 % along x about the block's middle (so the current frame is stretched).
    let shifted: Vec<f32> = state
        .chunks(4)
        .flat_map(|r| [r[0] - 0.05, r[1] + 0.02, r[2], r[3]])
        .collect();
    let squeezed: Vec<f32> = state
        .chunks(4)
        .flat_map(|r| [0.355 + 0.8 * (r[0] - 0.355), r[1], r[2], r[3]])
        .collect();
    let roll = |first: &[f32]| {
        model
            .rollout(Some(first), &[state.clone()], &material, 0.016, 1)
            .unwrap()
    };
    let own = roll(&state);
    assert!(
        max_abs_diff(&own, &roll(&shifted)) < 1e-5,
        "a rigid shift of the reference"
    );
    assert!(
        max_abs_diff(&own, &roll(&squeezed)) > 1e-4,
        "a stretch since the reference"
    );
}

/// The grid update: every particle's velocity change is the G2P of one field, so two
/// particles at the same place (whatever their velocities and materials) get the same one.
#[test]
fn grid_update_gives_particles_at_one_place_one_velocity_change() {
    let model = surrogate(config(true, Update::Grid), 11);
    let (mut state, mut material) = scene();
    // A twin of particle 0 at its place, with another velocity and material.
    state.extend([state[0], state[1], -0.3, 0.4]);
    material.push(2);
    let out = model
        .rollout(None, &[state.clone()], &material, 0.016, 1)
        .unwrap();
    let n = material.len();
    let dv = |i: usize| {
        [
            out[0][4 * i + 2] - state[4 * i + 2],
            out[0][4 * i + 3] - state[4 * i + 3],
        ]
    };
    let (a, b) = (dv(0), dv(n - 1));
    assert!(
        (a[0] - b[0]).abs() < 1e-6 && (a[1] - b[1]).abs() < 1e-6,
        "{a:?} {b:?}"
    );
}

/// Permuting the particles permutes the predictions of a model with rest-shape features
/// and the grid+head update, over three steps.
#[test]
fn rest_shape_model_is_independent_of_particle_order() {
    let model = surrogate(config(true, Update::GridHead), 13);
    let (state, material) = scene();
    let n = material.len();
    let perm: Vec<usize> = (0..n).map(|i| (i * 37 + 11) % n).collect();
    let p_state: Vec<f32> = perm
        .iter()
        .flat_map(|&i| state[4 * i..4 * i + 4].to_vec())
        .collect();
    let p_material: Vec<u8> = perm.iter().map(|&i| material[i]).collect();
    let a = model.rollout(None, &[state], &material, 0.016, 3).unwrap();
    let b = model
        .rollout(None, &[p_state], &p_material, 0.016, 3)
        .unwrap();
    for (fa, fb) in a.iter().zip(&b) {
        for (k, &i) in perm.iter().enumerate() {
            for c in 0..4 {
                let (x, y) = (fa[4 * i + c], fb[4 * k + c]);
                assert!((x - y).abs() < 1e-5, "particle {i} value {c}: {x} vs {y}");
            }
        }
    }
}

/// The node keeps the rest neighbourhoods as the scene's state: a stream restarted over a
/// gap (`Surrogate::restart`) predicts from the same reference as before it, not from the
/// frame after the gap.
#[test]
fn restart_keeps_the_rest_state() {
    let model = surrogate(config(true, Update::Free), 17);
    let (state, material) = scene();
    let stretched = stretched(&state);
    let dt = [0.016f32];
    let (_, first) = model
        .step(&state, &material, &dt, model.init_state())
        .unwrap();
    let kept = model.restart(first);
    let (after_gap, _) = model.step(&stretched, &material, &dt, kept).unwrap();
    let (fresh, _) = model
        .step(&stretched, &material, &dt, model.init_state())
        .unwrap();
    let (given, _) = model
        .step(
            &stretched,
            &material,
            &dt,
            model.init_state_at(&state, 1).unwrap(),
        )
        .unwrap();
    assert_eq!(
        after_gap, given,
        "the kept reference is the stream's first frame"
    );
    let diff = after_gap
        .iter()
        .zip(&fresh)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(
        diff > 1e-5,
        "a fresh stream takes the stretched frame as its rest shape"
    );
}

/// `--rest-shape advect`: F is carried from step to step. A model without memory and with one
/// velocity frame carries nothing else a restart drops, so stepping a stretched frame after a
/// restart (F fitted to it: it sees the stretch) predicts otherwise than stepping it with the
/// F carried from the step before (advected by the predicted velocities: it does not);
/// with the fitted F (variant (b)) the two are equal, bit for bit.
#[test]
fn advected_deformation_is_carried_state() {
    let (state, material) = scene();
    let stretched = stretched(&state);
    let dt = [0.016f32];
    let mut diffs = Vec::new();
    for deformation in [Deformation::Fit, Deformation::Advect] {
        let mut c = config(true, Update::Free)
            .with_window(1)
            .with_deformation(deformation);
        c.memory = MemoryKind::None;
        let model = surrogate(c, 23);
        let (_, after_first) = model
            .step(&state, &material, &dt, model.init_state())
            .unwrap();
        let restarted = model.restart(after_first.clone());
        let (carried, _) = model.step(&stretched, &material, &dt, after_first).unwrap();
        let (refitted, _) = model.step(&stretched, &material, &dt, restarted).unwrap();
        diffs.push(max_abs_diff(&[carried], &[refitted]));
    }
    assert_eq!(diffs[0], 0.0, "the fitted F is no state");
    assert!(diffs[1] > 1e-5, "the advected F is: {}", diffs[1]);
}

/// The neighbourhoods of a batch of two scenes index each scene's own rows.
#[test]
fn neighbourhoods_stay_in_their_scene() {
    let (state, material) = scene();
    let n = material.len();
    let pos: Vec<f32> = state.chunks(4).flat_map(|r| [r[0], r[1]]).collect();
    let both = [pos.clone(), pos].concat();
    let nb = Neighbourhood::build(&both, &[material.clone(), material].concat(), [2, n], |m| {
        m != 0
    });
    for (row, near) in nb.index.chunks(8).enumerate() {
        let scene = row / n;
        assert!(
            near.iter().all(|&j| j as usize / n == scene),
            "row {row}: {near:?}"
        );
    }
}

/// CPU inference's per-particle host passes (`model/grid/host_pass.rs`: the input rows, the head,
/// the integration) predict what the tensor path predicts, to 1e-5, over a rollout that
/// carries the memory: minGRU, minLSTM and no memory, one frame and three frames a call,
/// with and without the rest-shape features, two scenes of different dt in one batch; and a
/// rest-shape model given no neighbourhoods.
#[test]
fn host_pass_predicts_what_the_tensor_path_does() {
    let device = Default::default();
    let (state, material) = scene();
    let moved: Vec<f32> = state
        .chunks(4)
        .flat_map(|r| [r[0] + 0.05, r[1] - 0.02, -r[2], r[3] + 0.1])
        .collect();
    let both = [material.clone(), material].concat();
    let seed = vec![
        [state.clone(), moved.clone()].concat(),
        [stretched(&state), moved].concat(),
    ];
    let first = seed[0].clone();
    for (memory, bundle, rest) in [
        (MemoryKind::MinGru, 1, true),
        (MemoryKind::MinGru, 3, true),
        (MemoryKind::MinLstm, 1, false),
        (MemoryKind::None, 2, false),
    ] {
        let mut c = config(rest, Update::Free).with_bundle(bundle);
        c.memory = memory;
        let model = initial_grid_model::<B>(&c, 31, &device).unwrap();
        let meta = meta(c);
        let run = |host_pass: bool| {
            let net = store::Net::Grid(model.clone().with_host_pass(host_pass));
            let s = Surrogate::from_net(net, meta.clone(), &device);
            let mut frames = Vec::new();
            s.rollout_batch(Some(&first), &seed, &both, &[0.016, 0.008], 6, |_, f| {
                frames.push(f)
            })
            .unwrap();
            frames
        };
        let (fused, tensor) = (run(true), run(false));
        let what = format!("{memory:?}, K = {bundle}, rest shape {rest}");
        assert_eq!(fused.len(), 6, "{what}");
        let diff = max_abs_diff(&fused, &tensor);
        assert!(diff < 1e-5, "{what}: {diff}");
        let moved = max_abs_diff(&fused[5..], &[seed[1].clone()]);
        assert!(moved > 1e-3, "{what}: the rollout moves ({moved})");
    }
    // A rest-shape model stepped without neighbourhoods reads zero features on both paths
    // (its rest layer's bias included).
    let c = config(true, Update::Free);
    let model = initial_grid_model::<B>(&c, 37, &device).unwrap();
    for n in [state.len() / 4, 60] {
        let step = |host_pass: bool| {
            let rows = &state[..n * 4];
            let frame =
                Tensor::<B, 3>::from_data(TensorData::new(rows.to_vec(), [1, n, 4]), &device);
            let vel = frame.clone().narrow(2, 2, 2);
            let input = StepInput {
                pos: frame.narrow(2, 0, 2),
                vel: Tensor::cat(vec![vel.clone(), vel], 2),
                material: one_hot(&both[..n], c.materials, 1, n, &device),
                dt: Tensor::from_data(TensorData::new(vec![0.016f32], [1]), &device),
                reference: None,
                rest: None,
                deformation: None,
            };
            let net = model.clone().with_host_pass(host_pass);
            let (out, _) = net.step(input, MemoryState::Empty);
            out.pos.into_data().to_vec::<f32>().unwrap()
        };
        let (fused, tensor) = (step(true), step(false));
        assert_eq!(fused.len(), n * 2);
        let diff = max_abs_diff(&[fused], &[tensor]);
        assert!(diff < 1e-5, "no neighbourhoods, N = {n}: {diff}");
    }
}
