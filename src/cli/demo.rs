//! `minflow demo`: the main job on a fresh machine. For now (ground truth only): summarise
//! the bundled bags in `bags/`, simulate one `multi` and one `fluid` scene into `--out`,
//! validate everything with `bag check`, and print the simulator's speed on them. Later
//! stages (train, node, eval) extend this command.

use super::Outcome;
use crate::bag::{self, FRAMES_TOPIC};
use crate::sim::families::{self, Family};
use anyhow::Context;
use clap::Args;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Debug, Args)]
pub struct DemoArgs {
    /// Folder of bundled bags to summarise.
    #[arg(long, default_value = "bags")]
    bags: PathBuf,
    /// Where the freshly simulated scenes go.
    #[arg(short, long, default_value = "data/demo")]
    out: PathBuf,
    /// Frames per simulated scene.
    #[arg(long, default_value_t = 200)]
    frames: u32,
}

pub fn run(args: DemoArgs) -> anyhow::Result<Outcome> {
    let bundled = bag::bag_paths(std::slice::from_ref(&args.bags))
        .with_context(|| format!("finding the bundled bags in {}", args.bags.display()))?;
    let info = bag::info(&bundled).context("reading the bundled bags")?;
    println!("== bundled bags ({}) ==", args.bags.display());
    for f in &info.files {
        let scenes: Vec<&str> = f.scenes.keys().map(String::as_str).collect();
        println!(
            "{:<40} {:>5} frames  {}",
            f.path.display(),
            f.messages,
            scenes.join(", ")
        );
    }
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;
    println!("\n== simulating (MLS-MPM, one thread per scene) ==");
    println!(
        "{:<24} {:>6} {:>10} {:>10}  bag",
        "scene", "frames", "ms/frame", "realtime"
    );
    let mut written = Vec::new();
    for (family, id) in [(Family::Multi, 6), (Family::Fluid, 5)] {
        let mut scene = families::scene(family, id, 0);
        scene.frames = scene.frames.min(args.frames.max(1));
        let name = scene.name.clone();
        let frames = scene.frames;
        let bar = super::progress(frames as u64, "frames");
        let start = Instant::now();
        let path = super::simulate::write_scene(scene, &args.out, FRAMES_TOPIC, &bar, &|_| Ok(()))?;
        bar.finish_and_clear();
        let ms = start.elapsed().as_secs_f64() * 1e3 / frames as f64;
        // Real time = 62.5 frames per time unit, i.e. 16 ms per frame.
        println!(
            "{name:<24} {frames:>6} {ms:>10.2} {:>9.1}x  {}",
            16.0 / ms,
            path.display()
        );
        written.push(path);
    }
    println!("\n== bag check ==");
    let mut ok = true;
    for (what, files) in [("bundled", &bundled), ("simulated", &written)] {
        let report = bag::check(files).with_context(|| format!("checking the {what} bags"))?;
        print!("{what}: {report}");
        ok &= report.is_ok();
    }
    anyhow::ensure!(ok, "bag check found problems");
    Ok(Outcome::Done)
}
