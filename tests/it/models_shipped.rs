//! Every run folder shipped under `models/` loads in every command that reads one, with one
//! short rollout each: `eval` (horizon 5 on one bundled bag), `node` over zenoh (a few
//! predicted frames of a replayed bag) and `bench node --skip-node` (`eval` and `bench` take
//! all the folders in one run). Folders saved before a
//! field of `model.json` existed must still load (issue 33: `eval` failed on
//! `models/all-grid-mingru-small` with "missing field `reference`").

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::Duration;

use crate::transport_support::*;

const BAG: &str = "bags/multi_rope+snow_001.mcap";

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The folders under `models/` that hold a `model.json`, sorted.
fn shipped() -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(repo("models"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("model.json").is_file())
        .collect();
    dirs.sort();
    assert!(!dirs.is_empty(), "no run folder under models/");
    dirs
}

/// `minflow args...` from the repository root, at most `timeout`.
fn minflow(args: &[&str], timeout: Duration) -> Output {
    let mut child = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(args)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let deadline = std::time::Instant::now() + timeout;
    while child.try_wait().unwrap().is_none() {
        if std::time::Instant::now() > deadline {
            let _ = child.kill();
            break;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    child.wait_with_output().unwrap()
}

/// `--model DIR` once per shipped folder, for the commands that take several.
fn every_model_flag() -> Vec<String> {
    shipped()
        .iter()
        .flat_map(|d| ["--model".to_owned(), d.to_str().unwrap().to_owned()])
        .collect()
}

/// One `eval` of all the shipped models together (the bag's ground truth is loaded and
/// scored once): each has its column of scores in the table, a number on every row.
#[test]
fn every_shipped_model_evaluates() {
    let out = crate::tmp::tempdir().unwrap();
    let mut args = vec!["eval".to_owned()];
    args.extend(every_model_flag());
    args.extend(
        [
            "--data",
            BAG,
            "--split",
            "all",
            "--horizon",
            "5",
            "--no-render",
        ]
        .map(String::from),
    );
    args.extend(["--out".to_owned(), out.path().to_str().unwrap().to_owned()]);
    let o = minflow(
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        Duration::from_secs(240),
    );
    ok(&o, "eval of every shipped model");
    let table = std::fs::read_to_string(out.path().join("table.csv")).unwrap();
    let rows: Vec<Vec<&str>> = table.lines().map(|l| l.split(',').collect()).collect();
    for dir in shipped() {
        let name = dir.file_name().unwrap().to_str().unwrap();
        let column = rows[0].iter().position(|h| *h == format!("avg5_{name}"));
        let column = column.unwrap_or_else(|| panic!("no column of {name} in {table}"));
        for row in &rows[1..] {
            let score = row.get(column).and_then(|v| v.parse::<f64>().ok());
            assert!(score.is_some_and(f64::is_finite), "{name}: {row:?}");
        }
    }
}

#[test]
fn every_shipped_model_serves_as_a_node_over_zenoh() {
    for dir in shipped() {
        let name = dir.file_name().unwrap().to_str().unwrap().to_owned();
        let input = unique_topic("shipped_in");
        let node = Node::spawn(
            "node",
            &[
                "node",
                "--model",
                dir.to_str().unwrap(),
                "--transport",
                "zenoh",
                "--in",
                &input,
                "--out",
                &unique_topic("shipped_out"),
                "--status",
                "none",
                "--max-published",
                "3",
            ],
        );
        let replay = Node::spawn(
            "replay",
            &[
                "replay",
                "--transport",
                "zenoh",
                "--topic",
                &input,
                "--rate",
                "0",
                repo(BAG).to_str().unwrap(),
            ],
        );
        let err = ok(
            &node.wait(Duration::from_secs(120)),
            &format!("node {name}"),
        );
        drop(replay);
        assert_eq!(counter(&err, "published"), Some(3), "{name}: {err}");
        assert_eq!(counter(&err, "rejected"), Some(0), "{name}: {err}");
    }
}

/// One `bench node --skip-node` of all the shipped models together: each has its row in the
/// batched table.
#[test]
fn every_shipped_model_benches() {
    let mut args = ["bench", "node"].map(String::from).to_vec();
    args.extend(every_model_flag());
    args.extend(["--skip-node", "--batch", "1"].map(String::from));
    let o = minflow(
        &args.iter().map(String::as_str).collect::<Vec<_>>(),
        Duration::from_secs(240),
    );
    ok(&o, "bench node of every shipped model");
    let stdout = String::from_utf8_lossy(&o.stdout);
    for dir in shipped() {
        let name = dir.file_name().unwrap().to_str().unwrap();
        assert!(
            stdout.contains(&format!("| {name} | 1 |")),
            "{name}: {stdout}"
        );
    }
}
