//! A grid run split into calls (`--call-steps`, each call resumed with `--resume`) ends
//! with the uninterrupted run's losses, to the last digit, and its weights, whether the
//! calls stop mid-epoch or at an epoch's end, in memory and streamed from the bags; its
//! ledger (`run.json`) counts every call and every sample.

use std::path::Path;
use std::process::Command;

use burn::backend::NdArray;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;
use minflow::model::store::Net;

use crate::json;

/// `train --arch grid` with the tiny network and schedule on the bundled bags, a flag of
/// theirs that `extra` sets taking `extra`'s value.
fn train_grid(out: &Path, extra: &[&str]) -> std::process::Output {
    train_grid_on(concat!(env!("CARGO_MANIFEST_DIR"), "/bags"), out, extra)
}

/// [`train_grid`] on the bags of `data`.
fn train_grid_on(data: &str, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["train", "--data", data, "--out", out.to_str().unwrap()];
    let schedule = crate::TINY_GRID_SCHEDULE;
    let set = |f: &[&str]| !extra.contains(&f[0]);
    args.extend(schedule.chunks(2).filter(|f| set(f)).flatten().copied());
    args.extend(
        crate::TINY_GRID_NET
            .chunks(2)
            .filter(|f| set(f))
            .flatten()
            .copied(),
    );
    args.extend_from_slice(extra);
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&args)
        .output()
        .unwrap()
}

fn ok(o: &std::process::Output) {
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// metrics.csv's (train loss, validation loss) per epoch, as text.
fn losses(out: &Path) -> Vec<(String, String)> {
    let text = std::fs::read_to_string(out.join("metrics.csv")).unwrap_or_default();
    (text.lines().skip(1))
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[1].to_owned(), f[2].to_owned())
        })
        .collect()
}

/// Every weight of the run's kept model, in module order (the files themselves differ: a
/// parameter's id is drawn per process).
fn weights(dir: &Path) -> Vec<u32> {
    struct Collect(Vec<u32>);
    impl ModuleVisitor<NdArray<f32>> for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<NdArray<f32>, D>>) {
            let values = param.val().into_data().to_vec::<f32>().unwrap();
            self.0.extend(values.iter().map(|v| v.to_bits()));
        }
    }
    let (net, _) =
        minflow::model::store::load_net::<NdArray<f32>>(dir, &Default::default()).unwrap();
    let Net::Grid(model) = net else {
        panic!("{}: not a grid model", dir.display())
    };
    let mut c = Collect(Vec::new());
    model.visit(&mut c);
    c.0
}

/// One straight run and one of calls of 3 steps (epochs of 4 batches: the calls stop after
/// steps 3, 6 (mid-epoch) and 8 (the end)), with `extra` flags.
fn straight_and_in_calls(extra: &[&str]) {
    let flags = [
        &[
            "--epochs",
            "2",
            "--model",
            "mingru",
            "--mirror",
            "--samples-per-epoch",
            "16",
        ][..],
        extra,
    ]
    .concat();
    let straight = crate::tmp::tempdir().unwrap();
    ok(&train_grid(straight.path(), &flags));
    let calls = crate::tmp::tempdir().unwrap();
    let first = [&flags[..], &["--call-steps", "3"]].concat();
    ok(&train_grid(calls.path(), &first));
    // Stopped mid-epoch 1: no epoch recorded, the unfinished one checkpointed.
    assert!(losses(calls.path()).is_empty());
    let partial = json(&calls.path().join("checkpoint/partial.json"));
    assert_eq!(
        (partial["epoch"].as_u64(), partial["pass"]["steps"].as_u64()),
        (Some(0), Some(3))
    );
    let rest = [&flags[..], &["--call-steps", "3", "--resume"]].concat();
    ok(&train_grid(calls.path(), &rest));
    assert_eq!(
        losses(calls.path()).len(),
        1,
        "the second call finishes epoch 1"
    );
    ok(&train_grid(calls.path(), &rest));
    assert!(!calls.path().join("checkpoint/partial.json").exists());
    let (a, b) = (losses(straight.path()), losses(calls.path()));
    assert_eq!(a.len(), 2);
    assert_eq!(a, b, "(train loss, validation loss) per epoch");
    let (a, b) = (weights(straight.path()), weights(calls.path()));
    assert!(!a.is_empty() && a == b, "the kept weights differ");
    let ledger = json(&calls.path().join("run.json"));
    let samples = json(&straight.path().join("run.json"))["samples"].as_u64();
    assert!(samples.is_some_and(|s| s > 24), "{ledger}");
    assert_eq!(ledger["samples"].as_u64(), samples, "{ledger}");
    let per_call: Vec<u64> = (ledger["calls"].as_array().unwrap().iter())
        .map(|c| c["samples"].as_u64().unwrap())
        .collect();
    assert_eq!(per_call.len(), 3, "{ledger}");
    assert_eq!(Some(per_call.iter().sum::<u64>()), samples, "{ledger}");
    assert!(ledger["device_hours"].as_f64().unwrap() > 0.0, "{ledger}");
    assert_eq!(
        ledger["calls"][0]["devices"][0].as_str(),
        Some("Cpu"),
        "{ledger}"
    );
}

#[test]
fn a_run_in_calls_equals_the_straight_run() {
    straight_and_in_calls(&[]);
}

/// The same streamed from the bags (a budget of two of the bundled 25-frame scenes: chunks
/// of one scene, the next read ahead): the resumed call skips the chunks before its batch.
#[test]
fn a_streamed_run_in_calls_equals_the_straight_run() {
    straight_and_in_calls(&["--max-resident-frames", "50"]);
}

/// A run started `--init-from` a parent (trained on four of the six bundled scenes with
/// another seed: another split, scaler and velocity statistics than this run would fit) and
/// resumed without it (`--resume` refuses `--init-from`) keeps the parent's held-out scenes
/// and normalisation: it ends with the straight run's losses and weights, and its checkpoint
/// is a model folder of its own.
#[test]
fn a_run_from_a_parent_resumes_with_the_parents_split_and_normalisation() {
    let bags = Path::new(env!("CARGO_MANIFEST_DIR")).join("bags");
    let some = crate::tmp::tempdir().unwrap();
    let four = [
        "fluid_circle_000",
        "fluid_splash_002",
        "multi_jelly+liquid_002",
        "multi_rope+snow_001",
    ];
    for scene in four {
        let bag = format!("{scene}.mcap");
        std::fs::copy(bags.join(&bag), some.path().join(&bag)).unwrap();
    }
    let parent = crate::tmp::tempdir().unwrap();
    let parent_flags = ["--epochs", "1", "--seed", "5", "--samples-per-epoch", "16"];
    ok(&train_grid_on(
        some.path().to_str().unwrap(),
        parent.path(),
        &parent_flags,
    ));
    let flags = ["--epochs", "2", "--mirror", "--samples-per-epoch", "16"];
    // What this run would fit on its own: another split and normalisation than the parent's.
    let own = crate::tmp::tempdir().unwrap();
    ok(&train_grid(own.path(), &flags));
    let parent_meta = json(&parent.path().join("model.json"));
    let own_meta = json(&own.path().join("model.json"));
    assert_ne!(parent_meta["scaler"], own_meta["scaler"]);
    assert_ne!(parent_meta["vel_scale"], own_meta["vel_scale"]);

    let from = ["--init-from", parent.path().to_str().unwrap()];
    let straight = crate::tmp::tempdir().unwrap();
    ok(&train_grid(straight.path(), &[&flags[..], &from].concat()));
    let split = json(&straight.path().join("split.json"));
    assert_ne!(split, json(&own.path().join("split.json")));
    let calls = crate::tmp::tempdir().unwrap();
    ok(&train_grid(
        calls.path(),
        &[&flags[..], &from, &["--call-steps", "3"]].concat(),
    ));
    let rest = [&flags[..], &["--call-steps", "3", "--resume"]].concat();
    ok(&train_grid(calls.path(), &rest));
    ok(&train_grid(calls.path(), &rest));
    assert_eq!(json(&calls.path().join("split.json")), split);
    let (a, b) = (losses(straight.path()), losses(calls.path()));
    assert_eq!(a.len(), 2);
    assert_eq!(a, b, "(train loss, validation loss) per epoch");
    assert_eq!(weights(straight.path()), weights(calls.path()));
    // The checkpoint is a model folder: the latest weights with the parent's normalisation.
    let checkpoint = calls.path().join("checkpoint");
    let meta = json(&checkpoint.join("model.json"));
    for field in ["vel_scale", "dv_mean", "dv_scale", "scaler"] {
        assert_eq!(meta[field], parent_meta[field], "{field}");
    }
    assert!(!weights(&checkpoint).is_empty());
}

/// A run stopped in its first epoch (no kept model yet) refuses a resume with other network
/// flags: its checkpoint's `model.json` is what the flags are checked against.
#[test]
fn a_run_stopped_before_its_first_epoch_refuses_other_flags() {
    let flags = [
        "--epochs",
        "2",
        "--samples-per-epoch",
        "16",
        "--call-steps",
        "3",
    ];
    let calls = crate::tmp::tempdir().unwrap();
    ok(&train_grid(calls.path(), &flags));
    assert!(!calls.path().join("model.json").exists());
    assert!(calls.path().join("checkpoint/model.json").exists());
    let other = train_grid(
        calls.path(),
        &[&flags[..], &["--resume", "--box-grid", "64"]].concat(),
    );
    let stderr = String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success(), "{stderr}");
    assert!(stderr.contains("box_grid"), "{stderr}");
    ok(&train_grid(
        calls.path(),
        &[&flags[..], &["--resume"]].concat(),
    ));
}
