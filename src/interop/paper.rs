//! `minflow import --format paper FILE`: the paper's HDF5 layout as bags. The file holds a
//! float dataset of shape (T, N, F) — one trajectory — or (S, T, N, F) — S trajectories —
//! with F >= 5 features per particle and frame: x, y (domain units, the unit square, as
//! minflow's), vx, vy (domain units per time unit), m (the material id as a float, as
//! [`crate::material`] numbers them); further features are ignored. Positions and velocities
//! are copied as stored (to f32); the material is `round(m)`, which must be a known id and the
//! same in every frame.
//!
//! The frame spacing is not in the file: `--dt`, by default [`DEFAULT_DT`] (the paper's
//! solver step 8e-4 with every 20th step saved). Scene ids `paper/<file stem>/<dataset>`,
//! with `/<s>` (3 digits) added for the trajectories of an (S, T, N, F) dataset.

use std::path::Path;

use super::import::{read_error, BagSink, ImportError, Imported};

/// Seconds between saved frames of the paper's data: 20 solver steps of 8e-4.
pub const DEFAULT_DT: f64 = 0.016;

/// Frames read from the file at once (for a (T, N, F) dataset).
const BLOCK_FRAMES: u64 = 64;

/// A checked paper-format dataset.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Source {
    /// The dataset's name in the file's root.
    pub dataset: String,
    /// `Some(S)` for an (S, T, N, F) dataset, `None` for (T, N, F).
    pub trajectories: Option<u64>,
    /// T.
    pub frames: u64,
    /// N.
    pub particles: u64,
    /// F (>= 5).
    pub features: u64,
}

impl Source {
    /// Frames over all trajectories (S * T).
    pub fn total_frames(&self) -> u64 {
        self.trajectories.unwrap_or(1) * self.frames
    }
}

/// Picks the dataset of `path` (`dataset`, or the root's only dataset) and checks its shape.
///
/// # Errors
/// [`ImportError::Dataset`] (a usage error) when the file has no dataset named `dataset`, or
/// several and none was named; [`ImportError::Invalid`] when it has none;
/// [`ImportError::Shape`]; [`ImportError::Read`] for a file that is not HDF5.
pub fn survey(path: &Path, dataset: Option<&str>) -> Result<Source, ImportError> {
    let h5 = hdf5_pure::File::open(path).map_err(read_error(path, "opening"))?;
    let mut names = h5
        .root()
        .datasets()
        .map_err(read_error(path, "listing datasets"))?;
    names.sort();
    let choose = |what: String| ImportError::Dataset {
        path: path.to_owned(),
        what,
        names: names.clone(),
    };
    let name = match (dataset, names.as_slice()) {
        (Some(d), _) if names.iter().any(|n| n == d) => d.to_owned(),
        (Some(d), _) => return Err(choose(format!("no dataset {d:?} (--dataset)"))),
        (None, [only]) => only.clone(),
        (None, []) => {
            return Err(ImportError::Invalid {
                path: path.to_owned(),
                what: "no dataset in the file's root".into(),
            })
        }
        (None, _) => return Err(choose("several datasets: choose one with --dataset".into())),
    };
    let shape = h5
        .dataset(&name)
        .and_then(|ds| ds.shape())
        .map_err(read_error(path, &name))?;
    let (trajectories, rest) = match shape[..] {
        [t, n, f] => (None, [t, n, f]),
        [s, t, n, f] => (Some(s), [t, n, f]),
        _ => (None, [0; 3]),
    };
    let [frames, particles, features] = rest;
    if frames == 0 || particles == 0 || features < 5 || trajectories == Some(0) {
        return Err(ImportError::Shape {
            path: path.to_owned(),
            dataset: name,
            shape,
            expected: "(T, N, F >= 5) or (S, T, N, F >= 5): x, y, vx, vy, m",
        });
    }
    Ok(Source {
        dataset: name,
        trajectories,
        frames,
        particles,
        features,
    })
}

/// Converts the trajectories of `source` in `path` into bags in `out_dir` (frames `dt`
/// seconds apart, on `topic`), calling `on_frame` after every frame written.
///
/// # Errors
/// [`ImportError::BadMaterial`]; [`ImportError::Read`]; bag and I/O errors.
pub fn convert(
    path: &Path,
    source: &Source,
    dt: f64,
    out_dir: &Path,
    topic: &str,
    on_frame: &mut dyn FnMut(),
) -> Result<Vec<Imported>, ImportError> {
    let h5 = hdf5_pure::File::open(path).map_err(read_error(path, "opening"))?;
    let ds = h5
        .dataset(&source.dataset)
        .map_err(read_error(path, &source.dataset))?;
    let stem = path
        .file_stem()
        .map_or_else(|| "data".into(), |s| s.to_string_lossy().into_owned());
    let scene = format!("paper/{stem}/{}", source.dataset);
    let mut written = Vec::new();
    match source.trajectories {
        None => {
            let mut read = |start: u64| ds.read_f64_rows(start, BLOCK_FRAMES);
            written.push(convert_one(
                path, source, &scene, dt, out_dir, topic, &mut read, on_frame,
            )?);
        }
        Some(s) => {
            for k in 0..s {
                // One trajectory (row k) at a time; its frames come back whole.
                let mut read = |start: u64| match start {
                    0 => ds.read_f64_rows(k, 1),
                    _ => Ok(Vec::new()),
                };
                let scene = format!("{scene}/{k:03}");
                written.push(convert_one(
                    path, source, &scene, dt, out_dir, topic, &mut read, on_frame,
                )?);
            }
        }
    }
    Ok(written)
}

/// Converts one trajectory whose frames `read(start)` returns a block at a time from frame
/// `start` on (flat, (frames, N, F) row-major; empty past the end).
#[allow(clippy::too_many_arguments)]
fn convert_one(
    path: &Path,
    source: &Source,
    scene: &str,
    dt: f64,
    out_dir: &Path,
    topic: &str,
    read: &mut dyn FnMut(u64) -> Result<Vec<f64>, hdf5_pure::Error>,
    on_frame: &mut dyn FnMut(),
) -> Result<Imported, ImportError> {
    let (n, f) = (source.particles as usize, source.features as usize);
    let row = n * f;
    let mut sink: Option<BagSink> = None;
    let mut material: Vec<u8> = Vec::new();
    let mut t = 0usize;
    while (t as u64) < source.frames {
        let block = read(t as u64).map_err(read_error(path, &source.dataset))?;
        if block.is_empty() || block.len() % row != 0 {
            return Err(ImportError::Read {
                path: path.to_owned(),
                reason: format!(
                    "{}: {} values read from frame {t}, not a multiple of N x F = {row}",
                    source.dataset,
                    block.len()
                ),
            });
        }
        for frame in block.chunks_exact(row) {
            let here = materials(frame, f);
            if t == 0 {
                material = here.iter().map(|&m| m.unwrap_or(u8::MAX)).collect();
            }
            if let Some(i) = (0..n).find(|&i| here[i] != Some(material[i])) {
                return Err(ImportError::BadMaterial {
                    path: path.to_owned(),
                    dataset: source.dataset.clone(),
                    frame: t,
                    particle: i,
                    mass: frame[i * f + 4],
                });
            }
            let sink = match &mut sink {
                Some(s) => s,
                None => sink.insert(BagSink::create(
                    out_dir,
                    scene,
                    topic,
                    dt,
                    material.clone(),
                )?),
            };
            let pick = |c: usize| -> Vec<f32> {
                frame
                    .chunks_exact(f)
                    .flat_map(|p| [p[c] as f32, p[c + 1] as f32])
                    .collect()
            };
            sink.push(pick(0), pick(2))?;
            on_frame();
            t += 1;
        }
    }
    let sink = sink.ok_or_else(|| ImportError::Invalid {
        path: path.to_owned(),
        what: format!("{}: no frames", source.dataset),
    })?;
    sink.finish()
}

/// Per particle of one frame (N x F values), `round(m)` when it is a material id.
fn materials(frame: &[f64], f: usize) -> Vec<Option<u8>> {
    frame
        .chunks_exact(f)
        .map(|p| {
            let m = p[4].round();
            let known = m.is_finite() && (0.0..crate::material::COUNT as f64).contains(&m);
            known.then_some(m as u8)
        })
        .collect()
}
