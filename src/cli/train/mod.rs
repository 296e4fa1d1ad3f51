//! `minflow train --data DIR --out runs/NAME [--arch grid|paper]`: one command for both
//! architectures. It loads trajectories from bags, splits them 80:10:10 by scene (seeded),
//! fits the scaler on the training scenes, trains with a progress bar per epoch, and leaves
//! in the run folder: `model.json` + `model.mpk` (best epoch), `checkpoint/` (last epoch, for
//! `--resume`), `metrics.csv`, `loss.png`, `split.json` and `train.json` (the options).
//! `--device` picks the backend: the CPU (burn ndarray, default) or a GPU (burn CUDA,
//! feature `cuda`).
//!
//! Layout: the flags in [`args`]; each architecture's run in [`grid`] and [`paper`], over the
//! shared epoch loop of [`crate::train::epochs`]; the run folder's files in
//! `cli/run_folder.rs`.

pub mod args;
mod grid;
mod net_args;
mod paper;

pub use args::{CpuTrain, TrainArgs};

use std::path::PathBuf;

use anyhow::Context;

use crate::cli::device::Device;
use crate::cli::Outcome;
use crate::data::{self, LoadReport, SceneInfo, Trajectory};
use crate::ops::NetOps;
use crate::train::{EpochRecord, TrainError};
use burn::tensor::backend::AutodiffBackend;

/// Runs `minflow train`: the architecture `--arch` names.
///
/// # Errors
/// Bad flags (before any data is read), unreadable bags, no training scenes, training errors.
pub fn run(args: TrainArgs) -> anyhow::Result<Outcome> {
    match args.arch.as_str() {
        "paper" => paper::run(args),
        _ => grid::run(args),
    }
}

/// Where a run's split comes from besides its seed: `--split-from`, else, resuming, the run
/// folder's own `split.json` (written at its start: a resumed run trains on the scenes it
/// started with, whatever `--split-from` or `--init-from` chose them then).
fn split_source(args: &TrainArgs) -> Option<PathBuf> {
    let own = crate::model::store::RunFolder::new(&args.out).split_json();
    (args.split_from.clone()).or_else(|| (args.resume && own.is_file()).then(|| args.out.clone()))
}

/// A training run that can start on any backend: each architecture's run in [`grid`] and
/// [`paper`] implements it, and [`fit_on`] picks the backend `--device` names.
trait FitOn {
    /// Trains on `devices` of backend `B` (one, or several for a data-parallel run).
    ///
    /// # Errors
    /// The run's [`TrainError`].
    fn fit<B: AutodiffBackend + NetOps>(
        self,
        devices: Vec<B::Device>,
    ) -> Result<Vec<EpochRecord>, TrainError>
    where
        B::InnerBackend: NetOps;
}

/// Runs `run` on the CPU backend, or on the GPUs `device` names opened with `kernels` (a
/// build with the `cuda` feature).
///
/// # Errors
/// The GPUs cannot be opened, or the run fails.
#[cfg_attr(not(feature = "cuda"), allow(unused_variables))]
fn fit_on(
    device: &Device,
    kernels: crate::ops::Kernels,
    run: impl FitOn,
) -> anyhow::Result<Vec<EpochRecord>> {
    Ok(match device {
        Device::Cpu => run.fit::<CpuTrain>(vec![Default::default()])?,
        #[cfg(feature = "cuda")]
        Device::Cuda(ids) => {
            use crate::cli::device::cuda::{devices, CudaTrain};
            run.fit::<CudaTrain>(devices(ids, kernels)?)?
        }
        #[cfg(not(feature = "cuda"))]
        Device::Cuda(_) => unreachable!("--device cuda is refused without the cuda feature"),
    })
}

/// The run's scene index, with the trajectories themselves when the bags fit in
/// memory (`--max-resident-frames`, by their summaries' frame counts): then the bags are
/// read once. Otherwise (a large dataset, or bags without summary statistics) the index
/// comes from a decoding pass and the trajectories are streamed or loaded afterwards.
pub(super) fn read_data(
    args: &TrainArgs,
    topic: Option<&str>,
) -> anyhow::Result<(Vec<SceneInfo>, Option<Vec<Trajectory>>, LoadReport)> {
    // Before the scenes are indexed their particle count is unknown: assume the largest.
    let budget = args.max_resident_frames.frames(data::budget::LARGEST_SCENE);
    let fits =
        data::summary_frames(&args.data, topic).is_some_and(|frames| frames <= budget as u64);
    if fits {
        let (trajs, report) = load(&args.data, topic)?;
        Ok((SceneInfo::of(&trajs), Some(trajs), report))
    } else {
        let (infos, report) =
            data::scan_with_report(&args.data, topic).context("reading the bags")?;
        Ok((infos, None, report))
    }
}

/// The resident budget in frames of the dataset `infos` indexes (`--max-resident-frames` at
/// its largest particle count), and whether its training scenes `train` must be streamed
/// (logged with the budget and the chunks when they are).
pub(super) fn resident_budget(
    args: &TrainArgs,
    infos: &[SceneInfo],
    train: &[SceneInfo],
) -> (usize, bool) {
    let n = infos.iter().map(|s| s.n).max().unwrap_or(2500);
    let budget = args.max_resident_frames.frames(n);
    let total: usize = infos.iter().map(|s| s.frames).sum();
    let streamed = total > budget;
    if streamed {
        let train_frames: usize = train.iter().map(|s| s.frames).sum();
        tracing::info!(
            "streaming {} training frames of {} scenes from the bags: the dataset's {total} \
             frames are over --max-resident-frames {} = {}; chunks of up to {} frames, the \
             next read while one is trained on",
            train_frames,
            train.len(),
            args.max_resident_frames,
            args.max_resident_frames.describe(n, budget),
            budget / 2,
        );
    }
    (budget, streamed)
}

/// What the run's ledger (`run.json`) says of its dataset.
pub(super) fn dataset_info(
    args: &TrainArgs,
    train: &[SceneInfo],
    streamed: bool,
) -> crate::train::DatasetInfo {
    crate::train::DatasetInfo {
        inputs: args.data.iter().map(|p| p.display().to_string()).collect(),
        train_scenes: train.len(),
        train_frames: train.iter().map(|s| s.frames).sum(),
        streamed,
    }
}

/// [`data::load`], with its gaps logged.
pub(super) fn load(
    inputs: &[PathBuf],
    topic: Option<&str>,
) -> anyhow::Result<(Vec<Trajectory>, LoadReport)> {
    let (trajs, report) = data::load(inputs, topic).context("loading trajectories")?;
    for gap in &report.gaps {
        tracing::warn!("{gap}");
    }
    Ok((trajs, report))
}
