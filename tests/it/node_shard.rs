//! Issue 40, sharding: three `minflow node --shard GROUP` processes on loopback over zenoh
//! divide 64 live streams among them (zenoh liveliness tokens, rendezvous hashing), every
//! frame predicted exactly once; after `kill -9` of one node its scenes are predicted again
//! by the others, every frame published from one second after the kill on, and the takeovers
//! are counted in the survivors' logs. The group name and topics are this test's own.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::mpsc::{channel, Receiver};
use std::time::{Duration, Instant};

use minflow::msgs::{ParticleFrame, Time};
use minflow::transport::{self, FramePublisher, Sample, Transport};
use zenoh::Wait;

use crate::transport_support::*;

const STREAMS: usize = 64;

/// Frame `index` of stream `k`: the bag's frames looped.
fn frame(base: &[ParticleFrame], k: usize, index: u32) -> ParticleFrame {
    let mut f = base[(k + index as usize) % base.len()].clone();
    f.scene = format!("shard/{k:02}");
    f.frame_index = index;
    f.header.stamp = Time::from_nanos(u64::from(index) * 16_000_000);
    f
}

/// Publishes frames `rounds` of every stream, one round per `period`; returns when each
/// (scene, index) was published.
fn publish_rounds(
    publisher: &mut dyn FramePublisher,
    base: &[ParticleFrame],
    rounds: std::ops::Range<u32>,
    period: Duration,
) -> HashMap<(String, u32), Instant> {
    let mut sent = HashMap::new();
    let start = Instant::now();
    for (r, i) in rounds.enumerate() {
        std::thread::sleep((start + period * r as u32).saturating_duration_since(Instant::now()));
        for k in 0..STREAMS {
            let f = frame(base, k, i);
            publisher.publish(&f).unwrap();
            sent.insert((f.scene, i), Instant::now());
        }
    }
    sent
}

/// Counts predictions by (scene, input frame index) until `want` keys are in or `timeout`.
fn count(
    rx: &Receiver<Sample>,
    seen: &mut BTreeMap<(String, u32), u32>,
    want: impl Fn(&BTreeMap<(String, u32), u32>) -> bool,
    timeout: Duration,
) {
    let deadline = Instant::now() + timeout;
    while Instant::now() < deadline && !want(seen) {
        if let Ok(s) = rx.recv_timeout(Duration::from_millis(50)) {
            let f = s.decode().unwrap();
            *seen.entry((f.scene, f.frame_index - 1)).or_default() += 1;
        }
    }
}

/// Waits until `n` members of `group` are alive (their liveliness tokens), at most 60 s.
fn wait_for_members(session: &zenoh::Session, group: &str, n: usize) {
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let replies = session
            .liveliness()
            .get(format!("minflow/shard/{group}/*"))
            .timeout(Duration::from_secs(1))
            .wait()
            .unwrap();
        let alive = std::iter::from_fn(|| replies.recv().ok()).count();
        if alive >= n {
            return;
        }
        assert!(
            Instant::now() < deadline,
            "{alive} of {n} shard members alive after 60 s"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn sharded_nodes_predict_each_frame_once_and_take_over_a_killed_nodes_scenes() {
    let (input, output) = (unique_topic("shard_in"), unique_topic("shard_out"));
    let group = format!("test{}_{}", std::process::id(), input.len());
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("models/all-grid-mingru-small");
    let nodes: Vec<Node> = (0..3)
        .map(|i| {
            let name = format!("shard{i}");
            Node::spawn(
                &name,
                &[
                    "node",
                    "--model",
                    model.to_str().unwrap(),
                    "--in",
                    &input,
                    "--out",
                    &output,
                    "--status",
                    "none",
                    "--queue-depth",
                    "1024",
                    "--shard",
                    &group,
                    "--name",
                    &name,
                ],
            )
        })
        .collect();
    let zt = transport::zenoh::ZenohTransport::open(None).unwrap();
    let (tx, rx) = channel();
    let _sub = zt.subscribe(&output, tx).unwrap();
    let mut publisher = zt.publisher(&input).unwrap();
    wait_for_members(zt.session(), &group, 3);
    assert!(
        transport::wait_for_subscribers(publisher.as_ref(), 3, Duration::from_secs(60)),
        "the nodes never subscribed"
    );
    // Each node's own view of the group settles (tokens travel between the nodes too).
    std::thread::sleep(Duration::from_secs(1));
    let base: Vec<ParticleFrame> = raw_messages(&source_bag(), Some(minflow::bag::FRAMES_TOPIC))
        .iter()
        .map(|b| minflow::msgs::decode(b).unwrap())
        .collect();
    // Phase 1: all three alive, 5 rounds at 5 Hz per stream.
    let period = Duration::from_millis(200);
    let first = publish_rounds(publisher.as_mut(), &base, 0..5, period);
    let mut seen = BTreeMap::new();
    count(
        &rx,
        &mut seen,
        |s| s.len() >= first.len(),
        Duration::from_secs(120),
    );
    count(&rx, &mut seen, |_| false, Duration::from_secs(1));
    assert_eq!(
        seen.len(),
        first.len(),
        "every frame predicted while all three were alive"
    );
    assert!(
        seen.values().all(|&c| c == 1),
        "a frame predicted twice: {seen:?}"
    );
    // Phase 2: kill -9 one node, 15 more rounds (3 s: 2 s of them after the first second).
    nodes[0].signal("KILL");
    let killed = Instant::now();
    let second = publish_rounds(publisher.as_mut(), &base, 5..20, period);
    let must: Vec<_> = second
        .iter()
        .filter(|(_, &t)| t >= killed + Duration::from_secs(1))
        .map(|(k, _)| k.clone())
        .collect();
    assert!(
        must.len() >= 9 * STREAMS,
        "{} frames after the first second",
        must.len()
    );
    let all_in = |s: &BTreeMap<(String, u32), u32>| must.iter().all(|k| s.contains_key(k));
    count(&rx, &mut seen, all_in, Duration::from_secs(120));
    count(&rx, &mut seen, |_| false, Duration::from_secs(1));
    let mut logs = String::new();
    for n in nodes.into_iter().skip(1) {
        n.signal("INT");
        logs += &ok(&n.wait(Duration::from_secs(30)), "node");
    }
    let missing: Vec<_> = must.iter().filter(|k| !seen.contains_key(*k)).collect();
    assert!(
        missing.is_empty(),
        "not predicted 1 s after the kill: {missing:?}\n{logs}"
    );
    assert!(
        seen.values().all(|&c| c == 1),
        "a frame predicted twice\n{logs}"
    );
    let taken: u64 = logs.lines().filter_map(|l| counter(l, "taken_over")).sum();
    assert!(taken >= 1, "no takeover counted\n{logs}");
}
