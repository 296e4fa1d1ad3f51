//! A trained model on disk and the stateful inference API every consumer uses
//! (`eval`, `node`, `report`): [`Surrogate`] with `init_state`, `step`, `rollout` in
//! physical units (scaling inside).
//!
//! A run folder holds `model.json` (the [`ModelConfig`], the scaler, the window T) and
//! `model.mpk` (weights, burn's named MessagePack, full precision). `minflow train` writes
//! them (the best epoch); its resumable checkpoint lives in `checkpoint/` beside them.

use super::{FusedElu, LayerState, Model, ModelConfig, Scaling};
use crate::data::Scaler;
use burn::module::Module;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use burn::tensor::backend::Backend;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Errors loading or saving a model.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{path}: {what}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        what: String,
    },
    /// Input that does not fit the model.
    #[error("{0}")]
    Shape(String),
}

/// `model.json`: everything needed to rebuild the network and use it.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ModelMeta {
    /// Network hyper-parameters.
    pub config: ModelConfig,
    /// The scaler fitted on the training split.
    pub scaler: Scaler,
    /// Epoch the weights come from.
    pub epoch: usize,
    /// Validation loss at that epoch.
    pub val_loss: f64,
}

impl ModelMeta {
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

fn io(path: &Path, what: impl ToString) -> StoreError {
    StoreError::Io {
        path: path.to_path_buf(),
        what: what.to_string(),
    }
}

/// Writes `model.json` + `model.mpk` into `dir` (via temporary names, renamed at the end).
pub fn save<B: FusedElu>(dir: &Path, model: &Model<B>, meta: &ModelMeta) -> Result<(), StoreError> {
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
    // The recorder appends `.mpk`, replacing any extension: `model-tmp` -> `model-tmp.mpk`.
    let tmp = dir.join("model-tmp");
    model
        .clone()
        .save_file(tmp.clone(), &recorder)
        .map_err(|e| io(&tmp, e))?;
    let json = serde_json::to_string_pretty(meta).map_err(|e| io(dir, e))?;
    std::fs::write(dir.join("model.json.tmp"), json).map_err(|e| io(dir, e))?;
    std::fs::rename(dir.join("model-tmp.mpk"), dir.join("model.mpk")).map_err(|e| io(dir, e))?;
    std::fs::rename(dir.join("model.json.tmp"), dir.join("model.json")).map_err(|e| io(dir, e))?;
    Ok(())
}

/// Reads `model.json` and the weights from `dir`.
pub fn load<B: FusedElu>(
    dir: &Path,
    device: &B::Device,
) -> Result<(Model<B>, ModelMeta), StoreError> {
    let path = dir.join("model.json");
    let text = std::fs::read_to_string(&path).map_err(|e| io(&path, e))?;
    let meta: ModelMeta = serde_json::from_str(&text).map_err(|e| io(&path, e))?;
    let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
    let weights = dir.join("model.mpk");
    let model = meta
        .config
        .init::<B>(device)
        .load_file(weights.clone(), &recorder, device)
        .map_err(|e| io(&weights, e))?;
    Ok((model, meta))
}

/// A trained model ready for step-by-step prediction in physical units.
pub struct Surrogate<B: Backend> {
    model: Model<B>,
    meta: ModelMeta,
    scaling: Scaling,
    device: B::Device,
}

/// Per-trajectory recurrent state (one batch row per trajectory).
pub struct State<B: Backend> {
    layers: Vec<LayerState<B>>,
    /// Frames consumed since the state was reset.
    pub frames: usize,
}

impl<B: FusedElu> Surrogate<B> {
    /// Loads a run folder.
    pub fn load(dir: &Path, device: &B::Device) -> Result<Self, StoreError> {
        let (model, meta) = load(dir, device)?;
        Ok(Self::new(model, meta, device))
    }

    /// Wraps an in-memory model.
    pub fn new(model: Model<B>, meta: ModelMeta, device: &B::Device) -> Self {
        let scaling = meta.scaling();
        Self {
            model,
            meta,
            scaling,
            device: device.clone(),
        }
    }

    /// The model's description.
    pub fn meta(&self) -> &ModelMeta {
        &self.meta
    }

    /// A fresh (empty) state. The batch size is set by the first `step`.
    pub fn init_state(&self) -> State<B> {
        State {
            layers: self.model.core.init_state(),
            frames: 0,
        }
    }

    /// Predicts the next frame of each trajectory in the batch and advances the state.
    ///
    /// # Shapes
    /// - `frames`: `[B, N, 4]` physical x, y, vx, vy; `material`: `[B, N]`; `dt`: `[B]`
    /// - returns `[B, N, 4]` physical, the frame `dt` later
    pub fn step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
    ) -> Result<(Vec<f32>, State<B>), StoreError> {
        let b = dt.len();
        let n = material.len().checked_div(b).unwrap_or(0);
        if b == 0 || frames.len() != b * n * 4 || material.len() != b * n {
            return Err(StoreError::Shape(format!(
                "step: {} state values, {} materials for {b} frames",
                frames.len(),
                material.len()
            )));
        }
        let expected = self.meta.config.particles;
        if self.meta.config.decoder == super::DecoderKind::Global && n != expected {
            return Err(StoreError::Shape(format!(
                "model was trained for N = {expected} particles, frame has {n}"
            )));
        }
        // The training batches' own scaling (data::Scaler), so inputs match training exactly.
        let mut feats = Vec::with_capacity(b * n * 5);
        self.meta.scaler.scale_into(frames, material, &mut feats);
        let x = super::upload::<B, 3>(feats, [b, n, 5], &self.device);
        let dt_t = super::upload::<B, 1>(dt.to_vec(), [b], &self.device);
        let (out, layers) = self.model.step(x, dt_t, state.layers, &self.scaling);
        let mut out = super::download(out).map_err(StoreError::Shape)?;
        self.meta.scaler.unscale_rows(&mut out, 4);
        Ok((
            out,
            State {
                layers,
                frames: state.frames + 1,
            },
        ))
    }

    /// Seeds with `seed` frames (each `[N, 4]` physical, one trajectory) and predicts `k`
    /// frames autoregressively, feeding predictions back. Returns the `k` predicted frames.
    pub fn rollout(
        &self,
        seed: &[Vec<f32>],
        material: &[u8],
        dt: f32,
        k: usize,
    ) -> Result<Vec<Vec<f32>>, StoreError> {
        let mut state = self.init_state();
        let mut next = Vec::new();
        for frame in seed {
            let (out, s) = self.step(frame, material, &[dt], state)?;
            state = s;
            next = out;
        }
        let mut frames = Vec::with_capacity(k);
        for i in 0..k {
            frames.push(next.clone());
            if i + 1 < k {
                let (out, s) = self.step(&next, material, &[dt], state)?;
                state = s;
                next = out;
            }
        }
        Ok(frames)
    }
}
