//! CDR encoding of `ParticleFrame`: exact bytes of a small known message built by hand from the
//! CDR rules, round trips of random messages, and malformed input (every truncation, random
//! bytes, corrupted bytes) giving errors rather than panics. Property tests (issue 16) over
//! random frames: a cut anywhere is an error, any number of flipped bytes and any value in any
//! length or count prefix never panic; the same for `SurrogateStatus`. Also the `ros2msg`
//! schema text.

use minflow::msgs::status::{decode_status, encode_status, SurrogateStatus};
use minflow::msgs::{self, CdrError, FrameError, Header, ParticleFrame, Time};
use proptest::prelude::*;

/// 2 particles, frame_id "world" (6 bytes with NUL, so 2 bytes of padding follow), scene "a/b".
fn small_frame() -> ParticleFrame {
    ParticleFrame {
        header: Header {
            stamp: Time {
                sec: 1,
                nanosec: 500_000_000,
            },
            frame_id: "world".into(),
        },
        scene: "a/b".into(),
        frame_index: 7,
        dt: 0.016,
        position: vec![0.25, 0.5, 0.75, 1.0],
        velocity: vec![-1.0, 2.0, 0.0, 0.5],
        material: vec![0, 3],
    }
}

/// The bytes of `small_frame()` by hand. Offsets in comments are from the first byte after the
/// encapsulation header, where CDR alignment is measured from.
fn small_frame_bytes_le() -> Vec<u8> {
    let mut b: Vec<u8> = Vec::new();
    b.extend([0x00, 0x01, 0x00, 0x00]); // encapsulation: CDR_LE, options 0
    b.extend([0x01, 0x00, 0x00, 0x00]); // @0  header.stamp.sec = 1 (int32)
    b.extend([0x00, 0x65, 0xcd, 0x1d]); // @4  header.stamp.nanosec = 500_000_000 (uint32)
    b.extend([0x06, 0x00, 0x00, 0x00]); // @8  header.frame_id length = 5 chars + NUL = 6
    b.extend(b"world\0"); //               @12 "world" + NUL, ends at @18
    b.extend([0x00, 0x00]); //             @18 padding to 4-byte alignment for the next uint32
    b.extend([0x04, 0x00, 0x00, 0x00]); // @20 scene length = 3 chars + NUL = 4
    b.extend(b"a/b\0"); //                 @24 "a/b" + NUL, ends at @28 (aligned, no padding)
    b.extend([0x07, 0x00, 0x00, 0x00]); // @28 frame_index = 7 (uint32)
    b.extend([0x6f, 0x12, 0x83, 0x3c]); // @32 dt = 0.016 (float32 0x3c83126f)
    b.extend([0x04, 0x00, 0x00, 0x00]); // @36 position count = 4 (2N)
    b.extend([0x00, 0x00, 0x80, 0x3e]); // @40 0.25
    b.extend([0x00, 0x00, 0x00, 0x3f]); // @44 0.5
    b.extend([0x00, 0x00, 0x40, 0x3f]); // @48 0.75
    b.extend([0x00, 0x00, 0x80, 0x3f]); // @52 1.0
    b.extend([0x04, 0x00, 0x00, 0x00]); // @56 velocity count = 4 (2N)
    b.extend([0x00, 0x00, 0x80, 0xbf]); // @60 -1.0
    b.extend([0x00, 0x00, 0x00, 0x40]); // @64 2.0
    b.extend([0x00, 0x00, 0x00, 0x00]); // @68 0.0
    b.extend([0x00, 0x00, 0x00, 0x3f]); // @72 0.5
    b.extend([0x02, 0x00, 0x00, 0x00]); // @76 material count = 2 (N)
    b.extend([0x00, 0x03]); //             @80 liquid, rope; message ends at @82, no end padding
    b
}

#[test]
fn known_message_bytes_match_hand_built_cdr() {
    let bytes = msgs::encode(&small_frame());
    assert_eq!(bytes, small_frame_bytes_le());
    assert_eq!(msgs::decode(&bytes), Ok(small_frame()));
}

#[test]
fn empty_string_is_length_one_and_padding_is_three_bytes() {
    let mut frame = small_frame();
    frame.header.frame_id.clear();
    let bytes = msgs::encode(&frame);
    // @8 length 1, @12 NUL, @13..16 three bytes of padding, @16 scene length.
    assert_eq!(&bytes[12..20], &[1, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(&bytes[20..24], &[4, 0, 0, 0]);
    assert_eq!(msgs::decode(&bytes), Ok(frame));
}

#[test]
fn big_endian_and_end_padding_are_accepted() {
    // The same message big-endian: swap every 4-byte word except strings and the uint8s.
    let le = small_frame_bytes_le();
    let mut be = vec![0x00, 0x00, 0x00, 0x00];
    let body = &le[4..];
    let words_at = [
        0, 4, 8, 20, 28, 32, 36, 40, 44, 48, 52, 56, 60, 64, 68, 72, 76,
    ];
    let mut i = 0;
    while i < body.len() {
        if words_at.contains(&i) {
            be.extend(body[i..i + 4].iter().rev());
            i += 4;
        } else {
            be.push(body[i]);
            i += 1;
        }
    }
    assert_eq!(msgs::decode(&be), Ok(small_frame()));
    // rmw_cyclonedds pads the serialized message to a multiple of 4.
    let mut padded = le.clone();
    padded.extend([0, 0]);
    assert_eq!(msgs::decode(&padded), Ok(small_frame()));
}

#[test]
fn malformed_messages_give_errors_naming_field_and_offset() {
    let good = small_frame_bytes_le();
    let mut bad = good.clone();
    bad[1] = 0x07; // XCDR2 little-endian
    assert_eq!(
        msgs::decode(&bad),
        Err(CdrError::Encapsulation { kind: 0x0007 })
    );
    let mut bad = good.clone();
    bad[4 + 12] = 0xff; // first byte of "world": not UTF-8
    let err = msgs::decode(&bad).unwrap_err();
    assert_eq!(
        err,
        CdrError::NotUtf8 {
            field: "header.frame_id",
            offset: 16
        }
    );
    let mut bad = good.clone();
    bad[4 + 17] = b'!'; // the NUL of "world"
    assert!(matches!(
        msgs::decode(&bad),
        Err(CdrError::MissingNul { offset: 16, .. })
    ));
    let mut bad = good.clone();
    bad[4 + 36..4 + 40].copy_from_slice(&u32::MAX.to_le_bytes()); // position count
    let err = msgs::decode(&bad).unwrap_err();
    assert!(matches!(
        err,
        CdrError::LengthPastEnd {
            field: "position",
            offset: 40,
            ..
        }
    ));
    assert!(err.to_string().contains("position") && err.to_string().contains("offset 40"));
    let mut bad = good.clone();
    bad.extend([0; 4]);
    assert!(matches!(
        msgs::decode(&bad),
        Err(CdrError::TrailingBytes {
            offset: 86,
            count: 4
        })
    ));
}

#[test]
fn every_truncation_is_an_error() {
    let bytes = msgs::encode(&small_frame());
    for cut in 0..bytes.len() {
        let result = msgs::decode(&bytes[..cut]);
        assert!(result.is_err(), "prefix of {cut} bytes decoded: {result:?}");
    }
}

#[test]
fn schema_text_is_msg_files_joined_rosbag2_style() {
    let rule = "=".repeat(80);
    let expected = format!(
        "{}\n{rule}\nMSG: std_msgs/Header\n{}\n{rule}\nMSG: builtin_interfaces/Time\n{}",
        msgs::PARTICLE_FRAME_MSG,
        msgs::HEADER_MSG,
        msgs::TIME_MSG
    );
    assert_eq!(msgs::schema_text(), expected);
    assert!(msgs::PARTICLE_FRAME_MSG.contains("uint8[] material"));
    assert!(msgs::TIME_MSG.contains("uint32 nanosec"));
}

#[test]
fn validate_names_the_problem() {
    assert_eq!(small_frame().validate(), Ok(()));
    let mut f = small_frame();
    f.velocity.pop();
    assert!(matches!(
        f.validate(),
        Err(FrameError::Length {
            field: "velocity",
            found: 3,
            expected: 4,
            ..
        })
    ));
    let mut f = small_frame();
    f.position[3] = f32::NAN;
    assert!(matches!(
        f.validate(),
        Err(FrameError::NotFinite {
            field: "position",
            index: 3,
            ..
        })
    ));
    let mut f = small_frame();
    f.material[1] = 4;
    assert!(matches!(
        f.validate(),
        Err(FrameError::UnknownMaterial { index: 1, value: 4 })
    ));
}

#[test]
fn time_conversions() {
    let t = Time::from_nanos(1_500_000_001);
    assert_eq!((t.sec, t.nanosec), (1, 500_000_001));
    assert_eq!(t.as_nanos(), 1_500_000_001);
    assert_eq!(
        Time::from_secs_f64(0.016),
        Time {
            sec: 0,
            nanosec: 16_000_000
        }
    );
    assert_eq!(
        Time::from_secs_f64(-0.25),
        Time {
            sec: -1,
            nanosec: 750_000_000
        }
    );
    assert_eq!(
        Time {
            sec: -1,
            nanosec: 750_000_000
        }
        .as_nanos(),
        -250_000_000
    );
    assert_eq!(Time::from_secs_f64(f64::NAN), Time::default());
}

fn arb_frame() -> impl Strategy<Value = ParticleFrame> {
    (
        0usize..40,
        any::<(i32, u32, u32)>(),
        ".{0,12}",
        "\\PC{0,20}",
        any::<f32>(),
    )
        .prop_flat_map(|(n, (sec, nanosec, frame_index), frame_id, scene, dt)| {
            (
                prop::collection::vec(any::<f32>(), 2 * n),
                prop::collection::vec(any::<f32>(), 2 * n),
                prop::collection::vec(0u8..4, n),
            )
                .prop_map(move |(position, velocity, material)| ParticleFrame {
                    header: Header {
                        stamp: Time { sec, nanosec },
                        frame_id: frame_id.clone(),
                    },
                    scene: scene.clone(),
                    frame_index,
                    dt,
                    position,
                    velocity,
                    material,
                })
        })
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

proptest! {
    #[test]
    fn round_trip(frame in arb_frame()) {
        let bytes = msgs::encode(&frame);
        let back = msgs::decode(&bytes).expect("decodes");
        // Compare floats by bits so NaN payloads count too.
        prop_assert_eq!(bits(&back.position), bits(&frame.position));
        prop_assert_eq!(bits(&back.velocity), bits(&frame.velocity));
        prop_assert_eq!(back.dt.to_bits(), frame.dt.to_bits());
        prop_assert_eq!(&back.header, &frame.header);
        prop_assert_eq!(&back.scene, &frame.scene);
        prop_assert_eq!(back.frame_index, frame.frame_index);
        prop_assert_eq!(&back.material, &frame.material);
        // A sharded node's decoder reads only the scene.
        prop_assert_eq!(msgs::cdr::scene_of(&bytes), Ok(frame.scene.as_str()));
        prop_assert_eq!(msgs::encode(&back), bytes);
    }

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..200)) {
        let _ = msgs::decode(&bytes);
        let mut with_header = vec![0, 1, 0, 0];
        with_header.extend(&bytes);
        let _ = msgs::decode(&with_header);
    }

    #[test]
    fn corrupted_messages_never_panic(frame in arb_frame(), at in any::<usize>(), byte in any::<u8>()) {
        let mut bytes = msgs::encode(&frame);
        let i = at % bytes.len();
        bytes[i] = byte;
        let _ = msgs::decode(&bytes);
        let _ = msgs::cdr::scene_of(&bytes);
    }

    #[test]
    fn a_frame_cut_before_its_scene_ends_has_no_scene(frame in arb_frame(), at in any::<usize>()) {
        let bytes = msgs::encode(&frame);
        // The scene's NUL is the last byte it needs: 4 (encapsulation) + 8 (stamp) + the frame
        // id's length prefix, text and padding + the scene's prefix and text.
        let id = frame.header.frame_id.len() + 1;
        let scene_end = 4 + 8 + 4 + id + (4 - id % 4) % 4 + 4 + frame.scene.len() + 1;
        let cut = at % scene_end;
        prop_assert!(msgs::cdr::scene_of(&bytes[..cut]).is_err());
    }
}

/// Buffer offsets (encapsulation header included) of the five length prefixes of `frame`'s
/// encoding: header.frame_id, scene, position, velocity, material.
fn length_offsets(frame: &ParticleFrame) -> [usize; 5] {
    let align = |x: usize| x.div_ceil(4) * 4;
    let n2 = 4 * frame.position.len();
    let frame_id = 8;
    let scene = align(frame_id + 4 + frame.header.frame_id.len() + 1);
    let position = align(scene + 4 + frame.scene.len() + 1) + 8;
    let velocity = position + 4 + n2;
    let material = velocity + 4 + 4 * frame.velocity.len();
    [frame_id, scene, position, velocity, material].map(|at| at + 4)
}

fn arb_status() -> impl Strategy<Value = SurrogateStatus> {
    (
        any::<(i32, u32)>(),
        "\\PC{0,12}",
        any::<[u64; 6]>(),
        any::<u32>(),
        "\\PC{0,40}",
        any::<(u64, u64, u32)>(),
    )
        .prop_map(
            |((sec, nanosec), node, c, active_scenes, last_error, b)| SurrogateStatus {
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
                calls: b.0,
                batched: b.1,
                batch_max: b.2,
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    /// A message cut anywhere short of its end is an error, never a panic or a shorter frame.
    #[test]
    fn a_cut_message_is_an_error(frame in arb_frame(), cut in any::<prop::sample::Index>()) {
        let bytes = msgs::encode(&frame);
        let len = cut.index(bytes.len());
        let result = msgs::decode(&bytes[..len]);
        prop_assert!(result.is_err(), "a cut at {} of {} bytes decoded", len, bytes.len());
    }

    /// Up to 8 bytes flipped anywhere: an error or a frame, never a panic; a frame that
    /// decodes can be validated and encoded again.
    #[test]
    fn flipped_bytes_never_panic(
        frame in arb_frame(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..8),
    ) {
        let mut bytes = msgs::encode(&frame);
        for (at, mask) in &flips {
            let i = at.index(bytes.len());
            bytes[i] ^= mask;
        }
        if let Ok(back) = msgs::decode(&bytes) {
            let _ = back.validate();
            let _ = msgs::encode(&back);
        }
    }

    /// Any value in any string length or sequence count (0, small, huge, u32::MAX): never a
    /// panic nor an allocation of the claimed size; the written value decodes the frame.
    #[test]
    fn any_length_prefix_never_panics(
        frame in arb_frame(),
        which in 0usize..5,
        value in prop_oneof![any::<u32>(), 0u32..64, (u32::MAX - 8)..=u32::MAX, Just(u32::MAX / 4 + 1)],
    ) {
        let mut bytes = msgs::encode(&frame);
        let at = length_offsets(&frame)[which];
        let original = u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        let lengths = [
            frame.header.frame_id.len() + 1,
            frame.scene.len() + 1,
            frame.position.len(),
            frame.velocity.len(),
            frame.material.len(),
        ];
        prop_assert_eq!(original as usize, lengths[which], "not a length prefix at {}", at);
        bytes[at..at + 4].copy_from_slice(&value.to_le_bytes());
        let result = msgs::decode(&bytes);
        if value == original {
            let back = result.expect("the written length decodes");
            prop_assert_eq!(msgs::encode(&back), msgs::encode(&frame));
        }
    }

    /// `SurrogateStatus` (decoded from live payloads by a status subscriber): round trip,
    /// every cut an error, flips and random bytes never a panic.
    #[test]
    fn status_decoding_never_panics(
        status in arb_status(),
        cut in any::<prop::sample::Index>(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), 1u8..=255), 1..6),
        noise in prop::collection::vec(any::<u8>(), 0..120),
    ) {
        let bytes = encode_status(&status);
        prop_assert_eq!(decode_status(&bytes), Ok(status.clone()));
        let len = cut.index(bytes.len());
        // One cut decodes: at the end of an older node's message (before the batching
        // fields), which reads them as 0.
        if let Ok(older) = decode_status(&bytes[..len]) {
            let want = SurrogateStatus { calls: 0, batched: 0, batch_max: 0, ..status.clone() };
            prop_assert_eq!(older, want, "a cut at {} decoded", len);
        }
        let mut flipped = bytes.clone();
        for (at, mask) in &flips {
            let i = at.index(flipped.len());
            flipped[i] ^= mask;
        }
        let _ = decode_status(&flipped);
        let _ = decode_status(&noise);
        let _ = decode_status(&[&[0, 1, 0, 0][..], &noise].concat());
    }
}
