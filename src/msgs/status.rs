//! `minflow_msgs/msg/SurrogateStatus` (msgs/SurrogateStatus.msg): a surrogate node's
//! counters and last error, published once per second on `/surrogate/status`, with its CDR
//! encoding (XCDR1 little-endian, encapsulation header, 8-byte alignment for `uint64`,
//! byte-identical to a ROS 2 node's). Decoding never panics. The batching fields (`calls`,
//! `batched`, `batch_max`) come last: a message of an older node, which ends at
//! `last_error`, decodes with them 0, and an older reader stops before them.

use super::Time;

/// Full ROS 2 type name.
pub const STATUS_TYPE_NAME: &str = "minflow_msgs/msg/SurrogateStatus";
/// The `.msg` definition (single source of truth).
pub const STATUS_MSG: &str = include_str!("../../msgs/SurrogateStatus.msg");
/// Default topic.
pub const STATUS_TOPIC: &str = "/surrogate/status";

/// A surrogate node's health report. Counters are totals since the node started.
#[derive(Debug, Clone, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
pub struct SurrogateStatus {
    /// Wall-clock time of the report.
    pub stamp: Time,
    /// Node name.
    pub node: String,
    /// Frames that arrived on the input topic.
    pub received: u64,
    /// Frames predicted on.
    pub predicted: u64,
    /// Predicted frames sent.
    pub published: u64,
    /// Frames dropped from a full per-scene queue.
    pub dropped: u64,
    /// Payloads that are not decodable frames.
    pub malformed: u64,
    /// Decodable frames not predicted on (wrong N, non-finite values, unknown material).
    pub rejected: u64,
    /// Scenes with a hidden state now.
    pub active_scenes: u32,
    /// Most recent reason a frame was not predicted on, empty if none.
    pub last_error: String,
    /// Network calls made; each steps one or more scenes (dynamic batching).
    pub calls: u64,
    /// Scenes stepped by those calls.
    pub batched: u64,
    /// Most scenes stepped by one call.
    pub batch_max: u32,
}

impl SurrogateStatus {
    /// Mean scenes per network call (0 before the first call).
    pub fn batch_mean(&self) -> f64 {
        if self.calls == 0 {
            0.0
        } else {
            self.batched as f64 / self.calls as f64
        }
    }
}

/// Encodes `status` as CDR little-endian with the encapsulation header.
pub fn encode_status(status: &SurrogateStatus) -> Vec<u8> {
    let mut out = super::cdr::CDR_LE_HEADER.to_vec();
    let align = |out: &mut Vec<u8>, n: usize| {
        let pad = (n - (out.len() - 4) % n) % n;
        out.extend(std::iter::repeat_n(0u8, pad));
    };
    let string = |out: &mut Vec<u8>, s: &str| {
        align(out, 4);
        out.extend_from_slice(&(s.len() as u32 + 1).to_le_bytes());
        out.extend_from_slice(s.as_bytes());
        out.push(0);
    };
    out.extend_from_slice(&(status.stamp.sec as u32).to_le_bytes());
    out.extend_from_slice(&status.stamp.nanosec.to_le_bytes());
    string(&mut out, &status.node);
    for v in [
        status.received,
        status.predicted,
        status.published,
        status.dropped,
        status.malformed,
        status.rejected,
    ] {
        align(&mut out, 8);
        out.extend_from_slice(&v.to_le_bytes());
    }
    align(&mut out, 4);
    out.extend_from_slice(&status.active_scenes.to_le_bytes());
    string(&mut out, &status.last_error);
    for v in [status.calls, status.batched] {
        align(&mut out, 8);
        out.extend_from_slice(&v.to_le_bytes());
    }
    align(&mut out, 4);
    out.extend_from_slice(&status.batch_max.to_le_bytes());
    out
}

/// Why a `SurrogateStatus` message could not be decoded; each names the field.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StatusError {
    /// The encapsulation header is missing or is not CDR little-endian.
    #[error("not CDR little-endian")]
    NotCdrLe,
    /// The message ends inside this field.
    #[error("{field}: truncated")]
    Truncated {
        /// The field being read.
        field: &'static str,
    },
    /// A string field without its NUL terminator.
    #[error("{field}: no NUL terminator")]
    NoNul {
        /// The string field.
        field: &'static str,
    },
    /// A string field that is not UTF-8.
    #[error("{field}: {source}")]
    Utf8 {
        /// The string field.
        field: &'static str,
        /// Where the bytes stop being UTF-8.
        #[source]
        source: std::string::FromUtf8Error,
    },
}

/// Decodes a CDR little-endian `SurrogateStatus`.
///
/// # Errors
/// A [`StatusError`] naming the field that is missing or malformed.
pub fn decode_status(bytes: &[u8]) -> Result<SurrogateStatus, StatusError> {
    if bytes.len() < 4 || bytes[..2] != [0, 1] {
        return Err(StatusError::NotCdrLe);
    }
    let mut r = Reader {
        body: &bytes[4..],
        pos: 0,
    };
    let sec = r.u32("stamp.sec")? as i32;
    let nanosec = r.u32("stamp.nanosec")?;
    let node = r.string("node")?;
    let mut c = [0u64; 6];
    for (v, field) in c.iter_mut().zip([
        "received",
        "predicted",
        "published",
        "dropped",
        "malformed",
        "rejected",
    ]) {
        *v = r.u64(field)?;
    }
    let active_scenes = r.u32("active_scenes")?;
    let last_error = r.string("last_error")?;
    // An older node's message ends here (module doc).
    let (calls, batched, batch_max) = if r.pos < r.body.len() {
        (r.u64("calls")?, r.u64("batched")?, r.u32("batch_max")?)
    } else {
        (0, 0, 0)
    };
    Ok(SurrogateStatus {
        stamp: Time { sec, nanosec },
        node,
        received: c[0],
        predicted: c[1],
        published: c[2],
        dropped: c[3],
        malformed: c[4],
        rejected: c[5],
        active_scenes,
        last_error,
        calls,
        batched,
        batch_max,
    })
}

struct Reader<'a> {
    body: &'a [u8],
    pos: usize,
}

impl<'a> Reader<'a> {
    fn take(
        &mut self,
        n: usize,
        align: usize,
        field: &'static str,
    ) -> Result<&'a [u8], StatusError> {
        let start = self.pos.div_ceil(align) * align;
        let end = start
            .checked_add(n)
            .filter(|&e| e <= self.body.len())
            .ok_or(StatusError::Truncated { field })?;
        self.pos = end;
        Ok(&self.body[start..end])
    }

    fn u32(&mut self, field: &'static str) -> Result<u32, StatusError> {
        Ok(u32::from_le_bytes(
            self.take(4, 4, field)?.try_into().expect("4 bytes"),
        ))
    }

    fn u64(&mut self, field: &'static str) -> Result<u64, StatusError> {
        Ok(u64::from_le_bytes(
            self.take(8, 8, field)?.try_into().expect("8 bytes"),
        ))
    }

    fn string(&mut self, field: &'static str) -> Result<String, StatusError> {
        let len = self.u32(field)? as usize;
        let raw = self.take(len, 1, field)?;
        let text = raw.strip_suffix(&[0]).ok_or(StatusError::NoNul { field })?;
        String::from_utf8(text.to_vec()).map_err(|source| StatusError::Utf8 { field, source })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn status_round_trips_with_ros2_alignment() {
        let s = SurrogateStatus {
            stamp: Time { sec: 5, nanosec: 7 },
            node: "abc".into(),
            received: 1,
            predicted: 2,
            published: 3,
            dropped: 4,
            malformed: 5,
            rejected: 6,
            active_scenes: 2,
            last_error: "wrong N".into(),
            calls: 9,
            batched: 27,
            batch_max: 5,
        };
        let bytes = encode_status(&s);
        // stamp (8) + "abc\0" with length (8) = 16, already 8-aligned: first u64 at body 16.
        assert_eq!(&bytes[4 + 16..4 + 24], &1u64.to_le_bytes());
        assert_eq!(decode_status(&bytes).unwrap(), s);
        assert_eq!(
            decode_status(&bytes[..bytes.len() - 3]),
            Err(StatusError::Truncated { field: "batch_max" })
        );
        // An older node's message: ends after last_error; the batching fields read 0.
        // calls and batched (8 each; last_error ends 8-aligned at body 80) and batch_max (4).
        let old_len = bytes.len() - 20;
        let old = decode_status(&bytes[..old_len]).unwrap();
        assert_eq!((old.calls, old.batched, old.batch_max), (0, 0, 0));
        assert_eq!(old.last_error, "wrong N");
        assert_eq!(s.batch_mean(), 3.0);
        assert_eq!(decode_status(&[1, 0, 0, 0]), Err(StatusError::NotCdrLe));
        let mut odd = s.clone();
        odd.node = "ab".into(); // body 15 -> padded to 16
        assert_eq!(decode_status(&encode_status(&odd)).unwrap(), odd);
    }
}
