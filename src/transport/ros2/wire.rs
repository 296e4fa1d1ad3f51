//! The serde mirror of `minflow_msgs/msg/ParticleFrame` that ros2-client serializes: plain
//! CDR little-endian whose body is byte-identical to [`cdr::encode`](crate::msgs::cdr::encode)
//! (tested here), converted from and to [`ParticleFrame`].

use serde::{Deserialize, Serialize};

use crate::msgs::{Header, ParticleFrame, Time};

/// serde mirror of `builtin_interfaces/Time`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct WireTime {
    sec: i32,
    nanosec: u32,
}

/// serde mirror of `std_msgs/Header`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct WireHeader {
    stamp: WireTime,
    frame_id: String,
}

/// serde mirror of `minflow_msgs/msg/ParticleFrame`, fields in `.msg` order. Serialized by a
/// CDR serializer it gives exactly [`cdr::encode`]'s body: structs add no padding, strings
/// are length (with NUL) + bytes + NUL, sequences are a u32 count + elements, each primitive
/// aligned to its size. `material` stays a plain sequence of u8 (not `serialize_bytes`, which
/// cdr-encoding 0.10, used by ros2-client's zenoh backend, writes without the count).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(super) struct WireFrame {
    header: WireHeader,
    scene: String,
    frame_index: u32,
    dt: f32,
    position: Vec<f32>,
    velocity: Vec<f32>,
    material: Vec<u8>,
}

impl From<ParticleFrame> for WireFrame {
    fn from(f: ParticleFrame) -> Self {
        WireFrame {
            header: WireHeader {
                stamp: WireTime {
                    sec: f.header.stamp.sec,
                    nanosec: f.header.stamp.nanosec,
                },
                frame_id: f.header.frame_id,
            },
            scene: f.scene,
            frame_index: f.frame_index,
            dt: f.dt,
            position: f.position,
            velocity: f.velocity,
            material: f.material,
        }
    }
}

impl From<WireFrame> for ParticleFrame {
    fn from(w: WireFrame) -> Self {
        ParticleFrame {
            header: Header {
                stamp: Time {
                    sec: w.header.stamp.sec,
                    nanosec: w.header.stamp.nanosec,
                },
                frame_id: w.header.frame_id,
            },
            scene: w.scene,
            frame_index: w.frame_index,
            dt: w.dt,
            position: w.position,
            velocity: w.velocity,
            material: w.material,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::cdr;
    use ros2_client::dds::rustdds::no_key::SerializerAdapter;
    use ros2_client::dds::rustdds::serialization::deserialize_from_cdr_with_rep_id;
    use ros2_client::dds::rustdds::{CDRSerializerAdapter, RepresentationIdentifier};

    fn frame(n: usize, scene: &str) -> ParticleFrame {
        ParticleFrame {
            header: Header {
                stamp: Time {
                    sec: -3,
                    nanosec: 123_456_789,
                },
                frame_id: "world".into(),
            },
            scene: scene.into(),
            frame_index: 77,
            dt: 0.0025,
            position: (0..2 * n).map(|i| i as f32 * 0.001).collect(),
            velocity: (0..2 * n).map(|i| -(i as f32) * 0.5).collect(),
            material: (0..n).map(|i| (i % 4) as u8).collect(),
        }
    }

    /// The serializer ros2-client's DDS publisher uses (rustdds `CDRSerializerAdapter`,
    /// little-endian) gives cdr::encode's body; the encapsulation header is CDR_LE, options 0.
    #[test]
    fn serde_cdr_matches_encoder() {
        // Odd string lengths and particle counts exercise every alignment case.
        for (n, scene) in [(0, ""), (1, "a"), (3, "multi/rope+snow/007"), (2500, "ab")] {
            let f = frame(n, scene);
            let expected = cdr::encode(&f);
            let body = <CDRSerializerAdapter<WireFrame> as SerializerAdapter<WireFrame>>::to_bytes(
                &WireFrame::from(f.clone()),
            )
            .unwrap();
            assert_eq!(&expected[4..], &body[..], "n={n} scene={scene:?}");
            let rep =
                <CDRSerializerAdapter<WireFrame> as SerializerAdapter<WireFrame>>::output_encoding(
                );
            assert_eq!(rep, RepresentationIdentifier::CDR_LE);
            assert_eq!(rep.to_bytes(), [expected[0], expected[1]]);
            assert_eq!(&expected[2..4], &[0, 0]);

            let (back, _) = deserialize_from_cdr_with_rep_id::<WireFrame>(
                &expected[4..],
                RepresentationIdentifier::CDR_LE,
            )
            .unwrap();
            assert_eq!(ParticleFrame::from(back), f);
        }
    }

    #[test]
    fn truncated_cdr_is_an_error() {
        let bytes = cdr::encode(&frame(10, "s"));
        for cut in [0, 3, 9, 20, bytes.len() - 1] {
            let r = deserialize_from_cdr_with_rep_id::<WireFrame>(
                &bytes[4..cut.max(4)],
                RepresentationIdentifier::CDR_LE,
            );
            assert!(r.is_err(), "cut at {cut}");
        }
    }
}
