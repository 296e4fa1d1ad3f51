//! `ParticleFrame` -> `foxglove.PointCloud` (protobuf, Foxglove's published schema): one
//! point per particle with its position (x, y in domain units, z = 0), a colour (by
//! material, or for a prediction by its position error against the ground truth) and the
//! raw values as fields Foxglove's 3D panel can colour by itself (`material`, `error`).
//! Used by the live view ([`super::live`]) of `replay`, `node` and `simulate --publish`, and
//! by `record --points` ([`WritePoints`]).
//!
//! Point layout (little-endian, [`POINT_STRIDE`] bytes): `x` f32 @0, `y` f32 @4, `z` f32 @8,
//! `error` f32 @12 (domain units; 0 when not known), `red` `green` `blue` `alpha` u8
//! @16..20, `material` u8 @20, three bytes of padding.

use foxglove::bytes::Bytes;
use foxglove::messages::packed_element_field::NumericType;
use foxglove::messages::{PackedElementField, PointCloud, Timestamp};

use crate::bag::{BagError, BagWriter, ForeignSchema};
use crate::msgs::ParticleFrame;

/// Bytes per point in [`PointCloud::data`].
pub const POINT_STRIDE: u32 = 24;

/// A position error at or above this (domain units, 1 % of the unit square) is drawn
/// fully red; 0 is green, half of it yellow.
pub const ERROR_FULL_SCALE: f32 = 0.01;

/// RGBA colour of a material id: its [`crate::material`] colour, opaque (unknown ids grey).
pub fn material_colour(material: u8) -> [u8; 4] {
    let [r, g, b] = crate::material::colour_of(material);
    [r, g, b, 255]
}

/// RGBA colour of a position error (domain units): green at 0, yellow at half of
/// [`ERROR_FULL_SCALE`], red at and above it. NaN is drawn red.
pub fn error_colour(error: f32) -> [u8; 4] {
    let t = if error.is_nan() {
        1.0
    } else {
        (error / ERROR_FULL_SCALE).clamp(0.0, 1.0)
    };
    let red = (2.0 * t).min(1.0);
    let green = (2.0 * (1.0 - t)).min(1.0);
    [(red * 255.0) as u8, (green * 255.0) as u8, 0, 255]
}

/// Per-particle Euclidean position error of `predicted` against `truth` (domain units);
/// None when the two frames do not hold the same number of particles.
pub fn position_errors(predicted: &ParticleFrame, truth: &ParticleFrame) -> Option<Vec<f32>> {
    if predicted.position.len() != truth.position.len() {
        return None;
    }
    Some(
        predicted
            .position
            .chunks_exact(2)
            .zip(truth.position.chunks_exact(2))
            .map(|(p, t)| ((p[0] - t[0]).powi(2) + (p[1] - t[1]).powi(2)).sqrt())
            .collect(),
    )
}

/// The frame as a point cloud coloured by material.
pub fn by_material(frame: &ParticleFrame) -> PointCloud {
    build(frame, None)
}

/// Point clouds in a bag (`record --points`): each frame as a `foxglove.PointCloud` coloured
/// by material, beside the frames, for Foxglove's 3D panel. Implemented here, not in `bag`:
/// storage knows no visualisation.
pub trait WritePoints {
    /// Writes `frame` as a `foxglove.PointCloud` (protobuf, Foxglove's schema; coloured by
    /// material) on `topic` at `stamp_ns` (log and publish time). The frame is not checked.
    ///
    /// # Errors
    /// Writing the bag fails ([`BagError::Mcap`]).
    fn write_points(
        &mut self,
        topic: &str,
        stamp_ns: u64,
        frame: &ParticleFrame,
    ) -> Result<(), BagError>;
}

impl WritePoints for BagWriter {
    fn write_points(
        &mut self,
        topic: &str,
        stamp_ns: u64,
        frame: &ParticleFrame,
    ) -> Result<(), BagError> {
        let schema = <PointCloud as foxglove::Encode>::get_schema()
            .expect("foxglove.PointCloud has a schema");
        let mut bytes = Vec::new();
        // Into a Vec, which grows: encoding cannot run out of room.
        let _ = foxglove::Encode::encode(&by_material(frame), &mut bytes);
        let schema = ForeignSchema {
            name: &schema.name,
            encoding: &schema.encoding,
            data: &schema.data,
            message_encoding: "protobuf",
        };
        self.write_foreign(topic, stamp_ns, &schema, &bytes)
    }
}

/// The predicted frame as a point cloud coloured by its position error against `truth`
/// (the ground-truth frame of the same scene and index); by material when the particle
/// counts differ.
pub fn by_error(predicted: &ParticleFrame, truth: &ParticleFrame) -> PointCloud {
    build(predicted, position_errors(predicted, truth).as_deref())
}

/// The cloud of `frame`, coloured by `errors` when given (one per particle), else by
/// material. Frame id "world", timestamp the frame's stamp (none before zero).
fn build(frame: &ParticleFrame, errors: Option<&[f32]>) -> PointCloud {
    let n = frame.len().min(frame.position.len() / 2);
    let mut data = Vec::with_capacity(n * POINT_STRIDE as usize);
    for i in 0..n {
        let material = frame.material[i];
        let error = errors.map_or(0.0, |e| e[i]);
        let colour = match errors {
            Some(_) => error_colour(error),
            None => material_colour(material),
        };
        data.extend_from_slice(&frame.position[2 * i].to_le_bytes());
        data.extend_from_slice(&frame.position[2 * i + 1].to_le_bytes());
        data.extend_from_slice(&0f32.to_le_bytes());
        data.extend_from_slice(&error.to_le_bytes());
        data.extend_from_slice(&colour);
        data.extend_from_slice(&[material, 0, 0, 0]);
    }
    let stamp = &frame.header.stamp;
    PointCloud {
        timestamp: u32::try_from(stamp.sec)
            .ok()
            .and_then(|sec| Timestamp::new_checked(sec, stamp.nanosec)),
        frame_id: "world".to_owned(),
        pose: None,
        point_stride: POINT_STRIDE,
        fields: fields(),
        data: Bytes::from(data),
    }
}

/// The field table of the point layout in the module doc.
fn fields() -> Vec<PackedElementField> {
    let field = |name: &str, offset: u32, kind: NumericType| PackedElementField {
        name: name.to_owned(),
        offset,
        r#type: kind as i32,
    };
    vec![
        field("x", 0, NumericType::Float32),
        field("y", 4, NumericType::Float32),
        field("z", 8, NumericType::Float32),
        field("error", 12, NumericType::Float32),
        field("red", 16, NumericType::Uint8),
        field("green", 17, NumericType::Uint8),
        field("blue", 18, NumericType::Uint8),
        field("alpha", 19, NumericType::Uint8),
        field("material", 20, NumericType::Uint8),
    ]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgs::{Header, Time};

    fn frame(position: Vec<f32>, material: Vec<u8>) -> ParticleFrame {
        ParticleFrame {
            header: Header {
                stamp: Time { sec: 2, nanosec: 5 },
                frame_id: "world".into(),
            },
            scene: "s".into(),
            frame_index: 3,
            dt: 0.016,
            velocity: vec![0.0; position.len()],
            position,
            material,
        }
    }

    #[test]
    fn points_carry_position_and_material_colour() {
        let cloud = by_material(&frame(vec![0.25, 0.5, 0.75, 1.0], vec![0, 3]));
        assert_eq!(cloud.data.len(), 2 * POINT_STRIDE as usize);
        let p1 = &cloud.data[POINT_STRIDE as usize..];
        assert_eq!(f32::from_le_bytes(p1[0..4].try_into().unwrap()), 0.75);
        assert_eq!(f32::from_le_bytes(p1[4..8].try_into().unwrap()), 1.0);
        assert_eq!(&p1[16..20], &material_colour(3));
        assert_eq!(p1[20], 3);
        assert_eq!(cloud.timestamp, Some(Timestamp::new(2, 5)));
    }

    #[test]
    fn prediction_is_coloured_by_its_error() {
        // Particle 0 is exact (green), particle 1 is off by 0.03 - 0.0 = 3 x full scale (red).
        let truth = frame(vec![0.1, 0.1, 0.5, 0.5], vec![1, 1]);
        let predicted = frame(vec![0.1, 0.1, 0.5, 0.53], vec![1, 1]);
        let cloud = by_error(&predicted, &truth);
        let s = POINT_STRIDE as usize;
        assert_eq!(&cloud.data[16..20], &[0, 255, 0, 255]);
        assert_eq!(&cloud.data[s + 16..s + 20], &[255, 0, 0, 255]);
        let e1 = f32::from_le_bytes(cloud.data[s + 12..s + 16].try_into().unwrap());
        assert!((e1 - 0.03).abs() < 1e-6, "{e1}");
        assert_eq!(error_colour(ERROR_FULL_SCALE / 2.0), [255, 255, 0, 255]);
    }
}
