//! `minflow import` on files written by the reference HDF5 library: h5py
//! (`tests/python/write_lagrangebench.py`) writes a LagrangeBench-style dataset whose
//! positions are chunked and gzip-compressed, in a periodic box where particles cross the x
//! boundary; the pure-Rust reader must give back every value, and the velocities must be
//! unwrapped across the boundary (minimum image), as LagrangeBench's own displacement does.
//!
//! The interpreter: [`crate::python_support::interpreter`].

use std::path::Path;
use std::process::Command;

use crate::python_support::{interpreter, INSTALL_HINT};
use minflow::bag::{read_frames, FRAMES_TOPIC};

const N: usize = 300;
const T: usize = 12;

/// `position` of the script: x = (0.5 + 0.3 u + 0.07 t) mod 1, y = 0.25 + 0.1 u + 0.001 t,
/// u = i / N. Bounds [0, 1] x [0, 0.5]: the scale is 1, so the unit box is the data's frame.
fn h5py_position(t: usize, i: usize) -> [f64; 2] {
    let (t, u) = (t as f64, i as f64 / N as f64);
    [(0.5 + 0.3 * u + 0.07 * t) % 1.0, 0.25 + 0.1 * u + 0.001 * t]
}

fn write_dataset(dir: &Path) {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/write_lagrangebench.py");
    let o = Command::new(interpreter())
        .arg(script)
        .arg(dir)
        .args([T.to_string(), N.to_string()])
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "{}\n(install: {INSTALL_HINT})",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Every position comes back as h5py wrote it; every velocity is the unwrapped step over
/// the frame spacing 0.01 * 2: (0.07, 0.001) / 0.02 = (3.5, 0.05), across the boundary too.
#[test]
fn h5py_written_lagrangebench_dataset_imports() {
    let dir = crate::tmp::tempdir().unwrap();
    let (data, out) = (dir.path().join("lb"), dir.path().join("bags"));
    std::fs::create_dir(&data).unwrap();
    write_dataset(&data);
    let o = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["import", "--format", "lagrangebench"])
        .arg(&data)
        .arg("-o")
        .arg(&out)
        .args(["--material-map", "0=liquid,1=snow"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut crossed = 0;
    for bag in [
        "lagrangebench_train_00000.mcap",
        "lagrangebench_valid_00007.mcap",
    ] {
        let frames = read_frames(out.join(bag), Some(FRAMES_TOPIC))
            .unwrap()
            .frames;
        assert_eq!(frames.len(), T, "{bag}");
        for (t, (_, _, f)) in frames.iter().enumerate() {
            assert_eq!(f.dt, 0.02);
            assert_eq!(f.header.stamp.as_nanos(), t as i64 * 20_000_000);
            for i in 0..N {
                let p = h5py_position(t, i);
                assert_eq!(
                    f.position[2 * i],
                    p[0] as f32,
                    "{bag} frame {t} particle {i}"
                );
                assert_eq!(f.position[2 * i + 1], p[1] as f32);
                assert!(
                    (f.velocity[2 * i] - 3.5).abs() < 1e-4,
                    "{}",
                    f.velocity[2 * i]
                );
                assert!((f.velocity[2 * i + 1] - 0.05).abs() < 1e-4);
                assert_eq!(f.material[i], [0, 2][i % 2]);
                if t > 0 && p[0] < h5py_position(t - 1, i)[0] {
                    crossed += 1;
                }
            }
        }
    }
    assert!(
        crossed > 100,
        "the data crosses the boundary ({crossed} steps)"
    );
}
