//! Decoded frames: [`Frames`] narrows a [`BagReader`] to the validated [`ParticleFrame`]s of one
//! topic (or of every ParticleFrame channel), skipping and counting other topics and schemas,
//! and [`read_frames`] / [`read_frames_with`] collect a whole bag into a [`ReadOutcome`]
//! (frames with their topic and `log_time` in ns, truncation, skipped and invalid counts),
//! strictly or leniently. Used by `train` and `eval` (through `data`), `eval --pred` and
//! `bench node`.

use std::path::Path;

use super::read::{decode_checked, BagReader, Truncation};
use super::BagError;
use crate::msgs::ParticleFrame;

impl BagReader {
    /// The ParticleFrames on every channel that carries them (others skipped and counted).
    pub fn frames(self) -> Frames {
        self.frames_on(None)
    }

    /// The ParticleFrames on `topic` (all ParticleFrame channels when `None`). A channel on a
    /// requested topic with another schema gives one [`BagError::ForeignSchema`].
    pub fn frames_on(self, topic: Option<&str>) -> Frames {
        Frames {
            raw: self,
            topic: topic.map(str::to_owned),
            reported: Vec::new(),
            skipped: 0,
        }
    }
}

/// The decoded ParticleFrames of one bag; see [`BagReader::frames_on`].
pub struct Frames {
    raw: BagReader,
    topic: Option<String>,
    /// Channels already reported as foreign.
    reported: Vec<u16>,
    skipped: u64,
}

/// One decoded, validated frame and where it came from.
#[derive(Debug, Clone, PartialEq)]
pub struct BagMessage {
    /// Channel topic.
    pub topic: String,
    /// Log time, ns.
    pub log_time: u64,
    /// 0-based index within its channel.
    pub index: u64,
    /// The frame.
    pub frame: ParticleFrame,
    /// The solver's grid of the frame's scene, when the channel's metadata says
    /// ([`super::SOLVER_GRID_KEY`]).
    pub solver_grid: Option<u32>,
}

impl Frames {
    /// Messages passed over so far: other topics, other schemas.
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    /// The underlying reader (path, size, truncation).
    pub fn reader(&self) -> &BagReader {
        &self.raw
    }
}

impl Iterator for Frames {
    type Item = Result<BagMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            let message = match self.raw.next()? {
                Ok(message) => message,
                Err(err) => return Some(Err(err)),
            };
            let requested = self.topic.as_deref().is_some_and(|t| t == message.topic());
            if self.topic.is_some() && !requested {
                self.skipped += 1;
                continue;
            }
            if !message.is_particle_frame() {
                if requested && !self.reported.contains(&message.channel.id) {
                    self.reported.push(message.channel.id);
                    return Some(Err(BagError::ForeignSchema {
                        path: self.raw.path().to_path_buf(),
                        topic: message.topic().to_owned(),
                        schema: message.schema_name().to_owned(),
                        encoding: message.channel.message_encoding.clone(),
                    }));
                }
                self.skipped += 1;
                continue;
            }
            let decoded = decode_checked(
                self.raw.path(),
                message.topic(),
                message.index,
                &message.data,
            );
            return Some(decoded.map(|frame| {
                BagMessage {
                    topic: message.channel.topic.clone(),
                    log_time: message.log_time,
                    index: message.index,
                    frame,
                    solver_grid: message
                        .channel
                        .metadata
                        .get(super::SOLVER_GRID_KEY)
                        .and_then(|v| v.parse().ok()),
                }
            }));
        }
    }
}

/// Options for [`read_frames_with`].
#[derive(Debug, Clone, Default)]
pub struct ReadOptions {
    /// Read only this topic (every ParticleFrame channel when `None`).
    pub topic: Option<String>,
    /// Count and skip messages that fail to decode or validate instead of failing on the first.
    pub lenient: bool,
}

/// Everything read from one bag by [`read_frames`].
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadOutcome {
    /// `(topic, log_time in ns, frame)` in file order.
    pub frames: Vec<(String, u64, ParticleFrame)>,
    /// Set when the bag is cut or damaged; `frames` then holds everything before the damage.
    pub truncated: Option<Truncation>,
    /// Messages on other topics or with other schemas, passed over.
    pub skipped: u64,
    /// Messages that failed to decode or validate (lenient mode only; strict mode fails).
    pub invalid: u64,
}

/// Reads every frame of the bag at `path` (only `topic_filter`'s when given), strictly: the
/// first message that fails to decode or validate is an error naming file, topic and index.
pub fn read_frames(
    path: impl AsRef<Path>,
    topic_filter: Option<&str>,
) -> Result<ReadOutcome, BagError> {
    let options = ReadOptions {
        topic: topic_filter.map(str::to_owned),
        lenient: false,
    };
    read_frames_with(path, &options)
}

/// Reads every frame of the bag at `path` as `options` say.
pub fn read_frames_with(
    path: impl AsRef<Path>,
    options: &ReadOptions,
) -> Result<ReadOutcome, BagError> {
    let mut frames = BagReader::open(path)?.frames_on(options.topic.as_deref());
    let mut out = ReadOutcome::default();
    for item in frames.by_ref() {
        match item {
            Ok(m) => out.frames.push((m.topic, m.log_time, m.frame)),
            Err(BagError::Truncated { truncation, .. }) => out.truncated = Some(truncation),
            Err(err) if options.lenient && err.is_message_error() => {
                if out.invalid == 0 {
                    tracing::warn!("skipping invalid message: {err}");
                }
                out.invalid += 1;
            }
            Err(err) => return Err(err),
        }
    }
    if out.invalid > 1 {
        tracing::warn!(
            "{}: skipped {} invalid messages in all",
            frames.reader().path().display(),
            out.invalid
        );
    }
    out.skipped = frames.skipped();
    if let (Some(topic), true) = (&options.topic, out.frames.is_empty()) {
        tracing::warn!(
            "{}: no frames on topic {topic} ({} messages on other topics or schemas)",
            frames.reader().path().display(),
            out.skipped
        );
    }
    Ok(out)
}
