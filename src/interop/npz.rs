//! `minflow export --format npz`: each [`Trajectory`] of a set of bags as one numpy `.npz`
//! archive (uncompressed zip of `.npy` files, written with `ndarray-npy`), so
//! `d = np.load("multi_rope+snow_001.npz")` gives:
//!
//! | array | dtype | shape | content |
//! | --- | --- | --- | --- |
//! | `position` | float32 | [T, N, 2] | x, y in domain units (unit square) |
//! | `velocity` | float32 | [T, N, 2] | vx, vy in domain units per simulation time unit |
//! | `material` | uint8 | [N] | 0 liquid, 1 jelly, 2 snow, 3 rope |
//! | `frame_index` | uint32 | [T] | the messages' `frame_index` (contiguous) |
//! | `dt` | float32 | [] | simulation time between frames |
//!
//! Values are copied bit for bit from the bags. A scene with missing frames has one archive
//! per contiguous segment.

use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};

use ndarray::{arr0, Array1, Array3};
use ndarray_npy::NpzWriter;

use super::InteropError;
use crate::data::Trajectory;

/// The archive's file name for `traj`: the scene id with `/` as `_` (`multi/rope+snow/001` ->
/// `multi_rope+snow_001.npz`); with `segmented`, `_from<start_index>` is added before `.npz`.
pub fn file_name(traj: &Trajectory, segmented: bool) -> String {
    let stem = crate::bag::scene_file_stem(&traj.scene);
    match segmented {
        true => format!("{stem}_from{}.npz", traj.start_index),
        false => format!("{stem}.npz"),
    }
}

/// Writes `traj` to `path` as described in the module documentation.
///
/// # Errors
/// [`InteropError::Write`] when the file cannot be created or written.
pub fn write_trajectory(traj: &Trajectory, path: &Path) -> Result<(), InteropError> {
    let fail = |reason: String| InteropError::Write {
        path: path.to_owned(),
        reason,
    };
    let (t, n) = (traj.frames, traj.n);
    let mut position = Vec::with_capacity(t * n * 2);
    let mut velocity = Vec::with_capacity(t * n * 2);
    for p in traj.states.chunks_exact(4) {
        position.extend_from_slice(&p[..2]);
        velocity.extend_from_slice(&p[2..]);
    }
    let shape = (t, n, 2);
    let position = Array3::from_shape_vec(shape, position).map_err(|e| fail(e.to_string()))?;
    let velocity = Array3::from_shape_vec(shape, velocity).map_err(|e| fail(e.to_string()))?;
    let frame_index: Array1<u32> = (0..t).map(|k| traj.frame_index(k)).collect();
    let file = File::create(path).map_err(|e| fail(e.to_string()))?;
    let mut npz = NpzWriter::new(BufWriter::new(file));
    let write = |npz: &mut NpzWriter<_>| -> Result<(), ndarray_npy::WriteNpzError> {
        npz.add_array("position", &position)?;
        npz.add_array("velocity", &velocity)?;
        npz.add_array("material", &Array1::from(traj.material.clone()))?;
        npz.add_array("frame_index", &frame_index)?;
        npz.add_array("dt", &arr0(traj.dt))
    };
    write(&mut npz).map_err(|e| fail(e.to_string()))?;
    npz.finish().map(drop).map_err(|e| fail(e.to_string()))
}

/// Writes every trajectory of `trajs` into `out_dir` (created if missing), named by
/// [`file_name`] (segments of a scene get their start index). Returns the paths written.
///
/// # Errors
/// [`InteropError::Write`] for the folder or any file.
pub fn export(trajs: &[Trajectory], out_dir: &Path) -> Result<Vec<PathBuf>, InteropError> {
    std::fs::create_dir_all(out_dir).map_err(|e| InteropError::Write {
        path: out_dir.to_owned(),
        reason: e.to_string(),
    })?;
    let mut written = Vec::with_capacity(trajs.len());
    for traj in trajs {
        let segmented = trajs.iter().filter(|o| o.scene == traj.scene).count() > 1;
        let path = out_dir.join(file_name(traj, segmented));
        write_trajectory(traj, &path)?;
        written.push(path);
    }
    Ok(written)
}
