//! A [`ParticleFrame`] as `sensor_msgs/msg/PointCloud2`, the message RViz's PointCloud2
//! display shows (`--pointcloud2 TOPIC` on `replay`, `node` and `simulate --publish`;
//! docs/ros2.md).
//!
//! One point per particle, unordered (`height` 1, `width` N), little-endian, dense, 16 bytes a
//! point: `x`, `y` (float32, domain units, the particle's position), `z` (float32, always 0)
//! and `rgb` (float32 at offset 12), the colour by material packed as PCL packs it: the
//! 32-bit word `0x00RRGGBB` stored as the bits of a float32 (so the bytes are `B G R 0`),
//! which RViz's "RGB8" colour transformer unpacks. Colours are the one palette of
//! [`crate::material`], as in the Foxglove view and `eval`'s renders. The header is the
//! frame's (stamp = simulation time, `frame_id` as published, "world" in minflow's bags).
//!
//! The `.msg` definitions (`msgs/sensor_msgs/`, verbatim from `sensor_msgs` 5.5) give the
//! REP-2016 type hash that the DDS endpoints announce ([`type_hash`]).

use serde::{Deserialize, Serialize};

use super::{ParticleFrame, Time};
use crate::material;

/// Full ROS 2 type name of [`PointCloud2`].
pub const TYPE_NAME: &str = "sensor_msgs/msg/PointCloud2";
/// `msgs/sensor_msgs/PointCloud2.msg`, verbatim.
pub const POINT_CLOUD2_MSG: &str = include_str!("../../msgs/sensor_msgs/PointCloud2.msg");
/// `msgs/sensor_msgs/PointField.msg`, verbatim.
pub const POINT_FIELD_MSG: &str = include_str!("../../msgs/sensor_msgs/PointField.msg");
/// Bytes per point: x, y, z, rgb, four float32s.
pub const POINT_STEP: u32 = 16;
/// `sensor_msgs/msg/PointField` datatype of a float32.
pub const FLOAT32: u8 = 7;

/// serde mirror of `builtin_interfaces/Time` (field order of the `.msg`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CloudTime {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, `0..1e9`.
    pub nanosec: u32,
}

/// serde mirror of `std_msgs/Header`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CloudHeader {
    /// Time of the data (here: the frame's simulation time).
    pub stamp: CloudTime,
    /// Coordinate frame of the points.
    pub frame_id: String,
}

/// `sensor_msgs/msg/PointField`: one named field of a point.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointField {
    /// Field name (`x`, `y`, `z`, `rgb`).
    pub name: String,
    /// Byte offset within a point.
    pub offset: u32,
    /// Element type (7 = float32).
    pub datatype: u8,
    /// Elements in the field.
    pub count: u32,
}

/// `sensor_msgs/msg/PointCloud2`, fields in `.msg` order, ready for a CDR serializer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PointCloud2 {
    /// Stamp and frame.
    pub header: CloudHeader,
    /// Rows (1: unordered).
    pub height: u32,
    /// Points per row (N particles).
    pub width: u32,
    /// The point layout.
    pub fields: Vec<PointField>,
    /// Always false: little-endian.
    pub is_bigendian: bool,
    /// Bytes per point ([`POINT_STEP`]).
    pub point_step: u32,
    /// Bytes per row (`point_step * width`).
    pub row_step: u32,
    /// The points, `row_step * height` bytes.
    pub data: Vec<u8>,
    /// True: no NaN or infinite points (frames are validated before publishing).
    pub is_dense: bool,
}

/// The four float32 fields of a point: x, y, z, rgb.
pub fn fields() -> Vec<PointField> {
    ["x", "y", "z", "rgb"]
        .iter()
        .zip((0u32..).step_by(4))
        .map(|(name, offset)| PointField {
            name: (*name).to_owned(),
            offset,
            datatype: FLOAT32,
            count: 1,
        })
        .collect()
}

/// The PCL packing of a colour: `0x00RRGGBB` as the bits of a float32, little-endian bytes.
pub fn packed_rgb(rgb: [u8; 3]) -> [u8; 4] {
    let word = (u32::from(rgb[0]) << 16) | (u32::from(rgb[1]) << 8) | u32::from(rgb[2]);
    f32::from_bits(word).to_le_bytes()
}

impl PointCloud2 {
    /// The cloud of `frame`: one point per particle (as many as both `position` and
    /// `material` describe), coloured by material.
    pub fn from_frame(frame: &ParticleFrame) -> Self {
        let n = (frame.position.len() / 2).min(frame.material.len());
        let mut data = Vec::with_capacity(n * POINT_STEP as usize);
        for i in 0..n {
            data.extend_from_slice(&frame.position[2 * i].to_le_bytes());
            data.extend_from_slice(&frame.position[2 * i + 1].to_le_bytes());
            data.extend_from_slice(&0f32.to_le_bytes());
            data.extend_from_slice(&packed_rgb(material::colour_of(frame.material[i])));
        }
        let Time { sec, nanosec } = frame.header.stamp;
        let width = n as u32;
        PointCloud2 {
            header: CloudHeader {
                stamp: CloudTime { sec, nanosec },
                frame_id: frame.header.frame_id.clone(),
            },
            height: 1,
            width,
            fields: fields(),
            is_bigendian: false,
            point_step: POINT_STEP,
            row_step: POINT_STEP * width,
            data,
            is_dense: true,
        }
    }
}

/// The RIHS01 type hash of `sensor_msgs/msg/PointCloud2`, from the `.msg` files.
///
/// # Errors
/// Never for the shipped definitions (a unit test computes it); the error type is
/// [`super::type_hash::rihs01`]'s.
pub fn type_hash() -> Result<String, super::type_hash::TypeHashError> {
    super::type_hash::rihs01(
        TYPE_NAME,
        &[
            (TYPE_NAME, POINT_CLOUD2_MSG),
            ("sensor_msgs/msg/PointField", POINT_FIELD_MSG),
            ("std_msgs/msg/Header", super::HEADER_MSG),
            ("builtin_interfaces/msg/Time", super::TIME_MSG),
        ],
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::Header;

    fn frame() -> ParticleFrame {
        ParticleFrame {
            header: Header {
                stamp: Time { sec: 2, nanosec: 5 },
                frame_id: "world".into(),
            },
            scene: "s".into(),
            frame_index: 0,
            dt: 0.016,
            position: vec![0.25, 0.5, 0.75, 1.0],
            velocity: vec![0.0; 4],
            material: vec![0, 3],
        }
    }

    #[test]
    fn points_carry_xy_zero_z_and_pcl_rgb() {
        let cloud = PointCloud2::from_frame(&frame());
        assert_eq!((cloud.height, cloud.width, cloud.row_step), (1, 2, 32));
        assert_eq!(cloud.data.len(), 32);
        let f = |at: usize| f32::from_le_bytes(cloud.data[at..at + 4].try_into().unwrap());
        assert_eq!((f(0), f(4), f(8)), (0.25, 0.5, 0.0));
        assert_eq!((f(16), f(20), f(24)), (0.75, 1.0, 0.0));
        // Liquid [40, 120, 255] -> 0x002878ff -> bytes ff 78 28 00; rope [240, 160, 40].
        assert_eq!(&cloud.data[12..16], &[255, 120, 40, 0]);
        assert_eq!(&cloud.data[28..32], &[40, 160, 240, 0]);
        let names: Vec<_> = cloud
            .fields
            .iter()
            .map(|f| (f.name.as_str(), f.offset))
            .collect();
        assert_eq!(names, [("x", 0), ("y", 4), ("z", 8), ("rgb", 12)]);
        assert_eq!(cloud.header.frame_id, "world");
        assert_eq!((cloud.header.stamp.sec, cloud.header.stamp.nanosec), (2, 5));
    }

    /// The hash rosidl computes for sensor_msgs 5.5 (`share/sensor_msgs/msg/PointCloud2.json`
    /// of the ROS 2 Kilted wheels).
    #[test]
    fn type_hash_is_rosidls() {
        assert_eq!(
            type_hash().unwrap(),
            "RIHS01_9198cabf7da3796ae6fe19c4cb3bdd3525492988c70522628af5daa124bae2b5"
        );
    }
}
