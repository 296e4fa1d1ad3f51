//! Issue 40, one node and many live streams: `Surrogate::step_scenes` (several scenes' states
//! stacked into one network call and split back) predicts what stepping each scene alone
//! does, within 1e-5 on the CPU, for single-frame and bundled models, mirror ensembles and
//! scenes of different particle counts (one call per count), also when each batch's
//! predictions are taken only after the next batch's call (`Surrogate::submit_scenes`, the
//! node's pipelined calls); a node batching up to 8 scenes a call publishes the predictions
//! of a node stepping one scene a call, pipelined or not; and in closed loop
//! under load (long scenes arriving faster than they are rolled out, an idle timeout shorter
//! than the rollouts) every scene gets exactly one rollout; warming up the batch sizes first
//! (`--warm-up-batches`, live calls and closed loop) changes no prediction.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use burn::backend::NdArray;
use minflow::model::store::{Predict, SceneStep, State, Submitted, Surrogate};
use minflow::msgs::{ParticleFrame, Time};
use minflow::node::surrogate::state_rows;
use minflow::transport::{self, Sample, Transport};

use crate::transport_support::*;

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The frames of the bundled bag `name`.
fn bag(name: &str) -> Vec<ParticleFrame> {
    raw_messages(
        &repo(&format!("bags/{name}.mcap")),
        Some(minflow::bag::FRAMES_TOPIC),
    )
    .iter()
    .map(|b| minflow::msgs::decode(b).unwrap())
    .collect()
}

/// Frame `index` of scene `scene`: the `base` frames looped, the first `n` particles.
fn frame_of(base: &[ParticleFrame], scene: &str, n: usize, index: u32) -> ParticleFrame {
    let mut f = base[index as usize % base.len()].clone();
    f.scene = scene.to_owned();
    f.frame_index = index;
    f.header.stamp = Time::from_nanos((f64::from(index) * f64::from(f.dt) * 1e9) as u64);
    f.position.truncate(2 * n);
    f.velocity.truncate(2 * n);
    f.material.truncate(n);
    f
}

/// Four scenes of 6 frames: three bags of 2,500 particles and one of 1,000.
fn four_scenes() -> Vec<Vec<ParticleFrame>> {
    let names = [
        "multi_rope+snow_001",
        "fluid_circle_000",
        "multi_jelly+liquid_002",
    ];
    let mut scenes: Vec<Vec<ParticleFrame>> = names
        .iter()
        .map(|n| (0..6).map(|i| frame_of(&bag(n), n, 2500, i)).collect())
        .collect();
    let small = bag("multi_liquid+snow_000");
    scenes.push((0..6).map(|i| frame_of(&small, "small", 1000, i)).collect());
    scenes
}

/// A copy of the shipped model `name` that advects its rest-shape features' F
/// (`"deformation": "Advect"` in its model.json): the same weights, another physical state.
fn advected(name: &str) -> tempfile::TempDir {
    let dir = crate::tmp::tempdir().unwrap();
    let from = repo(&format!("models/{name}"));
    std::fs::copy(from.join("model.mpk"), dir.path().join("model.mpk")).unwrap();
    let mut meta = crate::json(&from.join("model.json"));
    meta["deformation"] = "Advect".into();
    std::fs::write(dir.path().join("model.json"), meta.to_string()).unwrap();
    dir
}

fn worst(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// Streams that restart (a gap: `Surrogate::restart`) before frame 3, scenes 1 and 3.
const RESTARTS: (usize, [usize; 2]) = (3, [1, 3]);

/// Batched steps equal steps one scene a call, with two streams restarting midway: the
/// restarted scenes still share their call with the continuing ones (one call per particle
/// count every frame), and each predicts what a scene restarted alone does.
#[test]
fn batched_steps_equal_steps_one_scene_at_a_time() {
    let scenes = four_scenes();
    let advected = advected("all-grid-mingru-small-k4-rest");
    for (model, mirror) in [
        ("all-grid-mingru-small", false),
        ("all-grid-mingru-small", true),
        ("all-grid-mingru-small-k4", false),
        // Rest neighbourhoods stack and split with the other per-scene state.
        ("all-grid-mingru-small-k4-rest", false),
        ("all-grid-mingru-small-k4-rest", true),
        // So does the advected deformation gradient.
        ("advected", false),
        ("advected", true),
        // Calls padded to a power of two (copies of the last scene, dropped).
        ("padded", false),
    ] {
        let dir = match model {
            "advected" => advected.path().to_path_buf(),
            "padded" => repo("models/all-grid-mingru-small"),
            _ => repo(&format!("models/{model}")),
        };
        let s = Surrogate::<NdArray<f32>>::load(&dir, &Default::default())
            .unwrap()
            .with_mirror(mirror)
            .with_padded_batches(model == "padded");
        let whole = s.bundle() > 1;
        // Alone: each scene its own calls.
        let mut alone = Vec::new();
        for frames in &scenes {
            let mut state = s.init_state();
            let mut outs = Vec::new();
            for (i, f) in frames.iter().enumerate() {
                if i == RESTARTS.0 && RESTARTS.1.contains(&alone.len()) {
                    state = s.restart(state);
                }
                let (out, st) = s
                    .step_bundle(&state_rows(f), &f.material, &[f.dt], state)
                    .unwrap();
                let out = if whole { out } else { out[..1].to_vec() };
                outs.push(out);
                state = st;
            }
            alone.push(outs);
        }
        // Every scene's frame i as one batch (the restarted streams restarted first).
        let steps_at = |i: usize, states: &mut [Option<State<NdArray<f32>>>]| {
            scenes
                .iter()
                .zip(states.iter_mut())
                .enumerate()
                .map(|(k, (frames, st))| {
                    let mut state = st.take().unwrap();
                    if i == RESTARTS.0 && RESTARTS.1.contains(&k) {
                        state = s.restart(state);
                    }
                    SceneStep {
                        rows: state_rows(&frames[i]),
                        material: &frames[i].material,
                        dt: frames[i].dt,
                        state,
                    }
                })
                .collect::<Vec<_>>()
        };
        // Batched: every scene's frame i in one step_scenes.
        let mut states: Vec<_> = scenes.iter().map(|_| Some(s.init_state())).collect();
        for i in 0..6 {
            let steps = steps_at(i, &mut states);
            let predict = if whole {
                Predict::Bundle
            } else {
                Predict::Next
            };
            let batch = s.step_scenes(steps, predict);
            assert_eq!(batch.calls, [1, 3], "{model}: one call per particle count");
            for (k, result) in batch.results.into_iter().enumerate() {
                let (out, st) = result.unwrap();
                let restarted = i >= RESTARTS.0 && RESTARTS.1.contains(&k);
                assert_eq!(
                    st.frames,
                    if restarted { i + 1 - RESTARTS.0 } else { i + 1 }
                );
                assert_eq!(out.len(), alone[k][i].len());
                for (got, want) in out.iter().zip(&alone[k][i]) {
                    let w = worst(got, want);
                    assert!(
                        w <= 1e-5,
                        "{model} mirror {mirror}: scene {k} frame {i}: {w}"
                    );
                }
                states[k] = Some(st);
            }
        }
        if whole {
            continue;
        }
        // Pipelined, as the node on a GPU (`--pipeline`): batch i's predictions are taken
        // and projected onto the constraints only after batch i + 1's call is recorded from
        // the states batch i left; the same frames.
        let mut states: Vec<_> = scenes.iter().map(|_| Some(s.init_state())).collect();
        let check = |i: usize, call: Submitted<NdArray<f32>>| {
            for (k, got) in call.finish(&s).frames.into_iter().enumerate() {
                let w = worst(&got.unwrap()[0], &alone[k][i][0]);
                assert!(
                    w <= 1e-5,
                    "{model} mirror {mirror}, pipelined: scene {k} frame {i}: {w}"
                );
            }
        };
        let mut flying = None;
        for i in 0..6 {
            let mut call = s.submit_scenes(steps_at(i, &mut states), Predict::Next);
            assert_eq!(call.calls, [1, 3], "{model}: one call per particle count");
            for (k, st) in std::mem::take(&mut call.states).into_iter().enumerate() {
                states[k] = Some(st.unwrap());
            }
            if let Some((before, call)) = flying.replace((i, call)) {
                check(before, call);
            }
        }
        let (last, call) = flying.unwrap();
        check(last, call);
    }
}

/// A stream restarted after a gap (`Surrogate::restart`) predicts what a fresh stream started
/// on the same frame does, for a model that reads no reference positions and no rest shape
/// (`all-grid-mingru-small`): alone, and as a row of a batch beside streams that go on (in
/// the same call).
#[test]
fn a_restarted_stream_predicts_what_a_fresh_one_does() {
    let scenes = four_scenes();
    let dir = repo("models/all-grid-mingru-small");
    let s = Surrogate::<NdArray<f32>>::load(&dir, &Default::default()).unwrap();
    let step =
        |f: &ParticleFrame, state| s.step(&state_rows(f), &f.material, &[f.dt], state).unwrap();
    // Fresh: scene 0 from frame 3.
    let (want3, state) = step(&scenes[0][3], s.init_state());
    let (want4, _) = step(&scenes[0][4], state);
    // Alone: frames 0-2, a restart, frames 3 and 4.
    let mut state = s.init_state();
    for f in &scenes[0][..3] {
        state = step(f, state).1;
    }
    let (got3, state) = step(&scenes[0][3], s.restart(state));
    let (got4, _) = step(&scenes[0][4], state);
    assert!(worst(&got3, &want3) <= 1e-5, "alone, frame 3");
    assert!(worst(&got4, &want4) <= 1e-5, "alone, frame 4");
    // Batched: scenes 0-2 together, scene 0 restarted before frame 3.
    let mut states: Vec<_> = (0..3).map(|_| Some(s.init_state())).collect();
    let mut got = Vec::new();
    for i in 0..5 {
        let steps = (0..3)
            .map(|k| {
                let mut state = states[k].take().unwrap();
                if i == 3 && k == 0 {
                    state = s.restart(state);
                }
                SceneStep {
                    rows: state_rows(&scenes[k][i]),
                    material: &scenes[k][i].material,
                    dt: scenes[k][i].dt,
                    state,
                }
            })
            .collect();
        let batch = s.step_scenes(steps, Predict::Next);
        assert_eq!(batch.calls, [3], "frame {i}: one call");
        for (k, result) in batch.results.into_iter().enumerate() {
            let (out, state) = result.unwrap();
            if k == 0 && i >= 3 {
                got.push(out[0].clone());
            }
            states[k] = Some(state);
        }
    }
    assert!(worst(&got[0], &want3) <= 1e-5, "batched, frame 3");
    assert!(worst(&got[1], &want4) <= 1e-5, "batched, frame 4");
}

/// A `minflow node` of the shipped small model on `input` -> `output` with `extra` flags.
fn node(input: &str, output: &str, extra: &[&str]) -> Node {
    let model = repo("models/all-grid-mingru-small");
    let mut args = vec![
        "node",
        "--model",
        model.to_str().unwrap(),
        "--in",
        input,
        "--out",
        output,
        "--status",
        "none",
        "--queue-depth",
        "1024",
    ];
    args.extend_from_slice(extra);
    Node::spawn("node", &args)
}

/// Collects frames from `rx` until `done` says so or `timeout` passes.
fn collect(
    rx: &Receiver<Sample>,
    timeout: Duration,
    mut done: impl FnMut(&[ParticleFrame]) -> bool,
) -> Vec<ParticleFrame> {
    let deadline = Instant::now() + timeout;
    let mut got = Vec::new();
    while Instant::now() < deadline && !done(&got) {
        if let Ok(s) = rx.recv_timeout(Duration::from_millis(50)) {
            got.push(s.decode().unwrap());
        }
    }
    got
}

#[test]
fn a_batching_node_publishes_what_a_node_of_one_scene_a_call_does() {
    let input = unique_topic("batch_in");
    let (out_one, out_many) = (unique_topic("batch_one"), unique_topic("batch_many"));
    let one = node(&input, &out_one, &["--max-batch", "1"]);
    // Pipelined (each call's frames published after the next call is recorded), as on a GPU.
    let many = node(
        &input,
        &out_many,
        &[
            "--max-batch",
            "8",
            "--max-batch-delay",
            "20",
            "--pipeline",
            "true",
            "--pad-batches",
            "true",
            "--warm-up-batches",
            "true",
        ],
    );
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx1, rx1) = channel();
    let (tx8, rx8) = channel();
    let _s1 = session.subscribe(&out_one, tx1).unwrap();
    let _s8 = session.subscribe(&out_many, tx8).unwrap();
    let mut publisher = session.publisher(&input).unwrap();
    assert!(
        transport::wait_for_subscribers(publisher.as_ref(), 2, Duration::from_secs(30)),
        "the nodes never subscribed"
    );
    // Eight scenes (two particle counts), ten frames each, interleaved, as fast as possible.
    let base = bag("multi_rope+snow_001");
    let sent: Vec<ParticleFrame> = (0..10u32)
        .flat_map(|i| {
            let base = &base;
            (0..8).map(move |k| frame_of(base, &format!("s{k}"), [2500, 1200][k % 2], i))
        })
        .collect();
    for f in &sent {
        publisher.publish(f).unwrap();
    }
    let enough = |got: &[ParticleFrame]| got.len() >= sent.len();
    let got_one = collect(&rx1, Duration::from_secs(120), enough);
    let got_many = collect(&rx8, Duration::from_secs(120), enough);
    one.signal("INT");
    many.signal("INT");
    let log_one = ok(&one.wait(Duration::from_secs(30)), "node --max-batch 1");
    let log_many = ok(&many.wait(Duration::from_secs(30)), "node --max-batch 8");
    assert_eq!(got_one.len(), sent.len(), "{log_one}");
    assert_eq!(got_many.len(), sent.len(), "{log_many}");
    let by_key = |v: &[ParticleFrame]| -> BTreeMap<(String, u32), Vec<f32>> {
        v.iter()
            .map(|f| ((f.scene.clone(), f.frame_index), state_rows(f)))
            .collect()
    };
    let (a, b) = (by_key(&got_one), by_key(&got_many));
    assert_eq!(a.len(), sent.len());
    for (key, want) in &a {
        let w = worst(&b[key], want);
        assert!(w <= 1e-5, "{key:?}: batched differs from unbatched by {w}");
    }
    assert_eq!(counter(&log_one, "batch_max"), Some(1), "{log_one}");
    let max = counter(&log_many, "batch_max").unwrap();
    assert!((2..=8).contains(&max), "batch_max {max}\n{log_many}");
    // Both particle counts warmed up (four scenes each: calls of 1, 2 and 4 copies), which
    // moved no frame.
    for n in [2500, 1200] {
        assert_eq!(warmed_sizes(&log_many, n, ""), [1, 2, 4], "{log_many}");
    }
}

/// The batch sizes a node's log says it warmed up for scenes of `n` particles (`what`: the
/// kind of call, "" or " (closed loop)"), in the order logged.
fn warmed_sizes(log: &str, n: usize, what: &str) -> Vec<usize> {
    let tail = format!(" of scenes of {n} particles{what} in ");
    log.lines()
        .filter_map(|l| l.split_once("warmed up batch sizes ")?.1.split_once(&tail))
        .flat_map(|(sizes, _)| sizes.split(", ").map(|v| v.parse::<usize>().unwrap()))
        .collect()
}

/// `Surrogate::warm_up_batches` makes one call of each batch size and leaves the scene, its
/// next predictions and the projection's sums as they were: a jelly disk falling into a
/// liquid under the `-mixed` model, whose rebound part keeps each contact between frames.
#[test]
fn warming_up_the_batch_sizes_changes_no_prediction() {
    let frames = &four_scenes()[2];
    let dir = repo("models/all-grid-mingru-small-k4-mixed");
    let run = |warm: bool| {
        let s = Surrogate::<NdArray<f32>>::load(&dir, &Default::default())
            .unwrap()
            .with_padded_batches(true);
        assert_eq!(s.batch_sizes(0, 5), [1, 2, 4, 8]);
        assert_eq!(s.batch_sizes(2, 5), [4, 8]);
        let mut state = s.init_state();
        let mut out = Vec::new();
        for (i, f) in frames.iter().enumerate() {
            let rows = state_rows(f);
            if warm && (i == 3 || i == 4) {
                let scene = (&rows[..], &f.material[..], f.dt);
                let ahead = i == 4;
                s.warm_up_batches(scene, &state, &[1, 2, 4, 8], Predict::Next, ahead)
                    .unwrap();
            }
            let (next, after) = s.step(&rows, &f.material, &[f.dt], state).unwrap();
            out.extend(next);
            state = after;
        }
        (out, s.take_corrections())
    };
    let (want, want_moved) = run(false);
    let (got, moved) = run(true);
    assert_eq!(got, want, "the frames after a warm-up");
    assert_eq!(moved, want_moved, "the projection's sums");
}

#[test]
fn in_closed_loop_under_load_every_scene_gets_one_rollout() {
    // Issue 40: eight 150-frame scenes arrive at 125 Hz each while the node rolls each out
    // 120 frames; the idle timeout (1 s) is shorter than the node needs for the rollouts.
    let (input, output) = (unique_topic("closed_in"), unique_topic("closed_out"));
    let horizon = 120u32;
    let n = node(
        &input,
        &output,
        // Pipelined: a rollout's start lands the live call in flight first.
        &[
            "--rollout",
            &horizon.to_string(),
            "--idle-timeout",
            "1",
            "--pipeline",
            "true",
            "--pad-batches",
            "true",
            "--warm-up-batches",
            "true",
        ],
    );
    let session = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx, rx) = channel();
    let _sub = session.subscribe(&output, tx).unwrap();
    let mut publisher = session.publisher(&input).unwrap();
    assert!(
        transport::wait_for_subscribers(publisher.as_ref(), 1, Duration::from_secs(30)),
        "the node never subscribed"
    );
    let base = bag("multi_liquid+snow_000");
    let scenes = 8;
    let start = Instant::now();
    for i in 0..150u32 {
        for k in 0..scenes {
            publisher
                .publish(&frame_of(&base, &format!("long{k}"), 2500, i))
                .unwrap();
        }
        let due = start + Duration::from_secs_f64(f64::from(i + 1) / 125.0);
        std::thread::sleep(due.saturating_duration_since(Instant::now()));
    }
    let want = scenes * horizon as usize;
    let mut got = collect(&rx, Duration::from_secs(180), |g| g.len() >= want);
    // Anything more (a second rollout) would come within the next seconds.
    got.extend(collect(&rx, Duration::from_secs(3), |_| false));
    n.signal("INT");
    let log = ok(&n.wait(Duration::from_secs(30)), "node");
    let mut per: BTreeMap<String, Vec<u32>> = BTreeMap::new();
    for f in &got {
        per.entry(f.scene.clone()).or_default().push(f.frame_index);
    }
    assert_eq!(per.len(), scenes, "{log}");
    for (scene, indices) in &per {
        // T = 2: the rollout follows frame 1 and predicts frames 2 ..= horizon + 1, once.
        let expect: Vec<u32> = (2..horizon + 2).collect();
        assert_eq!(indices, &expect, "{scene}: one rollout, in order\n{log}");
    }
    // The rollouts' calls warmed up as their scenes came (up to the CPU's default --max-batch,
    // 4); no live call was steady (each scene's T-th frame starts its rollout).
    assert_eq!(
        warmed_sizes(&log, 2500, " (closed loop)"),
        [1, 2, 4],
        "{log}"
    );
    assert_eq!(warmed_sizes(&log, 2500, ""), [0usize; 0], "{log}");
}
