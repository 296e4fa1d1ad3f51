//! `minflow train` end to end on the bundled bags with a tiny network: the run folder holds
//! the model, the checkpoint, metrics.csv (one row per epoch), a decodable loss.png, the
//! split and the options; `--resume` continues to more epochs; a dataset larger than
//! `--max-resident-frames` is streamed; bad flags fail clearly.

use std::path::Path;
use std::process::Command;

fn train(out: &Path, extra: &[&str]) -> std::process::Output {
    train_width(out, "48", extra)
}

/// [`train`] with latent width `width`.
fn train_width(out: &Path, width: &str, extra: &[&str]) -> std::process::Output {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let mut args = vec![
        "train",
        "--arch",
        "paper",
        "--data",
        bags,
        "--out",
        out.to_str().unwrap(),
        "--width",
        width,
        "--encoder-hidden",
        "16",
    ];
    args.extend_from_slice(extra);
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&args)
        .output()
        .unwrap()
}

fn epochs(out: &Path) -> usize {
    std::fs::read_to_string(out.join("metrics.csv"))
        .unwrap()
        .lines()
        .count()
        - 1
}

#[test]
fn train_writes_a_complete_run_folder_and_resumes() {
    let dir = crate::tmp::tempdir().unwrap();
    let o = train(dir.path(), &["--epochs", "2", "--model", "minlstm"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for file in [
        "model.json",
        "model.mpk",
        "checkpoint/model.mpk",
        "checkpoint/optim.mpk",
        "split.json",
        "train.json",
        "loss.png",
    ] {
        assert!(dir.path().join(file).exists(), "missing {file}");
    }
    assert_eq!(epochs(dir.path()), 2);
    let meta = std::fs::read_to_string(dir.path().join("model.json")).unwrap();
    assert!(
        meta.contains("MinLstm") && meta.contains("\"particles\": 2500"),
        "{meta}"
    );
    let png = std::fs::File::open(dir.path().join("loss.png")).unwrap();
    let info = png::Decoder::new(std::io::BufReader::new(png))
        .read_info()
        .unwrap();
    assert_eq!((info.info().width, info.info().height), (800, 500));
    // Resume to 4 epochs: 2 more rows, the first two unchanged.
    let before = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
    let o = train(
        dir.path(),
        &["--epochs", "4", "--model", "minlstm", "--resume"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let after = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
    assert_eq!(epochs(dir.path()), 4);
    let first_two = |s: &str| {
        s.lines()
            .take(3)
            .map(|l| l.split(',').take(3).collect::<Vec<_>>().join(","))
            .collect::<Vec<_>>()
    };
    assert_eq!(first_two(&before), first_two(&after));
    // Resuming with another --width is refused before training, naming the field (it was a
    // panic in burn's matmul, exit 101).
    let o = train_width(
        dir.path(),
        "32",
        &["--epochs", "5", "--model", "minlstm", "--resume"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("width: checkpoint 48, this run 32"), "{err}");
    assert_eq!(epochs(dir.path()), 4, "the refused run trained");
}

#[test]
fn large_datasets_are_streamed() {
    let dir = crate::tmp::tempdir().unwrap();
    let o = train(
        dir.path(),
        &["--epochs", "1", "--max-resident-frames", "60"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("streamed from the bags"));
    assert_eq!(epochs(dir.path()), 1);
}

#[test]
fn bad_flags_fail_clearly() {
    let dir = crate::tmp::tempdir().unwrap();
    // Unknown names are usage errors too.
    let o = train(dir.path(), &["--model", "transformer"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown --model"));
    // Out-of-range numbers are usage errors (exit 2) naming the flag, before data is read.
    for bad in [
        &["--batch-size", "0"][..],
        &["--epochs", "0"][..],
        &["--lr", "0"][..],
        &["--lr", "-1"][..],
        &["--lr=-1"][..],
        &["--lr", "nan"][..],
        &["--dropout", "2"][..],
        &["--dropout", "1.5"][..],
        &["--dropout=-0.5"][..],
        &["--density-grid", "0"][..],
        &["--rollout-discount", "0"][..],
        &["--rollout-discount", "1.5"][..],
        // Known only once the bags are scanned: the bundled scenes have 25 frames.
        &["--window", "30"][..],
    ] {
        let o = train(dir.path(), bad);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {stderr}");
        let flag = bad[0].split('=').next().unwrap();
        assert!(stderr.contains(flag), "{bad:?}: {stderr}");
    }
    // Nothing was written for the run that could not train.
    assert!(!dir.path().join("model.json").exists());
    let o = train_grid(dir.path(), &["--window", "30"]);
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("--window 30"));
}

/// `train --arch grid` with a tiny network (16 x 16 grid, two levels, a few samples per
/// epoch; a flag of [`crate::TINY_GRID_NET`] that `extra` sets takes `extra`'s value) on the
/// bundled bags.
fn train_grid(out: &Path, extra: &[&str]) -> std::process::Output {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let mut args = vec!["train", "--data", bags, "--out", out.to_str().unwrap()];
    args.extend_from_slice(&crate::TINY_GRID_SCHEDULE);
    let net = crate::TINY_GRID_NET;
    args.extend(
        net.chunks(2)
            .filter(|f| !extra.contains(&f[0]))
            .flatten()
            .copied(),
    );
    args.extend_from_slice(extra);
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&args)
        .output()
        .unwrap()
}

/// `--substeps S` trains a model whose every call runs the network S times (issue 81's lever),
/// saved with it and evaluated from its folder; a single-frame model fine-tunes into one;
/// substeps with a bundle, or out of range, are usage errors.
#[test]
fn grid_train_with_substeps() {
    let dir = crate::tmp::tempdir().unwrap();
    let (plain, sub) = (dir.path().join("plain"), dir.path().join("sub"));
    let o = train_grid(&plain, &["--epochs", "1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let init = plain.to_str().unwrap();
    let o = train_grid(
        &sub,
        &["--epochs", "1", "--substeps", "2", "--init-from", init],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("S = 2 substeps"), "{err}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(sub.join("model.json")).unwrap()).unwrap();
    assert_eq!(json["substeps"], 2, "{json}");
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let eval_out = dir.path().join("eval");
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args([
            "eval",
            "--model",
            sub.to_str().unwrap(),
            "--data",
            bags,
            "--split",
            "all",
        ])
        .args([
            "--starts",
            "1",
            "--horizon",
            "4",
            "--no-render",
            "--no-plausibility",
        ])
        .args(["--out", eval_out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(eval_out.join("table.csv").exists());
    for bad in [
        &["--substeps", "2", "--bundle", "4"][..],
        &["--substeps", "9"][..],
    ] {
        let o = train_grid(&dir.path().join("bad"), bad);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {err}");
        assert!(err.contains("--substeps"), "{bad:?}: {err}");
    }
}

/// The (train, val) loss columns of metrics.csv, as text (exact digits).
fn losses(out: &Path) -> Vec<(String, String)> {
    std::fs::read_to_string(out.join("metrics.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[1].to_owned(), f[2].to_owned())
        })
        .collect()
}

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
    let meta = |dir: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("model.json")).unwrap()).unwrap()
    };
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

/// `--init-from` starts from a finished run's weights: with a learning rate too small to
/// move them, the first validation rollout equals the source run's best to 3 digits (a fresh
/// start is far off), and the source's normalisation constants are kept. Another network is
/// refused as a usage error naming the field, before any training.
#[test]
fn grid_train_starts_from_another_runs_weights() {
    let source = crate::tmp::tempdir().unwrap();
    let o = train_grid(
        source.path(),
        &["--epochs", "3", "--model", "mingru", "--lr", "3e-3"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let meta = |dir: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("model.json")).unwrap()).unwrap()
    };
    let best = meta(source.path())["val_loss"].as_f64().unwrap();
    let run = |dir: &Path, extra: &[&str]| {
        let mut args = vec!["--epochs", "1", "--model", "mingru", "--lr", "1e-12"];
        args.extend_from_slice(extra);
        train_grid(dir, &args)
    };
    let tuned = crate::tmp::tempdir().unwrap();
    let o = run(
        tuned.path(),
        &["--init-from", source.path().to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let first: f64 = losses(tuned.path())[0].1.parse().unwrap();
    assert!(
        ((first - best) / best).abs() < 1e-3,
        "init-from val {first} vs source best {best}"
    );
    assert_eq!(
        meta(tuned.path())["dv_scale"],
        meta(source.path())["dv_scale"]
    );
    let fresh = crate::tmp::tempdir().unwrap();
    let o = run(fresh.path(), &[]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let scratch: f64 = losses(fresh.path())[0].1.parse().unwrap();
    assert!(
        ((scratch - best) / best).abs() > 1e-2,
        "a fresh start scored {scratch}, the source {best}: the test cannot tell them apart"
    );
    let other = crate::tmp::tempdir().unwrap();
    let o = run(
        other.path(),
        &[
            "--init-from",
            source.path().to_str().unwrap(),
            "--window",
            "3",
        ],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("window: checkpoint 2, this run 3"), "{err}");
    assert!(
        !other.path().join("metrics.csv").exists(),
        "the refused run trained"
    );
    // Another network grid is the same network (the U-Net is convolutional): it trains on.
    let regrid = crate::tmp::tempdir().unwrap();
    let o = run(
        regrid.path(),
        &[
            "--init-from",
            source.path().to_str().unwrap(),
            "--grid",
            "32",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(meta(regrid.path())["grid"], 32);
    // (That the weights predict otherwise on the new grid: model_grid.rs; this trained tiny
    // network leans too little on its grid for its validation loss to show it.)
    assert_eq!(
        meta(regrid.path())["dv_scale"],
        meta(source.path())["dv_scale"]
    );
}

/// `--split-from` keeps another split's validation and test scenes held out and trains on
/// every other scene; `--init-from` keeps its run's split by default and its scaler whatever
/// the split; a split none of whose validation scenes is in the data is a usage error.
#[test]
fn grid_train_keeps_the_held_out_scenes_of_another_split() {
    let split = |dir: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("split.json")).unwrap()).unwrap()
    };
    let names = |v: &serde_json::Value| -> Vec<String> {
        v.as_array()
            .unwrap()
            .iter()
            .map(|s| s.as_str().unwrap().to_owned())
            .collect()
    };
    let seeded = crate::tmp::tempdir().unwrap();
    let o = train_grid(seeded.path(), &["--epochs", "1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s0 = split(seeded.path());
    let train0 = names(&s0["train"]);
    assert_eq!(train0.len(), 4, "{s0}");
    // Held out: two scenes the seeded split trains on.
    let saved = serde_json::json!({"train": [], "val": [train0[0]], "test": [train0[1]]});
    let file = seeded.path().join("keep.json");
    std::fs::write(&file, saved.to_string()).unwrap();
    let kept = crate::tmp::tempdir().unwrap();
    let o = train_grid(
        kept.path(),
        &["--epochs", "1", "--split-from", file.to_str().unwrap()],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let s1 = split(kept.path());
    assert_eq!(names(&s1["val"]), [train0[0].clone()]);
    assert_eq!(names(&s1["test"]), [train0[1].clone()]);
    let mut expected: Vec<String> = train0[2..]
        .iter()
        .chain(&names(&s0["val"]))
        .chain(&names(&s0["test"]))
        .cloned()
        .collect();
    expected.sort();
    assert_eq!(names(&s1["train"]), expected);

    // --init-from: its run's split by default; with --split-from another training set, but
    // the parent's scaler (the units its validation and eval scores are in).
    let meta = |dir: &Path| -> serde_json::Value {
        serde_json::from_str(&std::fs::read_to_string(dir.join("model.json")).unwrap()).unwrap()
    };
    let child = crate::tmp::tempdir().unwrap();
    let init = [
        "--epochs",
        "1",
        "--init-from",
        kept.path().to_str().unwrap(),
    ];
    let o = train_grid(child.path(), &init);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(split(child.path()), s1);
    let reseeded = crate::tmp::tempdir().unwrap();
    let seeded_split = seeded.path().join("split.json");
    let mut args = init.to_vec();
    args.extend(["--split-from", seeded_split.to_str().unwrap()]);
    let o = train_grid(reseeded.path(), &args);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(split(reseeded.path()), s0);
    assert_ne!(
        meta(seeded.path())["scaler"],
        meta(kept.path())["scaler"],
        "the two training sets fit the same scaler: the next check cannot fail"
    );
    assert_eq!(meta(reseeded.path())["scaler"], meta(kept.path())["scaler"]);

    let foreign = seeded.path().join("foreign.json");
    let other = serde_json::json!({"train": [], "val": ["multi/jelly/999"], "test": []});
    std::fs::write(&foreign, other.to_string()).unwrap();
    let refused = crate::tmp::tempdir().unwrap();
    let o = train_grid(
        refused.path(),
        &["--epochs", "1", "--split-from", foreign.to_str().unwrap()],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--split-from") && err.contains("validation"),
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

/// `bench train --arch grid` trains each requested kernel and prints one table row per
/// (core, kernel) with a positive samples/s, and the stage times with `--stages`.
#[test]
fn bench_train_measures_the_grid_architecture() {
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args([
            "bench",
            "train",
            "--arch",
            "grid",
            "--cores",
            "none",
            "--conv",
            "gather,shift",
            "--particles",
            "64",
            "--grid",
            "16",
            "--samples",
            "2",
            "--micro-batch",
            "2",
            "--epochs",
            "1",
            "--rollout-steps",
            "2",
            "--stages",
        ])
        .output()
        .unwrap();
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

/// Issue 35: an invalid value of a paper-architecture flag is a usage error whatever the
/// architecture, and a paper-only flag set with `--arch grid` (the default) is refused
/// before any bag is read, naming the flag.
#[test]
fn paper_flags_are_checked_and_refused_with_the_grid_architecture() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("run");
    let bags = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags");
    let run = |extra: &[&str]| {
        let mut args = vec![
            "train",
            "--data",
            bags.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ];
        args.extend_from_slice(extra);
        Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args(&args)
            .output()
            .unwrap()
    };
    let banana = run(&["--decoder", "banana"]);
    assert_eq!(banana.status.code(), Some(2), "{banana:?}");
    let grid = run(&["--width", "48", "--pooling", "max"]);
    assert_eq!(grid.status.code(), Some(2), "{grid:?}");
    let err = String::from_utf8_lossy(&grid.stderr);
    assert!(
        err.contains("--width, --pooling are flags of --arch paper"),
        "{err}"
    );
    assert!(!out.exists(), "nothing written before the refusal");
}
