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
use std::io::{BufWriter, Seek, SeekFrom, Write};
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

/// Writes `traj` to `path` as described in the module documentation: into `path` + `.part`,
/// renamed to `path` once the archive is complete, so a file under the final name is always
/// a finished archive.
///
/// # Errors
/// [`InteropError::WriteIo`] (a full disk: the OS error, "No space left on device") or
/// [`InteropError::Write`] when the file cannot be created, written or renamed; the `.part`
/// file is then removed.
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
    let mut part = path.as_os_str().to_owned();
    part.push(".part");
    let part = PathBuf::from(part);
    let file = File::create(&part).map_err(|source| InteropError::WriteIo {
        path: part.clone(),
        source,
    })?;
    let sink = Sink {
        file: BufWriter::new(file),
        failed: std::rc::Rc::new(std::cell::RefCell::new(None)),
        pos: 0,
        len: 0,
    };
    let failed = std::rc::Rc::clone(&sink.failed);
    let mut npz = NpzWriter::new(sink);
    let write = |npz: &mut NpzWriter<_>| -> Result<(), ndarray_npy::WriteNpzError> {
        npz.add_array("position", &position)?;
        npz.add_array("velocity", &velocity)?;
        npz.add_array("material", &Array1::from(traj.material.clone()))?;
        npz.add_array("frame_index", &frame_index)?;
        npz.add_array("dt", &arr0(traj.dt))
    };
    let result = write(&mut npz).and_then(|()| npz.finish()).map(|mut sink| {
        // Errors are kept in `failed`.
        let _ = sink.flush();
        if !sink.broken() {
            if let Err(e) = sink.file.get_ref().sync_all() {
                sink.keep(e);
            }
        }
    });
    let os_error = failed.borrow_mut().take();
    let result = match (result, os_error) {
        (Ok(()), None) => std::fs::rename(&part, path).map_err(|e| fail(e.to_string())),
        (_, Some(source)) => Err(InteropError::WriteIo {
            path: part.clone(),
            source,
        }),
        (Err(e), None) => Err(fail(e.to_string())),
    };
    if result.is_err() {
        let _ = std::fs::remove_file(&part);
    }
    result
}

/// The archive's file: after its first failed write, later writes and seeks only move a
/// virtual position (and report success), so the zip writer dropped after an error finishes
/// quietly instead of printing "ZipWriter drop failed" (the `.part` file is removed anyway);
/// the first OS error is kept for the caller.
struct Sink {
    file: BufWriter<File>,
    failed: std::rc::Rc<std::cell::RefCell<Option<std::io::Error>>>,
    /// Position and length as the zip writer sees them.
    pos: u64,
    len: u64,
}

impl Sink {
    /// Whether a write failed before.
    fn broken(&self) -> bool {
        self.failed.borrow().is_some()
    }

    /// Keeps the first OS error; returns a copy for the zip writer.
    fn keep(&mut self, e: std::io::Error) -> std::io::Error {
        let copy = std::io::Error::new(e.kind(), e.to_string());
        *self.failed.borrow_mut() = Some(e);
        copy
    }
}

impl Write for Sink {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = match self.broken() {
            true => buf.len(),
            false => self.file.write(buf).map_err(|e| self.keep(e))?,
        };
        self.pos += n as u64;
        self.len = self.len.max(self.pos);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self.broken() {
            true => Ok(()),
            false => self.file.flush().map_err(|e| self.keep(e)),
        }
    }
}

impl Seek for Sink {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        if !self.broken() {
            let at = self.file.seek(pos).map_err(|e| self.keep(e))?;
            self.pos = at;
            return Ok(at);
        }
        let at = match pos {
            SeekFrom::Start(n) => Some(n),
            SeekFrom::Current(d) => self.pos.checked_add_signed(d),
            SeekFrom::End(d) => self.len.checked_add_signed(d),
        };
        self.pos = at.ok_or_else(|| std::io::Error::from(std::io::ErrorKind::InvalidInput))?;
        Ok(self.pos)
    }
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
