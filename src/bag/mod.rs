//! MCAP bags of [`ParticleFrame`](crate::msgs::ParticleFrame)s, in the layout rosbag2 writes:
//! profile `ros2`, schema `minflow_msgs/msg/ParticleFrame` in `ros2msg` encoding, message
//! encoding `cdr`, channel metadata `offered_qos_profiles`, zstd chunks, `log_time` =
//! `publish_time` = the frame's stamp in ns.
//!
//! [`mod@write`] creates bags (`simulate`, `record`); [`read`] streams the messages of any bag
//! that follows the format, whoever wrote it, and survives truncated files; [`frames`] decodes
//! them into frames (`train`, `eval`); [`inspect`] implements `minflow bag info` and
//! [`mod@check`] `minflow bag check` (with [`check_index`] for the summary and message
//! indexes); and [`bag_paths`] expands a dataset (a folder of bags) into
//! files. Every failure is one [`BagError`] that names the file and, where it applies, the topic
//! and the message index.

pub mod check;
pub mod check_index;
pub mod frames;
pub mod inspect;
pub mod read;
pub mod write;

use std::path::{Path, PathBuf};

pub use check::{check, CheckReport};
pub use frames::{read_frames, read_frames_with, BagMessage, Frames, ReadOptions, ReadOutcome};
pub use inspect::{info, BagInfo};
pub use read::{decode_checked, BagReader, RawMessage, Truncation};
pub use write::{BagWriter, ForeignSchema};

use crate::msgs::{CdrError, FrameError};

/// Topic of ground-truth frames (simulate, replay).
pub const FRAMES_TOPIC: &str = "/mpm/frames";
/// Topic of predicted frames (surrogate, record).
pub const PREDICTED_TOPIC: &str = "/surrogate/frames";
/// MCAP header profile.
pub const PROFILE: &str = "ros2";
/// Schema encoding of the message definition.
pub const SCHEMA_ENCODING: &str = "ros2msg";
/// Channel message encoding.
pub const MESSAGE_ENCODING: &str = "cdr";
/// Channel metadata key for the QoS profiles (rosbag2's name).
pub const QOS_KEY: &str = "offered_qos_profiles";
/// Channel metadata key for the solver's grid (cells per side) of the scene whose frames the
/// channel carries: `simulate` writes it, the liquid's pressure projection reads it
/// ([`crate::model::constraints`]). Other writers leave it out; readers ignore it.
pub const SOLVER_GRID_KEY: &str = "minflow/solver_grid";
/// rosbag2 (Humble) YAML for the default ROS 2 QoS: reliable, keep-last 10, volatile, and
/// infinite deadline / lifespan / liveliness lease.
pub const DEFAULT_QOS_YAML: &str = "- history: 1
  depth: 10
  reliability: 1
  durability: 2
  deadline:
    sec: 9223372036
    nsec: 854775807
  lifespan:
    sec: 9223372036
    nsec: 854775807
  liveliness: 1
  liveliness_lease_duration:
    sec: 9223372036
    nsec: 854775807
  avoid_ros_namespace_conventions: false";

/// Every way reading, writing or inspecting a bag can fail.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The file system refused (open, create, read, write, list a folder).
    #[error("{path}: {what}: {source}")]
    Io {
        /// File or folder.
        path: PathBuf,
        /// What was being done.
        what: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The file is empty or does not start with the MCAP magic bytes.
    #[error("{path}: not an MCAP bag: {what}")]
    NotMcap {
        /// File.
        path: PathBuf,
        /// What is wrong.
        what: String,
    },
    /// The MCAP library reported an error while writing. (Reading errors after the start of a
    /// bag are reported as [`BagError::Truncated`].)
    #[error("{path}: MCAP error: {source}")]
    Mcap {
        /// File.
        path: PathBuf,
        /// The library's error.
        #[source]
        source: mcap::McapError,
    },
    /// A requested topic's channel does not carry ParticleFrames.
    #[error(
        "{path}: topic {topic}: schema {schema:?} (message encoding {encoding:?}) is not {} in cdr",
        crate::msgs::TYPE_NAME
    )]
    ForeignSchema {
        /// File.
        path: PathBuf,
        /// Channel topic.
        topic: String,
        /// The channel's schema name (empty when it has none).
        schema: String,
        /// The channel's message encoding.
        encoding: String,
    },
    /// A message is not valid CDR for a ParticleFrame.
    #[error("{path}: topic {topic}: message {index}: {source}")]
    Decode {
        /// File.
        path: PathBuf,
        /// Channel topic.
        topic: String,
        /// Message index, 0-based within the channel.
        index: u64,
        /// The CDR error (field and byte offset).
        #[source]
        source: CdrError,
    },
    /// A message decodes but is not a valid frame.
    #[error("{path}: topic {topic}: message {index}: invalid frame: {source}")]
    Invalid {
        /// File.
        path: PathBuf,
        /// Channel topic.
        topic: String,
        /// Message index, 0-based within the channel.
        index: u64,
        /// What is wrong with the frame.
        #[source]
        source: FrameError,
    },
    /// Writing a message failed for a reason of our own (not the MCAP library's).
    #[error("{path}: topic {topic}: message {index}: {what}")]
    Write {
        /// File.
        path: PathBuf,
        /// Channel topic.
        topic: String,
        /// Message index, 0-based within the channel.
        index: u64,
        /// What is wrong.
        what: String,
    },
    /// The bag ends early or is damaged after some messages; the last item a streaming reader
    /// yields. [`read_frames`] turns it into [`ReadOutcome::truncated`].
    #[error("{path}: {truncation}")]
    Truncated {
        /// File.
        path: PathBuf,
        /// How much was read and why reading stopped.
        truncation: Truncation,
    },
    /// A folder given as input holds no `.mcap` files, or a pattern matches none.
    #[error("{path}: no .mcap files found")]
    NoBags {
        /// Folder or pattern.
        path: PathBuf,
    },
}

impl BagError {
    /// Whether this error concerns one message only (decode or validation), so a lenient
    /// reader may count it and go on.
    pub fn is_message_error(&self) -> bool {
        matches!(self, BagError::Decode { .. } | BagError::Invalid { .. })
    }

    pub(crate) fn io(
        path: impl Into<PathBuf>,
        what: impl Into<String>,
        source: std::io::Error,
    ) -> Self {
        BagError::Io {
            path: path.into(),
            what: what.into(),
            source,
        }
    }
}

/// The file stem of a scene's files: its id with `/` (and any backslash) as `_`
/// (`multi/rope+snow/007` -> `multi_rope+snow_007`), as `simulate`, `import` and `export` name
/// what they write.
pub fn scene_file_stem(scene: &str) -> String {
    scene.replace(['/', '\\'], "_")
}

/// The bag file name of a scene: [`scene_file_stem`] plus `.mcap`
/// (`multi_rope+snow_007.mcap`).
pub fn bag_name(scene: &str) -> String {
    format!("{}.mcap", scene_file_stem(scene))
}

/// Expands inputs into bag paths: a folder gives its `*.mcap` files sorted by name, a file is
/// kept as given, a glob pattern (`*`, `?`, `[`) gives its matches sorted. Input order is kept.
/// A folder or pattern with no bags, or a path that does not exist, is an error.
pub fn bag_paths(inputs: &[PathBuf]) -> Result<Vec<PathBuf>, BagError> {
    let mut out = Vec::new();
    for input in inputs {
        let mut found = if input.is_dir() {
            mcap_files_in(input)?
        } else if input.exists() {
            out.push(input.clone());
            continue;
        } else if let Some(pattern) = input.to_str().filter(|s| s.contains(['*', '?', '['])) {
            let no_bags = || BagError::NoBags {
                path: input.clone(),
            };
            glob::glob(pattern)
                .map_err(|_| no_bags())?
                .filter_map(Result::ok)
                .filter(|p| p.is_file())
                .collect()
        } else {
            let source = std::io::Error::from(std::io::ErrorKind::NotFound);
            return Err(BagError::io(input, "looking for bags", source));
        };
        if found.is_empty() {
            return Err(BagError::NoBags {
                path: input.clone(),
            });
        }
        found.sort();
        out.append(&mut found);
    }
    Ok(out)
}

fn mcap_files_in(folder: &Path) -> Result<Vec<PathBuf>, BagError> {
    let listing_error = |e| BagError::io(folder, "listing folder", e);
    let mut found = Vec::new();
    for entry in std::fs::read_dir(folder).map_err(listing_error)? {
        let path = entry.map_err(listing_error)?.path();
        if path.extension().is_some_and(|e| e == "mcap") && path.is_file() {
            found.push(path);
        }
    }
    Ok(found)
}
