//! Helpers the `bench` subcommands share: the transport flags of `bench transport` and
//! `bench node` ([`BenchTransportOptions`]), wall-clock stamps and percentiles of latency
//! samples, the training benchmarks' synthetic data, epoch means and peak memory, and the
//! scenes `bench sim` and `bench rollout` run ([`family_scenes`]).

use std::ffi::OsString;
use std::path::PathBuf;
use std::time::{SystemTime, UNIX_EPOCH};

use clap::Args;

use crate::data::Trajectory;
use crate::transport::{TransportKind, TransportOptions};

/// The transport flags of `bench transport` and `bench node`, flattened into both: the
/// shared [`TransportOptions`] flags, except that `--transport` is repeatable because a
/// benchmark measures several transports in one run.
#[derive(Debug, Clone, Args)]
pub struct BenchTransportOptions {
    /// Transports to measure (repeatable; default: zenoh, iceoryx2, ros2).
    #[arg(long = "transport", value_enum)]
    pub transports: Vec<TransportKind>,
    /// A standard zenoh JSON5 config file for every process of the benchmark; without it,
    /// embedded peer sessions that need no router.
    #[arg(long, value_name = "FILE")]
    pub zenoh_config: Option<PathBuf>,
}

impl BenchTransportOptions {
    /// The transports to measure: those given, or zenoh, iceoryx2 and ros2.
    pub fn kinds(&self) -> Vec<TransportKind> {
        if self.transports.is_empty() {
            vec![
                TransportKind::Zenoh,
                TransportKind::Iceoryx2,
                TransportKind::Ros2,
            ]
        } else {
            self.transports.clone()
        }
    }

    /// The options to open `kind` with in this process.
    pub fn options(&self, kind: TransportKind) -> TransportOptions {
        TransportOptions {
            zenoh_config: self.zenoh_config.clone(),
            ..TransportOptions::new(kind)
        }
    }

    /// The same flags for a `minflow` child process that opens `kind`.
    pub fn child_args(&self, kind: TransportKind) -> Vec<OsString> {
        let mut args = vec!["--transport".into(), kind.to_string().into()];
        if let Some(cfg) = &self.zenoh_config {
            args.push("--zenoh-config".into());
            args.push(cfg.clone().into());
        }
        args
    }
}

/// Wall-clock time, ns since the Unix epoch (the same clock in every process).
pub(crate) fn wall_ns() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The `p` quantile (0..=1) of sorted values, nearest rank; NaN when empty.
pub(crate) fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// A deterministic synthetic trajectory of `frames` frames (values uniform in [0, 1)).
pub(crate) fn synthetic(n: usize, frames: usize) -> Trajectory {
    let mut s = 7u64;
    let mut next = || {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let states = (0..frames * n * 4).map(|_| next()).collect();
    Trajectory {
        scene: "bench/synthetic/000".into(),
        dt: 0.016,
        material: (0..n).map(|p| (p % 4) as u8).collect(),
        start_index: 0,
        states,
        frames,
        n,
        solver_grid: None,
    }
}

/// Seconds per epoch of a benchmark run: the warm-up epochs' total, then the timed ones'
/// mean and maximum, and the mean seconds waiting for the device and for host batches.
pub(crate) struct EpochMeans {
    /// The warm-up epochs' total seconds.
    pub warmup: f64,
    /// Mean seconds of a timed epoch.
    pub mean: f64,
    /// The longest timed epoch, seconds.
    pub max: f64,
    /// Mean seconds per epoch waiting for the device.
    pub wait: f64,
    /// Mean seconds per epoch waiting for host batches.
    pub data: f64,
}

impl EpochMeans {
    /// The means of `history` after its first `warmup_epochs`.
    pub fn of(history: &[crate::train::EpochRecord], warmup_epochs: usize) -> Self {
        let (warm, timed) = history.split_at(warmup_epochs.min(history.len()));
        let n = timed.len().max(1) as f64;
        let mean_of =
            |f: fn(&crate::train::EpochRecord) -> f64| timed.iter().map(f).sum::<f64>() / n;
        Self {
            warmup: warm.iter().map(|r| r.seconds).sum(),
            mean: mean_of(|r| r.seconds),
            max: timed.iter().map(|r| r.seconds).fold(0.0, f64::max),
            wait: mean_of(|r| r.wait_seconds),
            data: mean_of(|r| r.data_seconds),
        }
    }
}

/// Peak resident memory in MiB since the last reset, and a reset.
pub(crate) fn peak_mib(reset: bool) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let kb: f64 = status
        .lines()
        .find(|l| l.starts_with("VmHWM:"))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()?;
    if reset {
        let _ = std::fs::write("/proc/self/clear_refs", "5");
    }
    Some(kb / 1024.0)
}

/// Scenes `ids` of `family` with `seed`, each refined onto a `grid` x `grid` grid where that
/// is finer than its own (`--grid`, [`crate::sim::Scene::refined`]).
///
/// # Errors
/// A usage error naming `--grid`: a grid that is not a multiple of a scene's, or a refined
/// scene that fails validation.
pub(crate) fn family_scenes(
    family: crate::sim::Family,
    ids: std::ops::Range<u32>,
    seed: u64,
    grid: Option<u32>,
) -> anyhow::Result<Vec<crate::sim::Scene>> {
    ids.map(|id| {
        let scene = crate::sim::families::scene(family, id, seed);
        match grid {
            Some(n) if n as usize > scene.grid => scene
                .refined(n as usize)
                .map_err(|e| crate::cli::UsageError(format!("--grid {n}: {e}")).into()),
            _ => Ok(scene),
        }
    })
    .collect()
}
