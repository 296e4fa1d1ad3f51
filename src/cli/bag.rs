//! `minflow bag info FILE...` (what `ros2 bag info` prints, plus scenes, particle counts and
//! materials) and `minflow bag check FILE...` (schema, frame order, constant particle count
//! per scene, finite values; exits non-zero on problems).

use super::Outcome;
use anyhow::Context;
use clap::Subcommand;
use std::path::PathBuf;

#[derive(Debug, Subcommand)]
pub enum BagCommand {
    /// Print a bag's duration, start, end, messages and topics, plus its scenes.
    Info {
        /// Bags or folders of bags.
        #[arg(required = true)]
        paths: Vec<PathBuf>,
    },
    /// Validate bags; exits 1 if any problem is found.
    Check {
        /// Bags or folders of bags (checked together as one dataset).
        #[arg(required = true)]
        paths: Vec<PathBuf>,
    },
}

pub fn run(cmd: BagCommand) -> anyhow::Result<Outcome> {
    match cmd {
        BagCommand::Info { paths } => {
            let files = crate::bag::bag_paths(&paths)?;
            let info = crate::bag::inspect::info(&files).context("reading bags")?;
            print!("{info}");
            let lost = info.files.iter().any(|f| f.truncated.is_some());
            Ok(if lost {
                Outcome::DataLost
            } else {
                Outcome::Done
            })
        }
        BagCommand::Check { paths } => {
            let files = crate::bag::bag_paths(&paths)?;
            let report = crate::bag::inspect::check(&files).context("checking bags")?;
            print!("{report}");
            if report.is_ok() {
                Ok(Outcome::Done)
            } else {
                anyhow::bail!("{} problem(s) found", report.problem_count)
            }
        }
    }
}
