//! `minflow bag info`: what is in one or more bags.
//!
//! [`info`] streams the bags and returns a [`BagInfo`] (size in bytes, start/end/duration from
//! `log_time` in ns and seconds, per-topic type/count/serialization, scenes with their frame
//! counts, particle counts, particles per material) whose `Display` is the table the CLI prints,
//! like `ros2 bag info`. It does not load a whole bag into memory. `minflow bag check` lives in
//! [`super::check`](mod@super::check), re-exported here for callers that name
//! `bag::inspect::check`.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

pub use super::check::{check, CheckReport};
use super::read::{BagReader, Truncation};
use super::BagError;
use crate::material;
use crate::msgs;

/// Scenes listed by name in the info table (the rest are counted).
const SCENES_LISTED: usize = 8;

/// One topic of one bag.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TopicInfo {
    /// Channel topic.
    pub topic: String,
    /// Schema name (message type), empty when the channel has none.
    pub type_name: String,
    /// Messages on the topic.
    pub count: u64,
    /// Message encoding, `cdr` for ROS 2 data.
    pub serialization: String,
}

/// One scene of one bag, from its ParticleFrames.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct SceneInfo {
    /// Frames of the scene (all topics).
    pub frames: u64,
    /// Particle count N of its first frame.
    pub particles: usize,
    /// Particles per material id of its first frame.
    pub materials: [u64; material::COUNT],
}

/// What one bag holds.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct FileInfo {
    /// The bag.
    pub path: PathBuf,
    /// File size, bytes.
    pub size_bytes: u64,
    /// Messages, all topics.
    pub messages: u64,
    /// Smallest and largest `log_time`, ns (None when there are no messages).
    pub start_end_ns: Option<(u64, u64)>,
    /// Topics by name.
    pub topics: Vec<TopicInfo>,
    /// Scenes by id.
    pub scenes: BTreeMap<String, SceneInfo>,
    /// Particle count N -> frames with N particles.
    pub particle_counts: BTreeMap<usize, u64>,
    /// ParticleFrame messages that failed to decode or validate.
    pub invalid: u64,
    /// Set when the bag is cut or damaged.
    pub truncated: Option<Truncation>,
}

/// What `minflow bag info` reports for one or more bags; `Display` is the printed table.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct BagInfo {
    /// One entry per bag, in input order.
    pub files: Vec<FileInfo>,
}

/// Inspects every bag in `paths` (see [`super::bag_paths`] to expand folders).
pub fn info<P: AsRef<Path>>(paths: &[P]) -> Result<BagInfo, BagError> {
    let files = paths
        .iter()
        .map(|p| info_file(p.as_ref()))
        .collect::<Result<_, _>>()?;
    Ok(BagInfo { files })
}

/// Inspects one bag. Cut bags give what was read plus `truncated`; invalid frames are counted.
pub fn info_file(path: &Path) -> Result<FileInfo, BagError> {
    let mut reader = BagReader::open(path)?;
    let mut out = FileInfo {
        path: path.to_path_buf(),
        size_bytes: reader.bytes_total(),
        ..FileInfo::default()
    };
    let mut topics: BTreeMap<String, TopicInfo> = BTreeMap::new();
    for item in reader.by_ref() {
        let Ok(message) = item else { continue };
        out.messages += 1;
        let t = message.log_time;
        out.start_end_ns = Some(
            out.start_end_ns
                .map_or((t, t), |(a, b)| (a.min(t), b.max(t))),
        );
        let topic = topics
            .entry(message.topic().to_owned())
            .or_insert_with(|| TopicInfo {
                topic: message.topic().to_owned(),
                type_name: message.schema_name().to_owned(),
                count: 0,
                serialization: message.channel.message_encoding.clone(),
            });
        topic.count += 1;
        if !message.is_particle_frame() {
            continue;
        }
        let frame = match msgs::decode(&message.data) {
            Ok(frame) if frame.validate().is_ok() => frame,
            _ => {
                out.invalid += 1;
                continue;
            }
        };
        *out.particle_counts.entry(frame.len()).or_insert(0) += 1;
        let scene = out.scenes.entry(frame.scene.clone()).or_default();
        if scene.frames == 0 {
            scene.particles = frame.len();
            for &m in &frame.material {
                scene.materials[usize::from(m)] += 1;
            }
        }
        scene.frames += 1;
    }
    out.truncated = reader.truncation().cloned();
    out.topics = topics.into_values().collect();
    Ok(out)
}

impl FileInfo {
    /// Particles per material over the first frame of every scene.
    pub fn materials(&self) -> [u64; material::COUNT] {
        let mut total = [0u64; material::COUNT];
        for scene in self.scenes.values() {
            for (t, m) in total.iter_mut().zip(scene.materials) {
                *t += m;
            }
        }
        total
    }

    /// `end - start` of the log times, ns.
    pub fn duration_ns(&self) -> u64 {
        self.start_end_ns.map_or(0, |(a, b)| b - a)
    }
}

fn human_bytes(n: u64) -> String {
    let (mut v, mut unit) = (n as f64, 0);
    while v >= 1024.0 && unit < 4 {
        v /= 1024.0;
        unit += 1;
    }
    let units = ["B", "KiB", "MiB", "GiB", "TiB"];
    format!("{v:.1} {} ({n} bytes)", units[unit])
}

fn seconds(ns: u64) -> String {
    format!("{:.9} s ({ns} ns)", ns as f64 * 1e-9)
}

/// Writes `key:` padded to one column, then `lines`, continuation lines indented alike.
fn rows(f: &mut fmt::Formatter<'_>, key: &str, lines: &[String]) -> fmt::Result {
    for (i, line) in lines.iter().enumerate() {
        let key = if i == 0 {
            format!("{key}:")
        } else {
            String::new()
        };
        writeln!(f, "{key:<19}{line}")?;
    }
    Ok(())
}

impl fmt::Display for FileInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (start, end) = self.start_end_ns.unwrap_or((0, 0));
        rows(f, "File", &[self.path.display().to_string()])?;
        rows(f, "Bag size", &[human_bytes(self.size_bytes)])?;
        rows(f, "Storage id", &["mcap".into()])?;
        rows(f, "Duration", &[seconds(self.duration_ns())])?;
        rows(f, "Start", &[seconds(start)])?;
        rows(f, "End", &[seconds(end)])?;
        rows(f, "Messages", &[self.messages.to_string()])?;
        let tw = self.topics.iter().map(|t| t.topic.len()).max().unwrap_or(0);
        let yw = self
            .topics
            .iter()
            .map(|t| t.type_name.len())
            .max()
            .unwrap_or(0);
        let topics: Vec<String> = (self.topics.iter())
            .map(|t| {
                let (topic, ty, count, ser) = (&t.topic, &t.type_name, t.count, &t.serialization);
                format!(
                    "Topic: {topic:<tw$} | Type: {ty:<yw$} | \
                     Count: {count} | Serialization Format: {ser}"
                )
            })
            .collect();
        rows(f, "Topic information", &topics)?;
        let mut scenes = vec![self.scenes.len().to_string()];
        scenes.extend(
            (self.scenes.iter().take(SCENES_LISTED)).map(|(name, s)| {
                format!("{name} ({} frames, {} particles)", s.frames, s.particles)
            }),
        );
        if self.scenes.len() > SCENES_LISTED {
            scenes.push(format!(
                "... and {} more",
                self.scenes.len() - SCENES_LISTED
            ));
        }
        rows(f, "Scenes", &scenes)?;
        let counts: Vec<String> = (self.particle_counts.iter())
            .map(|(n, frames)| format!("{n} particles: {frames} frames"))
            .collect();
        rows(f, "Particle counts", &counts)?;
        let materials: Vec<String> = (material::names().zip(self.materials()))
            .map(|(name, n)| format!("{name} {n}"))
            .collect();
        let materials = format!(
            "{} (particles, first frame of each scene)",
            materials.join(", ")
        );
        rows(f, "Materials", &[materials])?;
        if self.invalid > 0 {
            rows(f, "Invalid frames", &[self.invalid.to_string()])?;
        }
        if let Some(t) = &self.truncated {
            rows(f, "Truncated", &[t.to_string()])?;
        }
        Ok(())
    }
}

impl fmt::Display for BagInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, file) in self.files.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{file}")?;
        }
        if self.files.len() > 1 {
            let messages: u64 = self.files.iter().map(|f| f.messages).sum();
            let bytes: u64 = self.files.iter().map(|f| f.size_bytes).sum();
            let scenes: usize = self.files.iter().map(|f| f.scenes.len()).sum();
            writeln!(
                f,
                "\n{:<19}{} files, {} messages, {} scenes, {}",
                "Total:",
                self.files.len(),
                messages,
                scenes,
                human_bytes(bytes)
            )?;
        }
        Ok(())
    }
}
