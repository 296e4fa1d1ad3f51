//! A run folder (`minflow train --out`): the one description of its files, which every
//! command that writes or reads one goes through ([`RunFolder`]):
//!
//! - `model.json` ([`ModelMeta`]: the architecture and its config, the scaler, the epoch and
//!   validation loss of the kept weights, the constraints) and `model.mpk` (those weights,
//!   burn's named MessagePack, full precision): written by `minflow train` (the best epoch so
//!   far, [`RunFolder::save`]) and `minflow constraints fit`; read by `eval`, `node`, `bench`,
//!   `report` and `train --init-from` / `--resume`;
//! - `split.json` (the scenes trained, validated and tested on, [`Split`]) and `train.json`
//!   (the training flags), written when a run starts;
//! - `metrics.csv` and `loss.png` (one row and point per epoch), rewritten after each epoch;
//! - `checkpoint/` (the resumable checkpoint of the last epoch), written as `checkpoint.tmp/`
//!   and swapped in, the epoch before kept as `checkpoint.old/`
//!   ([`crate::train::checkpoint`] writes and reads their contents).

use std::path::{Path, PathBuf};

use burn::module::Module;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder};
use burn::tensor::backend::Backend;

use super::{io, parse_meta, write_file, write_record, ModelMeta, Net, StoreError, Surrogate};
use crate::data::Split;
use crate::ops::NetOps;

/// A run folder (see the module doc): where each of its files is, and reading and writing
/// the kept model. Holds only the folder's path; every read goes to the disk.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct RunFolder {
    dir: PathBuf,
}

impl RunFolder {
    /// The run folder `dir` (nothing is read or created).
    pub fn new(dir: impl Into<PathBuf>) -> Self {
        Self { dir: dir.into() }
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// `model.json`: the kept model's [`ModelMeta`].
    pub fn model_json(&self) -> PathBuf {
        self.dir.join("model.json")
    }

    /// `model.json.tmp`: a `model.json` being written, renamed to [`Self::model_json`] once
    /// whole.
    pub fn model_json_tmp(&self) -> PathBuf {
        self.dir.join("model.json.tmp")
    }

    /// `model.mpk`: the kept model's weights.
    pub fn model_mpk(&self) -> PathBuf {
        self.dir.join("model.mpk")
    }

    /// `split.json`: the run's [`Split`].
    pub fn split_json(&self) -> PathBuf {
        self.dir.join("split.json")
    }

    /// `train.json`: the training run's flags.
    pub fn train_json(&self) -> PathBuf {
        self.dir.join("train.json")
    }

    /// `metrics.csv`: one row per epoch (`epoch,train_loss,val_loss,seconds,samples_per_sec`).
    pub fn metrics_csv(&self) -> PathBuf {
        self.dir.join("metrics.csv")
    }

    /// `loss.png`: the training and validation loss per epoch.
    pub fn loss_png(&self) -> PathBuf {
        self.dir.join("loss.png")
    }

    /// `checkpoint/`: the resumable checkpoint after the last finished epoch.
    pub fn checkpoint(&self) -> PathBuf {
        self.dir.join("checkpoint")
    }

    /// `checkpoint.tmp/`: a checkpoint being written, renamed to [`Self::checkpoint`] once
    /// whole.
    pub fn checkpoint_tmp(&self) -> PathBuf {
        self.dir.join("checkpoint.tmp")
    }

    /// `checkpoint.old/`: the checkpoint of the epoch before, a resume's fallback.
    pub fn checkpoint_old(&self) -> PathBuf {
        self.dir.join("checkpoint.old")
    }

    /// `model.json` as a [`ModelMeta`], the fields added since older folders were saved
    /// filled in ([`super::meta_value`]).
    ///
    /// # Errors
    /// [`StoreError::Io`] naming `model.json` when it is missing, unreadable or not a model
    /// description.
    pub fn meta(&self) -> Result<ModelMeta, StoreError> {
        let path = self.model_json();
        let text = std::fs::read_to_string(&path).map_err(|e| io(&path, e))?;
        parse_meta(&text).map_err(|e| io(&path, e))
    }

    /// `split.json` (the scenes the model was trained, validated and tested on); None when
    /// the folder has none or it does not parse.
    pub fn split(&self) -> Option<Split> {
        std::fs::read_to_string(self.split_json())
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
    }

    /// The network `meta` describes (this folder's [`Self::meta`]) with the weights of
    /// `model.mpk`, of either architecture, on `device`.
    ///
    /// # Errors
    /// [`StoreError::Io`] naming `model.mpk` when it is missing or does not fit the network.
    pub fn net<B: NetOps>(
        &self,
        meta: &ModelMeta,
        device: &B::Device,
    ) -> Result<Net<B>, StoreError> {
        let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
        let weights = self.model_mpk();
        // Each architecture's weights are saved as its own module (not as a `Net`).
        Ok(match meta.net.init::<B>(device) {
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

    /// The kept model: `model.json` and the network with its weights, on `device`.
    ///
    /// # Errors
    /// As [`Self::meta`] and [`Self::net`].
    pub fn load<B: NetOps>(&self, device: &B::Device) -> Result<(Net<B>, ModelMeta), StoreError> {
        let meta = self.meta()?;
        Ok((self.net(&meta, device)?, meta))
    }

    /// The kept model ready to step, on `device`.
    ///
    /// # Errors
    /// As [`Self::load`].
    pub fn surrogate<B: NetOps>(&self, device: &B::Device) -> Result<Surrogate<B>, StoreError> {
        let (net, meta) = self.load(device)?;
        Ok(Surrogate::from_net(net, meta, device))
    }

    /// Writes `model` and `meta` as the kept model, `model.json` + `model.mpk` (via the
    /// temporary names `model.json.tmp` and `model-tmp.mpk`, renamed at the end); creates the
    /// folder if needed.
    ///
    /// # Errors
    /// [`StoreError::Io`] naming the file and keeping the OS error (a full disk: "No space left
    /// on device"); the temporary files are removed, and a model saved there before stays
    /// whole.
    pub fn save<B: Backend, M: Module<B>>(
        &self,
        model: &M,
        meta: &ModelMeta,
    ) -> Result<(), StoreError> {
        let dir = &self.dir;
        std::fs::create_dir_all(dir).map_err(|e| io(dir, e))?;
        let (tmp_mpk, tmp_json) = (dir.join("model-tmp.mpk"), self.model_json_tmp());
        let written = write_record::<B, _>(&tmp_mpk, model.clone().into_record()).and_then(|()| {
            let json = serde_json::to_string_pretty(meta).map_err(|e| io(dir, e))?;
            write_file(&tmp_json, json.as_bytes())
        });
        if let Err(e) = written {
            let _ = std::fs::remove_file(&tmp_mpk);
            let _ = std::fs::remove_file(&tmp_json);
            return Err(e);
        }
        std::fs::rename(&tmp_mpk, self.model_mpk()).map_err(|e| io(dir, e))?;
        std::fs::rename(&tmp_json, self.model_json()).map_err(|e| io(dir, e))?;
        Ok(())
    }
}
