//! `minflow constraints fit`: fits the material constraints a model projects its predicted
//! frames onto ([`crate::model::constraints`]) on the ground truth of its training split, and
//! writes them into the model's `model.json` (`"constraints"`). `eval`, `node`, `bench
//! rollout` and `demo` then project by default (`--constraints off` turns it off).
//! `minflow constraints copy` gives models another model's constraints as they are: they are
//! fitted on the truth, not on the network, so models of the same scenes may share them.
//!
//! The training scenes are those of the first model's `split.json` (else the seeded
//! 80:10:10 split of the data, `--seed`); test scenes are never read. Prints what it fitted
//! and what it measured on the truth.

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};
use clap::{Args, Subcommand};

use super::Outcome;
use crate::bag::FRAMES_TOPIC;
use crate::data::{self, Part, Split};
use crate::model::constraints::{self, Constraints, Parts};
use crate::model::store::{parse_meta, RunFolder};

#[derive(Debug, Subcommand)]
pub enum ConstraintsCommand {
    /// Fit the constraints on the training split's truth and write them into model.json.
    Fit(FitArgs),
    /// Copy another model's constraints into model.json, every part as it is there.
    Copy(CopyArgs),
}

#[derive(Debug, Args)]
pub struct CopyArgs {
    /// The run folder whose `model.json` holds the constraints to copy.
    #[arg(long, value_name = "DIR")]
    from: PathBuf,
    /// Run folders to write them into (repeatable); their other settings stay.
    #[arg(long = "model", value_name = "DIR", required = true)]
    models: Vec<PathBuf>,
}

#[derive(Debug, Args)]
pub struct FitArgs {
    /// Run folders to write the fitted constraints into (repeatable); the first one's
    /// `split.json` names the training scenes.
    #[arg(long = "model", value_name = "DIR", required = true)]
    models: Vec<PathBuf>,
    /// Ground-truth bags or folders holding the training scenes.
    #[arg(long, num_args = 1.., required = true)]
    data: Vec<PathBuf>,
    /// The parts to fit and write: the default (rope, jelly, the liquid's pressure
    /// projection, walls, and contact, momentum and rebound, written with their default
    /// values; snow stays off, as the ablation chose; the older `liquid` density part is
    /// replaced by `pressure`) | a list of rope, jelly, snow, liquid, walls, contact,
    /// momentum, rebound, pressure. The parts not named keep the model's own values (a snow
    /// part fitted before stays), except the older `liquid`, which `pressure` replaces.
    #[arg(
        long,
        value_name = "PARTS",
        default_value = "rope,jelly,pressure,walls,contact,momentum,rebound"
    )]
    parts: Parts,
    /// Training scenes read at most (evenly spaced over the split's list; 0: all).
    #[arg(long, default_value_t = 0)]
    max_scenes: usize,
    /// Seed of the split when the first model has no `split.json`.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Topic of the ground-truth frames.
    #[arg(long, default_value = FRAMES_TOPIC)]
    topic: String,
    /// Print the fit without writing model.json.
    #[arg(long)]
    dry_run: bool,
    /// The cell of the liquid's density grid, in particle spacings of the rest frame.
    #[arg(long, default_value_t = 3.0, value_parser = super::flags::positive)]
    liquid_radius: f64,
    /// The node spacing of the liquid's pressure grid, in particle spacings of the rest frame.
    #[arg(long, default_value_t = 2.0, value_parser = super::flags::positive)]
    pressure_radius: f64,
    /// Share of the kinetic energy the projection takes from the liquid that is given back
    /// to its motion about its mean velocity, each frame (0: none; docs/liquid.md, "The
    /// energy given back", for the shipped models' values).
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::share)]
    pressure_restore: f32,
}

/// Runs `minflow constraints`.
pub fn run(cmd: ConstraintsCommand) -> anyhow::Result<Outcome> {
    match cmd {
        ConstraintsCommand::Fit(args) => fit(args),
        ConstraintsCommand::Copy(args) => copy(args),
    }
}

/// `constraints copy`: `--from`'s constraints block into each `--model`'s `model.json`.
///
/// # Errors
/// A `model.json` that cannot be read or written, or a `--from` model without constraints.
fn copy(args: CopyArgs) -> anyhow::Result<Outcome> {
    let from = RunFolder::new(&args.from);
    let meta = from
        .meta()
        .with_context(|| format!("reading {}", from.model_json().display()))?;
    let Some(constraints) = meta.constraints else {
        bail!(
            "{} has no constraints to copy (`minflow constraints fit` fits them)",
            from.model_json().display()
        );
    };
    for dir in &args.models {
        write_meta(dir, |_| Some(constraints.clone()))?;
        println!("wrote {}", RunFolder::new(dir).model_json().display());
    }
    Ok(Outcome::Done)
}

fn fit(args: FitArgs) -> anyhow::Result<Outcome> {
    let first = RunFolder::new(&args.models[0]);
    first.meta().context("reading the model")?;
    let scenes = training_scenes(&args, first.split())?;
    let (trajs, report) = data::load_scenes(&args.data, Some(&args.topic), &scenes)
        .context("loading the training scenes")?;
    if trajs.is_empty() {
        bail!(
            "none of the {} training scenes is in {:?} (simulate them first: README, \"Constraints\")",
            scenes.len(),
            args.data
        );
    }
    let base = Constraints::defaults().select(args.parts);
    let mut base = Constraints {
        snow: base.snow.or(args.parts.snow.then_some(SNOW)),
        liquid: args
            .parts
            .liquid
            .then_some(constraints::DensityParams::LOOSE),
        ..base
    };
    if let Some(p) = base.liquid.as_mut() {
        p.radius = args.liquid_radius as f32;
    }
    if let Some(p) = base.pressure.as_mut() {
        p.radius = args.pressure_radius as f32;
        p.restore = args.pressure_restore;
    }
    let (fitted, measured) = constraints::fit(&trajs, &base);
    print_fit(&args, &trajs, &fitted, &measured);
    println!("{}", serde_json::to_string_pretty(&fitted)?);
    if !args.dry_run {
        for dir in &args.models {
            write_constraints(dir, &fitted, args.parts)?;
            println!("wrote {}", RunFolder::new(dir).model_json().display());
        }
    }
    Ok(super::read_to_damage(&report.truncated))
}

/// Prints what [`constraints::fit`] fitted (`fitted`) and measured on the truth (`measured`).
fn print_fit(
    args: &FitArgs,
    trajs: &[data::Trajectory],
    fitted: &Constraints,
    measured: &constraints::FitReport,
) {
    println!(
        "Fitted on {} training scenes ({} frames) of {}:",
        trajs.len(),
        trajs.iter().map(|t| t.frames).sum::<usize>(),
        args.models[0].display()
    );
    if let Some(p) = fitted.rope {
        println!(
            "- rope: stretch <= {:.4} (the truth's link stretch, {:.1}th percentile of {} \
             link-frames; largest {:.3})",
            p.stretch,
            constraints::fit::STRETCH_QUANTILE_PERCENT,
            measured.rope_links,
            measured.rope_max_stretch
        );
    }
    if let Some(p) = fitted.liquid {
        println!(
            "- liquid: rest mass {:.2}x the rest frame's, grid cell {} spacings{} \
             (the truth's own frames move, spacings per frame, on {} frames: {})",
            p.rest,
            p.radius,
            match measured.liquid_met {
                true => "",
                false => " (NOT MET: no rest density tried moves the truth less than 0.02)",
            },
            measured.liquid_frames,
            moves_text(&measured.liquid_moves)
        );
    }
    if let Some(p) = &fitted.pressure {
        println!(
            "- pressure: compressed above a volume fraction of {:.2}{} (the truth's own frames \
             move, spacings per frame: {})",
            p.rest,
            match measured.pressure_met {
                true => "",
                false => " (NOT MET: no threshold tried moves the truth less than 0.02)",
            },
            moves_text(&measured.pressure_moves)
        );
    }
    for (grid, moves, met) in &measured.pressure_by_grid {
        let rest = fitted
            .pressure
            .as_ref()
            .map_or(0.0, |p| p.rest_for(Some(*grid)));
        println!(
            "  - scenes of the {grid} x {grid} solver grid: above {rest:.2}{} ({})",
            if *met { "" } else { " (NOT MET)" },
            moves_text(moves)
        );
    }
    if let Some(w) = fitted.walls {
        println!("- walls: [{:.5}, {:.5}]", w.lo, w.hi);
        if let Some(c) = w.cells {
            println!("- walls in a scene whose solver grid n is known: {c:.3} of its cells from the edge ([{c:.3} / n, 1 - {c:.3} / n])");
        }
    }
}

/// The truth's move for each value tried, `value: move` in order.
fn moves_text(moves: &[(f32, f64)]) -> String {
    let each: Vec<String> = moves
        .iter()
        .map(|(r, m)| format!("{r:.2}: {m:.4}"))
        .collect();
    each.join(", ")
}

/// Snow shape matching when `--parts` asks for snow: a rest shape that yields half its
/// remaining deformation a frame.
const SNOW: constraints::ShapeParams = constraints::ShapeParams {
    stiffness: 1.0,
    linear: 0.0,
    plastic: 0.5,
};

/// The training scenes: the model's `split.json`, else the seeded split of the data;
/// thinned evenly to `--max-scenes`.
fn training_scenes(args: &FitArgs, split: Option<Split>) -> anyhow::Result<Vec<String>> {
    let mut scenes = match split {
        Some(split) => split.train,
        None => {
            let infos = data::scan(&args.data, Some(&args.topic))
                .context("reading the ground-truth bags")?;
            let split = Split::new(infos.iter().map(|s| &s.scene), args.seed);
            split.scenes(Part::Train).to_vec()
        }
    };
    if args.max_scenes > 0 && scenes.len() > args.max_scenes {
        let every = scenes.len() as f64 / args.max_scenes as f64;
        scenes = (0..args.max_scenes)
            .map(|i| scenes[(i as f64 * every) as usize].clone())
            .collect();
    }
    Ok(scenes)
}

/// Rewrites `dir/model.json` with the parts `parts` of `constraints` (through a temporary
/// file, renamed), the parts it does not name as they were but the older `liquid` dropped
/// when `parts` names `pressure` (which replaces it), the JSON ending in a newline.
fn write_constraints(dir: &Path, constraints: &Constraints, parts: Parts) -> anyhow::Result<()> {
    write_meta(dir, |old| {
        let mut merged = old.unwrap_or_default().replaced(constraints, parts);
        // The pressure projection replaces the older density part.
        if parts.pressure && !parts.liquid {
            merged.liquid = None;
        }
        Some(merged)
    })
}

/// Rewrites `dir/model.json` with its constraints block replaced by `block(old block)`
/// (through a temporary file, renamed), the JSON ending in a newline.
fn write_meta(
    dir: &Path,
    block: impl FnOnce(Option<Constraints>) -> Option<Constraints>,
) -> anyhow::Result<()> {
    let folder = RunFolder::new(dir);
    let path = folder.model_json();
    let text =
        std::fs::read_to_string(&path).with_context(|| format!("reading {}", path.display()))?;
    let mut meta = parse_meta(&text).with_context(|| format!("parsing {}", path.display()))?;
    meta.constraints = block(meta.constraints.take());
    let tmp = folder.model_json_tmp();
    std::fs::write(&tmp, serde_json::to_string_pretty(&meta)? + "\n")
        .with_context(|| format!("writing {}", tmp.display()))?;
    std::fs::rename(&tmp, &path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
