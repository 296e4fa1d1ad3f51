//! What `minflow import` shares between its input formats ([`super::lagrangebench`],
//! [`super::paper`]): the errors ([`ImportError`]), the particle-type to material map
//! (`--material-map`, [`MaterialMap`]), the mapping of a dataset's bounds into minflow's unit
//! box ([`UnitBox`]), finite-difference velocities ([`finite_difference`]), HDF5 reading
//! helpers, and [`BagSink`], which writes one imported trajectory as an MCAP bag laid out as
//! `minflow simulate` writes its bags: every frame on one topic, stamps `k * period` in
//! integer nanoseconds (`period = round(frame_dt * 1e9)`), `frame_id` `"world"`, the
//! message's `dt` that period in seconds, so `bag info`, `train` and `eval` read them.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use crate::bag::{BagError, BagWriter};
use crate::material::{self, Material};
use crate::msgs::ParticleFrame;

/// Why an import failed.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// A file could not be opened or parsed, or a dataset could not be read.
    #[error("{path}: {reason}")]
    Read {
        /// The input file.
        path: PathBuf,
        /// What failed (the HDF5 or JSON reader's message).
        reason: String,
    },
    /// An input file, group, dataset or metadata field is missing or out of range.
    #[error("{path}: {what}")]
    Invalid {
        /// The input file or folder.
        path: PathBuf,
        /// What is missing or wrong.
        what: String,
    },
    /// A dataset does not have the shape the format prescribes.
    #[error("{path}: dataset {dataset} has shape {shape:?}, expected {expected}")]
    Shape {
        /// The HDF5 file.
        path: PathBuf,
        /// The dataset's path inside the file.
        dataset: String,
        /// Its shape.
        shape: Vec<u64>,
        /// The shape the format prescribes, in words.
        expected: &'static str,
    },
    /// A particle type of the data has no material in `--material-map`.
    #[error(
        "{path}: particle type {particle_type} has no material in --material-map {map} \
         (add e.g. {particle_type}=liquid)"
    )]
    UnmappedType {
        /// The HDF5 file (and group) holding the type.
        path: String,
        /// The particle type.
        particle_type: i64,
        /// The map in use.
        map: MaterialMap,
    },
    /// A particle's mass (the paper format's material column) is not a material id.
    #[error(
        "{path}: {dataset}: particle {particle} of frame {frame} has m = {mass}, not a material \
         id (0 liquid, 1 jelly, 2 snow, 3 rope) or not the same in every frame"
    )]
    BadMaterial {
        /// The HDF5 file.
        path: PathBuf,
        /// The dataset.
        dataset: String,
        /// Frame index.
        frame: usize,
        /// Particle index.
        particle: usize,
        /// The value found.
        mass: f64,
    },
    /// `--dataset` names a dataset the file lacks, or the file has several and no `--dataset`.
    #[error("{path}: {what}; datasets in its root: {}", listed(names))]
    Dataset {
        /// The HDF5 file.
        path: PathBuf,
        /// What is wrong with the choice.
        what: String,
        /// The root datasets of the file.
        names: Vec<String>,
    },
    /// Writing an output bag failed (the error names the file).
    #[error(transparent)]
    Bag(#[from] BagError),
    /// Creating the output folder or renaming a finished bag failed.
    #[error("{path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
}

/// `names` joined by ", ", or "none".
fn listed(names: &[String]) -> String {
    match names.is_empty() {
        true => "none".to_owned(),
        false => names.join(", "),
    }
}

impl ImportError {
    /// Whether the error is the command line's fault (a flag that does not fit the data:
    /// exit code 2), not the data's.
    pub fn is_usage(&self) -> bool {
        matches!(self, Self::UnmappedType { .. } | Self::Dataset { .. })
    }
}

/// Turns an HDF5 reader error into [`ImportError::Read`] naming `path` and `what` was read.
pub(crate) fn read_error(path: &Path, what: &str) -> impl Fn(hdf5_pure::Error) -> ImportError {
    let path = path.to_owned();
    let what = what.to_owned();
    move |e| ImportError::Read {
        path: path.clone(),
        reason: format!("{what}: {e}"),
    }
}

/// Which material each particle type becomes: `TYPE=MATERIAL` pairs separated by commas,
/// materials by name (`liquid`, `jelly`, `snow`, `rope`: [`crate::material`]) or id, e.g.
/// `0=liquid,1=rope`. The default maps type 0 to liquid and nothing else.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MaterialMap(BTreeMap<i64, u8>);

impl Default for MaterialMap {
    fn default() -> Self {
        Self(BTreeMap::from([(0, 0)]))
    }
}

/// Why a `--material-map` value cannot be parsed.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0}")]
pub struct MaterialMapError(String);

impl FromStr for MaterialMap {
    type Err = MaterialMapError;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut map = BTreeMap::new();
        for pair in s.split(',') {
            let fail = |why: &str| MaterialMapError(format!("{pair:?}: {why}"));
            let (ty, material) = pair
                .split_once('=')
                .ok_or_else(|| fail("expected TYPE=MATERIAL, e.g. 0=liquid"))?;
            let ty: i64 = ty
                .trim()
                .parse()
                .map_err(|_| fail("the particle type is not an integer"))?;
            let material = material.trim();
            let id = Material::from_name(material)
                .or_else(|| material.parse::<u8>().ok().and_then(Material::from_id))
                .ok_or_else(|| fail(&format!("materials are {}", material::id_list())))?;
            if map.insert(ty, id.id()).is_some() {
                return Err(fail("the particle type is mapped twice"));
            }
        }
        Ok(Self(map))
    }
}

impl fmt::Display for MaterialMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let pairs: Vec<String> = self
            .0
            .iter()
            .map(|(ty, &m)| format!("{ty}={}", Material::from_id(m).map_or("?", Material::name)))
            .collect();
        f.write_str(&pairs.join(","))
    }
}

impl MaterialMap {
    /// The material id of particle type `ty`, if mapped.
    pub fn get(&self, ty: i64) -> Option<u8> {
        self.0.get(&ty).copied()
    }

    /// The materials of particles of types `types`; `source` names the file (and group)
    /// in the error when a type is not mapped.
    ///
    /// # Errors
    /// [`ImportError::UnmappedType`] naming the first type without a material.
    pub fn materials(&self, types: &[i64], source: &str) -> Result<Vec<u8>, ImportError> {
        types
            .iter()
            .map(|&ty| {
                self.get(ty).ok_or_else(|| ImportError::UnmappedType {
                    path: source.to_owned(),
                    particle_type: ty,
                    map: self.clone(),
                })
            })
            .collect()
    }
}

/// The map of a dataset's rectangle `[xmin, xmax] x [ymin, ymax]` into minflow's unit box
/// with one scale for both axes (the aspect ratio is kept): `x' = (x - xmin) / s`,
/// `y' = (y - ymin) / s`, `s = max(xmax - xmin, ymax - ymin)`. The longer side spans
/// `[0, 1]`, the shorter `[0, side / s]`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnitBox {
    /// `(xmin, ymin)`.
    pub origin: [f64; 2],
    /// `s`, dataset units per unit-box unit.
    pub scale: f64,
    /// Per axis, the period in unit-box units where that axis is periodic (its extent
    /// divided by `s`), used to unwrap displacements across the boundary.
    pub period: [Option<f64>; 2],
}

impl UnitBox {
    /// The map of `bounds` (`[[xmin, xmax], [ymin, ymax]]`), periodic along the axes that
    /// `periodic` marks; `None` when a side is not a positive finite length.
    pub fn new(bounds: [[f64; 2]; 2], periodic: [bool; 2]) -> Option<Self> {
        let extent = bounds.map(|[lo, hi]| hi - lo);
        if extent.iter().any(|e| !(e.is_finite() && *e > 0.0)) {
            return None;
        }
        let scale = extent[0].max(extent[1]);
        Some(Self {
            origin: [bounds[0][0], bounds[1][0]],
            scale,
            period: [0, 1].map(|a| periodic[a].then(|| extent[a] / scale)),
        })
    }

    /// Maps interleaved positions `x0, y0, x1, y1, ...` (dataset units) into the unit box.
    pub fn map(&self, xy: &[f64]) -> Vec<f64> {
        xy.iter()
            .enumerate()
            .map(|(i, &v)| (v - self.origin[i % 2]) / self.scale)
            .collect()
    }
}

/// Velocities `(to - from) / dt` of interleaved positions one frame apart (`to` the later
/// frame), as f32. Along a periodic axis (`period[a]`), a displacement longer than half the
/// period is taken across the boundary (minimum image), so a particle leaving on one side
/// and entering on the other keeps its speed.
pub fn finite_difference(from: &[f64], to: &[f64], dt: f64, period: [Option<f64>; 2]) -> Vec<f32> {
    from.iter()
        .zip(to)
        .enumerate()
        .map(|(i, (&a, &b))| {
            let mut d = b - a;
            if let Some(p) = period[i % 2] {
                d -= p * (d / p).round();
            }
            (d / dt) as f32
        })
        .collect()
}

/// One bag written by an import.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Imported {
    /// The scene id of its frames.
    pub scene: String,
    /// The bag.
    pub path: PathBuf,
    /// Frames written.
    pub frames: u32,
    /// Particles per frame.
    pub particles: usize,
}

/// Writes the frames of one imported trajectory to `OUT/NAME.mcap` (through
/// `NAME.mcap.part`, renamed by [`BagSink::finish`], as `simulate` does).
pub struct BagSink {
    writer: BagWriter,
    part: PathBuf,
    path: PathBuf,
    scene: String,
    topic: String,
    period_ns: u64,
    material: Vec<u8>,
    frames: u32,
}

impl BagSink {
    /// Starts the bag of `scene` in `out_dir` (created if missing), frames `frame_dt`
    /// seconds apart, with particle materials `material`.
    ///
    /// # Errors
    /// [`ImportError::Invalid`] when `frame_dt` rounds to less than 1 ns; I/O and bag errors.
    pub fn create(
        out_dir: &Path,
        scene: &str,
        topic: &str,
        frame_dt: f64,
        material: Vec<u8>,
    ) -> Result<Self, ImportError> {
        let period_ns = (frame_dt * 1e9).round();
        if !(period_ns >= 1.0 && period_ns < u64::MAX as f64) {
            return Err(ImportError::Invalid {
                path: out_dir.to_owned(),
                what: format!("frame spacing {frame_dt} s is not a positive number of ns"),
            });
        }
        std::fs::create_dir_all(out_dir).map_err(|source| ImportError::Io {
            path: out_dir.to_owned(),
            source,
        })?;
        let path = out_dir.join(crate::bag::bag_name(scene));
        let part = path.with_extension("mcap.part");
        Ok(Self {
            writer: BagWriter::create(&part)?,
            part,
            path,
            scene: scene.to_owned(),
            topic: topic.to_owned(),
            period_ns: period_ns as u64,
            material,
            frames: 0,
        })
    }

    /// Writes the next frame: interleaved positions (unit box) and velocities (unit-box
    /// units per second), 2N values each.
    ///
    /// # Errors
    /// A bag error, also for a frame that fails validation (lengths, non-finite values).
    pub fn push(&mut self, position: Vec<f32>, velocity: Vec<f32>) -> Result<(), ImportError> {
        let frame = ParticleFrame::on_clock(
            self.scene.clone(),
            self.frames,
            self.period_ns,
            position,
            velocity,
            self.material.clone(),
        );
        self.writer.write(&self.topic, &frame)?;
        self.frames += 1;
        Ok(())
    }

    /// Frames written so far.
    pub fn frames(&self) -> u32 {
        self.frames
    }

    /// Finishes the bag and gives it its final name.
    ///
    /// # Errors
    /// Bag and I/O errors.
    pub fn finish(self) -> Result<Imported, ImportError> {
        self.writer.finish()?;
        std::fs::rename(&self.part, &self.path).map_err(|source| ImportError::Io {
            path: self.path.clone(),
            source,
        })?;
        Ok(Imported {
            scene: self.scene,
            path: self.path,
            frames: self.frames,
            particles: self.material.len(),
        })
    }
}
