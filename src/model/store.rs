//! A trained model on disk and the stateful inference API every consumer uses
//! (`eval`, `node`, `report`): [`Surrogate`] with `init_state`, `step`, `rollout` in
//! physical units (scaling inside).
//!
//! A run folder holds `model.json` (the architecture and its config, [`NetConfig`], the
//! scaler, the window T) and `model.mpk` (weights, burn's named MessagePack, full
//! precision). `minflow train` writes them (the best epoch); its resumable checkpoint lives
//! in `checkpoint/` beside them. Both architectures, `paper` ([`Model`]) and `grid`
//! ([`GridModel`]), are served by one [`Surrogate`].

use super::grid::{mirror_rows, one_hot, GridConfig, GridModel, MemoryState, StepInput};
use super::{LayerState, Model, ModelConfig, Scaling};
use crate::data::Scaler;
use crate::ops::NetOps;
use burn::module::Module;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use burn::tensor::backend::Backend;
use burn::tensor::Tensor;
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

/// Writes `model.json` + `model.mpk` into `dir` (via temporary names, renamed at the end).
///
/// # Errors
/// [`StoreError::Io`] naming the file and keeping the OS error (a full disk: "No space left on
/// device"); the temporary files are removed, and a model saved there before stays whole.
pub fn save<B: Backend, M: Module<B>>(
    dir: &Path,
    model: &M,
    meta: &ModelMeta,
) -> Result<(), StoreError> {
    std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
    let (tmp_mpk, tmp_json) = (dir.join("model-tmp.mpk"), dir.join("model.json.tmp"));
    let written = write_record::<B, _>(&tmp_mpk, model.clone().into_record()).and_then(|()| {
        let json = serde_json::to_string_pretty(meta).map_err(|e| io(dir, e))?;
        write_file(&tmp_json, json.as_bytes())
    });
    if let Err(e) = written {
        let _ = std::fs::remove_file(&tmp_mpk);
        let _ = std::fs::remove_file(&tmp_json);
        return Err(e);
    }
    std::fs::rename(&tmp_mpk, dir.join("model.mpk")).map_err(|e| io(dir, e))?;
    std::fs::rename(&tmp_json, dir.join("model.json")).map_err(|e| io(dir, e))?;
    Ok(())
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

/// A run folder (`minflow train --out`) as every command reads it: `model.json` with the
/// fields added since older folders were saved filled in ([`meta_value`]), `split.json`
/// where there is one, and the weights `model.mpk` on demand. `eval`, `node`, `bench node`,
/// `report` and `train --init-from` all open run folders through this.
#[derive(Clone, Debug)]
pub struct RunFolder {
    /// The folder.
    pub dir: PathBuf,
    /// `model.json`, older fields defaulted.
    pub meta: ModelMeta,
    /// `split.json` (the scenes the model was trained, validated and tested on); None when
    /// the folder has none or it does not parse.
    pub split: Option<crate::data::Split>,
}

impl RunFolder {
    /// Reads `dir/model.json` (and `dir/split.json` where present); the weights are read
    /// by [`RunFolder::net`] or [`RunFolder::surrogate`].
    ///
    /// # Errors
    /// [`StoreError::Io`] naming `model.json` when it is missing, unreadable or not a model
    /// description.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        let path = dir.join("model.json");
        let text = std::fs::read_to_string(&path).map_err(|e| io(&path, e))?;
        let meta = parse_meta(&text).map_err(|e| io(&path, e))?;
        let split = std::fs::read_to_string(dir.join("split.json"))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok());
        Ok(Self {
            dir: dir.to_path_buf(),
            meta,
            split,
        })
    }

    /// The network with the weights of `model.mpk`, of either architecture, on `device`.
    ///
    /// # Errors
    /// [`StoreError::Io`] naming `model.mpk` when it is missing or does not fit the network.
    pub fn net<B: NetOps>(&self, device: &B::Device) -> Result<Net<B>, StoreError> {
        let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
        let weights = self.dir.join("model.mpk");
        // Each architecture's weights are saved as its own module (not as a `Net`).
        Ok(match self.meta.net.init::<B>(device) {
            Net::Paper(m) => Net::Paper(
                m.load_file(weights.clone(), &recorder, device)
                    .map_err(|e| io(&weights, e))?,
            ),
            Net::Grid(m) => Net::Grid(
                m.load_file(weights.clone(), &recorder, device)
                    .map_err(|e| io(&weights, e))?,
            ),
        })
    }

    /// The trained model ready to step, on `device`.
    ///
    /// # Errors
    /// As [`RunFolder::net`].
    pub fn surrogate<B: NetOps>(&self, device: &B::Device) -> Result<Surrogate<B>, StoreError> {
        Ok(Surrogate::from_net(
            self.net(device)?,
            self.meta.clone(),
            device,
        ))
    }
}

/// Reads `dir/model.json`: its path and contents ([`RunFolder::open`]'s reading).
///
/// # Errors
/// [`StoreError::Io`] when it is missing, unreadable or not a model description.
pub fn read_meta(dir: &Path) -> Result<(std::path::PathBuf, ModelMeta), StoreError> {
    let folder = RunFolder::open(dir)?;
    Ok((dir.join("model.json"), folder.meta))
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
/// channels; `conv` picks the kernel only (same weights, same results); the zero-initialised
/// last layers only matter for fresh weights.
const ADDED_FIELDS: [(&str, &str, fn() -> serde_json::Value); 4] = [
    ("grid", "reference", || serde_json::Value::Bool(false)),
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

/// Reads `model.json` and the weights from `dir`, of either architecture.
pub fn load_net<B: NetOps>(
    dir: &Path,
    device: &B::Device,
) -> Result<(Net<B>, ModelMeta), StoreError> {
    let folder = RunFolder::open(dir)?;
    Ok((folder.net(device)?, folder.meta))
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

/// A trained model ready for step-by-step prediction in physical units.
pub struct Surrogate<B: Backend> {
    net: Net<B>,
    meta: ModelMeta,
    scaling: Scaling,
    device: B::Device,
    mirror: bool,
}

/// What a grid model carries between steps: memory, velocity history, reference positions.
type GridCarry<B> = (MemoryState<B>, Option<Tensor<B, 3>>, Option<Tensor<B, 3>>);

/// Per-trajectory state (one batch row per trajectory).
pub struct State<B: Backend> {
    inner: NetState<B>,
    /// Frames consumed since the state was reset.
    pub frames: usize,
}

/// What each architecture carries between frames.
enum NetState<B: Backend> {
    /// The paper core's layer states.
    Paper(Vec<LayerState<B>>),
    /// The grid model's per-particle memory, the velocities of the last T - 1 frames
    /// (`[B, N, 2 (T - 1)]`, oldest first; `None` before the first frame or when T = 1) and
    /// the reference positions (`[B, N, 2]`: the first frame's, unless set by
    /// [`Surrogate::init_state_at`]; read only by a model with `reference`).
    Grid {
        memory: MemoryState<B>,
        history: Option<Tensor<B, 3>>,
        reference: Option<Tensor<B, 3>>,
    },
}

impl<B: NetOps> Surrogate<B> {
    /// Loads a run folder (either architecture).
    pub fn load(dir: &Path, device: &B::Device) -> Result<Self, StoreError> {
        RunFolder::open(dir)?.surrogate(device)
    }

    /// Wraps an in-memory paper model.
    pub fn new(model: Model<B>, meta: ModelMeta, device: &B::Device) -> Self {
        Self::from_net(Net::Paper(model), meta, device)
    }

    /// Wraps an in-memory network of either architecture.
    pub fn from_net(net: Net<B>, meta: ModelMeta, device: &B::Device) -> Self {
        let scaling = meta.scaling();
        Self {
            net,
            meta,
            scaling,
            device: device.clone(),
            mirror: false,
        }
    }

    /// This surrogate as a mirror ensemble (`--mirror`): a grid model steps each frame and
    /// its mirror image about the box's vertical midline (`x -> 1 - x`, `vx -> -vx`) as two
    /// batch rows, each with its own state, and predicts the mean of the first row's
    /// prediction and the second's mirrored back. MPM's box, walls (nodes `< 3` or `> n - 3`:
    /// free from 2.5 to n - 2.5 cells) and gravity are symmetric under that mirror, so the
    /// mirrored scene is one the model could have been trained on: test-time augmentation
    /// by a symmetry of the physics. Twice the work of a step; no effect on a paper model
    /// (its output is tied to particle index, not position). States made before this was
    /// switched do not fit: switch it before [`Surrogate::init_state`].
    pub fn with_mirror(self, mirror: bool) -> Self {
        Self { mirror, ..self }
    }

    /// Whether [`Surrogate::with_mirror`] is on (and the model is a grid model).
    pub fn mirrored(&self) -> bool {
        self.mirror && matches!(self.net, Net::Grid(_))
    }

    /// The model's description.
    pub fn meta(&self) -> &ModelMeta {
        &self.meta
    }

    /// A fresh (empty) state. The batch size is set by the first `step`.
    pub fn init_state(&self) -> State<B> {
        let inner = match &self.net {
            Net::Paper(model) => NetState::Paper(model.core.init_state()),
            Net::Grid(_) => NetState::Grid {
                memory: MemoryState::Empty,
                history: None,
                reference: None,
            },
        };
        State { inner, frames: 0 }
    }

    /// `state` reset as at the start of a stream (memory, velocity history, frame count),
    /// except that a grid model's reference positions are kept: what the node does over a
    /// gap in a stream that goes on.
    pub fn restart(&self, state: State<B>) -> State<B> {
        let mut fresh = self.init_state();
        if let (
            NetState::Grid { reference, .. },
            NetState::Grid {
                reference: kept, ..
            },
        ) = (&mut fresh.inner, state.inner)
        {
            *reference = kept;
        }
        fresh
    }

    /// A fresh state whose reference positions are those of `first` (`[B, N, 4]` physical
    /// frames: the first frame of each trajectory, when the prediction starts later in it).
    /// Without this the first frame a state steps on is taken as the reference. Only a grid
    /// model trained with `--reference first-frame` reads it; for others this is
    /// [`Surrogate::init_state`].
    ///
    /// # Errors
    /// [`StoreError::Shape`] when `first` is not `b` frames of 4 values per particle.
    pub fn init_state_at(&self, first: &[f32], b: usize) -> Result<State<B>, StoreError> {
        let mut state = self.init_state();
        if b == 0 || first.len() % (4 * b) != 0 {
            return Err(StoreError::Shape(format!(
                "reference: {} state values for {b} frames",
                first.len()
            )));
        }
        if let NetState::Grid { reference, .. } = &mut state.inner {
            let (first, b) = if self.mirror {
                (with_mirror_rows(first), 2 * b)
            } else {
                (first.to_vec(), b)
            };
            let n = first.len() / (4 * b);
            let frame = super::upload::<B, 3>(first, [b, n, 4], &self.device);
            *reference = Some(frame.narrow(2, 0, 2));
        }
        Ok(state)
    }

    /// Predicts the next frame of each trajectory in the batch and advances the state.
    ///
    /// # Shapes
    /// - `frames`: `[B, N, 4]` physical x, y, vx, vy; `material`: `[B, N]`; `dt`: `[B]`
    /// - returns `[B, N, 4]` physical, the frame `dt` later
    ///
    /// # Errors
    /// [`StoreError::Shape`] when the lengths disagree or the model is tied to another N.
    pub fn step(
        &self,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        state: State<B>,
    ) -> Result<(Vec<f32>, State<B>), StoreError> {
        // On the CPU: on the rayon pool with a worker awake (`NetOps::run_step`).
        B::run_step(|| self.step_here(frames, material, dt, state))
    }

    /// [`Surrogate::step`] on the calling thread.
    fn step_here(
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
        if let Some(expected) = self.meta.fixed_particles().filter(|&e| e != n) {
            return Err(StoreError::Shape(format!(
                "model was trained for N = {expected} particles, frame has {n}"
            )));
        }
        let (out, inner) = match (&self.net, state.inner) {
            (Net::Paper(model), NetState::Paper(layers)) => {
                // The training batches' own scaling (data::Scaler), so inputs match training.
                let mut feats = Vec::with_capacity(b * n * 5);
                self.meta.scaler.scale_into(frames, material, &mut feats);
                let x = super::upload::<B, 3>(feats, [b, n, 5], &self.device);
                let dt_t = super::upload::<B, 1>(dt.to_vec(), [b], &self.device);
                let (out, layers) = model.step(x, dt_t, layers, &self.scaling);
                let mut out = super::download(out)?;
                self.meta.scaler.unscale_rows(&mut out, 4);
                (out, NetState::Paper(layers))
            }
            (
                Net::Grid(model),
                NetState::Grid {
                    memory,
                    history,
                    reference,
                },
            ) => {
                let carry = (memory, history, reference);
                if self.mirror {
                    let (material, dt) = ([material, material].concat(), [dt, dt].concat());
                    let frames = with_mirror_rows(frames);
                    let (out, inner) = self.grid_step(model, &frames, &material, &dt, carry)?;
                    (mean_of_mirror_rows(&out), inner)
                } else {
                    self.grid_step(model, frames, material, dt, carry)?
                }
            }
            _ => return Err(StoreError::Shape("state of another architecture".into())),
        };
        Ok((
            out,
            State {
                inner,
                frames: state.frames + 1,
            },
        ))
    }

    /// [`Surrogate::step`] of a grid model: the velocity history is completed from the state
    /// (the current velocity repeated before T frames were seen, or when B or N changed), and
    /// the reference positions are this frame's when the state has none of this shape.
    fn grid_step(
        &self,
        model: &GridModel<B>,
        frames: &[f32],
        material: &[u8],
        dt: &[f32],
        (memory, history, reference): GridCarry<B>,
    ) -> Result<(Vec<f32>, NetState<B>), StoreError> {
        let (b, t) = (dt.len(), model.window());
        let n = material.len() / b;
        let frame = super::upload::<B, 3>(frames.to_vec(), [b, n, 4], &self.device);
        let pos = frame.clone().narrow(2, 0, 2);
        let vel = frame.narrow(2, 2, 2);
        let history = history.filter(|h| h.dims() == [b, n, 2 * (t - 1)]);
        let reference = reference
            .filter(|r| r.dims() == [b, n, 2])
            .unwrap_or_else(|| pos.clone());
        let memory = match memory.rows() {
            Some(rows) if rows != b * n => MemoryState::Empty,
            _ => memory,
        };
        let vel_hist = match history {
            Some(h) => Tensor::cat(vec![h, vel.clone()], 2),
            None => vel.repeat_dim(2, t),
        };
        let input = StepInput {
            pos,
            vel: vel_hist.clone(),
            material: one_hot(material, b, n, &self.device),
            dt: super::upload::<B, 1>(dt.to_vec(), [b], &self.device),
            reference: Some(reference.clone()),
        };
        let (out, memory) = model.step(input, memory);
        let next = Tensor::cat(vec![out.pos, out.vel], 2);
        let out = super::download(next)?;
        let history = (t > 1).then(|| vel_hist.narrow(2, 2, 2 * (t - 1)));
        let reference = Some(reference);
        Ok((
            out,
            NetState::Grid {
                memory,
                history,
                reference,
            },
        ))
    }

    /// Seeds with `seed` frames (each `[N, 4]` physical, one trajectory) and predicts `k`
    /// frames autoregressively, feeding predictions back. Returns the `k` predicted frames.
    /// `first`, the trajectory's first frame (`[N, 4]`), sets the reference positions (see
    /// [`Surrogate::init_state_at`]); without it the first seed frame is the reference.
    ///
    /// # Errors
    /// A step's [`StoreError`].
    pub fn rollout(
        &self,
        first: Option<&[f32]>,
        seed: &[Vec<f32>],
        material: &[u8],
        dt: f32,
        k: usize,
    ) -> Result<Vec<Vec<f32>>, StoreError> {
        let mut state = match first {
            Some(frame) => self.init_state_at(frame, 1)?,
            None => self.init_state(),
        };
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

/// `frames` (`[B, N, 4]`) followed by their mirror images: `[2B, N, 4]`.
fn with_mirror_rows(frames: &[f32]) -> Vec<f32> {
    let mut out = Vec::with_capacity(2 * frames.len());
    out.extend_from_slice(frames);
    out.extend_from_slice(frames);
    mirror_rows(&mut out[frames.len()..], 4);
    out
}

/// The mean of the first half of `out` (`[2B, N, 4]`) and its second half mirrored back.
fn mean_of_mirror_rows(out: &[f32]) -> Vec<f32> {
    let (direct, mirrored) = out.split_at(out.len() / 2);
    let mut back = mirrored.to_vec();
    mirror_rows(&mut back, 4);
    direct
        .iter()
        .zip(&back)
        .map(|(a, b)| 0.5 * (a + b))
        .collect()
}
