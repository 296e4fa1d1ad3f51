//! A bundled grid model with rest-shape features end to end: `train --bundle 2 --rest-shape
//! fit --update grid+head --pushforward 1 --chunks 2` with the structure losses on the
//! bundled bags, `eval --horizon full` (whole-scene blocks, plausibility and structure
//! tables and CSV, `--save-pred` bags), `bench rollout` on a tiny setting (its table against
//! the solver; no timing asserted), and the node in closed loop over zenoh, whose rollout
//! (rest neighbourhoods kept per scene) equals the offline `Surrogate::rollout` to 1e-5.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Duration;

use crate::transport_support::*;
use burn::backend::NdArray;
use minflow::bag::read_frames;
use minflow::model::store::Surrogate;
use minflow::node::surrogate::state_rows;

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// A tiny grid minGRU predicting 2 frames per call, with rest-shape features, the grid+head
/// update and the strain and volume losses, trained one short epoch on the bundled bags (once
/// per test binary): the tests below take its rest neighbourhoods through eval, bench and the
/// node's closed loop.
fn bundled_model() -> PathBuf {
    static DIR: OnceLock<tempfile::TempDir> = OnceLock::new();
    DIR.get_or_init(|| {
        // On disk, not `crate::tmp`: a static is never dropped, and a RAM folder would
        // outlive the run.
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("k2");
        let data = repo("bags");
        let mut args = vec![
            "train",
            "--data",
            data.to_str().unwrap(),
            "--epochs",
            "1",
            "--bundle",
            "2",
            "--rest-shape",
            "fit",
            "--update",
            "grid+head",
            // One push-forward call before the loss's, and the loss's calls in two chunks
            // (truncated backpropagation through time): the sample's path through both.
            "--pushforward",
            "1",
            "--chunks",
            "2",
            "--strain-loss",
            "100",
            "--volume-loss",
            "10",
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend(crate::TINY_GRID_NET);
        args.extend(crate::TINY_GRID_SCHEDULE);
        let o = Node::spawn("train", &args).wait(Duration::from_secs(300));
        let err = ok(&o, "train");
        assert!(err.contains("K = 2"), "train reports the bundle: {err}");
        assert!(
            err.contains("push-forward 1, chunks 2"),
            "and the chunks: {err}"
        );
        dir
    })
    .path()
    .join("k2")
}

#[test]
fn eval_full_horizon_scores_whole_scenes_and_plausibility() {
    let model = bundled_model();
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("eval");
    let pred = dir.path().join("pred");
    let bag = repo("bags/multi_rope+snow_001.mcap");
    let args = [
        "eval",
        "--model",
        model.to_str().unwrap(),
        "--data",
        bag.to_str().unwrap(),
        "--split",
        "all",
        "--horizon",
        "full",
        "--no-render",
        "--out",
        out.to_str().unwrap(),
        "--save-pred",
        pred.to_str().unwrap(),
    ];
    ok(
        &Node::spawn("eval", &args).wait(Duration::from_secs(300)),
        "eval",
    );
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(
        table.contains("avg_full") && table.contains("f_full"),
        "{table}"
    );
    assert!(
        table.contains("Plausibility") && table.contains("strain rope"),
        "{table}"
    );
    let csv = std::fs::read_to_string(out.join("plausibility.csv")).unwrap();
    // The bag's 25 frames after 2 seed frames: 23 steps, probed at 20 and at the end.
    for probe in [",20,rope,", ",end,rope,", ",end,snow,"] {
        assert!(csv.contains(probe), "{probe} in {csv}");
    }
    let metrics = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    assert!(
        metrics.lines().any(|l| l.contains(",23,")),
        "23 steps scored"
    );
    assert_structure(&table, &csv);
    // --save-pred: the model's rollout as a bag of its 23 predicted frames on the node's
    // topic, frame indices 2..=24 (after the 2 seed frames), the scene's materials.
    let saved = pred.join("k2").join("multi_rope+snow_001_from2.mcap");
    let read = read_frames(&saved, Some(minflow::bag::PREDICTED_TOPIC)).unwrap();
    let indices: Vec<u32> = read.frames.iter().map(|(_, _, f)| f.frame_index).collect();
    assert_eq!(
        indices,
        (2..25).collect::<Vec<u32>>(),
        "{}",
        saved.display()
    );
    assert!(read
        .frames
        .iter()
        .all(|(_, _, f)| f.scene == "multi/rope+snow/001"));
}

/// The structure section and columns of `eval`'s tables: `persist` copies the rollout's
/// first frame, so every rest-neighbour pair of the rope is intact and the rope one piece.
fn assert_structure(table: &str, csv: &str) {
    assert!(
        table.contains("Structure") && table.contains("rope connected"),
        "{table}"
    );
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let persist_rope = lines
        .map(|l| l.split(',').collect::<Vec<_>>())
        .find(|row| row[1] == "persist" && row[2] == "end" && row[3] == "rope")
        .expect("persist's rope row at the end");
    for name in ["intact", "connected"] {
        let v: f64 = persist_rope[col(name)].parse().unwrap();
        assert_eq!(v, 1.0, "persist's rope {name}");
    }
    let volume: f64 = persist_rope[col("volume")].parse().unwrap();
    assert!(volume > 0.0, "rope volume ratio {volume}");
}

/// `bench rollout` prints each model's row against the solver, and with `--constraints off
/// --constraints on` the projection's share and its setup: nothing when off, both above 0
/// for a shipped model with its parts on.
#[test]
fn bench_rollout_prints_the_model_against_the_solver() {
    let model = bundled_model();
    let shipped = repo("models/all-grid-mingru-small-k4");
    let args = [
        "bench",
        "rollout",
        "--model",
        model.to_str().unwrap(),
        "--model",
        shipped.to_str().unwrap(),
        "--constraints",
        "off",
        "--constraints",
        "on",
        "--scenes",
        "1",
        "--frames",
        "5",
    ];
    let o = Node::spawn("bench", &args).wait(Duration::from_secs(300));
    ok(&o, "bench rollout");
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(table.contains("MPM solver"), "{table}");
    let row = table
        .lines()
        .find(|l| l.contains("k2"))
        .unwrap_or_else(|| panic!("a row for the model: {table}"));
    // | model | K | calls/rollout | ms/frame | x solver | x GPU solver | avg5 MSE |
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    assert_eq!(
        (cells[2], cells[3]),
        ("2", "3"),
        "K = 2: 3 calls for 5 frames"
    );
    let ratio: f64 = cells[5].parse().unwrap();
    assert!(ratio.is_finite() && ratio > 0.0, "{row}");
    // No GPU solver on the CPU: its column stays empty and it has no row.
    assert_eq!(cells[6], "", "{row}");
    assert!(!table.contains("on the GPU"), "{table}");
    // | ... | avg5 MSE | projection ms/frame (share) | its setup ms/scene |
    let projection = |setting: &str| -> (f64, f64) {
        let name = format!("small-k4[{setting}]");
        let row = table.lines().find(|l| l.contains(&name)).expect(&name);
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        let ms = cells[8].split_whitespace().next().unwrap().parse().unwrap();
        (ms, cells[9].parse().unwrap())
    };
    assert_eq!(projection("off"), (0.0, 0.0), "{table}");
    let (ms, setup) = projection("on");
    assert!(ms > 0.0 && setup > 0.0, "{table}");
}

/// `node --rollout 9` with a K = 2 model: after the scene's two seed frames, 9 frames from 5
/// calls, equal to the offline rollout seeded with the same frames.
#[test]
fn zenoh_node_rolls_a_bundled_model_out_as_offline() {
    let model = bundled_model();
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("pred");
    let (input, output) = (unique_topic("bundle_in"), unique_topic("bundle_out"));
    let bag = repo("bags/multi_rope+snow_001.mcap");
    let recorder = Node::spawn(
        "record",
        &[
            "record",
            "--topic",
            &output,
            "-o",
            out.to_str().unwrap(),
            "--count",
            "9",
        ],
    );
    let node = Node::spawn(
        "node",
        &[
            "node",
            "--model",
            model.to_str().unwrap(),
            "--in",
            &input,
            "--out",
            &output,
            "--rollout",
            "9",
            "--wait-for-subscribers",
            "1",
            "--status",
            "none",
            "--queue-depth",
            "32",
        ],
    );
    let replay = ["replay", "--topic", &input, bag.to_str().unwrap()];
    ok(
        &Node::spawn("replay", &replay).wait(Duration::from_secs(120)),
        "replay",
    );
    let rec = ok(&recorder.wait(Duration::from_secs(120)), "record");
    node.signal("INT");
    ok(&node.wait(Duration::from_secs(30)), "node");

    let frames: Vec<_> = read_frames(&bag, None)
        .unwrap()
        .frames
        .into_iter()
        .map(|m| m.2)
        .collect();
    let rows = |i: usize| state_rows(&frames[i]);
    let s = Surrogate::<NdArray<f32>>::load(&model, &Default::default()).unwrap();
    assert_eq!(s.bundle(), 2);
    let want = s
        .rollout(
            Some(&rows(0)),
            &[rows(0), rows(1)],
            &frames[0].material,
            frames[0].dt,
            9,
        )
        .unwrap();
    let mut compared = 0;
    for bytes in raw_messages(&out, Some(&output)) {
        let f = minflow::msgs::decode(&bytes).unwrap();
        let k = f.frame_index as usize - 2;
        let got = state_rows(&f);
        let worst = got
            .iter()
            .zip(&want[k])
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst <= 1e-5, "frame {}: max |diff| {worst}", f.frame_index);
        compared += 1;
    }
    assert_eq!(compared, 9, "recorded: {rec}");
}
