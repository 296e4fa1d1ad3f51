//! `data`: what training and evaluation read from a dataset of bags. A dataset is a folder of
//! MCAP bags of [`ParticleFrame`](crate::msgs::ParticleFrame)s; a trajectory is the frames of
//! one `scene`, ordered by `frame_index`.
//!
//! - [`trajectory`]: [`Trajectory`] (a contiguous run of frames of one scene as a dense
//!   `[F, N, 4]` buffer of x, y in domain units and vx, vy in domain units per time unit),
//!   [`LoadReport`] (duplicates, gaps, truncated bags) and the pure assembly of frames into
//!   segments.
//! - [`mod@load`]: [`load()`] and [`load_scenes`] (bags -> trajectories, split at gaps) and
//!   [`scan`] (bags -> [`SceneInfo`], the index without the frames).
//! - [`decode`]: the bags decoded on worker threads, their frames handed on in reading order.
//! - [`split`]: [`Split`], the seeded 80:10:10 train/val/test partition by scene id.
//! - [`scaler`]: [`Scaler`], per-feature min-max scaling of (x, y, vx, vy, m) fitted on the
//!   training split only.
//! - [`windows`]: [`WindowIndex`] and [`Batch`]: T input frames + the next frame as target,
//!   batched and shuffled deterministically per (seed, epoch).
//! - [`streaming`]: [`StreamingLoader`], the same batches for datasets larger than memory,
//!   loading scenes chunk by chunk under a frame budget, the next chunk read ahead.
//! - [`budget`]: [`ResidentBudget`], that frame budget: a count, or a share of the machine's
//!   available memory.
//!
//! Used by `minflow train` (everything) and `minflow eval` (load, split, scaler). Every failure
//! is one [`DataError`] naming the bag, the scene and the frame where they apply.

pub mod budget;
pub mod decode;
pub mod load;
pub mod scaler;
pub mod split;
pub mod streaming;
pub mod trajectory;
pub mod windows;

use std::path::PathBuf;

pub use budget::ResidentBudget;
pub use load::{load, load_scenes, scan, scan_with_report, summary_frames, SceneInfo};
pub use scaler::{Scaler, ScalerFit, FEATURES, FEATURE_NAMES};
pub use split::{Part, Split, SplitFractions};
pub use streaming::{EpochBatches, StreamingLoader};
pub use trajectory::{Gap, LoadReport, Trajectory};
pub use windows::{Batch, Layout, WindowIndex};

use crate::bag::BagError;

/// Every way building a dataset can fail.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// Reading a bag failed (the error names the file, topic and message).
    #[error(transparent)]
    Bag(#[from] BagError),
    /// A frame disagrees with the earlier frames of its scene (particle count, material of a
    /// particle, frame spacing `dt`).
    #[error(
        "{path}: scene {scene:?}, frame {frame}: {what} (scene's first frame read: {reference})"
    )]
    Inconsistent {
        /// Bag holding the offending frame.
        path: PathBuf,
        /// Scene id.
        scene: String,
        /// `frame_index` of the offending frame.
        frame: u32,
        /// `frame_index` of the scene's first frame read, which the others are compared with.
        reference: u32,
        /// What differs, with both values.
        what: String,
    },
    /// The inputs hold no frames (on the requested topic).
    #[error("no ParticleFrames found in {bags} bag(s){}", topic_note(.topic))]
    NoFrames {
        /// Bags read.
        bags: usize,
        /// Topic filter, if any.
        topic: Option<String>,
    },
    /// A setting is out of range (window length, batch size, split fractions, frame budget).
    #[error("invalid {what}: {why}")]
    Config {
        /// The setting.
        what: &'static str,
        /// Why it is refused.
        why: String,
    },
    /// A scene needs more frames than the streaming budget allows.
    #[error(
        "scene {scene:?} has {frames} frames, more than the budget of {budget} resident frames; \
         raise the budget to at least {frames}"
    )]
    SceneTooLarge {
        /// Scene id.
        scene: String,
        /// Its frames.
        frames: usize,
        /// The budget (`max_resident_frames`).
        budget: usize,
    },
    /// A scene read back differs from what [`scan`] found (the bags changed meanwhile).
    #[error("scene {scene:?} changed since the dataset was scanned: {what}")]
    Changed {
        /// Scene id.
        scene: String,
        /// What differs.
        what: String,
    },
}

fn topic_note(topic: &Option<String>) -> String {
    topic
        .as_ref()
        .map_or(String::new(), |t| format!(" on topic {t}"))
}

impl DataError {
    pub(crate) fn config(what: &'static str, why: impl Into<String>) -> Self {
        DataError::Config {
            what,
            why: why.into(),
        }
    }
}
