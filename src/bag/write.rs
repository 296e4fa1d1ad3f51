//! Writing bags: [`BagWriter`] turns [`ParticleFrame`]s (or CDR bytes from a transport) into an
//! MCAP file that `ros2 bag`, Foxglove and `mcap-ros2-support` read.
//!
//! One channel per topic, created on first use, all sharing one schema
//! (`minflow_msgs/msg/ParticleFrame`, `ros2msg`, [`crate::msgs::schema_text`]); message
//! encoding `cdr`; channel metadata `offered_qos_profiles` = the default ROS 2 QoS in rosbag2's
//! YAML; profile `ros2`; zstd chunks of 1 MiB. `log_time` = `publish_time` = the frame's stamp
//! in ns; `sequence` counts messages per channel from 0. Output is deterministic: the same
//! frames give byte-identical files (the header's library string carries versions only, and
//! zstd runs single-threaded). Used by `simulate` and the `record` node. Other message types
//! (`record --points`' `foxglove.PointCloud`s, encoded by `viz`) go beside them through
//! [`BagWriter::write_foreign`]; this module knows none of them.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use mcap::records::MessageHeader;

use super::{BagError, DEFAULT_QOS_YAML, MESSAGE_ENCODING, PROFILE, QOS_KEY, SCHEMA_ENCODING};
use crate::msgs::{self, ParticleFrame};

/// Uncompressed size at which a chunk is closed (as mcap's default).
const CHUNK_BYTES: u64 = 1024 * 1024;

/// The schema of messages other than `ParticleFrame` in a bag, as MCAP stores it (e.g.
/// `foxglove.PointCloud`, `protobuf`, its file descriptor set, message encoding `protobuf`).
#[derive(Debug, Clone, Copy)]
pub struct ForeignSchema<'a> {
    /// Schema name, e.g. `foxglove.PointCloud`.
    pub name: &'a str,
    /// Schema encoding, e.g. `protobuf`.
    pub encoding: &'a str,
    /// The schema itself (for `protobuf`, a serialised `FileDescriptorSet`).
    pub data: &'a [u8],
    /// The messages' encoding, e.g. `protobuf`.
    pub message_encoding: &'a str,
}

/// Writes ParticleFrames to one MCAP bag. Call [`BagWriter::finish`] to write the summary and
/// footer and to see errors; a writer dropped without it still tries to finish the file.
pub struct BagWriter {
    path: PathBuf,
    writer: mcap::Writer<BufWriter<File>>,
    schema_id: u16,
    /// topic -> (channel id, messages written on it)
    channels: BTreeMap<String, (u16, u32)>,
    /// Schemas of other message types ([`BagWriter::write_foreign`]) by name -> schema id.
    foreign_schemas: BTreeMap<String, u16>,
    scratch: Vec<u8>,
    /// File length after the last successful [`BagWriter::flush`]: everything before it is
    /// whole records, where [`BagWriter::abandon`] cuts the file.
    flushed_len: u64,
    /// Metadata added to each ParticleFrame channel beside the QoS profiles.
    channel_metadata: BTreeMap<String, String>,
}

impl BagWriter {
    /// Creates (or truncates) the bag at `path` and writes the MCAP header.
    pub fn create(path: impl AsRef<Path>) -> Result<Self, BagError> {
        let path = path.as_ref().to_path_buf();
        let file = File::create(&path).map_err(|e| BagError::io(&path, "creating bag", e))?;
        let options = mcap::WriteOptions::new()
            .profile(PROFILE)
            .library(format!(
                "minflow/{} mcap-rust/{}",
                env!("CARGO_PKG_VERSION"),
                mcap::VERSION
            ))
            .compression(Some(mcap::Compression::Zstd))
            .compression_threads(0)
            .chunk_size(Some(CHUNK_BYTES));
        let mcap_err = |source| BagError::Mcap {
            path: path.clone(),
            source,
        };
        let mut writer = options.create(BufWriter::new(file)).map_err(mcap_err)?;
        let schema_id = writer
            .add_schema(
                msgs::TYPE_NAME,
                SCHEMA_ENCODING,
                msgs::schema_text().as_bytes(),
            )
            .map_err(mcap_err)?;
        Ok(Self {
            path,
            writer,
            schema_id,
            channels: BTreeMap::new(),
            foreign_schemas: BTreeMap::new(),
            scratch: Vec::new(),
            flushed_len: 0,
            channel_metadata: BTreeMap::new(),
        })
    }

    /// Adds `key: value` to the metadata of every ParticleFrame channel added from now on
    /// (`simulate` records the solver's grid, [`super::SOLVER_GRID_KEY`]).
    pub fn channel_metadata(&mut self, key: &str, value: &str) {
        self.channel_metadata
            .insert(key.to_owned(), value.to_owned());
    }

    /// The bag's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Validates `frame` and writes it on `topic` with `log_time` = `publish_time` = its stamp.
    /// A frame that fails [`ParticleFrame::validate`] or has a negative stamp is an error.
    pub fn write(&mut self, topic: &str, frame: &ParticleFrame) -> Result<(), BagError> {
        let index = self.channels.get(topic).map_or(0, |&(_, n)| u64::from(n));
        frame.validate().map_err(|source| BagError::Invalid {
            path: self.path.clone(),
            topic: topic.to_owned(),
            index,
            source,
        })?;
        let Some(stamp_ns) = frame.header.stamp.as_unsigned_nanos() else {
            return Err(BagError::Write {
                path: self.path.clone(),
                topic: topic.to_owned(),
                index,
                what: format!(
                    "negative stamp {:?} cannot be an MCAP log time",
                    frame.header.stamp
                ),
            });
        };
        let mut scratch = std::mem::take(&mut self.scratch);
        msgs::encode_into(frame, &mut scratch);
        let result = self.write_raw(topic, stamp_ns, &scratch);
        self.scratch = scratch;
        result
    }

    /// Writes already-encoded CDR bytes on `topic` at `stamp_ns` (log and publish time), as a
    /// recorder does with what a transport delivered. The bytes are not checked.
    pub fn write_raw(&mut self, topic: &str, stamp_ns: u64, cdr: &[u8]) -> Result<(), BagError> {
        let channel = self.channel(topic)?;
        self.write_message(channel, stamp_ns, cdr)
    }

    /// Writes already-encoded bytes of another message type on `topic` at `stamp_ns`: the
    /// channel is added on first use with `schema` and `message_encoding` (no QoS metadata:
    /// ROS 2 does not play these). `record --points` writes its `foxglove.PointCloud`s
    /// through this (`viz::cloud` encodes them). The bytes are not checked.
    pub fn write_foreign(
        &mut self,
        topic: &str,
        stamp_ns: u64,
        schema: &ForeignSchema<'_>,
        bytes: &[u8],
    ) -> Result<(), BagError> {
        let channel = self.foreign_channel(topic, schema)?;
        self.write_message(channel, stamp_ns, bytes)
    }

    /// Writes one message on a known channel, `log_time` = `publish_time` = `stamp_ns`.
    fn write_message(
        &mut self,
        (channel_id, sequence): (u16, u32),
        stamp_ns: u64,
        bytes: &[u8],
    ) -> Result<(), BagError> {
        self.writer
            .write_to_known_channel(
                &MessageHeader {
                    channel_id,
                    sequence,
                    log_time: stamp_ns,
                    publish_time: stamp_ns,
                },
                bytes,
            )
            .map_err(|source| BagError::Mcap {
                path: self.path.clone(),
                source,
            })
    }

    /// Returns the channel id for `topic` (adding the channel on first use) and the sequence
    /// number of the next message on it.
    fn channel(&mut self, topic: &str) -> Result<(u16, u32), BagError> {
        if let Some(next) = self.next_sequence(topic) {
            return Ok(next);
        }
        let mut metadata = self.channel_metadata.clone();
        metadata.insert(QOS_KEY.to_owned(), DEFAULT_QOS_YAML.to_owned());
        self.add_channel(topic, self.schema_id, MESSAGE_ENCODING, &metadata)
    }

    /// As [`BagWriter::channel`] for a channel of another message type: its schema is added
    /// once per schema name.
    fn foreign_channel(
        &mut self,
        topic: &str,
        schema: &ForeignSchema<'_>,
    ) -> Result<(u16, u32), BagError> {
        if let Some(next) = self.next_sequence(topic) {
            return Ok(next);
        }
        let schema_id = match self.foreign_schemas.get(schema.name) {
            Some(&id) => id,
            None => {
                let id = self
                    .writer
                    .add_schema(schema.name, schema.encoding, schema.data)
                    .map_err(|source| BagError::Mcap {
                        path: self.path.clone(),
                        source,
                    })?;
                self.foreign_schemas.insert(schema.name.to_owned(), id);
                id
            }
        };
        self.add_channel(topic, schema_id, schema.message_encoding, &BTreeMap::new())
    }

    /// The channel of `topic` and the sequence number of its next message, if it exists.
    fn next_sequence(&mut self, topic: &str) -> Option<(u16, u32)> {
        let (id, count) = self.channels.get_mut(topic)?;
        let sequence = *count;
        *count = count.wrapping_add(1);
        Some((*id, sequence))
    }

    /// Adds the channel of `topic`; returns its id and sequence number 0.
    fn add_channel(
        &mut self,
        topic: &str,
        schema_id: u16,
        encoding: &str,
        metadata: &BTreeMap<String, String>,
    ) -> Result<(u16, u32), BagError> {
        let id = self
            .writer
            .add_channel(schema_id, topic, encoding, metadata)
            .map_err(|source| BagError::Mcap {
                path: self.path.clone(),
                source,
            })?;
        self.channels.insert(topic.to_owned(), (id, 1));
        Ok((id, 0))
    }

    /// Closes the current chunk and pushes everything written so far to the OS, so a process
    /// killed afterwards (SIGKILL, power loss aside) leaves a bag that readers can stream up
    /// to this point. The recorder calls it periodically; smaller chunks compress a little
    /// worse.
    pub fn flush(&mut self) -> Result<(), BagError> {
        self.writer.flush().map_err(|source| BagError::Mcap {
            path: self.path.clone(),
            source,
        })?;
        self.flushed_len = self.bytes_written();
        Ok(())
    }

    /// After a failed write (a full disk): gives up the writer and closes the file at its last
    /// flush, so that what was flushed stays a complete bag that every reader opens without
    /// error. Everything written since that flush is cut off; a Data End record and a footer
    /// without summary (valid MCAP: readers then read the messages in file order) follow.
    /// Returns the bag's new length in bytes; 0 when it was never flushed, and then the file
    /// is removed (it holds no whole message).
    ///
    /// # Errors
    /// [`BagError::Io`] when the file cannot be cut or the footer not written (the disk is
    /// still full): the file then ends at the cut, readable as a truncated bag.
    pub fn abandon(self) -> Result<u64, BagError> {
        let (path, keep) = (self.path.clone(), self.flushed_len);
        // Dropping the writer tries to flush its buffer; what it adds is cut off below.
        drop(self);
        if keep == 0 {
            return std::fs::remove_file(&path)
                .map(|()| 0)
                .map_err(|e| BagError::io(&path, "removing the unflushed bag", e));
        }
        let fail = |e| BagError::io(&path, "closing the bag at its last flush", e);
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .map_err(fail)?;
        file.set_len(keep).map_err(fail)?;
        std::io::Seek::seek(&mut file, std::io::SeekFrom::Start(keep)).map_err(fail)?;
        file.write_all(&closing_records()).map_err(fail)?;
        file.sync_all().map_err(fail)?;
        Ok(keep + closing_records().len() as u64)
    }

    /// Bytes written to the file so far (chunks closed by [`BagWriter::flush`] or by size).
    pub fn bytes_written(&self) -> u64 {
        std::fs::metadata(&self.path).map_or(0, |m| m.len())
    }

    /// Writes the last chunk, the summary and the footer, and flushes the file.
    pub fn finish(mut self) -> Result<(), BagError> {
        let path = self.path.clone();
        self.writer.finish().map_err(|source| BagError::Mcap {
            path: path.clone(),
            source,
        })?;
        let mut file = self.writer.into_inner();
        file.flush()
            .map_err(|e| BagError::io(&path, "flushing bag", e))?;
        let file = file
            .into_inner()
            .map_err(|e| BagError::io(&path, "flushing bag", e.into_error()))?;
        file.sync_all()
            .map_err(|e| BagError::io(&path, "syncing bag", e))
    }
}

/// A Data End record (data section CRC 0: not computed), a Footer pointing at no summary,
/// and the closing magic: what [`BagWriter::abandon`] appends after the last whole record.
fn closing_records() -> Vec<u8> {
    const DATA_END: u8 = 0x0F;
    const FOOTER: u8 = 0x02;
    let mut out = Vec::with_capacity(58);
    out.push(DATA_END);
    out.extend_from_slice(&4u64.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.push(FOOTER);
    out.extend_from_slice(&20u64.to_le_bytes());
    out.extend_from_slice(&0u64.to_le_bytes()); // summary start: none
    out.extend_from_slice(&0u64.to_le_bytes()); // summary offset start: none
    out.extend_from_slice(&0u32.to_le_bytes()); // summary CRC: none
    out.extend_from_slice(mcap::MAGIC);
    out
}
