//! `minflow train --arch grid` (the default) end to end on the bundled bags with a tiny
//! network: the run folder, resuming (bit-exact, and past a damaged checkpoint), streamed
//! datasets, flags out of range, and `bench train`.

use std::path::Path;
use std::process::Command;

use crate::cli_train::{losses, train_grid};

/// A grid dataset larger than `--max-resident-frames` trains from chunks streamed from the
/// bags, with the normalisation (velocity statistics, min-max scaler) of the in-memory run
/// fitted chunk by chunk to the same values; a budget below one scene is refused.
#[test]
fn grid_train_streams_large_datasets() {
    let flags = ["--epochs", "2", "--model", "mingru"];
    let resident = crate::tmp::tempdir().unwrap();
    let o = train_grid(resident.path(), &flags);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!String::from_utf8_lossy(&o.stderr).contains("streamed"));
    let streamed = crate::tmp::tempdir().unwrap();
    let o = train_grid(
        streamed.path(),
        &[&flags[..], &["--max-resident-frames", "50"]].concat(),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("streamed from the bags"), "{err}");
    let losses = losses(streamed.path());
    assert_eq!(losses.len(), 2);
    for (train, val) in &losses {
        let (t, v): (f64, f64) = (train.parse().unwrap(), val.parse().unwrap());
        assert!(t.is_finite() && v.is_finite() && v > 0.0, "{train}, {val}");
    }
    let meta = |dir: &Path| crate::json(&dir.join("model.json"));
    let (a, b) = (meta(resident.path()), meta(streamed.path()));
    let numbers = |v: &serde_json::Value| -> Vec<f64> {
        let mut out = Vec::new();
        for key in ["vel_scale", "dv_mean", "dv_scale"] {
            let field = &v[key];
            out.extend(
                field
                    .as_array()
                    .unwrap_or_else(|| panic!("{key}: {v}"))
                    .iter()
                    .map(|x| x.as_f64().unwrap()),
            );
        }
        for key in ["min", "max"] {
            out.extend(
                v["scaler"][key]
                    .as_array()
                    .unwrap_or_else(|| panic!("{key}: {v}"))
                    .iter()
                    .map(|x| x.as_f64().unwrap()),
            );
        }
        out
    };
    let (na, nb) = (numbers(&a), numbers(&b));
    assert_eq!(na.len(), nb.len());
    for (x, y) in na.iter().zip(&nb) {
        assert!(
            (x - y).abs() <= 1e-6 * x.abs().max(1e-3),
            "{na:?} against {nb:?}"
        );
    }
    // Every bundled scene has 25 frames: a budget of 10 holds none.
    let o = train_grid(
        crate::tmp::tempdir().unwrap().path(),
        &[&flags[..], &["--max-resident-frames", "10"]].concat(),
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(err.contains("10"), "{err}");
}

/// The grid run folder is complete (grid is the default architecture), and a run stopped
/// after one epoch resumes from its checkpoint to the requested epochs.
#[test]
fn grid_train_writes_a_run_folder_and_resumes() {
    let straight = crate::tmp::tempdir().unwrap();
    let o = train_grid(straight.path(), &["--epochs", "2", "--model", "minlstm"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let meta = std::fs::read_to_string(straight.path().join("model.json")).unwrap();
    assert!(
        meta.contains("\"arch\": \"grid\"") && meta.contains("MinLstm"),
        "{meta}"
    );
    for file in [
        "model.mpk",
        "checkpoint/model.mpk",
        "checkpoint/optim.mpk",
        "loss.png",
    ] {
        assert!(straight.path().join(file).exists(), "missing {file}");
    }
    let resumed = crate::tmp::tempdir().unwrap();
    let o = train_grid(resumed.path(), &["--epochs", "1", "--model", "minlstm"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = train_grid(
        resumed.path(),
        &["--epochs", "2", "--model", "minlstm", "--resume"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (a, b) = (losses(straight.path()), losses(resumed.path()));
    assert_eq!(a.len(), 2);
    assert_eq!(b.len(), 2);
    // The first epoch's training loss is the same run (its learning-rate schedule, which
    // spans --epochs, differs after the first batch; `grid_resume_is_bit_exact` resumes a
    // run of the same length).
    assert_eq!(a[0].0, b[0].0);
    // Resuming with another network is refused before any training, naming the field.
    let o = train_grid(
        resumed.path(),
        &[
            "--epochs", "3", "--model", "minlstm", "--resume", "--window", "3",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("window: checkpoint 2, this run 3"), "{err}");
    assert_eq!(losses(resumed.path()).len(), 2, "the refused run trained");
}

/// Resume is bit-exact: a run resumed from its epoch-1 checkpoint (the straight run's
/// `checkpoint.old`, what a run killed during epoch 2 leaves behind) ends with the same
/// epoch-2 losses, to the last digit, and the same weights as the run that went straight
/// through, input noise and mirrored samples (`--mirror`) included. Mirroring changes what
/// the run trains on.
#[test]
fn grid_resume_is_bit_exact() {
    let flags = ["--epochs", "2", "--model", "mingru", "--mirror"];
    let straight = crate::tmp::tempdir().unwrap();
    let o = train_grid(straight.path(), &flags);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let resumed = crate::tmp::tempdir().unwrap();
    let checkpoint = resumed.path().join("checkpoint");
    std::fs::create_dir_all(&checkpoint).unwrap();
    for entry in std::fs::read_dir(straight.path().join("checkpoint.old")).unwrap() {
        let path = entry.unwrap().path();
        std::fs::copy(&path, checkpoint.join(path.file_name().unwrap())).unwrap();
    }
    let o = train_grid(resumed.path(), &[&flags[..], &["--resume"]].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (a, b) = (losses(straight.path()), losses(resumed.path()));
    assert_eq!(a.len(), 2);
    assert_eq!(a, b, "(train loss, validation loss) per epoch");
    let weights = |dir: &Path| std::fs::read(dir.join("checkpoint/model.mpk")).unwrap();
    assert!(
        weights(straight.path()) == weights(resumed.path()),
        "the epoch-2 weights differ"
    );
    let plain = crate::tmp::tempdir().unwrap();
    let o = train_grid(plain.path(), &flags[..4]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_ne!(
        losses(plain.path())[0].0,
        a[0].0,
        "--mirror changed nothing"
    );
}

/// A resume whose checkpoint was truncated afterwards falls back to the previous epoch's
/// (`checkpoint.old`) with a warning naming the file; with both damaged it fails naming them.
#[test]
fn a_damaged_checkpoint_falls_back_to_the_previous_one() {
    let dir = crate::tmp::tempdir().unwrap();
    let o = train_grid(dir.path(), &["--epochs", "2", "--model", "none"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let truncate = |folder: &str| {
        let path = dir.path().join(folder).join("model.mpk");
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    };
    truncate("checkpoint");
    let o = train_grid(
        dir.path(),
        &["--epochs", "3", "--model", "none", "--resume"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("checkpoint/model.mpk is damaged") && err.contains("(epoch 1) instead"),
        "{err}"
    );
    assert_eq!(losses(dir.path()).len(), 3);
    // An empty checkpoint file (a full disk) falls back the same way.
    std::fs::write(dir.path().join("checkpoint/optim.mpk"), b"").unwrap();
    let o = train_grid(
        dir.path(),
        &["--epochs", "4", "--model", "none", "--resume"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("checkpoint/optim.mpk is damaged") && err.contains("(epoch 2) instead"),
        "{err}"
    );
    assert_eq!(losses(dir.path()).len(), 4);
    truncate("checkpoint");
    truncate("checkpoint.old");
    let o = train_grid(
        dir.path(),
        &["--epochs", "5", "--model", "none", "--resume"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("cannot resume")
            && err.contains("checkpoint/model.mpk is damaged")
            && err.contains("checkpoint.old/model.mpk is damaged"),
        "{err}"
    );
}

#[test]
fn grid_flags_out_of_range_are_usage_errors_before_reading_data() {
    let dir = crate::tmp::tempdir().unwrap();
    for extra in [
        &["--grid", "20", "--levels", "4"][..],
        &["--teacher-steps", "3"][..],
        &["--model", "transformer"][..],
    ] {
        let o = train_grid(dir.path(), extra);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {err}");
        assert!(err.contains(extra[0]), "{extra:?}: {err}");
    }
}

/// A validation horizon longer than every validation scene is an error before the first
/// step: before, every epoch scored NaN, and the run said it kept a model it never wrote.
#[test]
fn a_validation_horizon_longer_than_the_scenes_is_an_error() {
    let dir = crate::tmp::tempdir().unwrap();
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let out = dir.path().join("run");
    let mut args = vec!["train", "--data", bags, "--out", out.to_str().unwrap()];
    let schedule = crate::TINY_GRID_SCHEDULE.chunks(2);
    args.extend(
        schedule
            .filter(|f| f[0] != "--val-horizon")
            .flatten()
            .copied(),
    );
    args.extend_from_slice(&crate::TINY_GRID_NET);
    args.extend_from_slice(&["--val-horizon", "100000", "--epochs", "1"]);
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&args)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{err}");
    assert!(err.contains("--val-horizon 100000"), "{err}");
    assert!(!out.join("metrics.csv").exists());
}

/// `bench train --arch grid` of a tiny network (64 particles, grid 16, 2 samples of P = 2,
/// one epoch) with `extra` flags.
fn bench_grid(extra: &[&str]) -> std::process::Output {
    let tiny = [
        "--particles",
        "64",
        "--grid",
        "16",
        "--samples",
        "2",
        "--micro-batch",
        "2",
    ];
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["bench", "train", "--arch", "grid"])
        .args(tiny)
        .args(["--epochs", "1", "--rollout-steps", "2"])
        .args(extra)
        .output()
        .unwrap()
}

/// `bench train --arch grid` trains each requested kernel and prints one table row per
/// (core, kernel) with a positive samples/s, and the stage times with `--stages`.
#[test]
fn bench_train_measures_the_grid_architecture() {
    let o = bench_grid(&["--cores", "none", "--conv", "gather,shift", "--stages"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let mut first_losses = Vec::new();
    for kernel in ["gather", "shift"] {
        let row = stdout
            .lines()
            .find(|l| l.starts_with("none") && l.split_whitespace().nth(1) == Some(kernel))
            .unwrap_or_else(|| panic!("no row for {kernel}: {stdout}"));
        let rate: f64 = row.split_whitespace().nth(4).unwrap().parse().unwrap();
        assert!(rate > 0.0, "{row}");
        let loss: f64 = row.split_whitespace().last().unwrap().parse().unwrap();
        assert!(loss.is_finite() && loss > 0.0, "{row}");
        first_losses.push(loss);
    }
    // The same weights and data through two convolution kernels of one function: the same
    // first-epoch loss (the column the GPU check in tests/gpu/run.sh compares).
    let (a, b) = (first_losses[0], first_losses[1]);
    assert!(
        (a - b).abs() <= 1e-5 * a,
        "gather {a} vs shift {b}: {stdout}"
    );
    assert_eq!(
        stdout.matches("ms per forward + backward").count(),
        2,
        "{stdout}"
    );
}

/// `bench train --arch grid --shape small` trains the demo's network (K = 4 frames a call):
/// a row with a positive rate and fewer parameters than the full shape's on the same grid.
#[test]
fn bench_train_takes_the_small_shape() {
    let params = |shape: &str| {
        let o = bench_grid(&["--cores", "mingru", "--shape", shape]);
        let stdout = String::from_utf8_lossy(&o.stdout).into_owned();
        assert!(
            o.status.success(),
            "{stdout}\n{}",
            String::from_utf8_lossy(&o.stderr)
        );
        assert!(stdout.contains(&format!("({shape} shape)")), "{stdout}");
        let row = (stdout.lines().find(|l| l.starts_with("mingru")))
            .unwrap_or_else(|| panic!("no row: {stdout}"))
            .to_owned();
        let cell = |k: usize| {
            row.split_whitespace()
                .nth(k)
                .unwrap()
                .parse::<f64>()
                .unwrap()
        };
        assert!(cell(4) > 0.0, "{row}");
        cell(2)
    };
    let (small, full) = (params("small"), params("full"));
    assert!(small < full, "small {small} against full {full} parameters");
}

/// `bench train --arch grid --feed` times the batch feed instead of training: one row for
/// each of 1, 2 and 4 shares with a positive rate, and no training row.
#[test]
fn bench_train_feed_times_the_feed_alone() {
    let o = bench_grid(&["--feed"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&o.stderr)
    );
    for shares in ["1", "2", "4"] {
        let row = (stdout.lines())
            .find(|l| l.split_whitespace().next() == Some(shares))
            .unwrap_or_else(|| panic!("no row for {shares} shares: {stdout}"));
        let rate: f64 = row.split_whitespace().nth(2).unwrap().parse().unwrap();
        assert!(rate > 0.0, "{row}");
    }
    assert!(!stdout.contains("mingru"), "trained: {stdout}");
}
