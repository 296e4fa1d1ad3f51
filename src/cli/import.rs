//! `minflow import --format lagrangebench DIR -o OUT` and `minflow import --format paper FILE
//! -o OUT`: HDF5 datasets of other tools as one MCAP bag per trajectory in OUT, which `bag
//! info`, `train` and `eval` read like simulated bags (layouts, units and mappings:
//! `src/interop/lagrangebench.rs`, `src/interop/paper.rs`). Flags are checked before any
//! file is read; a flag that does not fit the data (a particle type missing from
//! `--material-map`, a `--dataset` the file lacks) is a usage error, exit code 2. Prints
//! `SCENE<TAB>BAG` per bag written.

use std::path::PathBuf;

use anyhow::Context;

use super::{Outcome, UsageError};
use crate::bag::FRAMES_TOPIC;
use crate::interop::import::{ImportError, Imported, MaterialMap};
use crate::interop::{lagrangebench, paper};

/// Formats `import` reads.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ImportFormat {
    /// A LagrangeBench dataset folder: metadata.json and train/valid/test.h5.
    Lagrangebench,
    /// One HDF5 file with a (T, N, F) or (S, T, N, F) dataset: x, y, vx, vy, m.
    Paper,
}

/// A LagrangeBench split.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Split {
    /// train.h5
    Train,
    /// valid.h5
    Valid,
    /// test.h5
    Test,
}

#[derive(Debug, clap::Args)]
pub struct ImportArgs {
    /// LagrangeBench: the dataset folder; paper: the HDF5 file.
    input: PathBuf,
    /// Input format.
    #[arg(long, value_enum)]
    format: ImportFormat,
    /// Output folder (created if missing): one bag per trajectory, named after the scene.
    #[arg(short, long)]
    out: PathBuf,
    /// LagrangeBench: particle type to material, e.g. `0=liquid,1=rope` (materials: liquid,
    /// jelly, snow, rope). Default `0=liquid`.
    #[arg(long)]
    material_map: Option<MaterialMap>,
    /// LagrangeBench: the splits to import (default: every one whose file exists).
    #[arg(long, value_enum, value_delimiter = ',')]
    splits: Vec<Split>,
    /// Paper: the dataset to read (default: the file's only dataset).
    #[arg(long)]
    dataset: Option<String>,
    /// Seconds between frames. LagrangeBench: overrides metadata.json's `dt * write_every`;
    /// paper: default 0.016 (a step of 8e-4, every 20th step saved).
    #[arg(long, value_parser = super::flags::positive)]
    dt: Option<f64>,
    /// Topic the frames are written on.
    #[arg(long, default_value = FRAMES_TOPIC)]
    topic: String,
}

pub fn run(args: ImportArgs) -> anyhow::Result<Outcome> {
    let only = |flag: &str, set: bool, format: &str| match set {
        true => Err(UsageError(format!(
            "{flag} applies to --format {format} only"
        ))),
        false => Ok(()),
    };
    let written = match args.format {
        ImportFormat::Lagrangebench => {
            only("--dataset", args.dataset.is_some(), "paper")?;
            import_lagrangebench(&args)?
        }
        ImportFormat::Paper => {
            only(
                "--material-map",
                args.material_map.is_some(),
                "lagrangebench",
            )?;
            only("--splits", !args.splits.is_empty(), "lagrangebench")?;
            import_paper(&args)?
        }
    };
    for imported in &written {
        println!("{}\t{}", imported.scene, imported.path.display());
    }
    tracing::info!(
        "{} trajectories, {} frames imported to {}",
        written.len(),
        written.iter().map(|i| u64::from(i.frames)).sum::<u64>(),
        args.out.display()
    );
    Ok(Outcome::Done)
}

/// An import error as the command reports it: a usage error (exit 2) when a flag does not
/// fit the data.
fn reported(err: ImportError) -> anyhow::Error {
    match err.is_usage() {
        true => UsageError(err.to_string()).into(),
        false => err.into(),
    }
}

fn import_lagrangebench(args: &ImportArgs) -> anyhow::Result<Vec<Imported>> {
    let map = args.material_map.clone().unwrap_or_default();
    let splits: Option<Vec<String>> = (!args.splits.is_empty()).then(|| {
        args.splits
            .iter()
            .map(|s| match s {
                Split::Train => "train".to_owned(),
                Split::Valid => "valid".to_owned(),
                Split::Test => "test".to_owned(),
            })
            .collect()
    });
    let dir = &args.input;
    let meta = lagrangebench::read_metadata(dir, args.dt).map_err(reported)?;
    let sources = lagrangebench::survey(dir, splits.as_deref(), &map).map_err(reported)?;
    let bar = super::progress(sources.iter().map(|s| s.frames).sum(), "frames");
    let mut written = Vec::with_capacity(sources.len());
    for source in &sources {
        let imported =
            lagrangebench::convert(source, &meta, &args.out, &args.topic, &mut || bar.inc(1))
                .map_err(reported)
                .with_context(|| format!("importing {}", source.scene()))?;
        written.push(imported);
    }
    bar.finish_and_clear();
    Ok(written)
}

fn import_paper(args: &ImportArgs) -> anyhow::Result<Vec<Imported>> {
    let path = &args.input;
    let source = paper::survey(path, args.dataset.as_deref()).map_err(reported)?;
    let bar = super::progress(source.total_frames(), "frames");
    let dt = args.dt.unwrap_or(paper::DEFAULT_DT);
    let written = paper::convert(path, &source, dt, &args.out, &args.topic, &mut || {
        bar.inc(1)
    })
    .map_err(reported)
    .with_context(|| format!("importing {}", path.display()))?;
    bar.finish_and_clear();
    Ok(written)
}
