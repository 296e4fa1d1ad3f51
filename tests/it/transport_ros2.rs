//! ROS 2 transport (ros2-client) end to end, in one process: frames of 2,500 particles
//! (~50 KB, so RTPS fragments them) published at 60 Hz arrive complete, in order and
//! byte-equal to `cdr::encode` of what was sent; a sample of the right DDS type name but
//! wrong content becomes `Payload::Malformed` and later frames still arrive; the matched
//! subscriber count follows subscriptions; the rmw_zenoh backend carries frames too.
//!
//! Every test uses its own topic (`/minflow_test_<pid>_<name>/frames`), so tests running in
//! parallel on the same ROS domain do not see each other's frames.

use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use minflow::msgs::{cdr, Header, ParticleFrame, Time};
use minflow::transport::ros2::{Backend, Ros2Transport};
use minflow::transport::{wait_for_subscribers, Payload, Sample, Transport};

const PARTICLES: usize = 2500;
const PERIOD: Duration = Duration::from_micros(16_667);

fn topic(name: &str) -> String {
    format!("/minflow_test_{}_{name}/frames", std::process::id())
}

fn frame(index: u32) -> ParticleFrame {
    let n = PARTICLES;
    let t = index as f32 * 1e-3;
    ParticleFrame {
        header: Header {
            stamp: Time::from_nanos(u64::from(index) * 16_666_667),
            frame_id: "world".into(),
        },
        scene: "test/ros2/001".into(),
        frame_index: index,
        dt: 1.0 / 60.0,
        position: (0..2 * n).map(|i| (i as f32 * 1e-4 + t).fract()).collect(),
        velocity: (0..2 * n).map(|i| (i as f32).sin() + t).collect(),
        material: (0..n).map(|i| ((i + index as usize) % 4) as u8).collect(),
    }
}

fn recv(rx: &Receiver<Sample>, timeout: Duration) -> Sample {
    rx.recv_timeout(timeout)
        .expect("no sample within the timeout")
}

fn percentile(sorted: &[Duration], p: f64) -> Duration {
    sorted[((sorted.len() - 1) as f64 * p).round() as usize]
}

/// Publishes `count` frames at 60 Hz from `publisher_side` to a subscription on
/// `subscriber_side`; checks order and bytes; returns the sorted latencies.
fn stream_frames(
    publisher_side: &dyn Transport,
    subscriber_side: &dyn Transport,
    topic: &str,
    count: u32,
) -> Vec<Duration> {
    let (tx, rx) = channel();
    let subscription = subscriber_side.subscribe(topic, tx).unwrap();
    let mut publisher = publisher_side.publisher(topic).unwrap();
    assert!(
        wait_for_subscribers(publisher.as_ref(), 1, Duration::from_secs(20)),
        "the subscription was never matched"
    );
    let mut sent_at = Vec::new();
    let mut next = Instant::now();
    for i in 0..count {
        sent_at.push(Instant::now());
        publisher.publish(&frame(i)).unwrap();
        next += PERIOD;
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
    }
    let mut latencies = Vec::new();
    for i in 0..count {
        let sample = recv(&rx, Duration::from_secs(10));
        assert_eq!(sample.topic, topic);
        let Payload::Cdr(bytes) = &sample.payload else {
            panic!("frame {i}: {:?}", sample.payload)
        };
        let got = cdr::decode(bytes).unwrap();
        assert_eq!(got.frame_index, i, "frames out of order or lost");
        assert!(bytes == &cdr::encode(&frame(i)), "frame {i}: bytes differ");
        assert_eq!(sample.frame().unwrap(), frame(i));
        latencies.push(sample.received - sent_at[i as usize]);
    }
    assert!(
        rx.recv_timeout(Duration::from_millis(200)).is_err(),
        "unexpected extra sample"
    );

    // Dropping the subscription stops its thread promptly and the publisher sees it leave.
    let t = Instant::now();
    drop(subscription);
    assert!(
        t.elapsed() < Duration::from_secs(2),
        "drop took {:?}",
        t.elapsed()
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    while publisher.subscriber_count() > 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(
        publisher.subscriber_count(),
        0,
        "subscriber count did not drop to 0"
    );
    latencies.sort();
    latencies
}

#[test]
fn dds_frames_arrive_in_order_and_byte_equal() {
    crate::isolated::run(
        concat!(
            module_path!(),
            "::dds_frames_arrive_in_order_and_byte_equal"
        ),
        dds_frames_arrive_in_order_and_byte_equal_alone,
    );
}

/// [`dds_frames_arrive_in_order_and_byte_equal`]'s body, in a process of its own.
fn dds_frames_arrive_in_order_and_byte_equal_alone() {
    let a = Ros2Transport::open(Backend::Dds).unwrap();
    let b = Ros2Transport::open(Backend::Dds).unwrap();
    let lat = stream_frames(&a, &b, &topic("stream"), 200);
    eprintln!(
        "ros2 (DDS) latency, {} frames of {PARTICLES} particles ({} bytes) at 60 Hz: p50 {:?} p99 {:?} max {:?}",
        lat.len(),
        cdr::encode(&frame(0)).len(),
        percentile(&lat, 0.5),
        percentile(&lat, 0.99),
        lat[lat.len() - 1]
    );
}

/// A writer of another serde type with the same DDS type name (what a buggy or mismatched
/// peer would send): its samples become `Malformed` and the subscription keeps delivering.
#[test]
fn dds_malformed_sample_is_reported_and_delivery_continues() {
    crate::isolated::run(
        concat!(
            module_path!(),
            "::dds_malformed_sample_is_reported_and_delivery_continues"
        ),
        dds_malformed_sample_is_reported_and_delivery_continues_alone,
    );
}

/// [`dds_malformed_sample_is_reported_and_delivery_continues`]'s body, in a process of its own.
fn dds_malformed_sample_is_reported_and_delivery_continues_alone() {
    use ros2_client::dds::{Context, ContextOptions};
    use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions};

    let topic = topic("malformed");
    let sub_side = Ros2Transport::open(Backend::Dds).unwrap();
    let pub_side = Ros2Transport::open(Backend::Dds).unwrap();
    let (tx, rx) = channel();
    let _subscription = sub_side.subscribe(&topic, tx).unwrap();
    let mut good = pub_side.publisher(&topic).unwrap();
    assert!(wait_for_subscribers(
        good.as_ref(),
        1,
        Duration::from_secs(20)
    ));

    // The bad writer: body is a single u32, far too short for a ParticleFrame.
    let context =
        Context::with_options(ContextOptions::new().domain_id(sub_side.domain_id())).unwrap();
    let mut node = context
        .new_node(
            NodeName::new("/", &format!("bad_writer_{}", std::process::id())).unwrap(),
            NodeOptions::new()
                .enable_rosout(false)
                .start_parameter_services(false),
        )
        .unwrap();
    let bad_topic = node
        .create_topic(
            &Name::parse(&topic).unwrap(),
            MessageTypeName::new("minflow_msgs", "ParticleFrame"),
            &minflow::transport::ros2::QOS,
        )
        .unwrap();
    let bad = node
        .create_publisher::<u32>(&bad_topic, Some(minflow::transport::ros2::QOS))
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    while node.subscription_count(&topic) == 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(
        node.subscription_count(&topic) > 0,
        "bad writer never discovered the reader"
    );
    // What a DDS peer sees of minflow's reader: the ROS 2 name mangling.
    let readers = context.domain_participant().discovered_readers();
    let dds_topic = format!("rt{topic}");
    let ours = readers
        .iter()
        .find(|r| r.subscription_topic_data.topic_name() == &dds_topic)
        .expect("minflow's reader discovered under rt/<topic>");
    assert_eq!(
        ours.subscription_topic_data.type_name(),
        minflow::msgs::DDS_TYPE_NAME
    );
    std::thread::sleep(Duration::from_millis(500)); // let both sides finish matching

    good.publish(&frame(0)).unwrap();
    assert_eq!(
        recv(&rx, Duration::from_secs(10)).frame().unwrap(),
        frame(0)
    );

    bad.publish(0xdead_beef).unwrap();
    let sample = recv(&rx, Duration::from_secs(10));
    match &sample.payload {
        Payload::Malformed(reason) => eprintln!("malformed as expected: {reason}"),
        other => panic!("expected Malformed, got {other:?}"),
    }
    assert!(sample.frame().is_err());

    for i in 1..=5 {
        good.publish(&frame(i)).unwrap();
        let s = recv(&rx, Duration::from_secs(10));
        let Payload::Cdr(bytes) = &s.payload else {
            panic!("frame {i}: {:?}", s.payload)
        };
        assert!(bytes == &cdr::encode(&frame(i)));
    }
}

#[test]
fn invalid_topics_are_rejected() {
    crate::isolated::run(
        concat!(module_path!(), "::invalid_topics_are_rejected"),
        invalid_topics_are_rejected_alone,
    );
}

/// [`invalid_topics_are_rejected`]'s body, in a process of its own.
fn invalid_topics_are_rejected_alone() {
    let t = Ros2Transport::open(Backend::Dds).unwrap();
    assert!(t.publisher("no_slash").is_err());
    let (tx, _rx) = channel();
    assert!(t.subscribe("/trailing/", tx).is_err());
}

/// rmw_zenoh protocol: publisher and subscription in one session (local delivery; across
/// processes a zenoh router is needed, as with rmw_zenoh).
#[test]
fn zenoh_frames_arrive_in_order_and_byte_equal() {
    crate::isolated::run(
        concat!(
            module_path!(),
            "::zenoh_frames_arrive_in_order_and_byte_equal"
        ),
        zenoh_frames_arrive_in_order_and_byte_equal_alone,
    );
}

/// [`zenoh_frames_arrive_in_order_and_byte_equal`]'s body, in a process of its own.
fn zenoh_frames_arrive_in_order_and_byte_equal_alone() {
    use zenoh::Wait;

    // Let a plain zenoh session connect to the node's session to see the raw payloads
    // (ZENOH_CONFIG_OVERRIDE is read only by this test's transport in this test binary).
    let port = 20_000 + (std::process::id() % 20_000) as u16;
    std::env::set_var(
        "ZENOH_CONFIG_OVERRIDE",
        format!(r#"listen/endpoints=["tcp/127.0.0.1:{port}"]"#),
    );
    let t = Ros2Transport::open(Backend::Zenoh).unwrap();
    std::env::remove_var("ZENOH_CONFIG_OVERRIDE");
    let mut config = zenoh::Config::default();
    config.insert_json5("mode", r#""peer""#).unwrap();
    config
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    config.insert_json5("listen/endpoints", "[]").unwrap();
    config
        .insert_json5("connect/endpoints", &format!(r#"["tcp/127.0.0.1:{port}"]"#))
        .unwrap();
    let raw = zenoh::open(config).wait().unwrap();
    let topic = topic("zenoh");
    // rmw_zenoh key: <domain>/<topic without leading slash>/<DDS type name>/<type hash>.
    let key = format!(
        "{}/{}/{}/*",
        t.domain_id(),
        &topic[1..],
        minflow::msgs::DDS_TYPE_NAME
    );
    let raw_sub = raw.declare_subscriber(key).wait().unwrap();
    // Wait until the plain session is connected (it sees the node's liveliness token).
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let replies = raw
            .liveliness()
            .get(format!("@ros2_lv/{}/**", t.domain_id()))
            .wait()
            .unwrap();
        if replies
            .recv_timeout(Duration::from_millis(500))
            .ok()
            .flatten()
            .is_some()
        {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "plain zenoh session never connected"
        );
    }
    std::thread::sleep(Duration::from_millis(200));

    let lat = stream_frames(&t, &t, &topic, 50);
    let mut seen = Vec::new();
    while let Ok(Some(sample)) = raw_sub.recv_timeout(Duration::from_millis(500)) {
        if seen.is_empty() {
            eprintln!(
                "rmw_zenoh key of minflow's publisher: {}",
                sample.key_expr()
            );
            assert!(
                sample.attachment().is_some(),
                "rmw_zenoh attachment missing"
            );
        }
        let bytes = sample.payload().to_bytes();
        let i = cdr::decode(&bytes).unwrap().frame_index;
        assert!(
            bytes.as_ref() == cdr::encode(&frame(i)).as_slice(),
            "zenoh wire bytes of frame {i}"
        );
        seen.push(i);
    }
    assert!(
        seen.len() >= 45 && seen.windows(2).all(|w| w[0] < w[1]),
        "plain zenoh saw {seen:?}"
    );
    eprintln!(
        "ros2-zenoh latency, {} frames at 60 Hz: p50 {:?} p99 {:?}",
        lat.len(),
        percentile(&lat, 0.5),
        percentile(&lat, 0.99)
    );
}

/// Publisher and subscription on one transport (one DDS participant).
#[test]
fn dds_same_participant() {
    crate::isolated::run(
        concat!(module_path!(), "::dds_same_participant"),
        dds_same_participant_alone,
    );
}

/// [`dds_same_participant`]'s body, in a process of its own.
fn dds_same_participant_alone() {
    let t = Ros2Transport::open(Backend::Dds).unwrap();
    let lat = stream_frames(&t, &t, &topic("same"), 30);
    eprintln!(
        "ros2 (DDS, one participant) p50 {:?} p99 {:?}",
        percentile(&lat, 0.5),
        percentile(&lat, 0.99)
    );
}
