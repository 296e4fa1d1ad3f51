//! Reading bags: stream the messages of any MCAP bag that follows the format, whoever wrote it
//! (chunked or not; zstd, lz4 or uncompressed; with or without summary; other topics with other
//! schemas present).
//!
//! [`BagReader`] yields every message in file order ([`RawMessage`]: topic, `log_time` in ns,
//! 0-based index within its channel, CDR bytes); [`decode_checked`] turns one into a validated
//! [`ParticleFrame`], and [`super::frames`] narrows a reader to decoded frames. Memory stays at
//! one chunk, so datasets need not fit in memory. A bag cut anywhere (writer killed, disk full)
//! yields every complete message before the cut, then one [`BagError::Truncated`] with a
//! [`Truncation`] (also logged with `tracing::warn!`). Used by `train`, `replay`, `eval` and
//! `bag info/check`.

use std::collections::HashMap;
use std::fmt;
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use mcap::sans_io::LinearReaderOptions;

use super::{BagError, MESSAGE_ENCODING};
use crate::msgs::{self, ParticleFrame};

/// Records up to this size are accepted even in small files (a chunk may hold a record larger
/// than the file); beyond it a record must fit in the file. Keeps a corrupt length from making
/// the reader allocate without bound.
const MAX_RECORD_BYTES: usize = 256 << 20;

/// How much of a damaged or cut bag was read, and why reading stopped.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Truncation {
    /// Messages (all topics) read before the damage.
    pub messages_read: u64,
    /// Bytes consumed from the file when reading stopped.
    pub bytes_read: u64,
    /// File size in bytes.
    pub bytes_total: u64,
    /// The reader's error at the point where it stopped.
    pub error: String,
}

impl fmt::Display for Truncation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "bag is truncated or damaged: read {} messages from {} of {} bytes, then: {}; \
             anything after that point is lost",
            self.messages_read, self.bytes_read, self.bytes_total, self.error
        )
    }
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
        let next = match self.inner.as_mut()?.next()? {
            // A cut: recover the complete messages of a cut chunk, which validation withheld.
            Err(mcap::McapError::UnexpectedEof) if !self.recovering => {
                self.recover().ok_or(mcap::McapError::UnexpectedEof)
            }
            other => other,
        };
        match next {
            Ok(message) => {
                let counter = self.per_channel.entry(message.channel.id).or_insert(0);
                let index = *counter;
                *counter += 1;
                self.messages_read += 1;
                Some(Ok(RawMessage {
                    channel: message.channel,
                    index,
                    log_time: message.log_time,
                    publish_time: message.publish_time,
                    data: message.data.into_owned(),
                }))
            }
            Err(err) => {
                let truncation = Truncation {
                    messages_read: self.messages_read,
                    bytes_read: self.bytes_read.load(Ordering::Relaxed),
                    bytes_total: self.bytes_total,
                    error: err.to_string(),
                };
                tracing::warn!(
                    "bag {} is truncated or damaged: kept the {} messages before byte {} of {}, \
                     the rest is lost ({})",
                    self.path.display(),
                    truncation.messages_read,
                    truncation.bytes_read,
                    truncation.bytes_total,
                    truncation.error
                );
                self.truncation = Some(truncation.clone());
                self.inner = None;
                Some(Err(BagError::Truncated {
                    path: self.path.clone(),
                    truncation,
                }))
            }
        }
    }
}
