//! The shared-memory layout of a frame on iceoryx2: a slice of `#[repr(C)]` [`Particle`]s
//! with a `#[repr(C)]` [`FrameHeader`] user header (docs/design.md, "Topics and
//! transports"), and the conversions to and from [`ParticleFrame`].

use iceoryx2::prelude::*;

use super::KIND;
use crate::msgs::{Header, ParticleFrame, Time};
use crate::transport::TransportError;

/// Largest scene id that fits [`FrameHeader::scene`] (63 UTF-8 bytes + NUL).
pub const MAX_SCENE_BYTES: usize = 63;
/// One particle of a frame as it lies in shared memory: 20 bytes, no padding.
/// Units as in `ParticleFrame`: domain units and domain units per time unit.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("minflow::Particle")]
pub struct Particle {
    /// Position x.
    pub x: f32,
    /// Position y.
    pub y: f32,
    /// Velocity x.
    pub vx: f32,
    /// Velocity y.
    pub vy: f32,
    /// Material id: 0 liquid, 1 jelly, 2 snow, 3 rope.
    pub material: u32,
}

/// The per-sample user header: everything of a `ParticleFrame` but the particles.
/// `header.frame_id` is always `"world"` (docs/design.md, "Topics and transports") and is
/// not carried.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
#[type_name("minflow::FrameHeader")]
pub struct FrameHeader {
    /// Scene id, UTF-8, NUL-padded (at most 63 bytes).
    pub scene: [u8; 64],
    /// Frame number from the start of the scene.
    pub frame_index: u32,
    /// Seconds (simulation time units) between frames.
    pub dt: f32,
    /// Stamp, whole seconds.
    pub stamp_sec: i32,
    /// Stamp, nanoseconds part.
    pub stamp_nanosec: u32,
    /// Number of particles in the slice that follows.
    pub particle_count: u32,
}

impl Default for FrameHeader {
    fn default() -> Self {
        FrameHeader {
            scene: [0; 64],
            frame_index: 0,
            dt: 0.0,
            stamp_sec: 0,
            stamp_nanosec: 0,
            particle_count: 0,
        }
    }
}

impl FrameHeader {
    /// The header of `frame`.
    ///
    /// # Errors
    /// [`TransportError::Unrepresentable`] for a scene id longer than 63 bytes or one with a
    /// NUL byte, or a frame_id other than `"world"`.
    pub fn from_frame(frame: &ParticleFrame) -> Result<Self, TransportError> {
        let unrep = |reason: String| TransportError::Unrepresentable {
            transport: KIND,
            reason,
        };
        let scene = frame.scene.as_bytes();
        if scene.len() > MAX_SCENE_BYTES {
            return Err(unrep(format!(
                "scene id {:?} is {} bytes; at most {MAX_SCENE_BYTES} fit",
                frame.scene,
                scene.len()
            )));
        }
        if scene.contains(&0) {
            return Err(unrep(format!(
                "scene id {:?} contains a NUL byte",
                frame.scene
            )));
        }
        if frame.header.frame_id != "world" {
            return Err(unrep(format!(
                "frame_id {:?}: iceoryx2 frames are in \"world\"",
                frame.header.frame_id
            )));
        }
        let mut header = FrameHeader {
            frame_index: frame.frame_index,
            dt: frame.dt,
            stamp_sec: frame.header.stamp.sec,
            stamp_nanosec: frame.header.stamp.nanosec,
            particle_count: u32::try_from(frame.len())
                .map_err(|_| unrep("too many particles".into()))?,
            ..FrameHeader::default()
        };
        header.scene[..scene.len()].copy_from_slice(scene);
        Ok(header)
    }

    /// The scene id.
    ///
    /// # Errors
    /// [`SampleError::SceneUnterminated`] or [`SampleError::SceneUtf8`].
    pub fn scene(&self) -> Result<&str, SampleError> {
        let end = self
            .scene
            .iter()
            .position(|&b| b == 0)
            .ok_or(SampleError::SceneUnterminated)?;
        std::str::from_utf8(&self.scene[..end]).map_err(SampleError::SceneUtf8)
    }
}

/// Writes `frame`'s particles into `out` (same length as the frame).
pub fn write_particles(frame: &ParticleFrame, out: &mut [std::mem::MaybeUninit<Particle>]) {
    for (i, p) in out.iter_mut().enumerate() {
        p.write(Particle {
            x: frame.position[2 * i],
            y: frame.position[2 * i + 1],
            vx: frame.velocity[2 * i],
            vy: frame.velocity[2 * i + 1],
            material: u32::from(frame.material[i]),
        });
    }
}

/// Why a received sample is not a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SampleError {
    /// The header's particle count disagrees with the slice.
    #[error("header says {header} particles, sample carries {carried}")]
    Count {
        /// `particle_count` in the header.
        header: u32,
        /// Particles in the sample's slice.
        carried: usize,
    },
    /// The scene field has no NUL byte.
    #[error("scene id not NUL-terminated")]
    SceneUnterminated,
    /// The scene field is not UTF-8.
    #[error("scene id not UTF-8: {0}")]
    SceneUtf8(#[source] std::str::Utf8Error),
    /// A material id that does not fit the message's byte.
    #[error("material id {0} out of range")]
    Material(u32),
}

/// Rebuilds a `ParticleFrame` from a header and its particles.
///
/// # Errors
/// A [`SampleError`] if the header's count disagrees with the slice, the scene id is bad
/// or a material id does not fit a byte.
pub fn to_frame(
    header: &FrameHeader,
    particles: &[Particle],
) -> Result<ParticleFrame, SampleError> {
    if header.particle_count as usize != particles.len() {
        return Err(SampleError::Count {
            header: header.particle_count,
            carried: particles.len(),
        });
    }
    let mut position = Vec::with_capacity(2 * particles.len());
    let mut velocity = Vec::with_capacity(2 * particles.len());
    let mut material = Vec::with_capacity(particles.len());
    for p in particles {
        position.extend_from_slice(&[p.x, p.y]);
        velocity.extend_from_slice(&[p.vx, p.vy]);
        material.push(u8::try_from(p.material).map_err(|_| SampleError::Material(p.material))?);
    }
    Ok(ParticleFrame {
        header: Header {
            stamp: Time {
                sec: header.stamp_sec,
                nanosec: header.stamp_nanosec,
            },
            frame_id: "world".into(),
        },
        scene: header.scene()?.to_owned(),
        frame_index: header.frame_index,
        dt: header.dt,
        position,
        velocity,
        material,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_packed() {
        assert_eq!(std::mem::size_of::<Particle>(), 20);
        assert_eq!(std::mem::size_of::<FrameHeader>(), 64 + 5 * 4);
    }

    /// A sample that disagrees with its header is refused with the reason, not truncated.
    #[test]
    fn bad_samples_name_what_is_wrong() {
        let particle = |material| Particle {
            x: 0.5,
            y: 0.5,
            vx: 0.0,
            vy: 0.0,
            material,
        };
        let frame = ParticleFrame {
            header: Header {
                frame_id: "world".into(),
                ..Header::default()
            },
            scene: "s".into(),
            position: vec![0.5, 0.5],
            velocity: vec![0.0, 0.0],
            material: vec![1],
            ..ParticleFrame::default()
        };
        let header = FrameHeader::from_frame(&frame).unwrap();
        assert_eq!(to_frame(&header, &[particle(1)]).unwrap().scene, "s");
        assert_eq!(
            to_frame(&header, &[]).unwrap_err(),
            SampleError::Count {
                header: 1,
                carried: 0
            }
        );
        assert_eq!(
            to_frame(&header, &[particle(300)]).unwrap_err(),
            SampleError::Material(300)
        );
        let mut full = header;
        full.scene = [b'a'; 64];
        assert_eq!(full.scene(), Err(SampleError::SceneUnterminated));
    }
}
