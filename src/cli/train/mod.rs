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
mod paper;

pub use args::{CpuTrain, TrainArgs};

use crate::cli::Outcome;

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
