//! The training command's side of its run folder ([`RunFolder`], which names every file in
//! it), for both architectures: the progress bar and `metrics.csv` / `loss.png` kept current
//! ([`Progress`]), the split to train with ([`run_split`]), `split.json` and `train.json`
//! ([`write_run_files`]), the closing line ([`print_best`]), and the check that a `--resume`
//! or `--init-from` folder holds the network the flags describe ([`check_resume`],
//! [`differences`]).

use anyhow::{bail, Context};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::data::Split;
use crate::model::store::{NetConfig, RunFolder};
use crate::train::{EpochRecord, Observer};

/// Progress bar per epoch, one log line per epoch, metrics.csv and loss.png kept current.
pub(crate) struct Progress {
    folder: RunFolder,
    bar: Option<indicatif::ProgressBar>,
}

impl Progress {
    /// Progress of a run writing to the run folder `out`.
    pub(crate) fn new(out: PathBuf) -> Self {
        Self {
            folder: RunFolder::new(out),
            bar: None,
        }
    }
}

impl Observer for Progress {
    fn batch(&mut self, epoch: usize, done: usize, total: usize, loss: f64, rate: f64) {
        let bar = self
            .bar
            .get_or_insert_with(|| super::progress(total as u64, &format!("epoch {epoch}")));
        bar.set_position(done as u64);
        bar.set_message(format!("epoch {epoch} loss {loss:.3e} {rate:.1}/s"));
    }

    fn epoch(&mut self, r: &EpochRecord, history: &[EpochRecord]) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
        eprintln!(
            "epoch {:>3}  train {:.4e}  val {:.4e}  {:.1} s  {:.1} samples/s",
            r.epoch, r.train_loss, r.val_loss, r.seconds, r.samples_per_sec
        );
        if let Err(err) = write_metrics(&self.folder, history) {
            tracing::warn!("writing metrics: {err:#}");
        }
    }
}

/// Rewrites `metrics.csv` (and `loss.png`) from the whole history.
fn write_metrics(folder: &RunFolder, history: &[EpochRecord]) -> anyhow::Result<()> {
    let path = folder.metrics_csv();
    let mut f =
        std::fs::File::create(&path).with_context(|| format!("writing {}", path.display()))?;
    writeln!(f, "epoch,train_loss,val_loss,seconds,samples_per_sec")?;
    for r in history {
        writeln!(
            f,
            "{},{},{},{:.3},{:.3}",
            r.epoch, r.train_loss, r.val_loss, r.seconds, r.samples_per_sec
        )?;
    }
    super::loss_plot(&folder.loss_png(), history)
}

/// The split a run trains with, over the scene ids `scenes` of its data. With `split_from`
/// (a run folder or a `split.json`; default: `init_from`'s run folder when it has one) its
/// validation and test scenes stay held out and every other scene trains
/// ([`Split::keeping_held_out`]), so a model continued on more scenes never trains on what
/// its parent held out; otherwise (or when no scene of `scenes` is in `init_from`'s split: a
/// parent trained on another family or size) the seeded 80:10:10 split of `scenes`.
///
/// # Errors
/// The split file is unreadable or malformed; none of its validation scenes is in the data
/// (a usage error: no validation rollouts to choose the checkpoint by).
pub(crate) fn run_split(
    scenes: &[String],
    seed: u64,
    split_from: Option<&Path>,
    init_from: Option<&Path>,
) -> anyhow::Result<Split> {
    let path = |p: &Path| {
        if p.is_dir() {
            RunFolder::new(p).split_json()
        } else {
            p.to_path_buf()
        }
    };
    let source = match (split_from, init_from) {
        (Some(p), _) => Some(path(p)),
        (None, Some(dir)) => Some(RunFolder::new(dir).split_json()).filter(|p| p.is_file()),
        (None, None) => None,
    };
    let Some(file) = source else {
        return Ok(Split::new(scenes, seed));
    };
    let text = std::fs::read_to_string(&file)
        .with_context(|| format!("reading the split to keep, {}", file.display()))?;
    let saved: Split = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a split.json", file.display()))?;
    let unrelated = scenes.iter().all(|s| saved.part_of(s.as_ref()).is_none());
    if split_from.is_none() && unrelated {
        // `--init-from` a model trained on other scenes (another family or size): no scene
        // of --data is in its split, so the data gets a split of its own.
        tracing::warn!(
            "no scene of --data is in {}: a fresh split (seed {seed})",
            file.display()
        );
        return Ok(Split::new(scenes, seed));
    }
    let split = Split::keeping_held_out(&saved, scenes);
    if split.val.is_empty() && !saved.val.is_empty() {
        return Err(super::UsageError(format!(
            "{}: none of its {} validation scenes is in --data (the split that --split-from, \
             --init-from or --resume keeps)",
            file.display(),
            saved.val.len()
        ))
        .into());
    }
    tracing::info!(
        "split kept from {}: {} train, {} val, {} test scenes",
        file.display(),
        split.train.len(),
        split.val.len(),
        split.test.len()
    );
    Ok(split)
}

/// Creates the run folder `out` with its `split.json` and `train.json` (`options`).
///
/// # Errors
/// The folder or a file could not be written.
pub(crate) fn write_run_files(
    out: &Path,
    split: &Split,
    options: &impl serde::Serialize,
) -> anyhow::Result<()> {
    std::fs::create_dir_all(out).with_context(|| format!("creating {}", out.display()))?;
    let folder = RunFolder::new(out);
    for (path, text) in [
        (folder.split_json(), serde_json::to_string_pretty(split)?),
        (folder.train_json(), serde_json::to_string_pretty(options)?),
    ] {
        std::fs::write(&path, text).with_context(|| format!("writing {}", path.display()))?;
    }
    Ok(())
}

/// Prints the best epoch of `history` (by validation loss, called `what`) and where its
/// model was saved.
pub(crate) fn print_best(history: &[EpochRecord], what: &str, out: &Path) {
    if let Some(best) = history
        .iter()
        .min_by(|a, b| a.val_loss.total_cmp(&b.val_loss))
    {
        println!(
            "best epoch {} {what} {:.4e} -> {}",
            best.epoch,
            best.val_loss,
            RunFolder::new(out).model_json().display()
        );
    }
}

/// With `--resume`, the run folder's `model.json` (written with the first checkpoint) must
/// describe the network this invocation builds: weights of another shape cannot load, and
/// other settings would silently change the run. Compares every hyper-parameter of `net`
/// with the saved one, except the values fitted on the data (`vel_scale`, `dv_mean`,
/// `dv_scale`) and the convolution kernel (`conv`: the same weights and results). A folder
/// without `model.json` passes (nothing to resume yet).
///
/// # Errors
/// An unreadable `model.json`, or one whose settings differ: the error names each field with
/// both values.
pub(crate) fn check_resume(out: &Path, net: &NetConfig) -> anyhow::Result<()> {
    let Some(differ) = config_differences(out, net)? else {
        return Ok(());
    };
    if !differ.is_empty() {
        bail!(
            "--resume: {} was trained with other settings ({}); resume with the flags it was \
             started with, or train into a new --out",
            out.display(),
            differ.join("; ")
        );
    }
    Ok(())
}

/// Each hyper-parameter of `net` that differs from the one saved in `dir/model.json`, as
/// `"field: checkpoint OLD, this run NEW"`, skipping the values fitted on the data
/// (`vel_scale`, `dv_mean`, `dv_scale`) and the convolution kernel (`conv`). `None` when
/// `dir` has no `model.json`.
///
/// # Errors
/// An unreadable or unparsable `model.json`.
pub(crate) fn config_differences(
    dir: &Path,
    net: &NetConfig,
) -> anyhow::Result<Option<Vec<String>>> {
    let path = RunFolder::new(dir).model_json();
    let text = match std::fs::read_to_string(&path) {
        Ok(text) => text,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("reading {}", path.display())),
    };
    let saved = crate::model::store::meta_value(&text)
        .with_context(|| format!("parsing {}", path.display()))?;
    differences(&saved, net).map(Some)
}

/// Each hyper-parameter of `net` that differs from its value in `saved` (a `model.json`, or
/// a saved [`NetConfig`], as JSON), as [`config_differences`] lists them.
///
/// # Errors
/// `net` does not serialise (not expected).
pub(crate) fn differences(
    saved: &serde_json::Value,
    net: &NetConfig,
) -> anyhow::Result<Vec<String>> {
    const NOT_COMPARED: [&str; 4] = ["vel_scale", "dv_mean", "dv_scale", "conv"];
    let new = serde_json::to_value(net)?;
    let describe = |key: &str, old: &str, new: &serde_json::Value| {
        format!("{key}: checkpoint {old}, this run {new}")
    };
    Ok(fields_differing(saved, &new, &NOT_COMPARED, describe))
}

/// Each field of the JSON object `new` but those in `skip` whose value in `saved` differs,
/// as `describe(key, saved value or "absent", new value)`.
pub(crate) fn fields_differing(
    saved: &serde_json::Value,
    new: &serde_json::Value,
    skip: &[&str],
    describe: impl Fn(&str, &str, &serde_json::Value) -> String,
) -> Vec<String> {
    (new.as_object().into_iter().flatten())
        .filter(|(key, _)| !skip.contains(&key.as_str()))
        .filter_map(|(key, value)| {
            let old = saved.get(key);
            (old != Some(value)).then(|| {
                let old = old.map_or_else(|| "absent".to_owned(), ToString::to_string);
                describe(key, &old, value)
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A parent's `split.json` in a folder of its own, over scenes `a/0`..`a/19`.
    fn parent() -> (tempfile::TempDir, Split) {
        let dir = tempfile::tempdir().unwrap();
        let scenes: Vec<String> = (0..20).map(|i| format!("a/{i:03}")).collect();
        let split = Split::new(&scenes, 0);
        let json = serde_json::to_string(&split).unwrap();
        std::fs::write(RunFolder::new(dir.path()).split_json(), json).unwrap();
        (dir, split)
    }

    /// `--init-from` a parent trained on other scenes: a fresh split of the data; the same
    /// data named by `--split-from` is a usage error; the parent's own training scenes alone
    /// are a usage error too (none of its validation scenes to keep held out), never a fresh
    /// split that would hold out scenes the parent trained on.
    #[test]
    fn a_fresh_split_only_for_data_the_parent_never_saw() {
        let (dir, saved) = parent();
        let other: Vec<String> = (0..20).map(|i| format!("b/{i:03}")).collect();
        let split = run_split(&other, 3, None, Some(dir.path())).unwrap();
        assert_eq!(split, Split::new(&other, 3));
        assert!(run_split(&other, 3, Some(dir.path()), None).is_err());
        let trained = saved.train.clone();
        assert!(run_split(&trained, 3, None, Some(dir.path())).is_err());
    }
}
