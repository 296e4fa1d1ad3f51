//! CDR (XCDR1, "plain CDR") encoding of [`ParticleFrame`], byte-identical to what a ROS 2 node
//! on rmw_fastrtps or rmw_cyclonedds sends and what rosbag2 stores in a bag.
//!
//! Layout: a 4-byte encapsulation header `00 01 00 00` (CDR little-endian; `00 00` is
//! big-endian, accepted when decoding), then the fields in `.msg` order. Each primitive is
//! aligned to its own size, measured from the first byte after the encapsulation header;
//! padding bytes are zero. A string is a `uint32` length that counts the NUL terminator, the
//! UTF-8 bytes and the NUL; a sequence is a `uint32` element count and the elements. No padding
//! follows the last field. Input/output: a frame (units as in [`crate::msgs`]) <-> bytes.
//! Decoding never panics: malformed input gives a [`CdrError`] naming the field and the byte
//! offset (from the start of the buffer, header included).

use super::{Header, ParticleFrame, Time};

/// Encapsulation header for CDR little-endian with no options.
pub const CDR_LE_HEADER: [u8; 4] = [0x00, 0x01, 0x00, 0x00];

/// Why bytes are not a CDR-encoded [`ParticleFrame`]. Offsets count from the buffer's first
/// byte (the encapsulation header included).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CdrError {
    /// Fewer than 4 bytes: no room for the encapsulation header.
    #[error("CDR: {len} bytes is too short for the 4-byte encapsulation header")]
    NoHeader {
        /// Buffer length.
        len: usize,
    },
    /// The encapsulation is not plain CDR (e.g. parameter lists or XCDR2).
    #[error(
        "CDR: unsupported encapsulation {kind:#06x} at byte 0 \
         (expected 0x0000 CDR_BE or 0x0001 CDR_LE)"
    )]
    Encapsulation {
        /// The representation identifier found.
        kind: u16,
    },
    /// The data ends inside a field (or inside its alignment padding).
    #[error("CDR: {field}: needs {needed} bytes at byte offset {offset}, only {available} left")]
    Truncated {
        /// Field being read.
        field: &'static str,
        /// Where the field (or its padding) starts.
        offset: usize,
        /// Bytes the field needs.
        needed: usize,
        /// Bytes left in the buffer.
        available: usize,
    },
    /// A string length or sequence count runs past the end of the data.
    #[error(
        "CDR: {field}: length {count} at byte offset {offset} runs past the end \
         ({available} bytes left)"
    )]
    LengthPastEnd {
        /// Field being read.
        field: &'static str,
        /// Where the length prefix starts.
        offset: usize,
        /// The length or count read.
        count: u32,
        /// Bytes left after the length prefix.
        available: usize,
    },
    /// A string's last byte is not the NUL terminator.
    #[error("CDR: {field}: string at byte offset {offset} is not NUL-terminated")]
    MissingNul {
        /// Field being read.
        field: &'static str,
        /// Where the string's bytes start.
        offset: usize,
    },
    /// A string's bytes are not UTF-8.
    #[error("CDR: {field}: string at byte offset {offset} is not valid UTF-8")]
    NotUtf8 {
        /// Field being read.
        field: &'static str,
        /// Where the string's bytes start.
        offset: usize,
    },
    /// More than 3 bytes (more than end padding) follow the last field.
    #[error("CDR: {count} unexpected bytes after the message, from byte offset {offset}")]
    TrailingBytes {
        /// Where the extra bytes start.
        offset: usize,
        /// How many there are.
        count: usize,
    },
}

/// Encodes `frame` as CDR little-endian with the encapsulation header.
pub fn encode(frame: &ParticleFrame) -> Vec<u8> {
    let mut out = Vec::new();
    encode_into(frame, &mut out);
    out
}

/// Encodes `frame` into `out`, replacing its contents (reuse `out` to avoid allocations).
pub fn encode_into(frame: &ParticleFrame, out: &mut Vec<u8>) {
    out.clear();
    out.reserve(
        64 + frame.header.frame_id.len()
            + frame.scene.len()
            + 4 * (frame.position.len() + frame.velocity.len())
            + frame.material.len(),
    );
    out.extend_from_slice(&CDR_LE_HEADER);
    let mut w = Writer { out };
    w.u32(frame.header.stamp.sec as u32);
    w.u32(frame.header.stamp.nanosec);
    w.string(&frame.header.frame_id);
    w.string(&frame.scene);
    w.u32(frame.frame_index);
    w.u32(frame.dt.to_bits());
    w.f32s(&frame.position);
    w.f32s(&frame.velocity);
    w.u32(frame.material.len() as u32);
    w.out.extend_from_slice(&frame.material);
}

struct Writer<'a> {
    out: &'a mut Vec<u8>,
}

impl Writer<'_> {
    /// Pads with zeros to a multiple of 4, counted from the end of the encapsulation header.
    fn align4(&mut self) {
        let pad = (4 - (self.out.len() - 4) % 4) % 4;
        self.out.extend_from_slice(&[0u8; 3][..pad]);
    }

    fn u32(&mut self, v: u32) {
        self.align4();
        self.out.extend_from_slice(&v.to_le_bytes());
    }

    fn string(&mut self, s: &str) {
        self.u32(s.len() as u32 + 1);
        self.out.extend_from_slice(s.as_bytes());
        self.out.push(0);
    }

    fn f32s(&mut self, values: &[f32]) {
        self.u32(values.len() as u32);
        let start = self.out.len();
        self.out.resize(start + 4 * values.len(), 0);
        for (dst, v) in self.out[start..].chunks_exact_mut(4).zip(values) {
            dst.copy_from_slice(&v.to_le_bytes());
        }
    }
}

/// Decodes a CDR-encoded [`ParticleFrame`] (little- or big-endian). Does not validate the
/// frame's contents; see [`ParticleFrame::validate`].
pub fn decode(bytes: &[u8]) -> Result<ParticleFrame, CdrError> {
    let mut r = Reader::open(bytes)?;
    let body = r.body;
    let sec = r.u32("header.stamp.sec")? as i32;
    let nanosec = r.u32("header.stamp.nanosec")?;
    let frame_id = r.str("header.frame_id")?.to_owned();
    let scene = r.str("scene")?.to_owned();
    let frame_index = r.u32("frame_index")?;
    let dt = f32::from_bits(r.u32("dt")?);
    let position = r.f32s("position")?;
    let velocity = r.f32s("velocity")?;
    let material = r.bytes_seq("material")?.to_vec();
    let rest = body.len() - r.pos;
    if rest > 3 {
        return Err(CdrError::TrailingBytes {
            offset: r.pos + 4,
            count: rest,
        });
    }
    Ok(ParticleFrame {
        header: Header {
            stamp: Time { sec, nanosec },
            frame_id,
        },
        scene,
        frame_index,
        dt,
        position,
        velocity,
        material,
    })
}

/// The `scene` of a CDR-encoded [`ParticleFrame`], read without decoding the rest (its
/// header, stamp and frame id are skipped): what a sharded node needs to pass over the frames
/// of scenes another node owns.
///
/// # Errors
/// As [`decode`], for the fields up to `scene`.
pub fn scene_of(bytes: &[u8]) -> Result<&str, CdrError> {
    let mut r = Reader::open(bytes)?;
    r.u32("header.stamp.sec")?;
    r.u32("header.stamp.nanosec")?;
    r.str("header.frame_id")?;
    r.str("scene")
}

struct Reader<'a> {
    body: &'a [u8],
    pos: usize,
    big_endian: bool,
}

impl<'a> Reader<'a> {
    /// A reader of the body after `bytes`' 4-byte encapsulation header (CDR big- or
    /// little-endian).
    fn open(bytes: &'a [u8]) -> Result<Self, CdrError> {
        let Some((head, body)) = bytes.split_first_chunk::<4>() else {
            return Err(CdrError::NoHeader { len: bytes.len() });
        };
        let big_endian = match u16::from_be_bytes([head[0], head[1]]) {
            0x0000 => true,
            0x0001 => false,
            kind => return Err(CdrError::Encapsulation { kind }),
        };
        Ok(Reader {
            body,
            pos: 0,
            big_endian,
        })
    }

    fn left(&self) -> usize {
        self.body.len() - self.pos
    }

    /// Takes `n` bytes at the current position.
    fn take(&mut self, field: &'static str, n: usize) -> Result<&'a [u8], CdrError> {
        if n > self.left() {
            return Err(CdrError::Truncated {
                field,
                offset: self.pos + 4,
                needed: n,
                available: self.left(),
            });
        }
        let out = &self.body[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    fn u32(&mut self, field: &'static str) -> Result<u32, CdrError> {
        let start = self.pos;
        let pad = (4 - self.pos % 4) % 4;
        let raw = match self.take(field, pad + 4) {
            Ok(raw) => raw,
            Err(err) => {
                self.pos = start;
                return Err(err);
            }
        };
        let b = [raw[pad], raw[pad + 1], raw[pad + 2], raw[pad + 3]];
        Ok(if self.big_endian {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        })
    }

    /// Reads a `uint32` count and checks that `count * size` bytes follow.
    fn count(&mut self, field: &'static str, size: usize) -> Result<usize, CdrError> {
        let count = self.u32(field)?;
        let needed = (count as usize).checked_mul(size);
        match needed {
            Some(needed) if needed <= self.left() => Ok(count as usize),
            _ => Err(CdrError::LengthPastEnd {
                field,
                // The prefix started 4 bytes back; +4 for the encapsulation header.
                offset: self.pos,
                count,
                available: self.left(),
            }),
        }
    }

    fn str(&mut self, field: &'static str) -> Result<&'a str, CdrError> {
        let len = self.count(field, 1)?;
        let offset = self.pos + 4;
        let raw = self.take(field, len)?;
        // Fast-CDR reads a zero length as the empty string; accept it too.
        let Some((&last, text)) = raw.split_last() else {
            return Ok("");
        };
        if last != 0 {
            return Err(CdrError::MissingNul { field, offset });
        }
        std::str::from_utf8(text).map_err(|_| CdrError::NotUtf8 { field, offset })
    }

    fn bytes_seq(&mut self, field: &'static str) -> Result<&'a [u8], CdrError> {
        let n = self.count(field, 1)?;
        self.take(field, n)
    }

    fn f32s(&mut self, field: &'static str) -> Result<Vec<f32>, CdrError> {
        let n = self.count(field, 4)?;
        let raw = self.take(field, 4 * n)?;
        let words = raw.chunks_exact(4).map(|c| [c[0], c[1], c[2], c[3]]);
        Ok(if self.big_endian {
            words.map(f32::from_be_bytes).collect()
        } else {
            words.map(f32::from_le_bytes).collect()
        })
    }
}
