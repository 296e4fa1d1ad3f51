//! `minflow report` (issue 4) end to end on the bundled bags with two tiny cores in both
//! architectures and one epoch: REPORT.md states the machine, the configuration and the seed
//! and holds Tables 2, 3 and 4 with the paper's and the grid architecture side by side, and
//! the figures it links to; `--reuse` skips training.

use std::process::Command;

#[test]
fn report_trains_evaluates_and_writes_report_md() {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let tmp = crate::tmp::tempdir().unwrap();
    let out = tmp.path().join("report");
    let mut args = vec![
        "report",
        "--data",
        bags,
        "--out",
        out.to_str().unwrap(),
        "--cores",
        "mlp,mingru",
        "--epochs",
        "1",
        "--width",
        "24",
        "--encoder-hidden",
        "8",
        "--seed",
        "3",
        "--samples-per-epoch",
        "8",
    ];
    args.extend(crate::TINY_GRID_NET);
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&args)
        .args(["--eval-split", "all"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let report = std::fs::read_to_string(out.join("REPORT.md")).unwrap();
    for needle in [
        "logical cores",
        "- seed: 3",
        "## Table 2: fluid scenes",
        "## Table 3: multi-material scenes",
        "## Table 4: training speed",
        "| `fluid/circle/000` |",
        "| `multi/rope+snow/001` |",
        "| paper-mingru |",
        "| grid-mingru |",
        "avg20 paper-mlp",
        "avg20 grid-none",
        "f20 constvel",
        "not only held-out test",
        "minflow train --data",
    ] {
        assert!(report.contains(needle), "missing {needle:?} in\n{report}");
    }
    for file in [
        "eval/mse_curves.png",
        "eval/table.csv",
        "eval/render_fluid_circle_000.gif",
        "runs/paper-mingru/model.json",
        "runs/paper-mlp/loss.png",
        "runs/grid-mingru/model.json",
        "runs/grid-none/loss.png",
    ] {
        assert!(out.join(file).exists(), "missing {file}");
    }
    // Table 4 has one row per run with one epoch each.
    let rows: Vec<&str> = report
        .lines()
        .filter(|l| {
            [
                "| paper-mlp |",
                "| paper-mingru |",
                "| grid-none |",
                "| grid-mingru |",
            ]
            .iter()
            .any(|p| l.starts_with(p))
        })
        .filter(|l| l.split('|').count() == 10)
        .collect();
    assert_eq!(rows.len(), 4, "{rows:?}");
    assert!(rows
        .iter()
        .all(|r| r.split('|').nth(3).unwrap().trim() == "1"));

    // Rerun with --reuse: nothing is trained again (metrics.csv untouched). It evaluates the
    // test split only (one scene): what it reuses does not depend on what is evaluated.
    let before = std::fs::metadata(out.join("runs/paper-mlp/metrics.csv"))
        .unwrap()
        .modified()
        .unwrap();
    let mut again: Vec<&str> = args.to_vec();
    again.extend(["--eval-split", "test", "--reuse"]);
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(&again)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stderr).contains("paper-mlp: reusing"));
    let after = std::fs::metadata(out.join("runs/paper-mlp/metrics.csv"))
        .unwrap()
        .modified()
        .unwrap();
    assert_eq!(before, after);
}

/// The flags `report` hands to `train` and `eval` keep those commands' range checks: a zero
/// is a usage error naming the flag, before any folder is made or any run trains.
#[test]
fn report_flags_out_of_range_are_usage_errors() {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let tmp = crate::tmp::tempdir().unwrap();
    let out = tmp.path().join("report");
    for flag in [
        "--epochs",
        "--batch-size",
        "--window",
        "--width",
        "--horizon",
        "--starts",
    ] {
        let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args([
                "report",
                "--data",
                bags,
                "--out",
                out.to_str().unwrap(),
                flag,
                "0",
            ])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{flag}: {err}");
        assert!(err.contains(flag), "{flag}: {err}");
        assert!(!out.exists(), "{flag}: the report folder was made");
    }
}
