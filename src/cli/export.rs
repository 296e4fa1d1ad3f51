//! `minflow export --format npz BAG|DIR... -o OUT`: the trajectories of bags as numpy
//! archives, one `.npz` per trajectory in OUT (arrays and units: `src/interop/npz.rs`). Prints
//! the files written on stdout; exit code 3 when a bag was truncated (its frames before the
//! damage are exported).

use std::path::PathBuf;

use anyhow::Context;

use super::{read_to_damage, Outcome};

/// Formats `export` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum ExportFormat {
    /// numpy `.npz` (position, velocity [T, N, 2] float32; material [N] uint8; frame_index
    /// [T] uint32; dt float32).
    Npz,
}

#[derive(Debug, clap::Args)]
pub struct ExportArgs {
    /// Bags or folders of bags.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    /// Output format.
    #[arg(long, value_enum, default_value_t = ExportFormat::Npz)]
    format: ExportFormat,
    /// Output folder (created if missing): one file per trajectory, named after the scene.
    #[arg(short, long)]
    out: PathBuf,
    /// Only frames on this topic (default: every ParticleFrame in the bags).
    #[arg(long)]
    topic: Option<String>,
}

pub fn run(args: ExportArgs) -> anyhow::Result<Outcome> {
    let (trajs, report) =
        crate::data::load(&args.inputs, args.topic.as_deref()).context("reading bags")?;
    let written = match args.format {
        ExportFormat::Npz => crate::interop::npz::export(&trajs, &args.out)
            .with_context(|| format!("exporting to {}", args.out.display()))?,
    };
    for path in &written {
        println!("{}", path.display());
    }
    tracing::info!(
        "{} trajectories, {} frames exported to {}",
        written.len(),
        report.frames,
        args.out.display()
    );
    Ok(read_to_damage(&report.truncated))
}
