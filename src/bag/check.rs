//! `minflow bag check`: whether one or more bags make a sound dataset.
//!
//! [`check`] streams the bags in order, as one dataset, and returns a [`CheckReport`] whose
//! `Display` is the printed report: on our topics (and wherever our schema appears) the schema
//! name, schema encoding and text, and message encoding are ours, every frame decodes and
//! validates, and within each (topic, scene) `frame_index` rises by exactly 1, stamps (ns)
//! strictly increase, and particle count, materials and `dt` stay constant; and the summary and
//! message indexes agree with the data ([`super::check_index`]). Damaged or cut files are
//! problems in the report, not errors. It does not load a whole bag into memory.

use std::collections::BTreeMap;
use std::fmt;
use std::path::Path;

use super::check_index::check_index;
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
    // A cut or damaged file is already a problem; its index cannot be whole.
    if reader.truncation().is_none() {
        for problem in check_index(&path, reader.messages_read()) {
            report.problem(problem);
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
        let ours = definitions(&msgs::schema_text());
        let theirs = definitions(&String::from_utf8_lossy(&schema.data));
        if ours != theirs {
            report.problem(format!(
                "{path}: topic {topic}: schema differs from msgs/*.msg: {}",
                first_difference(&ours, &theirs)
            ));
        }
    }
}

/// The message definitions of a `ros2msg` schema text, as `(type name, fields)`: the main
/// definition first (name empty), then its dependencies sorted by name. Comments (`#` to the
/// end of the line), blank lines and spacing are dropped, so two texts that define the same
/// types compare equal however a writer laid them out (the MCAP `ros2msg` encoding: the
/// main `.msg` text, then for each dependency a line of `=`, `MSG: pkg/Type` and its text).
fn definitions(text: &str) -> Vec<(String, Vec<String>)> {
    let mut defs: Vec<(String, Vec<String>)> = vec![(String::new(), Vec::new())];
    for line in text.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.len() >= 3 && line.chars().all(|c| c == '=') {
            defs.push((String::new(), Vec::new()));
        } else if let Some(name) = line.strip_prefix("MSG:") {
            if let Some(def) = defs.last_mut() {
                def.0 = name.trim().to_owned();
            }
        } else if !line.is_empty() {
            let field = line.split_whitespace().collect::<Vec<_>>().join(" ");
            if let Some(def) = defs.last_mut() {
                def.1.push(field.replace(" =", "=").replace("= ", "="));
            }
        }
    }
    defs[1..].sort();
    defs
}

/// The first definition line where `theirs` differs from `ours`, for the report.
fn first_difference(ours: &[(String, Vec<String>)], theirs: &[(String, Vec<String>)]) -> String {
    for (k, (a, b)) in ours.iter().zip(theirs).enumerate() {
        let name = if k == 0 {
            msgs::TYPE_NAME
        } else {
            a.0.as_str()
        };
        if a.0 != b.0 {
            return format!("definition of {:?} where {name:?} was expected", b.0);
        }
        let fields = a.1.iter().map(Some).chain(std::iter::repeat(None));
        let other = b.1.iter().map(Some).chain(std::iter::repeat(None));
        if let Some((x, y)) = fields
            .zip(other)
            .take(a.1.len().max(b.1.len()))
            .find(|(x, y)| x != y)
        {
            let show = |f: Option<&String>| f.map_or("no field".to_owned(), |f| format!("{f:?}"));
            return format!(
                "in {name}, field {} where {} was expected",
                show(y),
                show(x)
            );
        }
    }
    format!(
        "{} definitions where {} were expected",
        theirs.len(),
        ours.len()
    )
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
    if frame.scene.trim().is_empty() && !scenes.contains_key(&key) {
        // Once per topic: the node keys its hidden states by scene, eval and train too.
        report.problem(format!("{at}: empty scene name"));
    }
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
