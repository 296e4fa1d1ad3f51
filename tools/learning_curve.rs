//! The long run's learning curve as a PNG (docs/training.md, "The long run"): avg20 over
//! `constvel`'s, the whole scenes' MSE over `persist`'s and, in two more panels where a
//! curve has them, the liquid's measures (covered area at steps 20, 200 and the end; kinetic
//! energy over the truth's and the share of surge fronts in time) on the unseen scenes,
//! against the samples seen, one line per `curve.csv` that `tests/gpu/long.sh` appends to
//! (phases 1 and 2's, rebuilt in `models/long-run/`; phase 3's in the run folder of its
//! archive).
//!
//! ```bash
//! tar xzf models/long-run/long3-run.tgz -C runs
//! cargo run --release --example learning_curve -- --out docs/long_run_curve.png \
//!     models/long-run/long/curve.csv models/long-run/long2/curve.csv runs/long3/curve.csv
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

/// The measures of a `curve.csv`, each as (million samples, value) points: avg20 over
/// `constvel`'s, the whole scenes' MSE over `persist`'s, and where the curve has the
/// liquid's columns, each of [`LIQUID`] (over the truth's; the fronts as the share in time
/// of those `liquid_table.py` counts). A row without a figure leaves that point out.
fn points(path: &Path) -> anyhow::Result<Vec<Vec<(f64, f64)>>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header: Vec<&str> = (lines.next().context("an empty curve.csv")?)
        .split(',')
        .collect();
    let column = |name: &str| header.iter().position(|h| *h == name);
    let need = |name: &str| column(name).with_context(|| format!("{}: no {name}", path.display()));
    let (samples, avg20, constvel) = (need("samples")?, need("avg20")?, need("avg20_constvel")?);
    let (whole, persist) = (need("whole")?, need("whole_persist")?);
    let (area, energy, fronts) = (
        column("liquid_area_20_200_end"),
        column("liquid_energy"),
        column("fronts"),
    );
    let mut out = vec![Vec::new(); 2 + LIQUID.len()];
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let cells: Vec<&str> = line.split(',').collect();
        let cell = |i: Option<usize>| i.and_then(|i| cells.get(i)).map(|c| c.trim());
        let value = |i: usize| cell(Some(i)).and_then(|c| c.parse::<f64>().ok());
        let Some(x) = value(samples).map(|s| s / 1e6) else {
            continue;
        };
        // "0.93 (5/11) / 0.56 (0/11) / 0.44 (0/11)": the area at steps 20, 200, the end.
        let areas: Vec<Option<f64>> = (cell(area).unwrap_or("").split(" / "))
            .map(|a| a.split_whitespace().next().and_then(|v| v.parse().ok()))
            .collect();
        // "4/11 (reached 5)": fronts within 10 % of the truth's step, of those counted.
        let front = cell(fronts).and_then(|f| {
            let (n, d) = f.split_whitespace().next()?.split_once('/')?;
            Some(n.parse::<f64>().ok()? / d.parse::<f64>().ok()?)
        });
        let values = [
            value(avg20).zip(value(constvel)).map(|(a, c)| a / c),
            value(whole).zip(value(persist)).map(|(w, p)| w / p),
            areas.first().copied().flatten(),
            areas.get(1).copied().flatten(),
            areas.get(2).copied().flatten(),
            cell(energy).and_then(|e| e.parse().ok()),
            front,
        ];
        for (measure, v) in out.iter_mut().zip(values) {
            measure.extend(v.filter(|v: &f64| v.is_finite()).map(|v| (x, v)));
        }
    }
    Ok(out)
}

/// The liquid's measures of a curve, as [`points`] gives them after avg20 and whole scenes.
const LIQUID: [&str; 5] = [
    "area at step 20",
    "area at step 200",
    "area at the end",
    "kinetic energy",
    "fronts in time (share)",
];

fn main() -> anyhow::Result<()> {
    let args = Args::parse();
    let (mut avg20, mut whole) = (Vec::new(), Vec::new());
    // The liquid's area at three steps in one panel, its energy and fronts in another.
    let (mut area, mut motion) = (Vec::new(), Vec::new());
    for path in &args.curves {
        let name = (path.parent().and_then(Path::file_name)).map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        let mut measures = points(path)?.into_iter();
        let series = |points| Series {
            name: name.clone(),
            points,
        };
        avg20.push(series(measures.next().unwrap_or_default()));
        whole.push(series(measures.next().unwrap_or_default()));
        for (k, (what, points)) in LIQUID.iter().zip(measures).enumerate() {
            if !points.is_empty() {
                let panel = if k < 3 { &mut area } else { &mut motion };
                panel.push(Series {
                    name: format!("{name}: {what}"),
                    points,
                });
            }
        }
    }
    let charts = vec![
        ("avg20 / constvel's, unseen scenes".to_string(), avg20),
        (
            "whole scenes' MSE / persist's, unseen scenes".to_string(),
            whole,
        ),
        (
            "the liquid's area / the truth's, unseen scenes".to_string(),
            area,
        ),
        (
            "the liquid's energy / the truth's; fronts in time".to_string(),
            motion,
        ),
    ];
    let axis = "million samples seen";
    panels(&args.out, &charts, axis, "ratio", false, 2, (620, 420))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
