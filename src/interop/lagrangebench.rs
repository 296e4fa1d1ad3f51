//! `minflow import --format lagrangebench DIR`: a LagrangeBench dataset as one bag per
//! trajectory. LagrangeBench (Toshev et al. 2023, "LagrangeBench: A Lagrangian Fluid
//! Mechanics Benchmarking Suite", NeurIPS Datasets and Benchmarks) ships each dataset as a
//! folder:
//!
//! | file | content |
//! | --- | --- |
//! | `metadata.json` | `dim` (2), `dt` (solver step, s), `write_every` (solver steps per saved frame, optional here), `bounds` `[[xmin, xmax], [ymin, ymax]]`, `periodic_boundary_conditions` (per axis, optional) |
//! | `train.h5`, `valid.h5`, `test.h5` | one group per trajectory (`00000`, ...), each with `position` [T, N, 2] (float, dataset units) and `particle_type` [N] (integer) |
//!
//! The import:
//! - frame spacing: `dt * write_every` (the saved frames are `write_every` solver steps
//!   apart; `dt` alone when the metadata has no `write_every`); `--dt` overrides it;
//! - positions: mapped into the unit box with one scale for both axes ([`UnitBox`]);
//! - velocities: finite differences of the mapped positions over the frame spacing, the
//!   backward difference `(x[t] - x[t-1]) / dt`, frame 0 the forward one (the same value as
//!   frame 1's), so a trajectory needs at least 2 frames; along a periodic axis a step across
//!   the boundary is unwrapped ([`finite_difference`]);
//! - materials: `particle_type` through `--material-map` ([`MaterialMap`]);
//! - scene ids `lagrangebench/<split>/<group>`, bags `lagrangebench_<split>_<group>.mcap`.
//!
//! Every trajectory's shapes and particle types are checked ([`survey`]) before any bag is
//! written; frames are then read a block at a time, so memory does not grow with T.

use std::path::{Path, PathBuf};

use super::import::{
    finite_difference, read_error, BagSink, ImportError, Imported, MaterialMap, UnitBox,
};

/// The splits of a LagrangeBench dataset, in this order; split `s` lives in `<s>.h5`.
pub const SPLITS: [&str; 3] = ["train", "valid", "test"];

/// Frames read from the file at once.
const BLOCK_FRAMES: u64 = 64;

/// What the import takes from `metadata.json`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Metadata {
    /// Seconds between saved frames: `dt * write_every`, or the `--dt` override.
    pub frame_dt: f64,
    /// The map of `bounds` into the unit box.
    pub unit_box: UnitBox,
}

/// Reads `DIR/metadata.json`; `dt_override` (`--dt`) replaces the frame spacing it gives.
///
/// # Errors
/// [`ImportError::Read`] for a missing or malformed file, [`ImportError::Invalid`] for a
/// missing or out-of-range field (no `dt` and no override, bounds not 2D or empty).
pub fn read_metadata(dir: &Path, dt_override: Option<f64>) -> Result<Metadata, ImportError> {
    let path = dir.join("metadata.json");
    let read = |reason: String| ImportError::Read {
        path: path.clone(),
        reason,
    };
    let invalid = |what: String| ImportError::Invalid {
        path: path.clone(),
        what,
    };
    let text = std::fs::read_to_string(&path).map_err(|e| read(e.to_string()))?;
    let meta: serde_json::Value = serde_json::from_str(&text).map_err(|e| read(e.to_string()))?;
    let bounds: Vec<Vec<f64>> = serde_json::from_value(meta["bounds"].clone()).map_err(|e| {
        invalid(format!(
            "bounds: {e} (expected [[xmin, xmax], [ymin, ymax]])"
        ))
    })?;
    // LagrangeBench reads `bounds[:dim]`: with `dim` 2, rows past the second are ignored.
    let dim = meta["dim"].as_u64();
    let bounds: [[f64; 2]; 2] = match (dim, bounds.as_slice()) {
        (None, [x, y]) | (Some(2), [x, y, ..]) if x.len() == 2 && y.len() == 2 => {
            [[x[0], x[1]], [y[0], y[1]]]
        }
        _ => {
            return Err(invalid(format!(
                "dim {dim:?}, bounds {bounds:?}: only 2D datasets can be imported"
            )))
        }
    };
    let periodic: Vec<bool> = match &meta["periodic_boundary_conditions"] {
        serde_json::Value::Null => vec![],
        v => serde_json::from_value(v.clone())
            .map_err(|e| invalid(format!("periodic_boundary_conditions: {e}")))?,
    };
    let periodic = [0, 1].map(|a| periodic.get(a).copied().unwrap_or(false));
    let unit_box = UnitBox::new(bounds, periodic)
        .ok_or_else(|| invalid(format!("bounds {bounds:?} enclose no area")))?;
    let frame_dt = match dt_override {
        Some(dt) => dt,
        None => {
            let dt = meta["dt"]
                .as_f64()
                .ok_or_else(|| invalid("no number dt (give the frame spacing with --dt)".into()))?;
            let every = match &meta["write_every"] {
                serde_json::Value::Null => 1,
                v => v
                    .as_u64()
                    .filter(|&w| w >= 1)
                    .ok_or_else(|| invalid(format!("write_every {v} is not a positive integer")))?,
            };
            dt * every as f64
        }
    };
    if !(frame_dt.is_finite() && frame_dt > 0.0) {
        return Err(invalid(format!(
            "frame spacing {frame_dt} is not positive (use --dt)"
        )));
    }
    Ok(Metadata { frame_dt, unit_box })
}

/// One trajectory of the dataset, checked and ready to convert.
#[derive(Debug, Clone, PartialEq)]
pub struct Source {
    /// `train`, `valid` or `test`.
    pub split: String,
    /// The split's HDF5 file.
    pub file: PathBuf,
    /// The trajectory's group in it.
    pub group: String,
    /// T, frames.
    pub frames: u64,
    /// The particles' materials (N of them), from `particle_type` through the map.
    pub material: Vec<u8>,
}

impl Source {
    /// The scene id of the trajectory's frames: `lagrangebench/<split>/<group>`.
    pub fn scene(&self) -> String {
        format!("lagrangebench/{}/{}", self.split, self.group)
    }
}

/// Lists and checks the trajectories of `splits` (all of [`SPLITS`] whose file exists when
/// `None`): every group's `position` is [T >= 2, N, 2] and `particle_type` [N], and every
/// particle type has a material in `map`.
///
/// # Errors
/// [`ImportError::Invalid`] for a split file that is missing (or no split file at all) and
/// a split without groups; [`ImportError::Shape`]; [`ImportError::UnmappedType`];
/// [`ImportError::Read`] for a file that is not HDF5 or a dataset that cannot be read.
pub fn survey(
    dir: &Path,
    splits: Option<&[String]>,
    map: &MaterialMap,
) -> Result<Vec<Source>, ImportError> {
    let wanted: Vec<String> = match splits {
        Some(s) => s.to_vec(),
        None => SPLITS
            .iter()
            .filter(|s| dir.join(format!("{s}.h5")).is_file())
            .map(|s| s.to_string())
            .collect(),
    };
    if wanted.is_empty() {
        return Err(ImportError::Invalid {
            path: dir.to_owned(),
            what: "holds none of train.h5, valid.h5, test.h5".into(),
        });
    }
    let mut sources = Vec::new();
    for split in wanted {
        let file = dir.join(format!("{split}.h5"));
        if !file.is_file() {
            return Err(ImportError::Invalid {
                path: file,
                what: format!("split {split} asked for (--splits) but the file is missing"),
            });
        }
        sources.extend(survey_split(&split, &file, map)?);
    }
    Ok(sources)
}

/// [`survey`] of one split file.
fn survey_split(split: &str, file: &Path, map: &MaterialMap) -> Result<Vec<Source>, ImportError> {
    let h5 = hdf5_pure::File::open(file).map_err(read_error(file, "opening"))?;
    let mut groups = h5
        .root()
        .groups()
        .map_err(read_error(file, "listing groups"))?;
    groups.sort();
    if groups.is_empty() {
        return Err(ImportError::Invalid {
            path: file.to_owned(),
            what: "has no trajectory groups".into(),
        });
    }
    let mut sources = Vec::with_capacity(groups.len());
    for group in groups {
        let shape = |name: &str| -> Result<Vec<u64>, ImportError> {
            let path = format!("{group}/{name}");
            let ds = h5.dataset(&path).map_err(read_error(file, &path))?;
            ds.shape().map_err(read_error(file, &path))
        };
        let position = shape("position")?;
        let [frames, n, 2] = position[..] else {
            return Err(shape_error(file, &group, "position", position, "[T, N, 2]"));
        };
        if frames < 2 {
            return Err(shape_error(
                file,
                &group,
                "position",
                position,
                "[T >= 2, N, 2]: velocities need two frames",
            ));
        }
        let types_shape = shape("particle_type")?;
        if types_shape != [n] {
            return Err(shape_error(
                file,
                &group,
                "particle_type",
                types_shape,
                "[N], N as in position",
            ));
        }
        let path = format!("{group}/particle_type");
        let types = h5
            .dataset(&path)
            .and_then(|ds| ds.read_i64())
            .map_err(read_error(file, &path))?;
        let material = map.materials(&types, &format!("{}: {group}", file.display()))?;
        sources.push(Source {
            split: split.to_owned(),
            file: file.to_owned(),
            group,
            frames,
            material,
        });
    }
    Ok(sources)
}

fn shape_error(
    file: &Path,
    group: &str,
    name: &str,
    shape: Vec<u64>,
    expected: &'static str,
) -> ImportError {
    ImportError::Shape {
        path: file.to_owned(),
        dataset: format!("{group}/{name}"),
        shape,
        expected,
    }
}

/// Converts one surveyed trajectory into `out_dir` (frames on `topic`), calling `on_frame`
/// after every frame written.
///
/// # Errors
/// [`ImportError::Read`] for data that cannot be read; bag and I/O errors.
pub fn convert(
    source: &Source,
    meta: &Metadata,
    out_dir: &Path,
    topic: &str,
    on_frame: &mut dyn FnMut(),
) -> Result<Imported, ImportError> {
    let file = &source.file;
    let path = format!("{}/position", source.group);
    let h5 = hdf5_pure::File::open(file).map_err(read_error(file, "opening"))?;
    let ds = h5.dataset(&path).map_err(read_error(file, &path))?;
    let mut sink = BagSink::create(
        out_dir,
        &source.scene(),
        topic,
        meta.frame_dt,
        source.material.clone(),
    )?;
    let row = source.material.len() * 2;
    let (dt, period) = (meta.frame_dt, meta.unit_box.period);
    let mut prev: Option<Vec<f64>> = None;
    let mut start = 0;
    while start < source.frames {
        let block = ds
            .read_f64_rows(start, BLOCK_FRAMES)
            .map_err(read_error(file, &path))?;
        if block.is_empty() || block.len() % row != 0 {
            return Err(ImportError::Read {
                path: file.to_owned(),
                reason: format!(
                    "{path}: frames {start}..: {} values read, not a multiple of 2N = {row}",
                    block.len()
                ),
            });
        }
        for frame in block.chunks_exact(row) {
            let now = meta.unit_box.map(frame);
            if let Some(before) = &prev {
                let velocity = finite_difference(before, &now, dt, period);
                if sink.frames() == 0 {
                    // Frame 0: the forward difference, which is frame 1's backward one.
                    sink.push(to_f32(before), velocity.clone())?;
                    on_frame();
                }
                sink.push(to_f32(&now), velocity)?;
                on_frame();
            }
            prev = Some(now);
        }
        start += (block.len() / row) as u64;
    }
    sink.finish()
}

fn to_f32(values: &[f64]) -> Vec<f32> {
    values.iter().map(|&v| v as f32).collect()
}
