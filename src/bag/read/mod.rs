//! Reading bags: stream the messages of any MCAP bag that follows the format, whoever wrote it
//! (chunked or not; zstd, lz4 or uncompressed; with or without summary; other topics with other
//! schemas present).
//!
//! [`BagReader`] yields every message in file order ([`RawMessage`]: topic, `log_time` in ns,
//! 0-based index within its channel, CDR bytes); [`decode_checked`] turns one into a validated
//! [`ParticleFrame`], and [`super::frames`] narrows a reader to decoded frames. Memory stays at
//! one chunk, so datasets need not fit in memory. A bag cut anywhere (writer killed, disk full)
//! yields every complete message before the cut, then one [`BagError::Truncated`] with a
//! [`Truncation`] (also logged with `tracing::warn!`). A damaged chunk (bad CRC, bad
//! compression, a bad record) in a bag that still has its summary is skipped: the rest is read
//! chunk by chunk through the summary's chunk index, as `mcap recover` does (Foxglove's `mcap`
//! CLI), and the closing [`BagError::Truncated`] counts the chunks skipped. A bag that reads to
//! its end is checked against its summary's statistics: a record with a damaged opcode is
//! skipped as unknown (as the specification tells readers to), and only the count shows the
//! loss, which is then reported the same way. Damage past the Data End record, in the summary
//! section, loses no message: it is logged and reading ends normally. Used by `train`,
//! `replay`, `eval` and `bag info/check`. The recovery's chunk reader lives in `chunk.rs`.

use std::collections::{HashMap, VecDeque};
use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use mcap::sans_io::LinearReaderOptions;

mod chunk;

use super::{BagError, MESSAGE_ENCODING};
use crate::msgs::{self, ParticleFrame};
use chunk::read_chunk;

/// Records up to this size are accepted even in small files (a chunk may hold a record larger
/// than the file); beyond it a record must fit in the file. Keeps a corrupt length from making
/// the reader allocate without bound.
const MAX_RECORD_BYTES: usize = 256 << 20;

/// How much of a damaged or cut bag was read, and what was lost.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Truncation {
    /// Messages (all topics) read before the damage.
    pub messages_read: u64,
    /// Bytes consumed from the file when the damage was met.
    pub bytes_read: u64,
    /// File size in bytes.
    pub bytes_total: u64,
    /// The reader's error at the damage.
    pub error: String,
    /// Damaged chunks skipped by reading on through the summary's chunk index (0 when the bag
    /// had no readable summary and reading stopped at the damage).
    pub chunks_skipped: u64,
    /// Messages read after the damage, from the intact chunks past it.
    pub messages_after: u64,
    /// The file read to its end without error, and only the summary's message count showed
    /// the loss (a record skipped as unknown). With `chunks_skipped` 0 where the lost
    /// messages were is unknown.
    pub found_at_end: bool,
}

impl fmt::Display for Truncation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.found_at_end && self.chunks_skipped == 0 {
            return write!(
                f,
                "bag is damaged: read {} messages to its end of {} bytes, then: {}; where the \
                 lost messages were is unknown",
                self.messages_read, self.bytes_total, self.error
            );
        }
        if self.chunks_skipped > 0 || self.messages_after > 0 {
            return write!(
                f,
                "bag is damaged: read {} messages, then at byte {} of {}: {}; skipped {} damaged \
                 chunk(s) (their messages are lost) and read {} messages after them from the \
                 summary's chunk index",
                self.messages_read,
                self.bytes_read,
                self.bytes_total,
                self.error,
                self.chunks_skipped,
                self.messages_after
            );
        }
        write!(
            f,
            "bag is truncated or damaged: read {} messages from {} of {} bytes, then: {}; \
             anything after that point is lost",
            self.messages_read, self.bytes_read, self.bytes_total, self.error
        )
    }
}

/// What reading through the summary's chunk index found after damage.
#[derive(Default)]
struct Recovery {
    /// Damaged chunks, skipped.
    damaged: u64,
    /// The first damaged chunk's offset in the file and the messages of the intact chunks
    /// before it.
    first_damaged: Option<(u64, u64)>,
}

/// A message read through the summary's chunk index after damage.
struct Recovered {
    channel: Arc<mcap::Channel<'static>>,
    log_time: u64,
    publish_time: u64,
    data: Vec<u8>,
}

/// One message of any topic, undecoded.
#[derive(Debug, Clone)]
pub struct RawMessage {
    /// The channel (topic, schema, message encoding, metadata).
    pub channel: Arc<mcap::Channel<'static>>,
    /// 0-based index of this message within its channel.
    pub index: u64,
    /// Log time, ns.
    pub log_time: u64,
    /// Publish time, ns.
    pub publish_time: u64,
    /// The serialized message (CDR for ParticleFrames).
    pub data: Vec<u8>,
}

impl RawMessage {
    /// The channel's topic.
    pub fn topic(&self) -> &str {
        &self.channel.topic
    }

    /// The channel's schema name, empty when it has no schema.
    pub fn schema_name(&self) -> &str {
        self.channel.schema.as_ref().map_or("", |s| s.name.as_str())
    }

    /// Whether the channel carries CDR-encoded ParticleFrames (schema name
    /// `minflow_msgs/msg/ParticleFrame`, or the ROS 1 style `minflow_msgs/ParticleFrame`).
    pub fn is_particle_frame(&self) -> bool {
        let name = self.schema_name();
        (name == msgs::TYPE_NAME || name == "minflow_msgs/ParticleFrame")
            && self.channel.message_encoding == MESSAGE_ENCODING
    }
}

/// Decodes and validates one message; the error names `path`, `topic` and `index`.
pub fn decode_checked(
    path: &Path,
    topic: &str,
    index: u64,
    data: &[u8],
) -> Result<ParticleFrame, BagError> {
    let frame = msgs::decode(data).map_err(|source| BagError::Decode {
        path: path.to_path_buf(),
        topic: topic.to_owned(),
        index,
        source,
    })?;
    frame.validate().map_err(|source| BagError::Invalid {
        path: path.to_path_buf(),
        topic: topic.to_owned(),
        index,
        source,
    })?;
    Ok(frame)
}

/// Counts the bytes handed to the MCAP reader.
struct Counted<R> {
    inner: R,
    bytes: Arc<AtomicU64>,
}

impl<R: Read> Read for Counted<R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.bytes.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }
}

/// Streams the messages of one bag in file order; an iterator of `Result<RawMessage>` whose
/// last item is [`BagError::Truncated`] when the file is cut or damaged.
pub struct BagReader {
    path: PathBuf,
    bytes_total: u64,
    bytes_read: Arc<AtomicU64>,
    inner: Option<mcap::io::MessageReader<Counted<BufReader<File>>>>,
    per_channel: HashMap<u16, u64>,
    messages_read: u64,
    truncation: Option<Truncation>,
    /// Set once the streaming re-read after a cut has started.
    recovering: bool,
    /// Messages still to yield from the intact chunks past a damaged one.
    pending: VecDeque<Recovered>,
    /// Set once the closing [`BagError::Truncated`] was yielded.
    truncation_reported: bool,
}

impl BagReader {
    /// Opens `path`; an empty file or one that does not start with the MCAP magic is an error.
    pub fn open(path: impl AsRef<Path>) -> Result<Self, BagError> {
        let path = path.as_ref().to_path_buf();
        let mut file = File::open(&path).map_err(|e| BagError::io(&path, "opening bag", e))?;
        let bytes_total = file
            .metadata()
            .map_err(|e| BagError::io(&path, "reading bag metadata", e))?
            .len();
        let mut head = Vec::with_capacity(8);
        (&mut file)
            .take(8)
            .read_to_end(&mut head)
            .map_err(|e| BagError::io(&path, "reading bag", e))?;
        if head.is_empty() {
            let what = "the file is empty (0 bytes)".to_owned();
            return Err(BagError::NotMcap { path, what });
        }
        if !mcap::MAGIC.starts_with(&head) {
            let what = format!("it starts with {head:02x?}, not the MCAP magic");
            return Err(BagError::NotMcap { path, what });
        }
        drop(file);
        let mut reader = Self {
            path,
            bytes_total,
            bytes_read: Arc::new(AtomicU64::new(0)),
            inner: None,
            per_channel: HashMap::new(),
            messages_read: 0,
            truncation: None,
            recovering: false,
            pending: VecDeque::new(),
            truncation_reported: false,
        };
        reader.start(true)?;
        Ok(reader)
    }

    /// (Re)starts the MCAP reader at the beginning of the file. `validated`: check each chunk's
    /// CRC before yielding any of its messages, so damaged chunks yield nothing; otherwise
    /// stream chunk contents as they decompress (used to recover the messages of a cut chunk).
    fn start(&mut self, validated: bool) -> Result<(), BagError> {
        let file =
            File::open(&self.path).map_err(|e| BagError::io(&self.path, "opening bag", e))?;
        self.bytes_read = Arc::new(AtomicU64::new(0));
        let file = Counted {
            inner: BufReader::new(file),
            bytes: Arc::clone(&self.bytes_read),
        };
        let limit = usize::try_from(self.bytes_total).unwrap_or(usize::MAX);
        let options = LinearReaderOptions::default()
            .with_validate_chunk_crcs(true)
            .with_prevalidate_chunk_crcs(validated)
            .with_record_length_limit(MAX_RECORD_BYTES.max(limit));
        self.inner = Some(mcap::io::MessageReader::new_with_options(file, options));
        Ok(())
    }

    /// After a cut found by the validating pass, re-reads the file streaming, skips the
    /// messages already yielded and returns the next one from the cut chunk, if any.
    fn recover(&mut self) -> Option<mcap::Message<'static>> {
        self.recovering = true;
        self.start(false).ok()?;
        let inner = self.inner.as_mut()?;
        for _ in 0..self.messages_read {
            inner.next()?.ok()?;
        }
        inner.next()?.ok()
    }

    /// After damage, reads the chunks of the summary's chunk index in file order (each
    /// CRC-checked as a whole), skips the first `messages_read` intact messages (already
    /// yielded) and queues the rest. Returns what it found, or None when the summary is
    /// unreadable or indexes no chunk. Loads the file into memory: only after damage.
    fn recover_indexed(&mut self) -> Option<Recovery> {
        let bytes = std::fs::read(&self.path).ok()?;
        let summary = mcap::Summary::read(&bytes).ok()??;
        let mut chunks = summary.chunk_indexes.clone();
        if chunks.is_empty() {
            return None;
        }
        chunks.sort_by_key(|c| c.chunk_start_offset);
        chunks.dedup_by_key(|c| c.chunk_start_offset);
        let (mut skip, mut found) = (self.messages_read, Recovery::default());
        let mut intact = 0u64;
        for index in &chunks {
            let Some(messages) = read_chunk(&summary, &bytes, index) else {
                found.damaged += 1;
                found
                    .first_damaged
                    .get_or_insert((index.chunk_start_offset, intact));
                continue;
            };
            intact += messages.len() as u64;
            for message in messages {
                if skip > 0 {
                    skip -= 1;
                } else {
                    self.pending.push_back(message);
                }
            }
        }
        Some(found)
    }

    /// Yields the next queued message of a recovery, or the closing truncation once empty.
    fn next_recovered(&mut self) -> Option<Result<RawMessage, BagError>> {
        let Some(message) = self.pending.pop_front() else {
            let truncation = self.truncation.clone()?;
            self.truncation_reported = true;
            // Logged here, where its counts are final, in the words of the error.
            tracing::warn!("{}: {truncation}", self.path.display());
            return Some(Err(BagError::Truncated {
                path: self.path.clone(),
                truncation,
            }));
        };
        if let Some(t) = self.truncation.as_mut() {
            t.messages_after += 1;
        }
        Some(Ok(self.numbered(
            message.channel,
            message.log_time,
            message.publish_time,
            message.data,
        )))
    }

    /// Counts a message and numbers it within its channel.
    fn numbered(
        &mut self,
        channel: Arc<mcap::Channel<'static>>,
        log_time: u64,
        publish_time: u64,
        data: Vec<u8>,
    ) -> RawMessage {
        let counter = self.per_channel.entry(channel.id).or_insert(0);
        let index = *counter;
        *counter += 1;
        self.messages_read += 1;
        RawMessage {
            channel,
            index,
            log_time,
            publish_time,
            data,
        }
    }

    /// The bag's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// File size in bytes.
    pub fn bytes_total(&self) -> u64 {
        self.bytes_total
    }

    /// Messages yielded so far (all topics).
    pub fn messages_read(&self) -> u64 {
        self.messages_read
    }

    /// Set once reading stopped at damage or a cut.
    pub fn truncation(&self) -> Option<&Truncation> {
        self.truncation.as_ref()
    }
}

impl Iterator for BagReader {
    type Item = Result<RawMessage, BagError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.inner.is_none() {
            return if self.truncation_reported {
                None
            } else {
                self.next_recovered()
            };
        }
        let next = match self.inner.as_mut()?.next() {
            None => {
                self.inner = None;
                return if self.recovering {
                    None
                } else {
                    self.finished()
                };
            }
            // A cut: recover the complete messages of a cut chunk, which validation withheld.
            Some(Err(mcap::McapError::UnexpectedEof)) if !self.recovering => {
                self.recover().ok_or(mcap::McapError::UnexpectedEof)
            }
            Some(other) => other,
        };
        match next {
            Ok(message) => {
                let data = message.data.into_owned();
                let (log, publish) = (message.log_time, message.publish_time);
                Some(Ok(self.numbered(message.channel, log, publish, data)))
            }
            Err(err) => {
                let at = self.bytes_read.load(Ordering::Relaxed);
                if self.only_summary_damaged(at) {
                    self.summary_damaged(at, &err.to_string())
                } else {
                    self.damaged(err.to_string(), false)
                }
            }
        }
    }
}

impl BagReader {
    /// The file read to its end without error: checks the count against the summary's
    /// statistics. A record whose opcode was damaged reads as an unknown record, which MCAP
    /// readers skip by the specification, so only the count shows that a chunk or message went
    /// missing. Bags without statistics (optional in MCAP) cannot be checked this way.
    fn finished(&mut self) -> Option<Result<RawMessage, BagError>> {
        let expected = super::check_index::summary_messages(&self.path)?;
        if expected <= self.messages_read {
            return None;
        }
        let error = format!(
            "the summary's statistics count {expected} messages but the file holds {} readable \
             ones: a record was skipped (most likely a damaged opcode)",
            self.messages_read
        );
        self.damaged(error, true)
    }

    /// Whether reading failed at byte `at` past the Data End record, the data section's record
    /// framing intact (so no record ran on into the summary) and no message missing by the
    /// summary's count where its CRC holds: then only the summary section is damaged.
    fn only_summary_damaged(&self, at: u64) -> bool {
        let past_data = super::check_index::data_end(&self.path).is_some_and(|end| at > end);
        past_data
            && super::check_index::summary_messages(&self.path)
                .is_none_or(|expected| expected <= self.messages_read)
    }

    /// The damage is in the summary section, after the Data End record: every message was
    /// read, so reading ends normally with a warning (`bag check` reports the summary's damage;
    /// indexed readers would not find the messages).
    fn summary_damaged(&mut self, at: u64, error: &str) -> Option<Result<RawMessage, BagError>> {
        self.inner = None;
        tracing::warn!(
            "bag {}: its summary section is damaged at byte {at} of {} ({error}); all {} \
             messages of its data section were read (`minflow bag check` names the damage)",
            self.path.display(),
            self.bytes_total,
            self.messages_read
        );
        None
    }

    /// Reading stopped at damage (`error`): reads on through the summary's chunk index where
    /// there is one and yields what follows, then the closing truncation (logged then).
    /// `at_end`: the damage was found only at the end of the file (by the message count), so
    /// every readable message was already yielded; the damage is placed at the first damaged
    /// chunk of the index when there is one.
    fn damaged(&mut self, error: String, at_end: bool) -> Option<Result<RawMessage, BagError>> {
        self.inner = None;
        let mut truncation = Truncation {
            messages_read: self.messages_read,
            bytes_read: self.bytes_read.load(Ordering::Relaxed),
            bytes_total: self.bytes_total,
            error,
            chunks_skipped: 0,
            messages_after: 0,
            found_at_end: at_end,
        };
        if let Some(found) = self.recover_indexed() {
            truncation.chunks_skipped = found.damaged;
            if let (true, Some((offset, before))) = (at_end, found.first_damaged) {
                truncation.bytes_read = offset;
                truncation.messages_read = before.min(self.messages_read);
                truncation.messages_after = self.messages_read - truncation.messages_read;
            }
        }
        self.truncation = Some(truncation);
        self.next_recovered()
    }
}
