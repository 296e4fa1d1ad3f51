//! Grid runs that start from another: `--init-from` (weights, normalisation, the network's
//! levers grown at zero: `--substeps`, `--interaction`) and `--split-from`.

use std::path::{Path, PathBuf};

use crate::cli_train::{eval_briefly, grid_usage_errors, losses, train_grid};
use crate::json;

/// `dir/model.json`.
fn meta(dir: &Path) -> serde_json::Value {
    json(&dir.join("model.json"))
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
    let split = |dir: &Path| json(&dir.join("split.json"));
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

/// A one-epoch run `dir/plain` (which must succeed), then a one-epoch run `dir/NAME` from
/// its weights with `flags` (`--init-from dir/plain`): the two folders and the second run's
/// output.
fn from_a_plain_parent(
    dir: &Path,
    name: &str,
    flags: &[&str],
) -> (PathBuf, PathBuf, std::process::Output) {
    let (plain, child) = (dir.join("plain"), dir.join(name));
    let o = train_grid(&plain, &["--epochs", "1"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let init = plain.to_str().unwrap();
    let mut args = vec!["--epochs", "1"];
    args.extend_from_slice(flags);
    args.extend_from_slice(&["--init-from", init]);
    let o = train_grid(&child, &args);
    (plain, child, o)
}

/// `--substeps S` trains a model whose every call runs the network S times (issue 81's lever),
/// saved with it and evaluated from its folder; a single-frame model fine-tunes into one;
/// substeps with a bundle, or out of range, are usage errors.
#[test]
fn grid_train_with_substeps() {
    let dir = crate::tmp::tempdir().unwrap();
    let (_, sub, o) = from_a_plain_parent(dir.path(), "sub", &["--substeps", "2"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("S = 2 substeps"), "{err}");
    let saved = meta(&sub);
    assert_eq!(saved["substeps"], 2, "{saved}");
    eval_briefly(&sub, &dir.path().join("eval"));
    let bads = [
        &["--substeps", "2", "--bundle", "4"][..],
        &["--substeps", "9"],
    ];
    grid_usage_errors(&dir.path().join("bad"), &bads, "--substeps");
}

/// `--interaction R` trains a model with R rounds of message passing between neighbouring
/// particles (issue 81's GNS lever), saved with its radius and neighbours and evaluated from
/// its folder. `--init-from` a model without it grows it at zero: with a learning rate too
/// small to move the weights, the first validation loss is the parent's best. Out of range
/// it is a usage error.
#[test]
fn grid_train_with_message_passing() {
    let dir = crate::tmp::tempdir().unwrap();
    let grown = [
        "--interaction",
        "2",
        "--interaction-radius",
        "0.05",
        "--lr",
        "1e-12",
        "--lr-final",
        "0",
    ];
    let (plain, mp, o) = from_a_plain_parent(dir.path(), "mp", &grown);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("2 rounds of message passing"), "{err}");
    let saved = meta(&mp);
    assert_eq!(saved["interaction"], 2, "{saved}");
    assert_eq!(saved["interaction_neighbours"], 12, "{saved}");
    let (parent, child) = (losses(&plain), losses(&mp));
    let val = |rows: &[(String, String)]| rows[0].1.parse::<f64>().unwrap();
    let (a, b) = (val(&parent), val(&child));
    assert!((a - b).abs() <= 1e-3 * a, "parent {a}, grown {b}");
    eval_briefly(&mp, &dir.path().join("eval"));
    let bads = [
        &["--interaction", "9"][..],
        &["--interaction", "1", "--interaction-radius", "0.5"],
        &["--interaction", "1", "--interaction-neighbours", "0"],
    ];
    grid_usage_errors(&dir.path().join("bad"), &bads, "--interaction");
}

/// `--box-grid G` clamps the predicted positions into MPM's box on G cells (issue 81's wall
/// lever): a trained model fine-tunes into one, saved with it and evaluated from its folder;
/// a grid below 8 is a usage error.
#[test]
fn grid_train_with_a_box_grid() {
    let dir = crate::tmp::tempdir().unwrap();
    let (plain, wide, o) = from_a_plain_parent(dir.path(), "wide", &["--box-grid", "256"]);
    assert_eq!(meta(&plain)["box_grid"], 0);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(meta(&wide)["box_grid"], 256);
    eval_briefly(&wide, &dir.path().join("eval"));
    let bads = [&["--box-grid", "4"][..]];
    grid_usage_errors(&dir.path().join("bad"), &bads, "--box-grid");
}
