//! REP-2016 type hashes (issue 17): minflow's Rust computation (`minflow::msgs::type_hash`)
//! against an independent Python one (`tests/python/rihs01.py`, standard library only) on the
//! `.msg` files in `msgs/`, both against the hashes ROS 2 Jazzy publishes for standard types
//! (its installed `share/<pkg>/msg/<Type>.json`, `type_hashes`), and `--transport ros2-zenoh`
//! putting the hash into its rmw_zenoh data keys and liveliness tokens (seen by a plain zenoh
//! session).

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use minflow::msgs::status::{SurrogateStatus, STATUS_TYPE_NAME};
use minflow::msgs::type_hash::{
    hashable_json, minflow_type_hash, parse_msg, rihs01, TypeHashError,
};
use minflow::msgs::{Header, ParticleFrame, Time, DDS_TYPE_NAME, TYPE_NAME};
use minflow::transport::ros2::{Backend, Ros2Transport};
use minflow::transport::Transport;
use serde_json::Value;

/// Jazzy's published hashes (`/opt/ros/jazzy/share/<pkg>/msg/<Type>.json`); String's is also
/// the one in rmw_zenoh's design document's key example.
const JAZZY: [(&str, &str); 3] = [
    (
        "builtin_interfaces/msg/Time",
        "RIHS01_b106235e25a4c5ed35098aa0a61a3ee9c9b18d197f398b0e4206cea9acf9c197",
    ),
    (
        "std_msgs/msg/Header",
        "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    ),
    (
        "std_msgs/msg/String",
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    ),
];

/// Runs `tests/python/rihs01.py --json ARGS` in the repository root (`.msg` files from
/// `msgs/` unless `--def` names them) and returns its JSON object.
fn python(args: &[&str]) -> Value {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = Command::new("python3")
        .arg(root.join("tests/python/rihs01.py"))
        .arg("--json")
        .args(args)
        .current_dir(root)
        .output()
        .expect("python3 (standard library only) runs tests/python/rihs01.py");
    assert!(
        out.status.success(),
        "rihs01.py failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    serde_json::from_slice(&out.stdout).expect("rihs01.py prints JSON")
}

#[test]
fn rust_and_python_agree_on_minflow_messages() {
    let types = [
        TYPE_NAME,
        STATUS_TYPE_NAME,
        "std_msgs/msg/Header",
        "builtin_interfaces/msg/Time",
    ];
    let py = python(&types);
    for t in types {
        let rust = minflow_type_hash(t).unwrap();
        eprintln!("{t}: {rust}");
        assert_eq!(py[t].as_str(), Some(rust.as_str()), "hash of {t}");
        let json = hashable_json(t, &minflow::msgs::type_hash::MSG_DEFINITIONS).unwrap();
        assert_eq!(
            py[format!("{t} json")].as_str(),
            Some(json.as_str()),
            "hashed text of {t}"
        );
    }
    // Header and Time are Jazzy's own .msg files: both implementations reproduce rosidl.
    for (t, published) in &JAZZY[..2] {
        assert_eq!(minflow_type_hash(t).unwrap(), *published, "{t}");
    }
}

#[test]
fn standard_types_hash_as_ros2_jazzy_publishes() {
    let dir = crate::tmp::tempdir().unwrap();
    let string_msg = dir.path().join("String.msg");
    std::fs::write(&string_msg, "string data\n").unwrap();
    let def = format!("std_msgs/msg/String={}", string_msg.display());
    let py = python(&[
        "builtin_interfaces/msg/Time",
        "std_msgs/msg/Header",
        "--def",
        &def,
        "std_msgs/msg/String",
    ]);
    for (t, published) in JAZZY {
        assert_eq!(py[t].as_str(), Some(published), "python: {t}");
    }
    let string = rihs01(
        "std_msgs/msg/String",
        &[("std_msgs/msg/String", "string data")],
    );
    assert_eq!(string.unwrap(), JAZZY[2].1);
}

/// Every kind of field rosidl distinguishes, in Rust and Python alike: `char` is `uint8` and
/// `byte` is `octet` after rosidl_adapter; arrays add 48, bounded sequences 96, unbounded 144;
/// constants and default values do not count.
#[test]
fn field_types_follow_type_description_interfaces() {
    let text = "char c\nbyte b\nfloat32[] p\nuint8[3] a\nint32[<=4] s\nstring<=8 n\n\
                wstring<=2[] w\nOther o  # same package\nstd_msgs/Header[] h\n\
                uint8 K=3\nint64 d 5\n";
    let d = parse_msg("p/msg/T", text).unwrap();
    let ids: Vec<_> = d
        .fields
        .iter()
        .map(|f| (f.name.as_str(), f.type_id, f.capacity, f.string_capacity))
        .collect();
    assert_eq!(
        ids,
        [
            ("c", 3, 0, 0),
            ("b", 16, 0, 0),
            ("p", 154, 0, 0),
            ("a", 51, 3, 0),
            ("s", 102, 4, 0),
            ("n", 21, 0, 8),
            ("w", 166, 0, 2),
            ("o", 1, 0, 0),
            ("h", 145, 0, 0),
            ("d", 8, 0, 0),
        ]
    );
    assert_eq!(d.fields[7].nested_type_name, "p/msg/Other");
    assert_eq!(d.fields[8].nested_type_name, "std_msgs/msg/Header");

    let dir = crate::tmp::tempdir().unwrap();
    let defs: [(&str, &str); 5] = [
        ("p/msg/T", text),
        ("p/msg/Other", "# nothing but a comment\nint32 A=1\n"),
        ("std_msgs/msg/Header", minflow::msgs::HEADER_MSG),
        ("builtin_interfaces/msg/Time", minflow::msgs::TIME_MSG),
        ("p/msg/Unused", "bool x"),
    ];
    let mut args = Vec::new();
    for (i, (name, body)) in defs.iter().enumerate() {
        let file = dir.path().join(format!("{i}.msg"));
        std::fs::write(&file, body).unwrap();
        args.push("--def".to_owned());
        args.push(format!("{name}={}", file.display()));
    }
    args.push("p/msg/T".to_owned());
    let py = python(&args.iter().map(String::as_str).collect::<Vec<_>>());
    let json = hashable_json("p/msg/T", &defs).unwrap();
    assert!(
        json.contains("structure_needs_at_least_one_member"),
        "{json}"
    );
    assert!(!json.contains("p/msg/Unused"), "{json}");
    assert_eq!(py["p/msg/T json"].as_str(), Some(json.as_str()));
    assert_eq!(
        py["p/msg/T"].as_str(),
        Some(rihs01("p/msg/T", &defs).unwrap().as_str())
    );
}

#[test]
fn bad_definitions_are_errors() {
    assert!(matches!(
        parse_msg("p/msg/T", "int32"),
        Err(TypeHashError::Syntax { line: 1, .. })
    ));
    assert!(matches!(
        parse_msg("p/msg/T", "\nfloat33 x"),
        Err(TypeHashError::Syntax { line: 2, .. })
    ));
    assert!(matches!(
        parse_msg("p/msg/T", "int32[x] a"),
        Err(TypeHashError::Syntax { line: 1, .. })
    ));
    assert!(matches!(
        parse_msg("p/msg/T", "int32 Bad"),
        Err(TypeHashError::Syntax { line: 1, .. })
    ));
    assert!(matches!(
        parse_msg("T", "int32 x"),
        Err(TypeHashError::TypeName(_))
    ));
    assert_eq!(
        rihs01("p/msg/T", &[("p/msg/T", "q/U u")]),
        Err(TypeHashError::MissingDefinition {
            type_name: "p/msg/T".into(),
            missing: "q/msg/U".into()
        })
    );
    assert!(matches!(
        minflow_type_hash("minflow_msgs/msg/Nope"),
        Err(TypeHashError::MissingDefinition { .. })
    ));
}

/// The rmw_zenoh data key of a ros2-zenoh frame publisher and the liveliness tokens of its
/// publishers and subscription end in the computed hash, never the all-zero placeholder.
#[test]
fn ros2_zenoh_keys_carry_the_type_hash() {
    crate::isolated::run(
        concat!(module_path!(), "::ros2_zenoh_keys_carry_the_type_hash"),
        ros2_zenoh_keys_carry_the_type_hash_alone,
    );
}

/// A plain zenoh peer connected to the transport's session on `port`.
fn plain_session(port: u16) -> zenoh::Session {
    use zenoh::Wait;
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", r#""peer""#.to_owned()),
        ("scouting/multicast/enabled", "false".to_owned()),
        ("listen/endpoints", "[]".to_owned()),
        ("connect/endpoints", format!(r#"["tcp/127.0.0.1:{port}"]"#)),
    ] {
        config.insert_json5(key, &value).unwrap();
    }
    zenoh::open(config).wait().unwrap()
}

/// The liveliness tokens under `@ros2_lv/<domain>/**` that contain `needle`, waiting up to 10 s
/// until there are `want` of them.
fn liveliness_keys(raw: &zenoh::Session, domain: u16, needle: &str, want: usize) -> Vec<String> {
    use zenoh::Wait;
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let replies = raw
            .liveliness()
            .get(format!("@ros2_lv/{domain}/**"))
            .timeout(Duration::from_secs(1))
            .wait()
            .unwrap();
        let mut keys = Vec::new();
        while let Ok(reply) = replies.recv() {
            if let Ok(sample) = reply.result() {
                keys.push(sample.key_expr().as_str().to_owned());
            }
        }
        keys.retain(|k| k.contains(needle));
        if keys.len() >= want || Instant::now() > deadline {
            return keys;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn ros2_zenoh_keys_carry_the_type_hash_alone() {
    use zenoh::Wait;
    let frame_hash = minflow_type_hash(TYPE_NAME).unwrap();
    let status_hash = minflow_type_hash(STATUS_TYPE_NAME).unwrap();
    let port = 40_000 + (std::process::id() % 20_000) as u16;
    std::env::set_var(
        "ZENOH_CONFIG_OVERRIDE",
        format!(r#"listen/endpoints=["tcp/127.0.0.1:{port}"]"#),
    );
    let t = Ros2Transport::open(Backend::Zenoh).unwrap();
    std::env::remove_var("ZENOH_CONFIG_OVERRIDE");
    let raw = plain_session(port);
    let domain = t.domain_id();
    let pid = std::process::id();
    let (frames, status) = (
        format!("/minflow_hash_{pid}/frames"),
        format!("/minflow_hash_{pid}/status"),
    );
    let raw_sub = raw
        .declare_subscriber(format!("{domain}/{}/{DDS_TYPE_NAME}/*", &frames[1..]))
        .wait()
        .unwrap();
    let mut publisher = t.publisher(&frames).unwrap();
    let (tx, _rx) = std::sync::mpsc::channel();
    let _subscription = t.subscribe(&frames, tx).unwrap();
    let mut status_pub = t.status_publisher(&status).unwrap();

    // Publisher (MP) and subscription (MS) tokens of the frame topic, the status publisher's.
    let frame_keys = liveliness_keys(&raw, domain, &format!("minflow_hash_{pid}%frames"), 2);
    let status_keys = liveliness_keys(&raw, domain, &format!("minflow_hash_{pid}%status"), 1);
    eprintln!("liveliness tokens: {frame_keys:#?} {status_keys:#?}");
    for kind in ["/MP/", "/MS/"] {
        assert!(
            frame_keys.iter().any(|k| k.contains(kind)
                && k.contains(&format!("/{DDS_TYPE_NAME}/{frame_hash}/"))),
            "no {kind} token with {frame_hash}: {frame_keys:?}"
        );
    }
    assert!(
        status_keys.iter().any(|k| k.contains("/MP/")
            && k.contains(&format!(
                "/minflow_msgs::msg::dds_::SurrogateStatus_/{status_hash}/"
            ))),
        "no status token with {status_hash}: {status_keys:?}"
    );

    let deadline = Instant::now() + Duration::from_secs(10);
    let key = loop {
        publisher.publish(&tiny_frame()).unwrap();
        status_pub.publish(&SurrogateStatus::default()).unwrap();
        if let Ok(Some(sample)) = raw_sub.recv_timeout(Duration::from_millis(200)) {
            break sample.key_expr().as_str().to_owned();
        }
        assert!(
            Instant::now() < deadline,
            "no frame reached the plain session"
        );
    };
    assert_eq!(
        key,
        format!("{domain}/{}/{DDS_TYPE_NAME}/{frame_hash}", &frames[1..]),
        "rmw_zenoh data key"
    );
}

fn tiny_frame() -> ParticleFrame {
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(1),
            frame_id: "world".into(),
        },
        scene: "test/hash/000".into(),
        frame_index: 0,
        dt: 0.01,
        position: vec![0.5, 0.5],
        velocity: vec![0.0, 0.0],
        material: vec![0],
    }
}
