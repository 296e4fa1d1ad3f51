//! The `minflow` binary end to end: `simulate` writes bags that `bag info` and `bag check`
//! accept and that read back frame for frame as the simulator made them; the same scene id
//! and seed give byte-identical bags (docs/mpm.md, "Validation checks", check 7); a truncated bag is reported with
//! exit code 3; the bundled sample in `bags/` is valid.

use minflow::bag::read_frames;
use minflow::sim::families::{self, Family};
use minflow::sim::SceneRun;
use std::path::Path;
use std::process::Command;

fn minflow(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(args)
        .output()
        .expect("running minflow")
}

fn simulate(out: &Path, family: &str, scenes: &str, frames: &str) {
    let o = minflow(&[
        "simulate",
        "--family",
        family,
        "--scenes",
        scenes,
        "--frames",
        frames,
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn simulate_writes_bags_that_read_back_exactly() {
    let dir = crate::tmp::tempdir().unwrap();
    simulate(dir.path(), "fluid", "1..3", "12");
    let bag = dir.path().join("fluid_rectangle_001.mcap");
    let outcome = read_frames(&bag, None).unwrap();
    assert!(outcome.truncated.is_none());
    let mut scene = families::scene(Family::Fluid, 1, 0);
    scene.frames = 12;
    let expected: Vec<_> = SceneRun::new(scene)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(outcome.frames.len(), 12);
    for (k, ((topic, log_time, frame), want)) in outcome.frames.iter().zip(&expected).enumerate() {
        assert_eq!(topic, "/mpm/frames");
        assert_eq!(*log_time, k as u64 * 16_000_000, "log_time = stamp in ns");
        assert_eq!(frame, want);
    }
    let info = minflow(&["bag", "info", bag.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&info.stdout);
    assert!(info.status.success());
    for needle in [
        "Messages:          12",
        "minflow_msgs/msg/ParticleFrame",
        "fluid/rectangle/001",
        "liquid 2500",
    ] {
        assert!(text.contains(needle), "missing {needle:?} in\n{text}");
    }
    let check = minflow(&["bag", "check", dir.path().to_str().unwrap()]);
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
    assert!(!dir.path().join("fluid_rectangle_001.mcap.part").exists());
}

#[test]
fn same_scene_and_seed_give_identical_bags() {
    let (a, b) = (
        crate::tmp::tempdir().unwrap(),
        crate::tmp::tempdir().unwrap(),
    );
    simulate(a.path(), "multi", "5,6", "15");
    simulate(b.path(), "multi", "5,6", "15");
    for id in [5, 6] {
        let name = minflow::cli::bag_name(&families::scene(Family::Multi, id, 0).name);
        let x = std::fs::read(a.path().join(&name)).unwrap();
        let y = std::fs::read(b.path().join(&name)).unwrap();
        assert!(x == y, "{name} differs between two runs");
    }
    let other = crate::tmp::tempdir().unwrap();
    let o = minflow(&[
        "simulate",
        "--scenes",
        "5",
        "--frames",
        "15",
        "--seed",
        "1",
        "--out",
        other.path().to_str().unwrap(),
    ]);
    assert!(o.status.success());
    let name = minflow::cli::bag_name(&families::scene(Family::Multi, 5, 0).name);
    let seeded = std::fs::read(other.path().join(&name)).unwrap();
    assert_ne!(seeded, std::fs::read(a.path().join(&name)).unwrap());
}

#[test]
fn truncated_bag_is_reported_with_exit_code_3() {
    let dir = crate::tmp::tempdir().unwrap();
    simulate(dir.path(), "multi", "0", "40");
    let bag = dir.path().join("multi_liquid+snow_000.mcap");
    let bytes = std::fs::read(&bag).unwrap();
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let info = minflow(&["bag", "info", cut.to_str().unwrap()]);
    assert_eq!(
        info.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&info.stderr)
    );
    let read = read_frames(&cut, None).unwrap();
    assert!(read.truncated.is_some());
    assert!(!read.frames.is_empty() && read.frames.len() < 40);
    for (k, (_, _, f)) in read.frames.iter().enumerate() {
        assert_eq!(f.frame_index as usize, k);
    }
    // replay plays what was read and exits 3 as well.
    let topic = format!("/minflow_test_{}_cut/frames", std::process::id());
    let o = minflow(&[
        "replay",
        cut.to_str().unwrap(),
        "--rate",
        "0",
        "--wait-for-subscribers",
        "0",
        "--topic",
        &topic,
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "replay: {stderr}");
    assert!(
        stderr.contains(&format!("replay: {} frame(s)", read.frames.len())),
        "{stderr}"
    );
    // train (both architectures) and eval use the frames before the damage and exit 3 too.
    let cut = cut.to_str().unwrap();
    let grid = dir.path().join("grid");
    let paper = dir.path().join("paper");
    let mut tiny_grid = crate::TINY_GRID_NET.to_vec();
    tiny_grid.extend([
        "--rollout-steps",
        "2",
        "--batch-size",
        "4",
        "--samples-per-epoch",
        "8",
        "--epochs",
        "1",
    ]);
    let tiny_paper = [
        "--arch",
        "paper",
        "--width",
        "16",
        "--encoder-hidden",
        "8",
        "--epochs",
        "1",
    ];
    for (out, flags) in [(&grid, &tiny_grid[..]), (&paper, &tiny_paper[..])] {
        let mut args = vec!["train", "--data", cut, "--out", out.to_str().unwrap()];
        args.extend_from_slice(flags);
        let o = minflow(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(3), "{args:?}: {stderr}");
        assert!(stderr.contains("truncated or damaged"), "{stderr}");
        assert!(out.join("model.json").exists(), "{args:?}: no model");
    }
    let o = minflow(&[
        "eval",
        "--model",
        grid.to_str().unwrap(),
        "--data",
        cut,
        "--split",
        "all",
        "--horizon",
        "5",
        "--starts",
        "1",
        "--no-render",
        "--out",
        dir.path().join("eval").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    assert!(stderr.contains("truncated or damaged"), "{stderr}");
}

/// Ids beyond the family's 60 keep cycling through its scene kinds (id 60 is a
/// liquid+snow pairing like id 0, id 64 a single liquid body like id 4) with placements of
/// their own: more training scenes of the same kinds.
#[test]
fn ids_beyond_the_family_are_more_scenes_of_its_kinds() {
    let dir = crate::tmp::tempdir().unwrap();
    simulate(dir.path(), "multi", "0,60,64", "3");
    let mut names: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "multi_liquid+snow_000.mcap",
            "multi_liquid+snow_060.mcap",
            "multi_liquid_064.mcap"
        ]
    );
    let a = std::fs::read(dir.path().join("multi_liquid+snow_000.mcap")).unwrap();
    let b = std::fs::read(dir.path().join("multi_liquid+snow_060.mcap")).unwrap();
    assert_ne!(a.len(), 0);
    assert_ne!(a, b, "id 60 repeated id 0's scene");
}

/// `--grid` puts the family's scenes on a finer grid with proportionally more particles
/// (docs/mpm.md, "The solver on a GPU"): a `multi` scene on 128 x 128 has 10,000 particles,
/// 80 substeps a frame and its name marked with the grid; a grid that is no multiple of the
/// scene's is a usage error before any work.
#[test]
fn simulate_refines_scenes_onto_a_finer_grid() {
    let dir = crate::tmp::tempdir().unwrap();
    let out = dir.path().to_str().unwrap();
    let o = minflow(&[
        "simulate", "--family", "multi", "--scenes", "1", "--frames", "2", "--grid", "128",
        "--out", out,
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let bag = dir.path().join("multi@128_rope+snow_001.mcap");
    let frames: Vec<_> = read_frames(&bag, None)
        .unwrap()
        .frames
        .into_iter()
        .map(|(_, _, frame)| frame)
        .collect();
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[1].len(), 10_000);
    assert_eq!(frames[1].scene, "multi@128/rope+snow/001");
    let mut run =
        SceneRun::new(families::scene(Family::Multi, 1, 0).refined(128).unwrap()).unwrap();
    assert_eq!(run.scene().substeps, 80);
    let truth = run.nth(1).unwrap().unwrap();
    assert_eq!(
        frames[1].position, truth.position,
        "the bag holds the refined scene's frame"
    );
    let o = minflow(&[
        "simulate", "--family", "multi", "--grid", "96", "--out", out,
    ]);
    assert_eq!(o.status.code(), Some(2), "--grid 96 on a 64 grid");
    assert!(String::from_utf8_lossy(&o.stderr).contains("--grid 96"));
}

#[test]
fn bad_arguments_fail_clearly() {
    let o = minflow(&["simulate", "--family", "gas", "--out", "/tmp/never"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&o.stderr).contains("unknown family"));
    let o = minflow(&["bag", "info", "/nonexistent/x.mcap"]);
    assert_eq!(o.status.code(), Some(1));
    let o = minflow(&["simulate", "--bogus"]);
    assert_eq!(o.status.code(), Some(2), "usage errors exit 2");
    // Scene ids are usage errors too, though checked after parsing (they need --family).
    for scenes in ["5..2", "x", "", "1,1"] {
        let o = minflow(&["simulate", "--scenes", scenes, "--out", "/tmp/never"]);
        assert_eq!(o.status.code(), Some(2), "--scenes {scenes:?}");
        assert!(String::from_utf8_lossy(&o.stderr).contains("--scenes"));
    }
    let o = minflow(&["simulate", "--frames", "0", "--out", "/tmp/never"]);
    assert_eq!(o.status.code(), Some(2), "--frames 0");
    // The GPU solver needs a `cuda` build: an error, before any work, that says how to get one.
    if !cfg!(feature = "cuda") {
        let o = minflow(&["simulate", "--device", "cuda", "--out", "/tmp/never"]);
        assert_eq!(
            o.status.code(),
            Some(1),
            "--device cuda without the feature"
        );
        assert!(!Path::new("/tmp/never").exists());
        assert!(String::from_utf8_lossy(&o.stderr).contains("--features cuda"));
    }
    assert!(String::from_utf8_lossy(&o.stderr).contains("--frames"));
    // Scene file values are usage errors naming the field: an empty name (it used to write a
    // hidden `.mcap` that `bag info DIR` cannot find), two files naming one scene.
    let dir = crate::tmp::tempdir().unwrap();
    let example = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/launch_configs/scenes/example.toml"
    ))
    .unwrap();
    let name_line = example
        .lines()
        .find(|l| l.starts_with("name"))
        .expect("the example names its scene");
    let file = |name: &str, text: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        path.to_str().unwrap().to_owned()
    };
    let out = dir.path().join("out");
    let empty = file("empty.toml", &example.replace(name_line, "name = \"\""));
    let same = file("same.toml", &example);
    for files in [&[empty.as_str()][..], &[same.as_str(), same.as_str()][..]] {
        let mut args = vec!["simulate", "--frames", "2", "--out", out.to_str().unwrap()];
        files.iter().for_each(|f| args.extend(["--scene-file", f]));
        let o = minflow(&args);
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{files:?}: {stderr}");
        assert!(
            stderr.contains("--scene-file") && stderr.contains("name"),
            "{stderr}"
        );
        assert!(!out.join(".mcap").exists());
    }
}

#[test]
fn bundled_bags_are_valid() {
    let bags = concat!(env!("CARGO_MANIFEST_DIR"), "/bags");
    let check = minflow(&["bag", "check", bags]);
    assert!(
        check.status.success(),
        "{}",
        String::from_utf8_lossy(&check.stdout)
    );
    let info = String::from_utf8_lossy(&minflow(&["bag", "info", bags]).stdout).to_string();
    assert!(info.contains("multi/") && info.contains("fluid/"), "{info}");
}
