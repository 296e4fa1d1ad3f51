//! The index half of `minflow bag check`: a bag whose data reads cleanly can still carry a
//! damaged summary or message index, which indexed readers (Foxglove, the Python and C++
//! `mcap` readers, `ros2 bag play`) trust to find messages. [`check_index`] checks what the
//! MCAP specification (mcap.dev/spec) lets a reader verify without decompressing:
//!
//! - the footer's summary CRC over the summary and summary offset sections;
//! - that the summary parses (schemas, channels, statistics, chunk indexes);
//! - the statistics' message and chunk counts against what the linear read found;
//! - each chunk index: a chunk record at its offset with its length, and the message index
//!   records after the chunk parse, name the chunk's channels, keep their offsets inside the
//!   uncompressed chunk and their log times inside the chunk's time range;
//! - the message index entries, summed, equal the messages read.
//!
//! Reads the footer, the summary and the message indexes only (seeks, no decompression).

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use mcap::records::{op, ChunkIndex, Record};
use mcap::sans_io::{SummaryReadEvent, SummaryReader, SummaryReaderOptions};

/// Footer record (opcode, length, summary start, summary offset start, CRC) and end magic.
const FOOTER_AND_MAGIC: u64 = 1 + 8 + 8 + 8 + 4 + 8;

/// Index records larger than this are damage, not data (a chunk's message index is a few KiB).
const MAX_INDEX_BYTES: u64 = 64 << 20;

/// Returns the problems with `path`'s summary and message indexes, each naming the file;
/// `messages` is the count the linear read found (all topics). A bag without a summary has
/// nothing to check here (the specification makes it optional).
pub fn check_index(path: &Path, messages: u64) -> Vec<String> {
    let name = path.display();
    match index_problems(path, messages) {
        Ok(problems) => problems
            .into_iter()
            .map(|p| format!("{name}: {p}"))
            .collect(),
        Err(err) => vec![format!("{name}: summary section unreadable: {err}")],
    }
}

/// What the footer says of the summary section.
enum SummaryCrc {
    /// The bag has no summary (summary start 0).
    Absent,
    /// The footer's CRC matches the summary and summary offset sections, or is 0 (not set).
    Good,
    /// The CRC does not match: the problem, worded for `bag check`.
    Bad(String),
}

/// The footer's summary start (0: no summary) and summary CRC (0: not set), mcap.dev/spec,
/// Footer; an error when the file is too short for one or the record there is no footer.
fn footer(file: &mut File, len: u64) -> Result<(u64, u32), String> {
    if len < FOOTER_AND_MAGIC + 8 {
        return Err("file too short for a footer".into());
    }
    let footer = read_at(file, len - FOOTER_AND_MAGIC, 29)?;
    if footer[0] != op::FOOTER {
        return Err(format!("no footer record (opcode {:#04x})", footer[0]));
    }
    let crc = u32::from_le_bytes(footer[25..29].try_into().unwrap_or_default());
    Ok((u64_at(&footer, 9), crc))
}

/// Reads the footer and checks the summary CRC it carries (mcap.dev/spec, Footer); an error
/// when there is no footer or it points outside the file.
fn summary_crc(file: &mut File, len: u64) -> Result<SummaryCrc, String> {
    let (summary_start, crc) = footer(file, len)?;
    if summary_start == 0 {
        return Ok(SummaryCrc::Absent);
    }
    let crc_end = len - FOOTER_AND_MAGIC + 25;
    if summary_start >= crc_end {
        return Err(format!("summary start {summary_start} is past the footer"));
    }
    if crc == 0 {
        return Ok(SummaryCrc::Good);
    }
    let covered = read_at(file, summary_start, crc_end - summary_start)?;
    let actual = crc32fast::hash(&covered);
    if actual != crc {
        return Ok(SummaryCrc::Bad(format!(
            "summary CRC is {actual:#010x}, the footer says {crc:#010x}: the summary or its \
             index is damaged"
        )));
    }
    Ok(SummaryCrc::Good)
}

fn index_problems(path: &Path, messages: u64) -> Result<Vec<String>, String> {
    let mut file = File::open(path).map_err(|e| e.to_string())?;
    let len = file.metadata().map_err(|e| e.to_string())?.len();
    let mut problems = Vec::new();
    match summary_crc(&mut file, len)? {
        SummaryCrc::Absent => return Ok(problems),
        SummaryCrc::Good => {}
        SummaryCrc::Bad(problem) => problems.push(problem),
    }
    let summary = read_summary(&mut file, len)?;
    if let Some(stats) = &summary.stats {
        if stats.message_count != messages {
            problems.push(format!(
                "summary statistics count {} messages, the file holds {messages}",
                stats.message_count
            ));
        }
        if stats.chunk_count as usize != summary.chunk_indexes.len() {
            problems.push(format!(
                "summary statistics count {} chunks, the chunk index lists {}",
                stats.chunk_count,
                summary.chunk_indexes.len()
            ));
        }
    }
    let mut indexed = 0u64;
    for (k, chunk) in summary.chunk_indexes.iter().enumerate() {
        match check_chunk(&mut file, len, chunk) {
            Ok(entries) => indexed += entries,
            Err(p) => problems.push(format!(
                "chunk index {k} (offset {}): {p}",
                chunk.chunk_start_offset
            )),
        }
    }
    if !summary.chunk_indexes.is_empty() && problems.is_empty() && indexed != messages {
        problems.push(format!(
            "message indexes list {indexed} messages, the file holds {messages}"
        ));
    }
    Ok(problems)
}

/// Checks one chunk index against the file; returns its message index entry count.
fn check_chunk(file: &mut File, len: u64, chunk: &ChunkIndex) -> Result<u64, String> {
    let end = chunk
        .chunk_start_offset
        .checked_add(chunk.chunk_length)
        .filter(|&end| end <= len && chunk.chunk_length >= 9)
        .ok_or("points outside the file")?;
    let head = read_at(file, chunk.chunk_start_offset, 9)?;
    if head[0] != op::CHUNK || u64_at(&head, 1) != chunk.chunk_length - 9 {
        return Err("no chunk record of the indexed length there".into());
    }
    if chunk.message_index_length > MAX_INDEX_BYTES
        || end.saturating_add(chunk.message_index_length) > len
    {
        return Err("message index length points outside the file".into());
    }
    let bytes = read_at(file, end, chunk.message_index_length)?;
    let (mut at, mut entries, mut channels) = (0usize, 0u64, 0usize);
    while at < bytes.len() {
        if bytes.len() - at < 9 {
            return Err("message index ends inside a record header".into());
        }
        let body_len = usize::try_from(u64_at(&bytes, at + 1)).unwrap_or(usize::MAX);
        let body = bytes
            .get(at + 9..(at + 9).saturating_add(body_len))
            .ok_or("message index record runs past the index")?;
        if bytes[at] != op::MESSAGE_INDEX {
            return Err(format!(
                "record {:#04x} among the message indexes",
                bytes[at]
            ));
        }
        let Ok(Record::MessageIndex(index)) = mcap::parse_record(op::MESSAGE_INDEX, body) else {
            return Err("message index record does not parse".into());
        };
        if !chunk.message_index_offsets.contains_key(&index.channel_id) {
            return Err(format!(
                "message index of channel {} not listed",
                index.channel_id
            ));
        }
        for entry in &index.records {
            if entry.offset >= chunk.uncompressed_size {
                return Err(format!("message offset {} outside the chunk", entry.offset));
            }
            if entry.log_time < chunk.message_start_time || entry.log_time > chunk.message_end_time
            {
                return Err(format!(
                    "log time {} outside the chunk's range",
                    entry.log_time
                ));
            }
        }
        entries += index.records.len() as u64;
        channels += 1;
        at += 9 + body_len;
    }
    if channels != chunk.message_index_offsets.len() {
        return Err(format!(
            "{} message index records, the chunk index lists {}",
            channels,
            chunk.message_index_offsets.len()
        ));
    }
    Ok(entries)
}

/// The parsed summary section, read with seeks.
fn read_summary(file: &mut File, len: u64) -> Result<mcap::Summary, String> {
    let options = SummaryReaderOptions::default().with_file_size(len);
    let mut reader = SummaryReader::new_with_options(options);
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            SummaryReadEvent::ReadRequest(n) => {
                let read = file.read(reader.insert(n)).map_err(|e| e.to_string())?;
                reader.notify_read(read);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file.seek(to).map_err(|e| e.to_string())?;
                reader.notify_seeked(pos);
            }
        }
    }
    reader.finish().ok_or_else(|| "no summary".to_owned())
}

/// Where `path`'s data section ends and its summary section starts (bytes), when the data
/// section's framing is intact: the footer's summary start, and the chain of record headers
/// (opcode, length) from the magic lands exactly on the Data End record just before it
/// (mcap.dev/spec). A damaged record length breaks the chain. None without a footer, a
/// summary, or an intact chain. Reads only the record headers (a seek per record).
pub fn data_end(path: &Path) -> Option<u64> {
    let mut file = File::open(path).ok()?;
    let len = file.metadata().ok()?.len();
    let (summary_start, _) = footer(&mut file, len).ok()?;
    if summary_start < 8 + 13 || summary_start >= len {
        return None;
    }
    let data_end = summary_start - 13;
    let mut at = 8u64;
    while at < data_end {
        let head = read_at(&mut file, at, 9).ok()?;
        at = at.checked_add(9)?.checked_add(u64_at(&head, 1))?;
    }
    let head = read_at(&mut file, data_end, 9).ok()?;
    (at == data_end && head[0] == op::DATA_END && u64_at(&head, 1) == 4).then_some(summary_start)
}

/// Messages of all topics that `path`'s summary statistics count, read with seeks; None
/// when the bag has no readable summary or statistics (a cut or streaming-written bag), or
/// when the footer's summary CRC does not match (a damaged count must not pass for lost
/// messages: `bag check` reports the CRC).
pub fn summary_messages(path: &Path) -> Option<u64> {
    let mut file = File::open(path).ok()?;
    let len = file.metadata().ok()?.len();
    if !matches!(summary_crc(&mut file, len).ok()?, SummaryCrc::Good) {
        return None;
    }
    let summary = read_summary(&mut file, len).ok()?;
    Some(summary.stats.as_ref()?.message_count)
}

/// ParticleFrame messages on `topic` (any topic when None) that `path`'s summary statistics
/// count, read with seeks (no decompression); None when the bag cannot be opened or has no
/// readable summary or statistics (a cut or streaming-written bag): then only reading the
/// bag tells.
pub fn summary_frames(path: &Path, topic: Option<&str>) -> Option<u64> {
    let mut file = File::open(path).ok()?;
    let len = file.metadata().ok()?.len();
    let summary = read_summary(&mut file, len).ok()?;
    let stats = summary.stats.as_ref()?;
    let counted = summary.channels.values().filter(|channel| {
        let frames = channel.schema.as_ref().is_some_and(|schema| {
            schema.name == crate::msgs::TYPE_NAME || schema.name == "minflow_msgs/ParticleFrame"
        });
        frames && topic.is_none_or(|t| channel.topic == t)
    });
    Some(
        counted
            .map(|channel| {
                stats
                    .channel_message_counts
                    .get(&channel.id)
                    .copied()
                    .unwrap_or(0)
            })
            .sum(),
    )
}

fn read_at(file: &mut File, at: u64, n: u64) -> Result<Vec<u8>, String> {
    file.seek(SeekFrom::Start(at)).map_err(|e| e.to_string())?;
    let mut buf = Vec::new();
    file.by_ref()
        .take(n)
        .read_to_end(&mut buf)
        .map_err(|e| e.to_string())?;
    if buf.len() as u64 != n {
        return Err(format!("file ends inside the {n} bytes at {at}"));
    }
    Ok(buf)
}

fn u64_at(bytes: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(bytes[at..at + 8].try_into().unwrap_or_default())
}
