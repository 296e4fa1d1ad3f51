//! The long run's learning curve as a PNG (docs/training.md, "The long run"): avg20 over
//! `constvel`'s and the whole scenes' MSE over `persist`'s on the unseen scenes, against the
//! samples seen, one line per `curve.csv` that `tests/gpu/long.sh` appends to (phase 1's
//! `runs/long/curve.csv`, phase 2's `runs/long2/curve.csv`).
//!
//! ```bash
//! cargo run --release --example learning_curve -- --out docs/long_run_curve.png \
//!     runs/long/curve.csv runs/long2/curve.csv  # phase 1's and phase 2's
//! ```

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Parser;
use minflow::plot::{panels, Series};

#[derive(Debug, Parser)]
#[command(about = "Plot the long run's curve.csv files: error against samples seen")]
struct Args {
    /// The PNG to write.
    #[arg(long)]
    out: PathBuf,
    /// `curve.csv` files (columns samples, avg20, avg20_constvel, whole, whole_persist, ...),
    /// each a line named by its run folder.
    #[arg(required = true)]
    curves: Vec<PathBuf>,
}

/// The (million samples, avg20 / constvel) and (million samples, whole / persist) points of
/// one `curve.csv`; a row without a whole-scene figure gives only the first.
fn points(path: &Path) -> anyhow::Result<[Vec<(f64, f64)>; 2]> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = lines
        .next()
        .context("an empty curve.csv")?
        .split(',')
        .collect();
    let column = |name: &str| {
        (header.iter().position(|h| *h == name))
            .with_context(|| format!("{}: no {name}", path.display()))
    };
    let [samples, avg20, constvel, whole, persist] = [
        "samples",
        "avg20",
        "avg20_constvel",
        "whole",
        "whole_persist",
    ]
    .map(column);
    let (samples, avg20, constvel) = (samples?, avg20?, constvel?);
    let (whole, persist) = (whole?, persist?);
    let mut out = [Vec::new(), Vec::new()];
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let cells: Vec<&str> = line.split(',').collect();
        let value = |i: usize| cells.get(i).and_then(|c| c.trim().parse::<f64>().ok());
        let Some(x) = value(samples).map(|s| s / 1e6) else {
            continue;
        };
        if let (Some(a), Some(c)) = (value(avg20), value(constvel)) {
            out[0].push((x, a / c));
        }
        if let (Some(w), Some(p)) = (value(whole), value(persist)) {
            out[1].push((x, w / p));
        }
    }
    Ok(out)
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let mut lines = [Vec::new(), Vec::new()];
    for path in &args.curves {
        let name = (path.parent().and_then(Path::file_name)).map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        for (line, points) in lines.iter_mut().zip(points(path)?) {
            line.push(Series {
                name: name.clone(),
                points,
            });
        }
    }
    let [avg20, whole] = lines;
    let charts = vec![
        ("avg20 / constvel's, unseen scenes".to_string(), avg20),
        (
            "whole scenes' MSE / persist's, unseen scenes".to_string(),
            whole,
        ),
    ];
    panels(
        &args.out,
        &charts,
        "million samples seen",
        "ratio",
        false,
        2,
        (560, 400),
    )?;
    println!("wrote {}", args.out.display());
    Ok(())
}
