//! `minflow bench train [--arch grid|paper]`: training speed on this machine, one command for
//! both architectures. The flags ([`TrainBenchArgs`]) and the shared epoch means live in
//! [`paper`] (the paper's Table 4: per core, parameters, seconds per epoch, microseconds per
//! sample, peak memory); [`grid`] measures the grid architecture (and its stages).

mod grid;
mod paper;

pub use paper::TrainBenchArgs;

use crate::cli::Outcome;

/// Runs `minflow bench train`: the architecture `--arch` names.
///
/// # Errors
/// Bad flags, a failed training epoch.
pub fn run(args: TrainBenchArgs) -> anyhow::Result<Outcome> {
    match args.arch.as_str() {
        "grid" => grid::run(&args),
        _ => paper::run(args),
    }
}
