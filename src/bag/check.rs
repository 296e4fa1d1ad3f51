//! `minflow bag check`: whether one or more bags make a sound dataset.
//!
//! [`check`] streams the bags in order, as one dataset, and returns a [`CheckReport`] whose
//! `Display` is the printed report: on our topics (and wherever our schema appears) the schema
//! name, schema encoding and text, and message encoding are ours, every frame decodes and
//! validates, and within each (topic, scene) `frame_index` rises by exactly 1, stamps (ns)
//! strictly increase, and particle count, materials and `dt` stay constant. Damaged or cut files
//! are problems in the report, not errors. It does not load a whole bag into memory. Also used
//! by `demo`.

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use super::read::{decode_checked, BagReader, RawMessage};
use super::{BagError, FRAMES_TOPIC, MESSAGE_ENCODING, PREDICTED_TOPIC, SCHEMA_ENCODING};
use crate::msgs;

/// Problems listed in a check report (the rest are counted).
const PROBLEMS_LISTED: usize = 20;

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
        match decode_checked(&path, message.topic(), message.index, &message.data) {
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
