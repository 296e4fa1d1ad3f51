//! The `minflow_msgs/msg/ParticleFrame` message and its dependencies as Rust types, plus the
//! text and names a ROS 2 graph or an MCAP bag uses to describe it.
//!
//! A [`ParticleFrame`] is one frame of a 2D particle simulation: N particles with interleaved
//! positions (2N values, domain units, domain = unit square), interleaved velocities (2N
//! values, domain units per simulation time unit) and one material id each (N values, see
//! [`crate::material`]); `dt` is in simulation time units, the header stamp is the simulation
//! time of the frame (sec + nanosec, i.e. stamps in ns). The `.msg` files in the repository's
//! `msgs/` folder are the single source of truth: [`schema_text`] is built from them with
//! `include_str!`. [`state_rows`] and [`split_rows`] convert a frame's arrays to and from the
//! `[N, 4]` rows (x, y, vx, vy) that trajectories and surrogates use.
//!
//! Submodules: [`cdr`] the wire format (CDR), [`type_hash`] the REP-2016 type hashes
//! (`RIHS01_…`), [`status`] the surrogate node's `SurrogateStatus` message, [`pointcloud2`] a
//! frame as `sensor_msgs/msg/PointCloud2` for RViz. Used by every subcommand that moves frames:
//! `simulate`, `bag`, `train`, `replay`, `record`, `node`, `eval`.

pub mod cdr;
pub mod pointcloud2;
pub mod status;
pub mod type_hash;

pub use cdr::{decode, encode, encode_into, CdrError};

/// Full ROS 2 type name of [`ParticleFrame`]; also the MCAP schema name.
pub const TYPE_NAME: &str = "minflow_msgs/msg/ParticleFrame";
/// DDS type name of [`ParticleFrame`] under the ROS 2 name mangling.
pub const DDS_TYPE_NAME: &str = "minflow_msgs::msg::dds_::ParticleFrame_";

/// `msgs/ParticleFrame.msg`, verbatim.
pub const PARTICLE_FRAME_MSG: &str = include_str!("../../msgs/ParticleFrame.msg");
/// `msgs/std_msgs/Header.msg`, verbatim.
pub const HEADER_MSG: &str = include_str!("../../msgs/std_msgs/Header.msg");
/// `msgs/builtin_interfaces/Time.msg`, verbatim.
pub const TIME_MSG: &str = include_str!("../../msgs/builtin_interfaces/Time.msg");

/// The complete message definition in rosbag2's `ros2msg` schema encoding: the top-level `.msg`
/// text, then each dependency (depth first) after `"\n"`, a line of 80 `=` and a line
/// `MSG: pkg/Type`, exactly as rosbag2's `LocalMessageDefinitionSource` concatenates them.
pub fn schema_text() -> String {
    let rule = "=".repeat(80);
    let mut text =
        String::with_capacity(PARTICLE_FRAME_MSG.len() + HEADER_MSG.len() + TIME_MSG.len() + 256);
    text.push_str(PARTICLE_FRAME_MSG);
    for (name, body) in [
        ("std_msgs/Header", HEADER_MSG),
        ("builtin_interfaces/Time", TIME_MSG),
    ] {
        text.push('\n');
        text.push_str(&rule);
        text.push_str("\nMSG: ");
        text.push_str(name);
        text.push('\n');
        text.push_str(body);
    }
    text
}

/// `builtin_interfaces/Time`: seconds plus nanoseconds (nanosec in `0..1e9`).
#[derive(
    Debug,
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Default,
    serde::Serialize,
    serde::Deserialize,
)]
pub struct Time {
    /// Whole seconds (may be negative).
    pub sec: i32,
    /// Nanoseconds added to `sec`, in `0..1_000_000_000`.
    pub nanosec: u32,
}

impl Time {
    /// A stamp from nanoseconds since zero; seconds saturate at `i32::MAX`.
    pub fn from_nanos(ns: u64) -> Self {
        let sec = ns / 1_000_000_000;
        match i32::try_from(sec) {
            Ok(sec) => Self {
                sec,
                nanosec: (ns % 1_000_000_000) as u32,
            },
            Err(_) => Self {
                sec: i32::MAX,
                nanosec: 999_999_999,
            },
        }
    }

    /// The stamp in nanoseconds (negative for stamps before zero).
    pub fn as_nanos(&self) -> i64 {
        i64::from(self.sec) * 1_000_000_000 + i64::from(self.nanosec)
    }

    /// The stamp in nanoseconds when it is not negative (what MCAP's `log_time` can hold).
    pub fn as_unsigned_nanos(&self) -> Option<u64> {
        u64::try_from(self.as_nanos()).ok()
    }

    /// A stamp from seconds, rounded to the nearest nanosecond; NaN gives zero, values out of
    /// range saturate.
    pub fn from_secs_f64(secs: f64) -> Self {
        if secs.is_nan() {
            return Self::default();
        }
        let ns = (secs * 1e9).round();
        let ns = ns.clamp(i32::MIN as f64 * 1e9, i32::MAX as f64 * 1e9 + 999_999_999.0) as i64;
        Self {
            sec: ns.div_euclid(1_000_000_000) as i32,
            nanosec: ns.rem_euclid(1_000_000_000) as u32,
        }
    }

    /// The stamp in seconds.
    pub fn as_secs_f64(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// `std_msgs/Header`: when (simulation time) and in which coordinate frame.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Header {
    /// Simulation time of the frame.
    pub stamp: Time,
    /// Coordinate frame, `"world"` for minflow data.
    pub frame_id: String,
}

/// `minflow_msgs/msg/ParticleFrame`: one frame of one scene (see the module doc for units).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ParticleFrame {
    /// Stamp (simulation time of this frame) and frame id.
    pub header: Header,
    /// Trajectory id, e.g. `"multi/rope+snow/007"`.
    pub scene: String,
    /// Frame number from the start of the scene.
    pub frame_index: u32,
    /// Simulation time between consecutive frames.
    pub dt: f32,
    /// Interleaved `x0, y0, x1, y1, ...`: 2N values, domain units.
    pub position: Vec<f32>,
    /// Interleaved `vx0, vy0, ...`: 2N values, domain units per time unit.
    pub velocity: Vec<f32>,
    /// N material ids, indexes into [`crate::material::TABLE`].
    pub material: Vec<u8>,
}

/// Why a [`ParticleFrame`] is not a valid frame.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FrameError {
    /// An array's length does not match the particle count N (= `material.len()`).
    #[error("{field} has {found} values, expected {expected} (2 x {particles} particles)")]
    Length {
        /// `"position"` or `"velocity"`.
        field: &'static str,
        /// Values found.
        found: usize,
        /// Values expected (2N).
        expected: usize,
        /// Particle count N.
        particles: usize,
    },
    /// A value is NaN or infinite.
    #[error("{field}[{index}] is {value}, not a finite number")]
    NotFinite {
        /// `"position"`, `"velocity"` or `"dt"`.
        field: &'static str,
        /// Index in the array (0 for `dt`).
        index: usize,
        /// The offending value.
        value: f32,
    },
    /// `dt` is zero or negative.
    #[error("dt is {0}, must be positive")]
    NonPositiveDt(f32),
    /// A material id outside [`crate::material::TABLE`].
    #[error(
        "material[{index}] is {value}, not a known material ({})",
        crate::material::id_list()
    )]
    UnknownMaterial {
        /// Particle index.
        index: usize,
        /// The offending id.
        value: u8,
    },
}

/// A frame's particles as `[N, 4]` rows (x, y, vx, vy per particle), copied bit for bit from
/// its interleaved `position` and `velocity` (`[N * 2]` each): the layout of
/// `data::Trajectory::states` and of what a surrogate steps on. The inverse of [`split_rows`].
pub fn state_rows(frame: &ParticleFrame) -> Vec<f32> {
    let mut rows = Vec::with_capacity(4 * frame.len());
    for (p, v) in frame
        .position
        .chunks_exact(2)
        .zip(frame.velocity.chunks_exact(2))
    {
        rows.extend_from_slice(&[p[0], p[1], v[0], v[1]]);
    }
    rows
}

/// `[N, 4]` rows (x, y, vx, vy per particle) -> a frame's interleaved `position` and
/// `velocity` (`[N * 2]` each), bit for bit. The inverse of [`state_rows`].
pub fn split_rows(rows: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let n = rows.len() / 4;
    let mut position = Vec::with_capacity(2 * n);
    let mut velocity = Vec::with_capacity(2 * n);
    for r in rows.chunks_exact(4) {
        position.extend_from_slice(&r[..2]);
        velocity.extend_from_slice(&r[2..]);
    }
    (position, velocity)
}

impl ParticleFrame {
    /// Frame `frame_index` of `scene` as minflow writes its bags (docs/design.md, "Bags"):
    /// stamped `frame_index * period_ns` in integer nanoseconds (so stamps never drift),
    /// `frame_id` `"world"`, `dt` the period in seconds. `position` and `velocity` are
    /// interleaved `[N * 2]`, `material` `[N]`.
    pub fn on_clock(
        scene: String,
        frame_index: u32,
        period_ns: u64,
        position: Vec<f32>,
        velocity: Vec<f32>,
        material: Vec<u8>,
    ) -> Self {
        Self {
            header: Header {
                stamp: Time::from_nanos(u64::from(frame_index) * period_ns),
                frame_id: "world".to_owned(),
            },
            scene,
            frame_index,
            dt: (period_ns as f64 * 1e-9) as f32,
            position,
            velocity,
            material,
        }
    }

    /// Particle count N (= `material.len()`).
    pub fn len(&self) -> usize {
        self.material.len()
    }

    /// Whether the frame holds no particles.
    pub fn is_empty(&self) -> bool {
        self.material.is_empty()
    }

    /// Checks that arrays have 2N / 2N / N values, every number is finite, `dt` is positive and
    /// every material id is known. The error names the field and the index.
    pub fn validate(&self) -> Result<(), FrameError> {
        let n = self.len();
        for (field, values) in [("position", &self.position), ("velocity", &self.velocity)] {
            if values.len() != 2 * n {
                return Err(FrameError::Length {
                    field,
                    found: values.len(),
                    expected: 2 * n,
                    particles: n,
                });
            }
        }
        if !self.dt.is_finite() {
            return Err(FrameError::NotFinite {
                field: "dt",
                index: 0,
                value: self.dt,
            });
        }
        if self.dt <= 0.0 {
            return Err(FrameError::NonPositiveDt(self.dt));
        }
        for (field, values) in [("position", &self.position), ("velocity", &self.velocity)] {
            // Fast path: one pass that the compiler vectorises, the slow search only on failure.
            if !values.iter().fold(true, |ok, v| ok & v.is_finite()) {
                if let Some((index, &value)) =
                    values.iter().enumerate().find(|(_, v)| !v.is_finite())
                {
                    return Err(FrameError::NotFinite {
                        field,
                        index,
                        value,
                    });
                }
            }
        }
        if let Some((index, value)) = crate::material::Material::first_unknown(&self.material) {
            return Err(FrameError::UnknownMaterial { index, value });
        }
        Ok(())
    }
}
