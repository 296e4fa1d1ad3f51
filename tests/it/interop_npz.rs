//! `minflow export --format npz` (issue 17, part 3): bags written here with known frames (two
//! scenes of different particle counts, one with a missing frame) come back from the `.npz`
//! archives value for value, with numpy's dtypes and shapes, one archive per trajectory.

use std::fs::File;
use std::io::Read;
use std::path::Path;
use std::process::Command;

use minflow::bag::BagWriter;
use minflow::msgs::{Header, ParticleFrame, Time};
use ndarray::{Array0, Array1, Array3};
use ndarray_npy::NpzReader;

const TOPIC: &str = "/mpm/frames";

fn frame(scene: &str, index: u32, n: usize) -> ParticleFrame {
    let v = |i: usize, k: usize| (i * 7 + k * 3 + index as usize) as f32 * 0.01 - 0.2;
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(index) * 10_000_000),
            frame_id: "world".into(),
        },
        scene: scene.into(),
        frame_index: index,
        dt: 0.01,
        position: (0..2 * n).map(|i| v(i, 1).abs()).collect(),
        velocity: (0..2 * n).map(|i| v(i, 2)).collect(),
        material: (0..n).map(|i| (i % 4) as u8).collect(),
    }
}

fn write_bag(path: &Path, frames: &[ParticleFrame]) {
    let mut writer = BagWriter::create(path).unwrap();
    for f in frames {
        writer.write(TOPIC, f).unwrap();
    }
    writer.finish().unwrap();
}

/// Asserts that the archive at `path` holds exactly `frames` (one contiguous trajectory).
fn assert_archive(path: &Path, frames: &[&ParticleFrame]) {
    let mut npz = NpzReader::new(File::open(path).unwrap()).unwrap();
    let mut names = npz.names().unwrap();
    names.sort();
    assert_eq!(
        names,
        ["dt", "frame_index", "material", "position", "velocity"]
    );
    let position: Array3<f32> = npz.by_name("position").unwrap();
    let velocity: Array3<f32> = npz.by_name("velocity").unwrap();
    let material: Array1<u8> = npz.by_name("material").unwrap();
    let index: Array1<u32> = npz.by_name("frame_index").unwrap();
    let dt: Array0<f32> = npz.by_name("dt").unwrap();
    let n = frames[0].material.len();
    assert_eq!(position.dim(), (frames.len(), n, 2));
    assert_eq!(velocity.dim(), (frames.len(), n, 2));
    for (t, f) in frames.iter().enumerate() {
        assert_eq!(
            position
                .slice(ndarray::s![t, .., ..])
                .iter()
                .copied()
                .collect::<Vec<_>>(),
            f.position
        );
        assert_eq!(
            velocity
                .slice(ndarray::s![t, .., ..])
                .iter()
                .copied()
                .collect::<Vec<_>>(),
            f.velocity
        );
        assert_eq!(index[t], f.frame_index);
    }
    assert_eq!(material.to_vec(), frames[0].material);
    assert_eq!(dt.into_scalar(), 0.01);
}

/// The `.npy` header numpy parses: little-endian float32, C order, the shape.
fn npy_header(path: &Path, member: &str) -> String {
    let mut zip_bytes = Vec::new();
    File::open(path)
        .unwrap()
        .read_to_end(&mut zip_bytes)
        .unwrap();
    let at = zip_bytes
        .windows(member.len())
        .position(|w| w == member.as_bytes())
        .expect("member in the archive");
    let rest = &zip_bytes[at..];
    let magic = rest.windows(6).position(|w| w == b"\x93NUMPY").unwrap();
    let len = u16::from_le_bytes([rest[magic + 8], rest[magic + 9]]) as usize;
    String::from_utf8_lossy(&rest[magic + 10..magic + 10 + len]).into_owned()
}

#[test]
fn export_npz_round_trips_frames_per_trajectory() {
    let dir = crate::tmp::tempdir().unwrap();
    let a: Vec<_> = (0..5).map(|i| frame("fluid/dam/000", i, 3)).collect();
    // Scene b misses frame 2: two trajectories, two archives.
    let b: Vec<_> = [0, 1, 3, 4]
        .iter()
        .map(|&i| frame("multi/rope+snow/001", i, 5))
        .collect();
    write_bag(&dir.path().join("a.mcap"), &a);
    write_bag(&dir.path().join("b.mcap"), &b);
    let out = dir.path().join("npz");
    let run = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["export", "--format", "npz", "-o"])
        .arg(&out)
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let mut listed: Vec<_> = String::from_utf8_lossy(&run.stdout)
        .lines()
        .map(str::to_owned)
        .collect();
    listed.sort();
    let expect = [
        "fluid_dam_000.npz",
        "multi_rope+snow_001_from0.npz",
        "multi_rope+snow_001_from3.npz",
    ];
    assert_eq!(listed, expect.map(|f| out.join(f).display().to_string()));

    assert_archive(&out.join(expect[0]), &a.iter().collect::<Vec<_>>());
    assert_archive(&out.join(expect[1]), &b[..2].iter().collect::<Vec<_>>());
    assert_archive(&out.join(expect[2]), &b[2..].iter().collect::<Vec<_>>());
    let header = npy_header(&out.join(expect[0]), "position.npy");
    assert!(header.contains("'descr': '<f4'"), "{header}");
    assert!(header.contains("'fortran_order': False"), "{header}");
    assert!(header.contains("'shape': (5, 3, 2)"), "{header}");
}

#[test]
fn export_of_no_bags_is_an_error() {
    let dir = crate::tmp::tempdir().unwrap();
    let run = Command::new(env!("CARGO_BIN_EXE_minflow"))
        .args(["export", "--format", "npz", "-o"])
        .arg(dir.path().join("out"))
        .arg(dir.path())
        .output()
        .unwrap();
    assert_eq!(
        run.status.code(),
        Some(1),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
}
