//! `minflow import` (issue 17, part 3): a LagrangeBench-style dataset (metadata.json and
//! train/valid/test.h5, 300 particles, 12 frames, known positions) and paper-format files,
//! all written here with `hdf5-pure`, come back from the bags as computed by hand: positions
//! mapped into the unit box with one scale, velocities the finite differences, materials
//! from the map or the mass column, stamps and `dt` from the frame spacing. Flags that do
//! not fit the data are usage errors (exit 2) naming the culprit, and the grid model trains
//! on the imported bags (300 particles, not the bundled bags' 2,500).

use std::path::Path;
use std::process::{Command, Output};

use minflow::bag::{read_frames, FRAMES_TOPIC};
use minflow::interop::import::MaterialMap;
use minflow::msgs::ParticleFrame;

const N: usize = 300;
const T: usize = 12;
/// `[[xmin, xmax], [ymin, ymax]]`: 2 wide, 1 high, so the scale is 2.
const BOUNDS: [[f64; 2]; 2] = [[-1.0, 1.0], [0.5, 1.5]];
/// metadata.json's `dt * write_every`.
const FRAME_DT: f64 = 0.002 * 5.0;

/// Position (dataset units) of particle `i` at frame `t` of trajectory `traj`: a grid of
/// particles drifting right and falling with a quadratic term (so backward, forward and
/// central differences all differ).
fn lb_position(traj: usize, t: usize, i: usize) -> [f64; 2] {
    let (col, row) = ((i % 20) as f64, (i / 20) as f64);
    let t = t as f64;
    [
        -0.9 + 0.08 * col + 0.01 * t * (1 + traj) as f64,
        0.6 + 0.05 * row - 0.002 * t * t,
    ]
}

/// LagrangeBench's particle type of particle `i`: every third particle is type 1.
fn lb_type(i: usize) -> i32 {
    i32::from(i.is_multiple_of(3))
}

/// Writes `split.h5` with one group per trajectory id in `trajs`.
fn write_split(dir: &Path, split: &str, trajs: &[usize]) {
    let mut file = hdf5_pure::FileBuilder::new();
    for &traj in trajs {
        let mut group = file.create_group(&format!("{traj:05}"));
        let position: Vec<f64> = (0..T)
            .flat_map(|t| (0..N).flat_map(move |i| lb_position(traj, t, i)))
            .collect();
        group
            .create_dataset("position")
            .with_f64_data(&position)
            .with_shape(&[T as u64, N as u64, 2]);
        let types: Vec<i32> = (0..N).map(lb_type).collect();
        group
            .create_dataset("particle_type")
            .with_i32_data(&types)
            .with_shape(&[N as u64]);
        file.add_group(group.finish());
    }
    file.write(dir.join(format!("{split}.h5"))).unwrap();
}

/// A LagrangeBench dataset folder: train (trajectories 0, 1), valid (2), test (3).
fn write_lagrangebench(dir: &Path) {
    let meta = serde_json::json!({
        "case": "TEST", "solver": "SPH", "dim": 2, "dt": 0.002, "write_every": 5,
        "bounds": BOUNDS, "periodic_boundary_conditions": [false, false, false],
        "num_particles_max": N, "sequence_length_train": T,
    });
    std::fs::write(dir.join("metadata.json"), meta.to_string()).unwrap();
    write_split(dir, "train", &[0, 1]);
    write_split(dir, "valid", &[2]);
    write_split(dir, "test", &[3]);
}

fn minflow(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(args)
        .output()
        .unwrap()
}

/// `minflow import --format FORMAT INPUT -o OUT EXTRA...`.
fn import(format: &str, input: &Path, out: &Path, extra: &[&str]) -> Output {
    let (input, out) = (input.to_str().unwrap(), out.to_str().unwrap());
    minflow(&[&["import", "--format", format, input, "-o", out][..], extra].concat())
}

fn text(o: &Output) -> String {
    format!(
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn frames_of(bag: &Path) -> Vec<ParticleFrame> {
    let read = read_frames(bag, Some(FRAMES_TOPIC)).unwrap();
    read.frames.into_iter().map(|(_, _, f)| f).collect()
}

fn close(a: f32, b: f64, what: &str) {
    assert!(
        (f64::from(a) - b).abs() <= 1e-5 * (1.0 + b.abs()),
        "{what}: {a} != {b}"
    );
}

/// Asserts that `bag` holds trajectory `traj` mapped by hand: `x' = (x + 1) / 2`,
/// `y' = (y - 0.5) / 2`, velocities `(x'[t] - x'[t-1]) / FRAME_DT` (frame 0: the forward
/// difference), type 1 -> rope (3), type 0 -> liquid (0).
fn assert_lagrangebench_bag(bag: &Path, scene: &str, traj: usize) {
    let frames = frames_of(bag);
    assert_eq!(frames.len(), T, "{}", bag.display());
    let unit = |t: usize, i: usize| {
        let [x, y] = lb_position(traj, t, i);
        [(x - BOUNDS[0][0]) / 2.0, (y - BOUNDS[1][0]) / 2.0]
    };
    for (t, f) in frames.iter().enumerate() {
        assert_eq!((f.scene.as_str(), f.frame_index), (scene, t as u32));
        assert_eq!(f.header.frame_id, "world");
        assert_eq!(f.header.stamp.as_nanos(), t as i64 * 10_000_000);
        assert_eq!(f.dt, 0.01);
        assert_eq!(f.len(), N);
        let (a, b) = if t == 0 { (0, 1) } else { (t - 1, t) };
        for i in 0..N {
            let (p, before, after) = (unit(t, i), unit(a, i), unit(b, i));
            for k in 0..2 {
                close(f.position[2 * i + k], p[k], "position");
                let v = (after[k] - before[k]) / FRAME_DT;
                close(f.velocity[2 * i + k], v, "velocity");
            }
            let material = if lb_type(i) == 1 { 3 } else { 0 };
            assert_eq!(f.material[i], material, "particle {i}");
        }
    }
}

/// The whole dataset becomes four bags, value for value, and the grid model trains on them.
#[test]
fn lagrangebench_dataset_imports_and_trains() {
    let dir = crate::tmp::tempdir().unwrap();
    let (data, out) = (dir.path().join("lb"), dir.path().join("bags"));
    std::fs::create_dir(&data).unwrap();
    write_lagrangebench(&data);
    let o = import(
        "lagrangebench",
        &data,
        &out,
        &["--material-map", "0=liquid,1=rope"],
    );
    assert!(o.status.success(), "{}", text(&o));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(stdout.lines().count(), 4, "{stdout}");
    for (split, traj) in [("train", 0), ("train", 1), ("valid", 2), ("test", 3)] {
        let scene = format!("lagrangebench/{split}/{traj:05}");
        let bag = out.join(format!("lagrangebench_{split}_{traj:05}.mcap"));
        assert!(stdout.contains(&scene), "{stdout}");
        assert_lagrangebench_bag(&bag, &scene, traj);
    }
    let o = minflow(&["bag", "info", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));

    let run = dir.path().join("run");
    let mut args = vec![
        "train",
        "--data",
        out.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
        "--epochs",
        "1",
    ];
    args.extend_from_slice(&crate::TINY_GRID_SCHEDULE);
    args.extend_from_slice(&crate::TINY_GRID_NET);
    let o = minflow(&args);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(
        std::fs::read_to_string(run.join("metrics.csv"))
            .unwrap()
            .lines()
            .count(),
        2,
        "one epoch of metrics"
    );
}

/// `--splits` picks the files, `--dt` overrides metadata.json's frame spacing.
#[test]
fn lagrangebench_splits_and_dt_flags() {
    let dir = crate::tmp::tempdir().unwrap();
    let (data, out) = (dir.path().join("lb"), dir.path().join("bags"));
    std::fs::create_dir(&data).unwrap();
    write_lagrangebench(&data);
    let o = import(
        "lagrangebench",
        &data,
        &out,
        &[
            "--material-map",
            "0=snow,1=jelly",
            "--splits",
            "valid",
            "--dt",
            "0.02",
        ],
    );
    assert!(o.status.success(), "{}", text(&o));
    let names: Vec<_> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(names, ["lagrangebench_valid_00002.mcap"]);
    let frames = frames_of(&out.join(&names[0]));
    assert_eq!(frames[3].dt, 0.02);
    assert_eq!(frames[3].header.stamp.as_nanos(), 60_000_000);
    let v = (lb_position(2, 3, 0)[0] - lb_position(2, 2, 0)[0]) / 2.0 / 0.02;
    close(frames[3].velocity[0], v, "velocity at --dt");
    assert_eq!(&frames[0].material[..3], [1, 2, 2]);
}

/// A particle type missing from the map, a malformed map and a flag of the other format are
/// usage errors (exit 2) that name the type or flag, and no bag is written.
#[test]
fn import_flag_errors_are_usage_errors() {
    let dir = crate::tmp::tempdir().unwrap();
    let (data, out) = (dir.path().join("lb"), dir.path().join("bags"));
    std::fs::create_dir(&data).unwrap();
    write_lagrangebench(&data);
    let o = import("lagrangebench", &data, &out, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("particle type 1") && err.contains("--material-map"),
        "{err}"
    );
    assert!(
        !out.exists(),
        "nothing written before the types are checked"
    );
    for bad in [
        &["--material-map", "0=water"][..],
        &["--material-map", "zero=liquid"],
        &["--material-map", "0=liquid,0=rope"],
        &["--splits", "training"],
        &["--dataset", "x"],
        &["--dt", "0"],
    ] {
        let o = import("lagrangebench", &data, &out, bad);
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {}", text(&o));
    }
    let parsed: MaterialMap = "1=rope, 0=liquid ,7=2".parse().unwrap();
    assert_eq!(parsed.to_string(), "0=liquid,1=rope,7=snow");
}

/// Paper layout (T, N, F = 6): x, y, vx, vy, m and one extra feature.
fn paper_values(t: usize, i: usize) -> [f64; 6] {
    let (t, f) = (t as f64, i as f64);
    [
        0.1 + 0.002 * f,
        0.2 + 0.01 * t,
        0.5 - 0.001 * f,
        -0.3 * t,
        (i % 4) as f64,
        9.0,
    ]
}

/// A paper-format file: positions and velocities come back as stored, materials from m,
/// frames `--dt` apart; a file of several datasets needs `--dataset` (exit 2 listing them).
#[test]
fn paper_file_imports() {
    let dir = crate::tmp::tempdir().unwrap();
    let (file, out) = (dir.path().join("sim.h5"), dir.path().join("bags"));
    let values: Vec<f64> = (0..T)
        .flat_map(|t| (0..N).flat_map(move |i| paper_values(t, i)))
        .collect();
    let mut h5 = hdf5_pure::FileBuilder::new();
    h5.create_dataset("rollout")
        .with_f64_data(&values)
        .with_shape(&[T as u64, N as u64, 6]);
    h5.create_dataset("other").with_f64_data(&[1.0]);
    h5.write(&file).unwrap();
    let o = import("paper", &file, &out, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("--dataset") && err.contains("other, rollout"),
        "{err}"
    );

    let o = import("paper", &file, &out, &["--dataset", "rollout"]);
    assert!(o.status.success(), "{}", text(&o));
    let frames = frames_of(&out.join("paper_sim_rollout.mcap"));
    assert_eq!(frames.len(), T);
    for (t, f) in frames.iter().enumerate() {
        assert_eq!(
            (f.scene.as_str(), f.frame_index),
            ("paper/sim/rollout", t as u32)
        );
        assert_eq!(f.dt, 0.016);
        assert_eq!(f.header.stamp.as_nanos(), t as i64 * 16_000_000);
        for i in 0..N {
            let p = paper_values(t, i);
            assert_eq!(f.position[2 * i..2 * i + 2], [p[0] as f32, p[1] as f32]);
            assert_eq!(f.velocity[2 * i..2 * i + 2], [p[2] as f32, p[3] as f32]);
            assert_eq!(f.material[i], (i % 4) as u8);
        }
    }
}

/// A mass that is no material id is an error naming the particle and frame.
#[test]
fn paper_bad_mass_is_an_error() {
    let dir = crate::tmp::tempdir().unwrap();
    let (file, out) = (dir.path().join("bad.h5"), dir.path().join("bags"));
    let mut values: Vec<f64> = (0..2)
        .flat_map(|t| (0..4).flat_map(move |i| paper_values(t, i)[..5].to_vec()))
        .collect();
    values[5 * 4 + 2 * 5 + 4] = 7.0; // frame 1, particle 2
    let mut h5 = hdf5_pure::FileBuilder::new();
    h5.create_dataset("d")
        .with_f64_data(&values)
        .with_shape(&[2, 4, 5]);
    h5.write(&file).unwrap();
    let o = import("paper", &file, &out, &[]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("particle 2 of frame 1 has m = 7"), "{err}");
}

/// An (S, T, N, F) dataset is S trajectories, one bag each, scenes numbered after the
/// dataset; `--dt` sets the frame spacing.
#[test]
fn paper_4d_dataset_is_one_bag_per_trajectory() {
    let dir = crate::tmp::tempdir().unwrap();
    let (file, out) = (dir.path().join("multi.h5"), dir.path().join("bags"));
    let value = |s: usize, t: usize, i: usize| -> [f64; 5] {
        let base = paper_values(t, i);
        [
            base[0] + 0.1 * s as f64,
            base[1],
            base[2],
            base[3] * s as f64,
            3.0,
        ]
    };
    let values: Vec<f64> = (0..2)
        .flat_map(|s| (0..3).flat_map(move |t| (0..4).flat_map(move |i| value(s, t, i))))
        .collect();
    let mut h5 = hdf5_pure::FileBuilder::new();
    h5.create_dataset("d")
        .with_f64_data(&values)
        .with_shape(&[2, 3, 4, 5]);
    h5.write(&file).unwrap();
    let o = import("paper", &file, &out, &["--dt", "0.5"]);
    assert!(o.status.success(), "{}", text(&o));
    for s in 0..2 {
        let frames = frames_of(&out.join(format!("paper_multi_d_{s:03}.mcap")));
        assert_eq!(frames.len(), 3);
        for (t, f) in frames.iter().enumerate() {
            assert_eq!(f.scene, format!("paper/multi/d/{s:03}"));
            assert_eq!(
                (f.dt, f.header.stamp.as_nanos()),
                (0.5, t as i64 * 500_000_000)
            );
            for i in 0..4 {
                let p = value(s, t, i);
                assert_eq!(f.position[2 * i..2 * i + 2], [p[0] as f32, p[1] as f32]);
                assert_eq!(f.velocity[2 * i..2 * i + 2], [p[2] as f32, p[3] as f32]);
            }
            assert_eq!(f.material, [3; 4]);
        }
    }
}
