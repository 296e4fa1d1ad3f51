//! `minflow launch FILE [NAME:=VALUE ...]`: starts the nodes of a launch file (see
//! [`crate::launch`]); a bare name such as `replay_eval` is looked up in `launch_configs/`.

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Args;

use super::Outcome;
use crate::launch;
use crate::node::shutdown_flag;

#[derive(Debug, Args)]
pub struct LaunchArgs {
    /// Launch file (YAML), or the name of one in launch_configs/ (e.g. replay_eval).
    file: String,
    /// Launch argument overrides, NAME:=VALUE.
    overrides: Vec<String>,
}

pub fn run(args: LaunchArgs) -> anyhow::Result<Outcome> {
    let path = PathBuf::from(&args.file);
    let path = if path.exists() {
        path
    } else {
        launch::bundled(&args.file)
    };
    let overrides = launch::parse_overrides(&args.overrides)?;
    let nodes = launch::load(&path, &overrides)?;
    let exe = std::env::current_exe().context("locating the minflow binary")?;
    let stop = shutdown_flag();
    let results = launch::run(&nodes, &exe, &stop)?;
    let failed: Vec<String> = results
        .iter()
        .filter(|r| !r.status.is_some_and(|s| s.success()))
        .map(|r| match r.status {
            Some(s) => format!("{} ({s})", r.name),
            None => format!("{} (not started)", r.name),
        })
        .collect();
    if !failed.is_empty() {
        bail!(
            "launch {}: {} failed: {}",
            path.display(),
            failed.len(),
            failed.join(", ")
        );
    }
    Ok(Outcome::Done)
}
