//! Bags minflow writes, read by the Python `mcap` + `mcap-ros2-support` readers (docs/design.md,
//! "Bags"): [`BagWriter`] writes two scenes of 2,500 particles with strings of odd byte lengths
//! (one not ASCII), `tests/python/read_bag.py` decodes them with `mcap_ros2`'s `DecoderFactory`
//! and prints a JSON summary, and every field is compared with what was written (floats after
//! rounding to float32).
//!
//! The interpreter: [`crate::python_support::interpreter`].

use std::path::Path;
use std::process::Command;

use crate::python_support::{interpreter, INSTALL_HINT};
use minflow::bag::{BagWriter, FRAMES_TOPIC, PREDICTED_TOPIC, QOS_KEY};
use minflow::msgs::{self, Header, ParticleFrame, Time};
use serde_json::Value;

const PARTICLES: usize = 2500;
const FRAMES_PER_SCENE: u32 = 3;

/// Scene ids and frame ids of odd byte lengths (15, 21; 5, 7); "é" is two bytes in UTF-8.
const SCENES: [(&str, &str); 2] = [
    ("fluid/café/003", "world"),
    ("multi/rope+snow/00017", "odom_x1"),
];

/// Frame `k` of scene `s`, deterministic pseudo-random values; stamps have sec > 0 and nanosec
/// not a multiple of 1000.
fn frame(s: usize, k: u32) -> ParticleFrame {
    let mut state = ((s as u64 + 7) * 0x9E37_79B9_7F4A_7C15) ^ u64::from(k);
    let mut next = move || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1);
        ((state >> 40) as f32) / (1u64 << 24) as f32
    };
    let (scene, frame_id) = SCENES[s];
    let dt = [0.016, 1.0 / 3.0][s];
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(1_234_567_891 + u64::from(k) * 16_000_001),
            frame_id: frame_id.into(),
        },
        scene: scene.into(),
        frame_index: k,
        dt,
        position: (0..2 * PARTICLES).map(|_| next()).collect(),
        velocity: (0..2 * PARTICLES).map(|_| next() - 0.5).collect(),
        material: (0..PARTICLES)
            .map(|i| ((i + s + k as usize) % 4) as u8)
            .collect(),
    }
}

/// Runs `tests/python/read_bag.py` on `bag`; fails with the install hint when the packages are
/// missing.
fn python_summary(bag: &Path) -> Value {
    let python = interpreter();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/python/read_bag.py");
    let output = Command::new(&python)
        .arg(&script)
        .arg(bag)
        .output()
        .unwrap_or_else(|e| {
            panic!("cannot run {python} (set MINFLOW_PYTHON to another interpreter): {e}")
        });
    let stderr = String::from_utf8_lossy(&output.stderr);
    if output.status.code() == Some(3) || stderr.contains("No module named") {
        panic!(
            "the Python MCAP readers are not installed for {python}; run `{INSTALL_HINT}`\n\
             {stderr}"
        );
    }
    assert!(
        output.status.success(),
        "{python} {} failed ({}):\n{stderr}",
        script.display(),
        output.status
    );
    serde_json::from_slice(&output.stdout).unwrap_or_else(|e| {
        let stdout = String::from_utf8_lossy(&output.stdout);
        panic!("read_bag.py printed no valid JSON ({e}):\n{stdout}\n{stderr}")
    })
}

/// What read_bag.py reports of one message, in the same shape for the written frame.
#[derive(Debug, PartialEq)]
struct Seen {
    topic: String,
    schema: String,
    log_time: u64,
    publish_time: u64,
    sequence: u64,
    stamp: (i64, u64),
    frame_id: String,
    scene: String,
    frame_index: u64,
    dt: f32,
    lens: [u64; 3],
    position_first_last: (f32, f32),
    velocity_1: f32,
    material_first_last: (u64, u64),
}

impl Seen {
    fn written(frame: &ParticleFrame, sequence: u64) -> Self {
        let stamp = frame.header.stamp;
        let log_time = stamp.as_unsigned_nanos().expect("stamp not negative");
        Seen {
            topic: FRAMES_TOPIC.into(),
            schema: msgs::TYPE_NAME.into(),
            log_time,
            publish_time: log_time,
            sequence,
            stamp: (i64::from(stamp.sec), u64::from(stamp.nanosec)),
            frame_id: frame.header.frame_id.clone(),
            scene: frame.scene.clone(),
            frame_index: u64::from(frame.frame_index),
            dt: frame.dt,
            lens: [frame.position.len(), frame.velocity.len(), frame.len()].map(|n| n as u64),
            position_first_last: (frame.position[0], frame.position[2 * PARTICLES - 1]),
            velocity_1: frame.velocity[1],
            material_first_last: (
                u64::from(frame.material[0]),
                u64::from(frame.material[PARTICLES - 1]),
            ),
        }
    }

    fn read(m: &Value) -> Self {
        let field = |key: &str| {
            m.get(key)
                .unwrap_or_else(|| panic!("message without {key:?}: {m}"))
        };
        let text = |key| field(key).as_str().expect("a string").to_owned();
        let int = |key| field(key).as_u64().expect("an unsigned integer");
        let float = |key| field(key).as_f64().expect("a number") as f32;
        Seen {
            topic: text("topic"),
            schema: text("schema"),
            log_time: int("log_time"),
            publish_time: int("publish_time"),
            sequence: int("sequence"),
            stamp: (field("sec").as_i64().expect("sec"), int("nanosec")),
            frame_id: text("frame_id"),
            scene: text("scene"),
            frame_index: int("frame_index"),
            dt: float("dt"),
            lens: ["n_position", "n_velocity", "n_material"].map(int),
            position_first_last: (float("position_first"), float("position_last")),
            velocity_1: float("velocity_1"),
            material_first_last: (int("material_first"), int("material_last")),
        }
    }
}

#[test]
fn python_mcap_ros2_reader_decodes_every_field() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let path = dir.path().join("interop.mcap");
    let frames: Vec<ParticleFrame> = (0..FRAMES_PER_SCENE)
        .flat_map(|k| [frame(0, k), frame(1, k)])
        .collect();
    let mut writer = BagWriter::create(&path).expect("create");
    for f in &frames {
        writer.write(FRAMES_TOPIC, f).expect("write");
    }
    // A second channel, which the script must leave out of its messages but list.
    writer.write(PREDICTED_TOPIC, &frames[0]).expect("write");
    writer.finish().expect("finish");

    let summary = python_summary(&path);

    assert_eq!(summary["profile"], "ros2", "header profile");
    let channels = summary["channels"].as_array().expect("channels");
    let topics: Vec<&str> = channels
        .iter()
        .filter_map(|c| c["topic"].as_str())
        .collect();
    assert_eq!(topics, [FRAMES_TOPIC, PREDICTED_TOPIC]);
    for channel in channels {
        assert_eq!(channel["schema_name"], msgs::TYPE_NAME, "{channel}");
        assert_eq!(channel["schema_encoding"], "ros2msg", "{channel}");
        assert_eq!(channel["message_encoding"], "cdr", "{channel}");
        let keys = channel["metadata_keys"].as_array().expect("metadata_keys");
        assert!(keys.iter().any(|k| k == QOS_KEY), "{channel}");
    }

    let read: Vec<Seen> = summary["messages"]
        .as_array()
        .expect("messages")
        .iter()
        .map(Seen::read)
        .collect();
    let written: Vec<Seen> = (frames.iter().enumerate())
        .map(|(i, f)| Seen::written(f, i as u64))
        .collect();
    assert_eq!(read.len(), written.len(), "messages on {FRAMES_TOPIC}");
    for (i, (read, written)) in read.iter().zip(&written).enumerate() {
        assert_eq!(read, written, "message {i}");
    }
}
