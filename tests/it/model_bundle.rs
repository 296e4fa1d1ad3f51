//! Temporal bundling (`train --bundle K`, `GridModel::step_bundle`): a bundled model grown
//! from a single-frame one predicts the single-frame model's next frame first; its K frames
//! are integrated in order (each from the one before, by the trapezoid rule); a rollout of H
//! frames is ceil(H / K) calls, each from the last frame of the call before; and an old
//! `model.json` without `bundle` loads as K = 1.

use burn::backend::NdArray;
use burn::tensor::{Tensor, TensorData};
use minflow::model::grid::{one_hot, GridConfig, MemoryKind, MemoryState, StepInput};
use minflow::model::store::{self, NetConfig, Surrogate};
use minflow::train::grid::initial_grid_model;

use crate::model_support::{meta, surrogate, tiny_grid};

type B = NdArray<f32>;

fn config(memory: MemoryKind, bundle: usize) -> GridConfig {
    tiny_grid(memory).with_bundle(bundle)
}

/// `n` particles in the middle of the box (away from the walls, so no clamp acts) with
/// small velocities, materials cycling through the four.
fn frame(n: usize) -> (Vec<f32>, Vec<u8>) {
    let state = (0..n)
        .flat_map(|i| {
            let (a, b) = ((i * 37 % 101) as f32 / 101.0, (i * 53 % 97) as f32 / 97.0);
            [
                0.3 + 0.4 * a,
                0.3 + 0.4 * b,
                0.2 * (b - 0.5),
                0.2 * (a - 0.5),
            ]
        })
        .collect();
    (state, (0..n).map(|i| (i % 4) as u8).collect())
}

fn input(state: &[f32], material: &[u8]) -> StepInput<B> {
    let device = Default::default();
    let n = material.len();
    let frame = Tensor::<B, 3>::from_data(TensorData::new(state.to_vec(), [1, n, 4]), &device);
    let vel = frame.clone().narrow(2, 2, 2);
    StepInput {
        pos: frame.narrow(2, 0, 2),
        vel: Tensor::cat(vec![vel.clone(), vel], 2),
        material: one_hot(material, minflow::material::COUNT, 1, n, &device),
        dt: Tensor::from_data(TensorData::new(vec![0.016f32], [1]), &device),
        reference: None,
        rest: None,
        deformation: None,
    }
}

fn host(t: Tensor<B, 3>) -> Vec<f32> {
    t.into_data().to_vec().unwrap()
}

/// `with_bundle(3)` tiles the U-Net's output head: the first frame of the bundle reads the
/// same latent field at the same positions as the single-frame model, with the same memory
/// update, so it is the single-frame model's next frame (to rounding); the later frames
/// differ (they read the field where the particle went).
#[test]
fn a_grown_bundle_predicts_the_single_frame_model_first() {
    let device = Default::default();
    for memory in [MemoryKind::None, MemoryKind::MinGru] {
        let single = initial_grid_model::<B>(&config(memory, 1), 5, &device).unwrap();
        let bundled = single.clone().with_bundle(3);
        assert_eq!((single.bundle(), bundled.bundle()), (1, 3));
        let (state, material) = frame(300);
        let (one, _) = single.step(input(&state, &material), MemoryState::Empty);
        let (three, _) = bundled.step_bundle(input(&state, &material), MemoryState::Empty);
        assert_eq!(three.len(), 3);
        for (a, b) in [(one.pos, &three[0].pos), (one.vel, &three[0].vel)] {
            let (a, b) = (host(a), host(b.clone()));
            let diff = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f32::max);
            assert!(diff < 1e-6, "{memory:?}: first frame differs by {diff}");
        }
        assert_ne!(
            host(three[1].vel.clone()),
            host(three[0].vel.clone()),
            "the second frame reads the field where the particles went"
        );
    }
}

/// Each frame of a bundle is integrated from the one before it: `x_{k+1} = x_k + dt (v_k +
/// v_{k+1}) / 2` (the trapezoid rule of the single-frame step), starting at the input.
#[test]
fn the_k_frames_of_a_bundle_are_integrated_in_order() {
    let device = Default::default();
    let model = initial_grid_model::<B>(&config(MemoryKind::MinLstm, 4), 9, &device).unwrap();
    let (state, material) = frame(200);
    let (frames, _) = model.step_bundle(input(&state, &material), MemoryState::Empty);
    assert_eq!(frames.len(), 4);
    let mut prev: Vec<f32> = state.clone();
    for (k, f) in frames.iter().enumerate() {
        let (pos, vel) = (host(f.pos.clone()), host(f.vel.clone()));
        for i in 0..material.len() {
            for c in 0..2 {
                let want = prev[4 * i + c] + 0.016 * (prev[4 * i + 2 + c] + vel[2 * i + c]) / 2.0;
                let got = pos[2 * i + c];
                assert!(
                    (want - got).abs() < 1e-6,
                    "frame {k}, particle {i}: {got} vs {want}"
                );
            }
        }
        prev = (0..material.len())
            .flat_map(|i| [pos[2 * i], pos[2 * i + 1], vel[2 * i], vel[2 * i + 1]])
            .collect();
    }
}

/// A surrogate around an untrained minGRU grid model with K = 2 (seed 2).
fn bundled_surrogate() -> Surrogate<B> {
    surrogate(config(MemoryKind::MinGru, 2), 2)
}

/// The 5 frames a K = 2 model predicts from `seed1` (`[B, N, 4]`) and `state`, call by call:
/// the bundle of `seed1`, the bundle of its last frame, and the first frame of the next.
fn five_frames_by_hand(
    s: &Surrogate<B>,
    seed1: &[f32],
    (material, dt): (&[u8], &[f32]),
    state: store::State<B>,
) -> Vec<Vec<f32>> {
    let (a, state) = s.step_bundle(seed1, material, dt, state).unwrap();
    let (b, state) = s.step_bundle(&a[1], material, dt, state).unwrap();
    let (c, _) = s.step_bundle(&b[1], material, dt, state).unwrap();
    [a, b, vec![c[0].clone()]].concat()
}

/// A rollout of 5 frames with K = 2 is three calls: the bundle of the seed frame, the bundle
/// of its last frame, and the first frame of the bundle after that.
#[test]
fn a_rollout_chains_whole_bundles() {
    let s = bundled_surrogate();
    let (seed0, material) = frame(150);
    let (seed1, state) = s.step(&seed0, &material, &[0.016], s.init_state()).unwrap();
    let rollout = s
        .rollout(None, &[seed0.clone(), seed1.clone()], &material, 0.016, 5)
        .unwrap();
    assert_eq!(rollout.len(), 5);
    let by_hand = five_frames_by_hand(&s, &seed1, (&material, &[0.016]), state);
    assert_eq!(rollout, by_hand);
}

/// A batched rollout can keep its loop on the device (no projection, no mirror; the default
/// on a GPU, asked for here on the CPU): two scenes, K = 2, 5 frames give the frames
/// stepping call by call gives, whether the device holds every prediction until the end,
/// reads each call's back at once, or is off (0 bytes, the CPU's default).
#[test]
fn a_device_side_rollout_equals_the_call_by_call_loop() {
    let s = bundled_surrogate();
    let (a0, material) = frame(150);
    let b0: Vec<f32> = a0.iter().map(|v| v * 0.9 + 0.05).collect();
    let seed0 = [a0, b0].concat();
    let material = [material.clone(), material].concat();
    let dt = [0.016, 0.02];
    let (seed1, state) = s.step(&seed0, &material, &dt, s.init_state()).unwrap();
    let by_hand = five_frames_by_hand(&s, &seed1, (&material, &dt), state);
    let seed = [seed0.clone(), seed1.clone()];
    let mut s = s;
    for bytes in [store::FEEDBACK_BYTES, 1, 0] {
        s = s.with_feedback_bytes(bytes);
        let mut seen = Vec::new();
        s.rollout_batch(None, &seed, &material, &dt, 5, |i, f| seen.push((i, f)))
            .unwrap();
        assert_eq!(
            seen.iter().map(|(i, _)| *i).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        let frames: Vec<Vec<f32>> = seen.into_iter().map(|(_, f)| f).collect();
        assert_eq!(frames, by_hand, "feedback bytes {bytes}");
    }
}

/// A `model.json` written before bundling existed (no `bundle` field) reads as K = 1, and a
/// bundled model round-trips through a run folder.
#[test]
fn run_folders_keep_the_bundle() {
    let device = Default::default();
    let dir = crate::tmp::tempdir().unwrap();
    let config = config(MemoryKind::MinGru, 3);
    let model = initial_grid_model::<B>(&config, 1, &device).unwrap();
    store::save(dir.path(), &model, &meta(config)).unwrap();
    let loaded = Surrogate::<B>::load(dir.path(), &device).unwrap();
    assert_eq!(loaded.bundle(), 3);

    let text = std::fs::read_to_string(dir.path().join("model.json")).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    json.as_object_mut().unwrap().remove("bundle");
    let old = store::parse_meta(&json.to_string()).unwrap();
    let NetConfig::Grid(old) = old.net else {
        panic!("a grid model")
    };
    assert_eq!(old.bundle, 1);
}
