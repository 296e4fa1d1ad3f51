//! Issue 35, a full disk: `record`, `simulate`, `export` and `train` (checkpoints) run with
//! `RLIMIT_FSIZE` set in the child (a file cannot grow past the limit, as on a disk that
//! filled up; no mount needed), so a write fails mid-run with EFBIG ("File too large"; on a
//! full tmpfs the same paths print "No space left on device"). Each must fail naming the file
//! and the cause with exit code 3, keep what it finished readable, leave no unfinished file
//! under a finished name, and (training) resume from its last good checkpoint.

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::{Command, Output};
use std::time::Duration;

use crate::transport_support::*;

/// Runs `minflow args` with every file it writes limited to `limit` bytes, killed after
/// `timeout`.
fn minflow_limited(args: &[&str], limit: u64, timeout: Duration) -> Output {
    let mut cmd = Command::new(minflow_bin());
    cmd.args(args);
    // SAFETY: only async-signal-safe calls between fork and exec.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: limit,
                rlim_max: limit,
            };
            libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
            match libc::setrlimit(libc::RLIMIT_FSIZE, &lim) {
                0 => Ok(()),
                _ => Err(std::io::Error::last_os_error()),
            }
        });
    }
    Node::start(args[0], &mut cmd).wait(timeout)
}

/// `minflow args` without a limit.
fn minflow(args: &[&str]) -> Output {
    Node::spawn(args[0], args).wait(Duration::from_secs(120))
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Files in `dir` (names), sorted.
fn names(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .map(|d| {
            d.filter_map(Result::ok)
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect()
        })
        .unwrap_or_default();
    v.sort();
    v
}

#[test]
fn record_on_a_full_disk_keeps_a_complete_bag_of_what_it_flushed() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("rec");
    let topic = unique_topic("full_disk");
    let source = source_bag();
    let _player = Node::spawn(
        "replay",
        &[
            "replay",
            source.to_str().unwrap(),
            "--topic",
            &topic,
            "--loop",
            "--rate",
            "4",
            "--wait-for-subscribers",
            "1",
        ],
    );
    let o = minflow_limited(
        &[
            "record",
            "--topic",
            &topic,
            "-o",
            out.to_str().unwrap(),
            // Flushes well inside the ~40 ms the 4x replay takes to fill the 400 kB limit
            // (about ten 40 kB frames), so a loaded machine still flushes some first.
            "--flush-interval",
            "0.01",
        ],
        400_000,
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(
        err.contains("rec_0.mcap") && err.contains("File too large"),
        "names the file and the cause:\n{err}"
    );
    let kept: u64 = err
        .split(" frames kept")
        .next()
        .and_then(|s| s.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no kept count:\n{err}"));
    assert!(kept > 0, "{err}");
    // The bag is closed at its last flush: info and check pass, every kept frame reads.
    for verb in ["info", "check"] {
        let o = minflow(&["bag", verb, out.to_str().unwrap()]);
        assert!(o.status.success(), "bag {verb}: {}", stderr(&o));
    }
    assert_eq!(raw_messages(&out, Some(&topic)).len() as u64, kept);
    let meta = std::fs::read_to_string(out.join("metadata.yaml")).unwrap();
    assert!(meta.contains(&format!("message_count: {kept}")), "{meta}");
}

#[test]
fn simulate_on_a_full_disk_names_the_file_and_leaves_only_finished_bags() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("sim");
    let o = minflow_limited(
        &[
            "simulate",
            "--family",
            "multi",
            "--scenes",
            "0..2",
            "--frames",
            "60",
            "--out",
            out.to_str().unwrap(),
        ],
        150_000,
        Duration::from_secs(120),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(
        err.contains(".mcap.part") && err.contains("File too large"),
        "{err}"
    );
    // Whatever carries the final name is a complete bag.
    for name in names(&out).iter().filter(|n| n.ends_with(".mcap")) {
        let o = minflow(&["bag", "check", out.join(name).to_str().unwrap()]);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
    }
}

#[test]
fn export_on_a_full_disk_leaves_no_truncated_archive() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().join("npz");
    let bag = source_bag();
    let o = minflow_limited(
        &[
            "export",
            "--format",
            "npz",
            bag.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
        ],
        100_000,
        Duration::from_secs(60),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(
        err.contains(".npz.part") && err.contains("File too large"),
        "{err}"
    );
    assert!(!err.contains("ZipWriter"), "{err}");
    assert!(names(&out).is_empty(), "left behind: {:?}", names(&out));
    // Without the limit the same export writes the finished archive.
    let o = minflow(&[
        "export",
        "--format",
        "npz",
        bag.to_str().unwrap(),
        "-o",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(names(&out), ["multi_rope+snow_001.npz"]);
}

/// `train --arch grid` with the tiny network on one bundled bag.
fn train_args<'a>(out: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let mut args = vec!["train", "--data", bags, "--out", out, "--model", "minlstm"];
    args.extend_from_slice(&crate::TINY_GRID_SCHEDULE);
    args.extend_from_slice(&crate::TINY_GRID_NET);
    args.extend_from_slice(extra);
    args
}

#[test]
fn train_on_a_full_disk_resumes_from_its_last_good_checkpoint() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let o = minflow(&train_args(out, &["--epochs", "1"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let mpk = std::fs::metadata(dir.path().join("checkpoint/model.mpk"))
        .unwrap()
        .len();
    // Room for the small files (metrics, history, plot), not for the weights.
    let o = minflow_limited(
        &train_args(out, &["--epochs", "2", "--resume"]),
        mpk / 2,
        Duration::from_secs(120),
    );
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(3), "{err}");
    assert!(
        err.contains(".mpk") && err.contains("File too large"),
        "{err}"
    );
    assert!(!err.contains("MessagePack"), "{err}");
    let left = names(dir.path());
    assert!(
        !left.iter().any(|n| n.contains("tmp")),
        "temporary files left: {left:?}"
    );
    assert!(dir.path().join("checkpoint/model.mpk").is_file());
    // The disk has room again: the run resumes from epoch 1's checkpoint and finishes.
    let o = minflow(&train_args(out, &["--epochs", "2", "--resume"]));
    assert!(o.status.success(), "{}", stderr(&o));
    let csv = std::fs::read_to_string(dir.path().join("metrics.csv")).unwrap();
    assert_eq!(csv.lines().count(), 3, "header and two epochs:\n{csv}");
}
