//! `minflow train` end to end on the bundled bags with a tiny network, the paper's
//! architecture: the run folder holds the model, the checkpoint, metrics.csv (one row per
//! epoch), a decodable loss.png, the split and the options; `--resume` continues to more
//! epochs; a dataset larger than `--max-resident-frames` is streamed; bad flags fail clearly.
//! Also the helpers of the grid architecture's files (`cli_train_grid`, `cli_train_init`).

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
pub(crate) fn train_grid(out: &Path, extra: &[&str]) -> std::process::Output {
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

/// The (train, val) loss columns of metrics.csv, as text (exact digits).
pub(crate) fn losses(out: &Path) -> Vec<(String, String)> {
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

/// `eval` of the run folder `model` on the bundled bags, 4 frames from one start, into `out`:
/// it succeeds and writes its table.
pub(crate) fn eval_briefly(model: &Path, out: &Path) {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["eval", "--model", model.to_str().unwrap(), "--data", bags])
        .args(["--split", "all", "--starts", "1", "--horizon", "4"])
        .args(["--no-render", "--no-plausibility"])
        .args(["--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("table.csv").exists());
}

/// Each flag set of `bads`, given to a tiny grid run into `out`, is a usage error (exit 2)
/// whose message names `flag`.
pub(crate) fn grid_usage_errors(out: &Path, bads: &[&[&str]], flag: &str) {
    for bad in bads {
        let o = train_grid(out, bad);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {err}");
        assert!(err.contains(flag), "{bad:?}: {err}");
    }
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
