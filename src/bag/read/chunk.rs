//! One chunk of a damaged bag read on its own (the recovery path of [`super::BagReader`]):
//! through the summary's chunk index, its CRC checked and every record length bounded, all of
//! its messages or none.

use std::sync::Arc;

use mcap::sans_io::LinearReaderOptions;

use super::{Recovered, MAX_RECORD_BYTES};

/// The messages of one indexed chunk, or None when the chunk is damaged (bad CRC, bad
/// compression, a bad record inside, an unknown channel): all or nothing, so no message of a
/// damaged chunk is used. The chunk record is fed alone to a linear reader that checks its CRC
/// before yielding and bounds every record length (a damaged length must not allocate).
pub(super) fn read_chunk(
    summary: &mcap::Summary,
    bytes: &[u8],
    index: &mcap::records::ChunkIndex,
) -> Option<Vec<Recovered>> {
    use mcap::records::{op, Record};
    use mcap::sans_io::{LinearReadEvent, LinearReader};
    // A damaged index may point anywhere: keep the record inside the file.
    let end = index.chunk_start_offset.checked_add(index.chunk_length)?;
    if index.chunk_length < 9 || end > bytes.len() as u64 {
        return None;
    }
    let mut record = &bytes[index.chunk_start_offset as usize..end as usize];
    if record[0] != op::CHUNK {
        return None;
    }
    let options = LinearReaderOptions::default()
        .with_skip_start_magic(true)
        .with_skip_end_magic(true)
        .with_validate_chunk_crcs(true)
        .with_prevalidate_chunk_crcs(true)
        .with_record_length_limit(MAX_RECORD_BYTES);
    let mut reader = LinearReader::new_with_options(options);
    let mut out = Vec::new();
    while let Some(event) = reader.next_event() {
        match event.ok()? {
            LinearReadEvent::ReadRequest(need) => {
                let n = need.min(record.len());
                reader.insert(n).copy_from_slice(&record[..n]);
                reader.notify_read(n);
                record = &record[n..];
            }
            LinearReadEvent::Record { opcode, data } => {
                if let Record::Message { header, data } = mcap::parse_record(opcode, data).ok()? {
                    out.push(Recovered {
                        channel: Arc::clone(summary.channels.get(&header.channel_id)?),
                        log_time: header.log_time,
                        publish_time: header.publish_time,
                        data: data.into_owned(),
                    });
                }
            }
        }
    }
    Some(out)
}
