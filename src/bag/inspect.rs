//! `minflow bag info` and `minflow bag check`: what is in a bag, and whether it is a sound
//! dataset.
//!
//! [`info`] streams one or more bags and returns a [`BagInfo`] (size in bytes, start/end/
//! duration from `log_time` in ns and seconds, per-topic type/count/serialization, scenes with
//! their frame counts, particle counts, particles per material) whose `Display` is the table the
//! CLI prints, like `ros2 bag info`. [`check`] returns a [`CheckReport`]: schema and encodings
//! are ours, every frame decodes and validates, and within each (topic, scene) `frame_index`
//! rises by exactly 1, stamps strictly increase, and particle count, materials and `dt` stay
//! constant. Neither loads a whole bag into memory.

use std::collections::BTreeMap;
use std::fmt;
use std::path::{Path, PathBuf};

use super::read::{RawMessage, Truncation};
use super::{
    BagError, BagReader, FRAMES_TOPIC, MESSAGE_ENCODING, PREDICTED_TOPIC, SCHEMA_ENCODING,
};
use crate::msgs::{self, MATERIAL_NAMES};

/// Scenes listed by name in the info table (the rest are counted).
const SCENES_LISTED: usize = 8;
/// Problems listed in a check report (the rest are counted).
const PROBLEMS_LISTED: usize = 20;

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
    pub materials: [u64; 4],
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
    pub fn materials(&self) -> [u64; 4] {
        let mut total = [0u64; 4];
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
        let materials: Vec<String> = (MATERIAL_NAMES.iter().zip(self.materials()))
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

/// What `minflow bag check` found; `Display` is the printed report.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct CheckReport {
    /// The first problems found (at most 20), each naming file, topic, scene or message.
    pub problems: Vec<String>,
    /// All problems found, listed or not.
    pub problem_count: usize,
    /// Messages read, all topics.
    pub messages: u64,
    /// Distinct (topic, scene) pairs seen.
    pub scenes: usize,
    /// Bags checked.
    pub files: usize,
}

impl CheckReport {
    /// True when no problem was found.
    pub fn is_ok(&self) -> bool {
        self.problem_count == 0
    }

    fn problem(&mut self, text: String) {
        self.problem_count += 1;
        if self.problems.len() < PROBLEMS_LISTED {
            self.problems.push(text);
        }
    }
}

impl fmt::Display for CheckReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "checked {} bags, {} messages, {} scenes: ",
            self.files, self.messages, self.scenes
        )?;
        if self.is_ok() {
            return writeln!(f, "OK");
        }
        writeln!(f, "{} problems", self.problem_count)?;
        for p in &self.problems {
            writeln!(f, "  - {p}")?;
        }
        if self.problem_count > self.problems.len() {
            writeln!(
                f,
                "  ... and {} more",
                self.problem_count - self.problems.len()
            )?;
        }
        Ok(())
    }
}

/// What the previous frame of a (topic, scene) looked like.
struct SceneState {
    frame_index: u32,
    stamp_ns: i64,
    dt: f32,
    material: Vec<u8>,
}

/// Checks every bag in `paths`, in order, as one dataset (a scene may continue in the next
/// bag). Unreadable files are problems, not errors; only a failing file system is an error.
pub fn check<P: AsRef<Path>>(paths: &[P]) -> Result<CheckReport, BagError> {
    let mut report = CheckReport::default();
    let mut scenes: BTreeMap<(String, String), SceneState> = BTreeMap::new();
    for path in paths {
        report.files += 1;
        let reader = match BagReader::open(path.as_ref()) {
            Ok(reader) => reader,
            Err(err @ BagError::Io { .. }) => return Err(err),
            Err(err) => {
                report.problem(err.to_string());
                continue;
            }
        };
        check_file(reader, &mut scenes, &mut report);
    }
    report.scenes = scenes.len();
    if scenes.is_empty() && report.problem_count == 0 {
        report.problem(format!("no {} messages found", msgs::TYPE_NAME));
    }
    Ok(report)
}

fn check_file(
    mut reader: BagReader,
    scenes: &mut BTreeMap<(String, String), SceneState>,
    report: &mut CheckReport,
) {
    let path = reader.path().to_path_buf();
    let mut channels_seen: Vec<u16> = Vec::new();
    for item in reader.by_ref() {
        let message = match item {
            Ok(message) => message,
            Err(err) => {
                report.problem(err.to_string());
                continue;
            }
        };
        report.messages += 1;
        let ours = message.schema_name() == msgs::TYPE_NAME || message.is_particle_frame();
        let our_topic = [FRAMES_TOPIC, PREDICTED_TOPIC].contains(&message.topic());
        if !ours && !our_topic {
            continue; // another topic's data, not ours to judge
        }
        if !channels_seen.contains(&message.channel.id) {
            channels_seen.push(message.channel.id);
            check_channel(&path, &message, report);
        }
        if !message.is_particle_frame() {
            continue;
        }
        match super::decode_checked(&path, message.topic(), message.index, &message.data) {
            Ok(frame) => check_sequence(&path, &message, frame, scenes, report),
            Err(err) => report.problem(err.to_string()),
        }
    }
}

/// Schema name, encoding and text, and the message encoding, are ours.
fn check_channel(path: &Path, message: &RawMessage, report: &mut CheckReport) {
    let (path, topic) = (path.display(), message.topic());
    if message.channel.message_encoding != MESSAGE_ENCODING {
        let enc = &message.channel.message_encoding;
        report.problem(format!(
            "{path}: topic {topic}: message encoding {enc:?}, expected \"cdr\""
        ));
    }
    let name = message.schema_name();
    if name != msgs::TYPE_NAME {
        let expected = msgs::TYPE_NAME;
        report.problem(format!(
            "{path}: topic {topic}: schema name {name:?}, expected {expected:?}"
        ));
    }
    let Some(schema) = &message.channel.schema else {
        return;
    };
    if schema.encoding != SCHEMA_ENCODING {
        let enc = &schema.encoding;
        report.problem(format!(
            "{path}: topic {topic}: schema encoding {enc:?}, expected \"ros2msg\""
        ));
    } else if schema.data.as_ref() != msgs::schema_text().as_bytes() {
        let ours = msgs::schema_text();
        let theirs = String::from_utf8_lossy(&schema.data);
        let line = (ours.lines().zip(theirs.lines()))
            .position(|(a, b)| a != b)
            .unwrap_or(ours.lines().count().min(theirs.lines().count()));
        report.problem(format!(
            "{path}: topic {topic}: schema text differs from msgs/*.msg (first at line {})",
            line + 1
        ));
    }
}

/// Frame index, stamp, particle count, materials and dt against the scene's previous frame.
fn check_sequence(
    path: &Path,
    message: &RawMessage,
    frame: msgs::ParticleFrame,
    scenes: &mut BTreeMap<(String, String), SceneState>,
    report: &mut CheckReport,
) {
    let key = (message.topic().to_owned(), frame.scene.clone());
    let at = format!(
        "{}: topic {}: message {}: scene {:?} frame {}",
        path.display(),
        message.topic(),
        message.index,
        frame.scene,
        frame.frame_index
    );
    let stamp_ns = frame.header.stamp.as_nanos();
    if let Some(prev) = scenes.get(&key) {
        let expected = u64::from(prev.frame_index) + 1;
        if u64::from(frame.frame_index) != expected {
            let what = if u64::from(frame.frame_index) > expected {
                "gap"
            } else {
                "not increasing"
            };
            report.problem(format!(
                "{at}: frame_index {what}: expected {expected} after {}",
                prev.frame_index
            ));
        }
        if stamp_ns <= prev.stamp_ns {
            report.problem(format!(
                "{at}: stamp {stamp_ns} ns not after previous {} ns",
                prev.stamp_ns
            ));
        }
        if frame.material.len() != prev.material.len() {
            let (n, m) = (frame.material.len(), prev.material.len());
            report.problem(format!("{at}: particle count changed from {m} to {n}"));
        } else if frame.material != prev.material {
            report.problem(format!("{at}: material array changed within the scene"));
        }
        if frame.dt.to_bits() != prev.dt.to_bits() {
            report.problem(format!("{at}: dt changed from {} to {}", prev.dt, frame.dt));
        }
    }
    scenes.insert(
        key,
        SceneState {
            frame_index: frame.frame_index,
            stamp_ns,
            dt: frame.dt,
            material: frame.material,
        },
    );
}
