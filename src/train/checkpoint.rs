//! What a training run writes, the same for both architectures: [`RunOutput`] (the run's
//! [`RunFolder`], the `model.json` of the kept model, the epoch limits) and the resumable
//! checkpoint. [`RunFolder::checkpoint`] holds the model and the optimizer state
//! (`model.mpk`, `optim.mpk`: burn named MessagePack, full precision) and `history.json`
//! (every epoch so far). It is written to [`RunFolder::checkpoint_tmp`] and swapped in with
//! renames, so a run killed at any moment leaves either the previous or the new checkpoint,
//! never a torn one; the previous epoch's stays as [`RunFolder::checkpoint_old`], and a
//! resume whose checkpoint was damaged afterwards (a truncated copy, a full disk) falls back
//! to it with a warning naming the file. Used by [`super::epochs::run_epochs`] for `minflow
//! train` of either architecture.

use super::{EpochRecord, TrainError};
use crate::data::Scaler;
use crate::model::store::{self, ModelMeta, NetConfig, RunFolder};
use burn::module::AutodiffModule;
use burn::optim::Optimizer;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder, Recorder};
use burn::tensor::backend::AutodiffBackend;
use std::path::Path;

/// A run's folder, what its `model.json` says, and how long it may run: everything
/// [`super::epochs::run_epochs`] needs to keep the best model and checkpoint each epoch,
/// whatever the architecture.
#[derive(Clone, Debug)]
pub struct RunOutput {
    /// The run folder (`train --out`).
    pub folder: RunFolder,
    /// The network's architecture and hyper-parameters.
    pub net: NetConfig,
    /// The training split's scaler, saved with the model.
    pub scaler: Scaler,
    /// Epochs at most.
    pub epochs: usize,
    /// Epochs without a better validation score before stopping (0: never).
    pub patience: usize,
    /// The material constraints the model projects its frames onto, saved with it.
    pub constraints: Option<crate::model::constraints::Constraints>,
}

impl RunOutput {
    /// What `model.json` says of the model after `epoch` epochs with `val_loss`.
    pub fn meta(&self, epoch: usize, val_loss: f64) -> ModelMeta {
        ModelMeta {
            net: self.net.clone(),
            scaler: self.scaler,
            epoch,
            val_loss,
            constraints: self.constraints.clone(),
        }
    }

    /// Saves `model` as the run's kept model (`model.json` + `model.mpk`).
    ///
    /// # Errors
    /// The files could not be written.
    pub fn save_best<B: burn::tensor::backend::Backend, M: burn::module::Module<B>>(
        &self,
        model: &M,
        epoch: usize,
        val_loss: f64,
    ) -> Result<(), TrainError> {
        Ok(self.folder.save(model, &self.meta(epoch, val_loss))?)
    }

    /// Writes the resumable checkpoint after the epochs in `history` ([`save`]).
    ///
    /// # Errors
    /// The files could not be written.
    pub fn checkpoint<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
        &self,
        model: &M,
        optim: &O,
        history: &[EpochRecord],
    ) -> Result<(), TrainError> {
        save(&self.folder, model, optim, history)
    }
}

fn err(path: &Path, source: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> TrainError {
    TrainError::Store(store::io(path, source))
}

/// Writes the checkpoint of the epoch just finished into `folder` (module doc).
///
/// # Errors
/// A file could not be written ([`store::StoreError::Io`] naming it); the previous
/// checkpoint stays.
pub fn save<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
    folder: &RunFolder,
    model: &M,
    optim: &O,
    history: &[EpochRecord],
) -> Result<(), TrainError> {
    let tmp = folder.checkpoint_tmp();
    let dir = folder.checkpoint();
    let old = folder.checkpoint_old();
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp).map_err(|e| err(&tmp, e))?;
    // Through store::write_record: a full disk is named ("No space left on device"), and the
    // unfinished checkpoint.tmp/ is removed; the previous checkpoint/ stays for a resume.
    let written = store::write_record::<B, _>(&tmp.join("model.mpk"), model.clone().into_record())
        .and_then(|()| store::write_record::<B, _>(&tmp.join("optim.mpk"), optim.to_record()))
        .map_err(TrainError::Store)
        .and_then(|()| {
            let json = serde_json::to_string_pretty(history).map_err(|e| err(&tmp, e))?;
            std::fs::write(tmp.join("history.json"), json)
                .map_err(|e| err(&tmp.join("history.json"), e))
        });
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&tmp);
        return Err(e);
    }
    let _ = std::fs::remove_dir_all(&old);
    if dir.exists() {
        std::fs::rename(&dir, &old).map_err(|e| err(&dir, e))?;
    }
    std::fs::rename(&tmp, &dir).map_err(|e| err(&tmp, e))?;
    Ok(())
}

/// A checkpoint read back.
pub struct Resumed<M, R> {
    /// Weights after the last finished epoch.
    pub model: M,
    /// Optimizer state.
    pub optim: R,
    /// Every finished epoch.
    pub history: Vec<EpochRecord>,
}

/// Reads the checkpoint of the run folder `out` ([`RunFolder::checkpoint`]) into `fresh` (a
/// model of the run's configuration), or, when it is missing or damaged, the previous
/// epoch's ([`RunFolder::checkpoint_old`]); `None` if there is neither.
///
/// # Errors
/// Every checkpoint there is damaged: [`store::StoreError::Io`] naming the first damaged file of
/// each (`model.mpk`, `optim.mpk` or `history.json`) and what was wrong with it.
pub fn load<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
    out: &Path,
    fresh: M,
    device: &B::Device,
    _optim: &O,
) -> Result<Option<Resumed<M, O::Record>>, TrainError> {
    let folder = RunFolder::new(out);
    let dirs: Vec<_> = [folder.checkpoint(), folder.checkpoint_old()]
        .into_iter()
        .filter(|d| d.join("history.json").exists())
        .collect();
    let mut damaged: Vec<String> = Vec::new();
    for dir in &dirs {
        match read::<B, M, O>(dir, fresh.clone(), device) {
            Ok(resumed) => {
                if !damaged.is_empty() {
                    tracing::warn!(
                        "{}; resuming from {} (epoch {}) instead",
                        damaged.join("; "),
                        dir.display(),
                        resumed.history.len()
                    );
                }
                return Ok(Some(resumed));
            }
            Err(e) => damaged.push(e.to_string()),
        }
    }
    match damaged.is_empty() {
        true => Ok(None),
        false => Err(err(
            &folder.checkpoint(),
            format!("cannot resume: {}", damaged.join("; ")),
        )),
    }
}

/// One checkpoint folder read back; the error names the damaged file.
fn read<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
    dir: &Path,
    fresh: M,
    device: &B::Device,
) -> Result<Resumed<M, O::Record>, store::StoreError> {
    let damaged =
        |file: &str, source: Box<dyn std::error::Error + Send + Sync>| store::StoreError::Damaged {
            path: dir.join(file),
            source,
        };
    let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
    let model = fresh
        .load_file(dir.join("model"), &recorder, device)
        .map_err(|e| damaged("model.mpk", e.into()))?;
    let optim: O::Record = Recorder::<B>::load(&recorder, dir.join("optim"), device)
        .map_err(|e| damaged("optim.mpk", e.into()))?;
    let text = std::fs::read_to_string(dir.join("history.json"))
        .map_err(|e| damaged("history.json", e.into()))?;
    let history = serde_json::from_str(&text).map_err(|e| damaged("history.json", e.into()))?;
    Ok(Resumed {
        model,
        optim,
        history,
    })
}
