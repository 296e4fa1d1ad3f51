//! `minflow eval --pred BAG --truth DIR` (issue 4): a predictions bag written offline from a
//! model's rollouts (BagWriter, `/surrogate/frames`, frame_index = input's + 1) scores
//! exactly like the direct `minflow eval --model`; frames missing from a predictions bag are
//! reported per scene, excluded from the scores (never scored as zero error) and make the
//! command exit with 3. `--reference-from` changes only rollouts that start after frame 0.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use burn::backend::NdArray;
use burn::tensor::backend::Backend;
use minflow::bag::{BagWriter, FRAMES_TOPIC, PREDICTED_TOPIC};
use minflow::data::{self, Scaler, Split};
use minflow::model::store::{self, ModelMeta, Surrogate};
use minflow::model::{CoreKind, ModelConfig};
use minflow::msgs::{Header, ParticleFrame, Time};

type B = NdArray<f32>;

fn bags() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/bags"))
}

/// A tiny untrained minGRU for the bundled bags' 2,500 particles, with the scaler fitted on
/// their training split (seed 0), saved as a run folder.
fn tiny_model(dir: &Path) {
    let infos = data::scan(&[bags()], Some(FRAMES_TOPIC)).unwrap();
    let split = Split::new(infos.iter().map(|s| &s.scene), 0);
    let (train, _) = data::load_scenes(&[bags()], Some(FRAMES_TOPIC), &split.train).unwrap();
    let scaler = Scaler::fit(&train.iter().collect::<Vec<_>>());
    let config = ModelConfig::new(CoreKind::MinGru, 2500)
        .with_width(24)
        .with_encoder_hidden(16)
        .with_dropout(0.0);
    B::seed(&Default::default(), 11);
    let model = config.init::<B>(&Default::default());
    let meta = ModelMeta {
        net: store::NetConfig::Paper(config),
        scaler,
        epoch: 0,
        val_loss: 0.0,
        constraints: None,
    };
    store::save(dir, &model, &meta).unwrap();
}

/// Rolls the model out offline on the test scenes (seed = the first 2 frames, 20 steps) and
/// writes the predicted frames to a bag, leaving out the steps in `skip` (1-based).
fn predictions_bag(model: &Path, path: &Path, skip: &[usize]) -> Vec<String> {
    let infos = data::scan(&[bags()], Some(FRAMES_TOPIC)).unwrap();
    let split = Split::new(infos.iter().map(|s| &s.scene), 0);
    let (test, _) = data::load_scenes(&[bags()], Some(FRAMES_TOPIC), &split.test).unwrap();
    assert!(!test.is_empty());
    let surrogate = Surrogate::<B>::load(model, &Default::default()).unwrap();
    let mut writer = BagWriter::create(path).unwrap();
    for traj in &test {
        let seed: Vec<Vec<f32>> = (0..2).map(|k| traj.state(k).to_vec()).collect();
        let frames = surrogate
            .rollout(None, &seed, &traj.material, traj.dt, 20)
            .unwrap();
        for (k, state) in frames.iter().enumerate() {
            if skip.contains(&(k + 1)) {
                continue;
            }
            let index = traj.start_index + 2 + k as u32;
            let frame = ParticleFrame {
                header: Header {
                    stamp: Time::from_secs_f64(f64::from(index) * f64::from(traj.dt)),
                    frame_id: "world".into(),
                },
                scene: traj.scene.clone(),
                frame_index: index,
                dt: traj.dt,
                position: state.chunks_exact(4).flat_map(|r| [r[0], r[1]]).collect(),
                velocity: state.chunks_exact(4).flat_map(|r| [r[2], r[3]]).collect(),
                material: traj.material.clone(),
            };
            writer.write(PREDICTED_TOPIC, &frame).unwrap();
        }
    }
    writer.finish().unwrap();
    split.test
}

fn minflow(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(args)
        .output()
        .unwrap()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn read(p: &Path) -> String {
    std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()))
}

/// `metrics.csv` rows of one predictor: step -> mse.
fn mse_by_step(csv: &str, predictor: &str) -> Vec<(usize, f64)> {
    csv.lines()
        .skip(1)
        .map(|l| l.split(',').collect::<Vec<_>>())
        .filter(|f| f[1] == predictor)
        .map(|f| (f[2].parse().unwrap(), f[4].parse().unwrap()))
        .collect()
}

#[test]
fn a_predictions_bag_scores_like_the_direct_rollout_and_gaps_are_reported() {
    let tmp = crate::tmp::tempdir().unwrap();
    let model = tmp.path().join("tiny");
    tiny_model(&model);
    let bags = bags();

    // Direct evaluation.
    let direct = tmp.path().join("direct");
    let o = minflow(&[
        "eval",
        "--model",
        s(&model),
        "--data",
        s(&bags),
        "--out",
        s(&direct),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("| Scene |") && stdout.contains("avg20 tiny"),
        "{stdout}"
    );

    // The same rollouts, written offline to a bag and scored as recorded predictions.
    let pred = tmp.path().join("pred.mcap");
    let scenes = predictions_bag(&model, &pred, &[]);
    let replay = tmp.path().join("replay");
    let o = minflow(&[
        "eval",
        "--pred",
        s(&pred),
        "--truth",
        s(&bags),
        "--model",
        s(&model),
        "--name",
        "tiny",
        "--out",
        s(&replay),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for file in ["table.csv", "metrics.csv"] {
        assert_eq!(read(&direct.join(file)), read(&replay.join(file)), "{file}");
    }
    // The structure at the last step (area, intact, strain, energy, the bodies' centres of
    // mass): eval's own end probe.
    let end_rows = |dir: &Path| -> Vec<String> {
        let csv = read(&dir.join("plausibility.csv"));
        csv.lines()
            .filter(|l| l.contains(",tiny,end,"))
            .map(|l| l.split(',').take(13).collect::<Vec<_>>().join(","))
            .collect()
    };
    let ends = end_rows(&replay);
    assert!(ends.len() >= scenes.len(), "{ends:?}");
    assert_eq!(ends, end_rows(&direct));
    let full = read(&replay.join("metrics.csv"));
    assert_eq!(mse_by_step(&full, "tiny").len(), 20 * scenes.len());
    assert!(mse_by_step(&full, "tiny").iter().all(|&(_, v)| v > 0.0));

    // Steps 3, 7 and 20 missing: counted per scene, excluded, exit code 3.
    let gappy = tmp.path().join("gappy.mcap");
    predictions_bag(&model, &gappy, &[3, 7, 20]);
    let out = tmp.path().join("gappy");
    let o = minflow(&[
        "eval",
        "--pred",
        s(&gappy),
        "--truth",
        s(&bags),
        "--model",
        s(&model),
        "--name",
        "tiny",
        "--out",
        s(&out),
        "--no-render",
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    for scene in &scenes {
        assert!(
            stderr.contains(&format!(
                "scene {scene:?}: 3 of 20 predicted frames missing"
            )),
            "{stderr}"
        );
    }
    let md = read(&out.join("table.md"));
    assert!(md.contains("| missing | unmatched |"), "{md}");
    assert!(md.contains(&format!("| `{}` | 3 | 0 |", scenes[0])), "{md}");
    let gappy_rows = mse_by_step(&read(&out.join("metrics.csv")), "tiny");
    let kept: Vec<usize> = gappy_rows.iter().map(|r| r.0).collect();
    assert!(!kept.contains(&3) && !kept.contains(&7) && !kept.contains(&20));
    assert_eq!(kept.len(), 17 * scenes.len());
    // avg20 over the 17 scored steps of the full run (one test scene), f20 not available.
    let expected: f64 = mse_by_step(&full, "tiny")
        .iter()
        .filter(|r| ![3, 7, 20].contains(&r.0))
        .map(|r| r.1)
        .sum::<f64>()
        / 17.0;
    let table = read(&out.join("table.csv"));
    let header: Vec<&str> = table.lines().next().unwrap().split(',').collect();
    let row: Vec<&str> = table.lines().nth(1).unwrap().split(',').collect();
    let col = |name: &str| header.iter().position(|h| *h == name).unwrap();
    let avg: f64 = row[col("avg20_tiny")].parse().unwrap();
    assert!(
        (avg - expected).abs() <= 1e-12 * expected,
        "{avg} vs {expected}"
    );
    assert_eq!(
        row[col("f20_tiny")],
        "",
        "f20 of a missing frame is not scored"
    );
    // The baselines are untouched by the gaps.
    let full_table = read(&replay.join("table.csv"));
    let full_row: Vec<&str> = full_table.lines().nth(1).unwrap().split(',').collect();
    assert_eq!(row[col("f20_persist")], full_row[col("f20_persist")]);
    assert_eq!(row[col("avg20_constvel")], full_row[col("avg20_constvel")]);
}

#[test]
fn without_a_model_the_baselines_use_a_scaler_fitted_on_the_training_split() {
    let tmp = crate::tmp::tempdir().unwrap();
    let o = minflow(&[
        "eval",
        "--data",
        s(&bags()),
        "--split",
        "all",
        "--no-render",
        "--out",
        s(tmp.path()),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("fitted on the 4 training scenes of the data (split seed 0)"),
        "{stderr}"
    );
    let table = read(&tmp.path().join("table.csv"));
    assert_eq!(
        table.lines().next().unwrap(),
        "scene,avg20_persist,avg20_constvel,f20_persist,f20_constvel"
    );
    assert_eq!(table.lines().count(), 1 + 6 + 1, "6 scenes and the average");
}

#[test]
fn bad_invocations_fail_clearly() {
    let tmp = crate::tmp::tempdir().unwrap();
    let o = minflow(&["eval", "--out", s(tmp.path())]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("give either --data"));
    let o = minflow(&[
        "eval",
        "--data",
        s(&bags()),
        "--split",
        "nope",
        "--out",
        s(tmp.path()),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown --split"));
    let o = minflow(&[
        "eval",
        "--model",
        s(&tmp.path().join("none")),
        "--data",
        s(&bags()),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("loading model"));
    // Zero horizons and start counts are usage errors naming the flag (they quietly became 1).
    for (flag, value) in [("--horizon", "0"), ("--starts", "0"), ("--horizon", "-3")] {
        let o = minflow(&[
            "eval",
            "--data",
            s(&bags()),
            flag,
            value,
            "--out",
            s(tmp.path()),
        ]);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{flag} {value}: {stderr}");
        assert!(stderr.contains(flag), "{flag} {value}: {stderr}");
    }
}

/// `eval --reference-from`: a model with reference positions (the shipped minGRU) takes them
/// from the scene's frame 0 or from each rollout's first seed frame. A rollout from the start
/// of a scene has the same reference either way; later rollouts do not. One bundled scene
/// (the table compares whole tables, and any scene that moves shows the difference).
#[test]
fn reference_from_changes_only_rollouts_that_start_late() {
    let root = env!("CARGO_MANIFEST_DIR");
    let tmp = crate::tmp::tempdir().unwrap();
    let table = |starts: &str, from: &str| {
        let out = tmp.path().join(format!("{starts}-{from}"));
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args(["eval", "--model", &format!("{root}/models/all-grid-mingru")])
            .args([
                "--data",
                &format!("{root}/bags/multi_rope+snow_001.mcap"),
                "--split",
                "all",
                "--horizon",
                "3",
            ])
            .args(["--starts", starts, "--reference-from", from, "--no-render"])
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        std::fs::read_to_string(out.join("table.csv")).unwrap()
    };
    assert_eq!(
        table("1", "scene-start"),
        table("1", "rollout-start"),
        "from the first frame the two references are the same frame"
    );
    assert_ne!(
        table("2", "scene-start"),
        table("2", "rollout-start"),
        "a later rollout's first seed frame is not frame 0"
    );
}
