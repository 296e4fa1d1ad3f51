//! A trained model on disk and the stateful inference API every consumer uses
//! (`eval`, `node`, `report`): [`Surrogate`] with `init_state`, `step`, `rollout` in
//! physical units (scaling inside).
//!
//! A run folder ([`RunFolder`], `run_folder.rs`: every file of it) holds `model.json` (the architecture and its config, [`NetConfig`], the
//! scaler, the window T) and `model.mpk` (weights, burn's named MessagePack, full
//! precision). `minflow train` writes them (the best epoch); its resumable checkpoint lives
//! in `checkpoint/` beside them. Both architectures, `paper` ([`Model`]) and `grid`
//! ([`GridModel`]), are served by one [`Surrogate`] (`surrogate.rs`; its step in `step.rs`,
//! a grid model's call in `grid_step.rs`, closed-loop rollouts in `rollout.rs`, dynamic
//! batching in `batch.rs` and its shapes warmed up in `warm_up.rs`, a call's predictions on
//! their way back in `outs.rs`), whose
//! per-batch [`State`] lives in `state.rs` (a grid model's part in `grid_state.rs`; stacked
//! and split by `stack.rs`; its constraint data in `constrained.rs`).

mod batch;
mod constrained;
mod events;
mod grid_state;
mod grid_step;
mod outs;
mod rollout;
mod run_folder;
mod stack;
pub mod stages;
mod state;
mod step;
mod surrogate;
mod warm_up;

pub use batch::{Finished, SceneStep, SceneSteps, StepTimes, Submitted};
pub use run_folder::RunFolder;
pub use state::State;
pub use surrogate::{Predict, Surrogate, FEEDBACK_BYTES};

use super::grid::{GridConfig, GridModel};
use super::{Model, ModelConfig, Scaling};
use crate::data::Scaler;
use crate::ops::NetOps;
use burn::module::Module;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use burn::tensor::backend::Backend;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Errors loading or saving a model.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written, or its contents could not be decoded.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed: the OS, JSON or weight-recorder error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A saved file that cannot be read back into the network it should hold.
    #[error("{path} is damaged or belongs to another network ({source})")]
    Damaged {
        /// The file.
        path: PathBuf,
        /// The recorder's, OS or JSON error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// Input that does not fit the model.
    #[error("{0}")]
    Shape(String),
    /// The prediction could not be read back from the device.
    #[error(transparent)]
    Download(#[from] super::DownloadError),
}

/// The architecture and its hyper-parameters (`"arch": "paper" | "grid"` in `model.json`).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "arch", rename_all = "lowercase")]
pub enum NetConfig {
    /// The paper's encoder - core - decoder ([`Model`]).
    Paper(ModelConfig),
    /// The grid architecture ([`GridModel`]).
    Grid(GridConfig),
}

/// A network of either architecture.
#[derive(Module, Debug)]
pub enum Net<B: Backend> {
    /// The paper's.
    Paper(Model<B>),
    /// The grid architecture.
    Grid(GridModel<B>),
}

impl NetConfig {
    /// A network with fresh weights.
    pub fn init<B: NetOps>(&self, device: &B::Device) -> Net<B> {
        match self {
            NetConfig::Paper(c) => Net::Paper(c.init(device)),
            NetConfig::Grid(c) => Net::Grid(c.init(device)),
        }
    }
}

/// `model.json`: everything needed to rebuild the network and use it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ModelMeta {
    /// Architecture and hyper-parameters.
    #[serde(flatten)]
    pub net: NetConfig,
    /// The scaler fitted on the training split.
    pub scaler: Scaler,
    /// Epoch the weights come from.
    pub epoch: usize,
    /// Validation loss at that epoch.
    pub val_loss: f64,
    /// The material constraints each predicted frame is projected onto
    /// ([`crate::model::constraints`]; `minflow constraints fit` writes them); none in
    /// folders saved before, or never fitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub constraints: Option<crate::model::constraints::Constraints>,
}

impl ModelMeta {
    /// Input frames a prediction reads (T).
    pub fn window(&self) -> usize {
        match &self.net {
            NetConfig::Paper(c) => c.window,
            NetConfig::Grid(c) => c.window,
        }
    }

    /// `paper` or `grid`.
    pub fn arch_name(&self) -> &'static str {
        match &self.net {
            NetConfig::Paper(_) => "paper",
            NetConfig::Grid(_) => "grid",
        }
    }

    /// The temporal core's or memory's command-line name.
    pub fn core_name(&self) -> &'static str {
        match &self.net {
            NetConfig::Paper(c) => c.core.name(),
            NetConfig::Grid(c) => c.memory.name(),
        }
    }

    /// The materials the model tells apart (ids `0..materials`): a grid model's one-hot
    /// width ([`GridConfig::materials`]); the paper's reads the id as one scaled feature and
    /// takes every material of [`crate::material`].
    pub fn materials(&self) -> usize {
        match &self.net {
            NetConfig::Paper(_) => crate::material::COUNT,
            NetConfig::Grid(c) => c.materials,
        }
    }

    /// The particle count the model is tied to (the paper's global decoder), if any.
    pub fn fixed_particles(&self) -> Option<usize> {
        match &self.net {
            NetConfig::Paper(c) if c.decoder == super::DecoderKind::Global => Some(c.particles),
            _ => None,
        }
    }

    /// The scaling constants as the network uses them.
    pub fn scaling(&self) -> Scaling {
        let mut range = [1.0; 5];
        for (f, r) in range.iter_mut().enumerate() {
            *r = self.scaler.range(f);
        }
        Scaling {
            min: self.scaler.min,
            range,
        }
    }
}

/// [`StoreError::Io`] for `path`, keeping `source`.
pub(crate) fn io(
    path: &Path,
    source: impl Into<Box<dyn std::error::Error + Send + Sync>>,
) -> StoreError {
    StoreError::Io {
        path: path.to_path_buf(),
        source: source.into(),
    }
}

/// Writes `model.json` + `model.mpk` into the run folder `dir` ([`RunFolder::save`]).
///
/// # Errors
/// As [`RunFolder::save`].
pub fn save<B: Backend, M: Module<B>>(
    dir: &Path,
    model: &M,
    meta: &ModelMeta,
) -> Result<(), StoreError> {
    RunFolder::new(dir).save(model, meta)
}

/// Writes `record` to `path` in the format of burn's `NamedMpkFileRecorder` with full
/// precision (byte for byte, so its `load` reads it), encoded in memory first so that a
/// failed write names its OS error instead of the encoder's "error while writing
/// multi-byte MessagePack value". Used for `model.mpk` and the training checkpoint.
///
/// # Errors
/// [`StoreError::Io`] naming `path`, with the OS error as its source; `path` is removed.
pub fn write_record<B: Backend, R: burn::record::Record<B>>(
    path: &Path,
    record: R,
) -> Result<(), StoreError> {
    use burn::record::{BurnRecord, NamedMpkBytesRecorder, Recorder};
    type Settings = FullPrecisionSettings;
    let item = record.into_item::<Settings>();
    let item = BurnRecord::<_, B>::new::<NamedMpkFileRecorder<Settings>>(item);
    let bytes = Recorder::<B>::save_item(&NamedMpkBytesRecorder::<Settings>::new(), item, ())
        .map_err(|e| io(path, e))?;
    write_file(path, &bytes)
}

/// Creates `path` with `bytes` and syncs it; on failure removes it and returns the OS error.
fn write_file(path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
    use std::io::Write;
    let written = std::fs::File::create(path).and_then(|mut f| {
        f.write_all(bytes)?;
        f.sync_all()
    });
    written.map_err(|e| {
        let _ = std::fs::remove_file(path);
        io(path, e)
    })
}

/// A `model.json`'s text as a [`ModelMeta`], older fields defaulted ([`meta_value`]).
///
/// # Errors
/// The text is not JSON or not a model description.
pub fn parse_meta(text: &str) -> Result<ModelMeta, serde_json::Error> {
    serde_json::from_value(meta_value(text)?)
}

/// Fields added to `model.json` after run folders were first saved, per architecture, at
/// the values that mean "as before": a grid model without `reference` reads no reference
/// channels, one without `bundle` predicts one frame per call, one without `materials` has
/// the one-hot width of the four materials there were, one without `rest_shape` reads no
/// rest-shape features, one without `update` has the free per-particle head, one without
/// `deformation` fits its rest-shape features' F, one without `substeps` runs the network
/// once a frame, one without `interaction` passes no messages (its radius and neighbours
/// then unread), one without `box_grid` clamps into its network grid's box; `conv` picks the kernel only (same weights, same results); the
/// zero-initialised last layers only matter for fresh weights.
const ADDED_FIELDS: [(&str, &str, fn() -> serde_json::Value); 14] = [
    ("grid", "reference", || serde_json::Value::Bool(false)),
    ("grid", "bundle", || serde_json::Value::from(1)),
    ("grid", "materials", || serde_json::Value::from(4)),
    ("grid", "rest_shape", || serde_json::Value::Bool(false)),
    ("grid", "update", || serde_json::Value::from("Free")),
    ("grid", "deformation", || serde_json::Value::from("Fit")),
    ("grid", "substeps", || serde_json::Value::from(1)),
    ("grid", "interaction", || serde_json::Value::from(0)),
    ("grid", "interaction_radius", || {
        serde_json::Value::from(0.02)
    }),
    ("grid", "interaction_neighbours", || {
        serde_json::Value::from(12)
    }),
    ("grid", "box_grid", || serde_json::Value::from(0)),
    ("grid", "conv", || serde_json::Value::from("auto")),
    ("grid", "head_zero_init", || serde_json::Value::Bool(true)),
    ("paper", "decoder_zero_init", || {
        serde_json::Value::Bool(false)
    }),
];

/// A `model.json`'s text as JSON, with the fields added since it was saved filled in
/// ([`ADDED_FIELDS`]). [`parse_meta`] and the comparison of a run folder's settings
/// (`train --resume`) both read it through this.
///
/// # Errors
/// The text is not JSON.
pub fn meta_value(text: &str) -> Result<serde_json::Value, serde_json::Error> {
    let mut value: serde_json::Value = serde_json::from_str(text)?;
    // The network's fields sit at the top level (`ModelMeta::net` is flattened).
    if let Some(meta) = value.as_object_mut() {
        let arch = meta
            .get("arch")
            .and_then(|a| a.as_str())
            .unwrap_or_default()
            .to_owned();
        for (of, field, default) in ADDED_FIELDS {
            if arch == of {
                meta.entry(field).or_insert_with(default);
            }
        }
    }
    Ok(value)
}

/// Reads `model.json` and the weights from the run folder `dir`, of either architecture
/// ([`RunFolder::load`]).
///
/// # Errors
/// As [`RunFolder::load`].
pub fn load_net<B: NetOps>(
    dir: &Path,
    device: &B::Device,
) -> Result<(Net<B>, ModelMeta), StoreError> {
    RunFolder::new(dir).load(device)
}

/// Reads a `paper` model (`model.json` and the weights) from `dir`.
pub fn load<B: NetOps>(
    dir: &Path,
    device: &B::Device,
) -> Result<(Model<B>, ModelMeta), StoreError> {
    match load_net(dir, device)? {
        (Net::Paper(model), meta) => Ok((model, meta)),
        (Net::Grid(_), _) => Err(StoreError::Shape(format!(
            "{}: a grid model, where a paper model was expected",
            dir.display()
        ))),
    }
}
