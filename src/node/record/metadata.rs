//! rosbag2's `metadata.yaml` for a recording (`minflow record`): the bag information that
//! `ros2 bag info OUT` and `ros2 bag play OUT` read, version 5 as Humble writes it: message
//! counts per topic and per file, start times and durations in ns.

use std::collections::BTreeMap;
use std::path::Path;

use super::{FileInfo, RecordError};
use crate::bag::{DEFAULT_QOS_YAML, MESSAGE_ENCODING};
use crate::msgs::TYPE_NAME;

/// rosbag2's `metadata.yaml` (bag information, version 5 as written by Humble).
#[derive(serde::Serialize)]
struct Metadata {
    rosbag2_bagfile_information: BagInformation,
}

#[derive(serde::Serialize)]
struct BagInformation {
    version: u32,
    storage_identifier: &'static str,
    duration: Nanoseconds,
    starting_time: SinceEpoch,
    message_count: u64,
    topics_with_message_count: Vec<TopicCount>,
    compression_format: &'static str,
    compression_mode: &'static str,
    relative_file_paths: Vec<String>,
    files: Vec<FileEntry>,
}

#[derive(serde::Serialize)]
struct Nanoseconds {
    nanoseconds: u64,
}

#[derive(serde::Serialize)]
struct SinceEpoch {
    nanoseconds_since_epoch: u64,
}

#[derive(serde::Serialize)]
struct TopicCount {
    topic_metadata: TopicMetadata,
    message_count: u64,
}

#[derive(serde::Serialize)]
struct TopicMetadata {
    name: String,
    #[serde(rename = "type")]
    type_name: &'static str,
    serialization_format: &'static str,
    offered_qos_profiles: &'static str,
}

#[derive(serde::Serialize)]
struct FileEntry {
    path: String,
    starting_time: SinceEpoch,
    duration: Nanoseconds,
    message_count: u64,
}

/// Writes `out/metadata.yaml` describing `files`.
pub(super) fn write_metadata(out: &Path, files: &[FileInfo]) -> Result<(), RecordError> {
    let first = files.iter().filter_map(|f| f.first_ns).min().unwrap_or(0);
    let last = files.iter().map(|f| f.last_ns).max().unwrap_or(0);
    let mut topics: BTreeMap<&str, u64> = BTreeMap::new();
    for f in files {
        for (t, n) in &f.per_topic {
            *topics.entry(t).or_default() += n;
        }
    }
    let name = |f: &FileInfo| {
        f.path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default()
    };
    let meta = Metadata {
        rosbag2_bagfile_information: BagInformation {
            version: 5,
            storage_identifier: "mcap",
            duration: Nanoseconds {
                nanoseconds: last.saturating_sub(first),
            },
            starting_time: SinceEpoch {
                nanoseconds_since_epoch: first,
            },
            message_count: files.iter().map(|f| f.count).sum(),
            topics_with_message_count: topics
                .into_iter()
                .map(|(t, n)| TopicCount {
                    topic_metadata: TopicMetadata {
                        name: t.to_owned(),
                        type_name: TYPE_NAME,
                        serialization_format: MESSAGE_ENCODING,
                        offered_qos_profiles: DEFAULT_QOS_YAML,
                    },
                    message_count: n,
                })
                .collect(),
            compression_format: "",
            compression_mode: "",
            relative_file_paths: files.iter().map(name).collect(),
            files: files
                .iter()
                .map(|f| FileEntry {
                    path: name(f),
                    starting_time: SinceEpoch {
                        nanoseconds_since_epoch: f.first_ns.unwrap_or(0),
                    },
                    duration: Nanoseconds {
                        nanoseconds: f.last_ns.saturating_sub(f.first_ns.unwrap_or(0)),
                    },
                    message_count: f.count,
                })
                .collect(),
        },
    };
    let path = out.join("metadata.yaml");
    let text = serde_yaml_ng::to_string(&meta).map_err(|source| RecordError::Metadata {
        path: path.clone(),
        source,
    })?;
    std::fs::write(&path, text).map_err(|source| RecordError::File { path, source })
}
