//! What a training run writes, the same for both architectures: [`RunOutput`] (the run's
//! [`RunFolder`], the `model.json` of the kept model, the epoch limits) and the resumable
//! checkpoint. [`RunFolder::checkpoint`] holds the model and the optimizer state
//! (`model.mpk`, `optim.mpk`: burn named MessagePack, full precision) and `history.json`
//! (every epoch so far), and, when the call ended or checkpointed mid-epoch, `partial.json`
//! (the unfinished epoch: its steps and sums, [`Unfinished`]); `model.json` describes the
//! network, normalisation and constraints the run trains with (so `checkpoint/` is a model
//! folder of the latest weights, and `--resume` keeps them); `ledger.json` is the run's
//! [`RunLedger`] (samples, device-hours, calls), also written beside it as `run.json`. It is
//! written to [`RunFolder::checkpoint_tmp`] and swapped in with
//! renames, so a run killed at any moment leaves either the previous or the new checkpoint,
//! never a torn one; the previous epoch's stays as [`RunFolder::checkpoint_old`], and a
//! resume whose checkpoint was damaged afterwards (a truncated copy, a full disk) falls back
//! to it with a warning naming the file. With `--keep-epochs N`, `epochs/NNNN` holds the
//! last N epochs' weights ([`RunOutput::keep_epoch`]). Used by
//! [`super::epochs::run_epochs`] for `minflow train` of either architecture.

use super::ledger::RunLedger;
use super::progress::Unfinished;
use super::{EpochRecord, TrainError};
use crate::data::Scaler;
use crate::model::store::{self, ModelMeta, NetConfig, RunFolder};
use burn::module::AutodiffModule;
use burn::optim::Optimizer;
use burn::record::{FullPrecisionSettings, NamedMpkFileRecorder, Recorder};
use burn::tensor::backend::AutodiffBackend;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

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
    /// Finished epochs whose weights [`Self::keep_epoch`] keeps (0: none).
    pub keep_epochs: usize,
    /// The material constraints the model projects its frames onto, saved with it.
    pub constraints: Option<crate::model::constraints::Constraints>,
    /// What the run has used over its calls, updated at each checkpoint.
    pub ledger: Arc<Mutex<RunLedger>>,
    /// When this call began (the ledger's current call).
    pub call_started: Instant,
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

    /// Keeps `model` after `epoch` epochs (the last one finished, or cut short by
    /// `--max-minutes` and validated) as the run folder `epochs/NNNN` (`model.json`,
    /// `model.mpk`, the run's `split.json`: loadable by every command that reads a model) and
    /// removes every other epoch's folder but the last [`Self::keep_epochs`]; nothing when
    /// that is 0. For weight averaging (`minflow average`, Izmailov et al. 2018) and for picking an
    /// epoch by a measure other than the validation loss.
    ///
    /// # Errors
    /// The files could not be written or the older folders removed.
    pub fn keep_epoch<B: burn::tensor::backend::Backend, M: burn::module::Module<B>>(
        &self,
        model: &M,
        epoch: usize,
        val_loss: f64,
    ) -> Result<(), TrainError> {
        if self.keep_epochs == 0 {
            return Ok(());
        }
        let kept = self.folder.dir().join("epochs");
        let folder = RunFolder::new(kept.join(format!("{epoch:04}")));
        folder.save(model, &self.meta(epoch, val_loss))?;
        let split = self.folder.split_json();
        if split.exists() {
            std::fs::copy(&split, folder.split_json()).map_err(|e| err(&split, e))?;
        }
        // Every other epoch's folder: older ones (also those a larger --keep-epochs left) and
        // later ones (a run trained again into this folder, or one resumed from an older
        // checkpoint, is not yet past `epoch`).
        let entries = std::fs::read_dir(&kept).map_err(|e| err(&kept, e))?;
        let kept_range = epoch.saturating_sub(self.keep_epochs) + 1..=epoch;
        for entry in entries.flatten() {
            let name = entry.file_name();
            let number = name.to_str().and_then(|n| n.parse::<usize>().ok());
            if number.is_some_and(|n| !kept_range.contains(&n)) {
                std::fs::remove_dir_all(entry.path()).map_err(|e| err(&entry.path(), e))?;
            }
        }
        Ok(())
    }

    /// Writes the resumable checkpoint after the epochs in `history` and the `unfinished`
    /// one's steps ([`save`]), the ledger brought up to date first.
    ///
    /// # Errors
    /// The files could not be written.
    pub fn checkpoint<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
        &self,
        model: &M,
        optim: &O,
        history: &[EpochRecord],
        unfinished: Option<&Unfinished>,
    ) -> Result<(), TrainError> {
        let samples = history.iter().map(|r| r.samples as u64).sum::<u64>()
            + unfinished.map_or(0, |u| u.pass.seen as u64);
        let ledger = {
            let mut ledger = self.ledger.lock().unwrap_or_else(|e| e.into_inner());
            ledger.update(samples, self.call_started.elapsed().as_secs_f64());
            ledger.clone()
        };
        // The latest weights' model.json: the last finished epoch's validation loss.
        let last = history.last();
        let meta = self.meta(
            last.map_or(0, |r| r.epoch),
            last.map_or(0.0, |r| r.val_loss),
        );
        let state = Progress {
            meta: &meta,
            history,
            unfinished,
            ledger: &ledger,
        };
        save(&self.folder, model, optim, &state)?;
        write_json(&self.folder.dir().join("run.json"), &ledger)
    }
}

fn err(path: &Path, source: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> TrainError {
    TrainError::Store(store::io(path, source))
}

/// Where a run is, besides its weights and optimizer: the finished epochs, the unfinished
/// one's steps, the ledger.
pub struct Progress<'a> {
    /// What `model.json` says of the latest weights.
    pub meta: &'a ModelMeta,
    /// Every finished epoch.
    pub history: &'a [EpochRecord],
    /// The epoch in progress, when the checkpoint is written mid-epoch.
    pub unfinished: Option<&'a Unfinished>,
    /// The run's ledger.
    pub ledger: &'a RunLedger,
}

/// Writes the checkpoint of the run at `progress` into `folder` (module doc).
///
/// # Errors
/// A file could not be written ([`store::StoreError::Io`] naming it); the previous
/// checkpoint stays.
pub fn save<B: AutodiffBackend, M: AutodiffModule<B>, O: Optimizer<M, B>>(
    folder: &RunFolder,
    model: &M,
    optim: &O,
    progress: &Progress<'_>,
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
        .and_then(|()| write_json(&tmp.join("model.json"), progress.meta))
        .and_then(|()| write_json(&tmp.join("history.json"), progress.history))
        .and_then(|()| write_json(&tmp.join("ledger.json"), progress.ledger))
        .and_then(|()| match progress.unfinished {
            Some(unfinished) => write_json(&tmp.join("partial.json"), unfinished),
            None => Ok(()),
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

/// `value` as pretty JSON in `path`.
fn write_json<T: serde::Serialize + ?Sized>(path: &Path, value: &T) -> Result<(), TrainError> {
    let json = serde_json::to_string_pretty(value).map_err(|e| err(path, e))?;
    std::fs::write(path, json).map_err(|e| err(path, e))
}

/// A checkpoint read back.
pub struct Resumed<M, R> {
    /// Weights after the last finished epoch, or at the unfinished one's last step.
    pub model: M,
    /// Optimizer state.
    pub optim: R,
    /// Every finished epoch.
    pub history: Vec<EpochRecord>,
    /// The epoch the checkpoint was written in, when mid-epoch.
    pub unfinished: Option<Unfinished>,
    /// The run's ledger (None in checkpoints written before it existed).
    pub ledger: Option<RunLedger>,
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
    let damaged = |file: &str, source| damaged(dir, file, source);
    let recorder = NamedMpkFileRecorder::<FullPrecisionSettings>::new();
    let model = fresh
        .load_file(dir.join("model"), &recorder, device)
        .map_err(|e| damaged("model.mpk", e.into()))?;
    let optim: O::Record = Recorder::<B>::load(&recorder, dir.join("optim"), device)
        .map_err(|e| damaged("optim.mpk", e.into()))?;
    // Checkpoints written before the unfinished epoch and the ledger existed lack them.
    let history = read_json(dir, "history.json", true)?.unwrap_or_default();
    let unfinished = read_json(dir, "partial.json", false)?;
    let ledger = read_json(dir, "ledger.json", false)?;
    Ok(Resumed {
        model,
        optim,
        history,
        unfinished,
        ledger,
    })
}

/// `dir/file` parsed as JSON; None when it is missing and not `required`.
fn read_json<T: serde::de::DeserializeOwned>(
    dir: &Path,
    file: &str,
    required: bool,
) -> Result<Option<T>, store::StoreError> {
    let text = match std::fs::read_to_string(dir.join(file)) {
        Ok(text) => text,
        Err(e) if !required && e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(damaged(dir, file, e.into())),
    };
    serde_json::from_str(&text)
        .map(Some)
        .map_err(|e| damaged(dir, file, e.into()))
}

/// The error of a damaged checkpoint file `dir/file`.
fn damaged(
    dir: &Path,
    file: &str,
    source: Box<dyn std::error::Error + Send + Sync>,
) -> store::StoreError {
    store::StoreError::Damaged {
        path: dir.join(file),
        source,
    }
}
