//! The surrogate node at scale: frames of 40,000 particles (`simulate --grid 256`, about 800
//! kB of CDR each) served with the scale model over zenoh, iceoryx2 and ROS 2 on loopback, as
//! separate `minflow` processes (replay -> node -> record).

use std::time::Duration;

use crate::transport_support::*;

/// The surrogate node serves frames of 40,000 particles with the scale model
/// (`models/scale-grid-mingru-small-k4`) over zenoh, iceoryx2 and ROS 2: replayed frames in,
/// predictions of 40,000 particles out, none rejected, a recorded prediction whole.
#[test]
fn the_node_serves_frames_of_40000_particles_over_every_transport() {
    let dir = crate::tmp::tempdir().unwrap();
    let data = dir.path().join("truth");
    let bag = scene_of_40000(&data, 2, 6);
    let model = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/scale-grid-mingru-small-k4"
    );
    for (i, transport) in ["zenoh", "iceoryx2", "ros2"].into_iter().enumerate() {
        let env = domain_env(transport, 6);
        let (input, output) = (unique_topic("big_in"), unique_topic("big_out"));
        let rec = dir.path().join(format!("pred{i}"));
        let recorder = Node::record(transport, &output, &rec, 1, &env);
        let node = Node::spawn_env(
            "node",
            &[
                "node",
                "--model",
                model,
                "--transport",
                transport,
                "--in",
                &input,
                "--out",
                &output,
                "--status",
                "none",
                "--max-published",
                "3",
                "--wait-for-subscribers",
                "1",
            ],
            &env,
        );
        let replay = Node::spawn_env(
            "replay",
            &[
                "replay",
                bag.to_str().unwrap(),
                "--transport",
                transport,
                "--topic",
                &input,
                "--wait-for-subscribers",
                "1",
                "--rate",
                "0.25",
                // Frames keep coming until the node has published its 3, whenever its
                // subscription is matched.
                "--loop",
            ],
            &env,
        );
        let err = ok(
            &node.wait(Duration::from_secs(120)),
            &format!("node {transport}"),
        );
        assert_eq!(counter(&err, "published"), Some(3), "{transport}: {err}");
        assert_eq!(counter(&err, "rejected"), Some(0), "{transport}: {err}");
        ok(
            &recorder.wait(Duration::from_secs(60)),
            &format!("record {transport}"),
        );
        drop(replay);
        let files = minflow::bag::bag_paths(std::slice::from_ref(&rec)).unwrap();
        let frames: Vec<_> = files
            .iter()
            .flat_map(|f| {
                minflow::bag::read_frames(f, Some(output.as_str()))
                    .unwrap()
                    .frames
            })
            .collect();
        assert_eq!(frames.len(), 1, "{transport}");
        assert!(frames.iter().all(|f| f.2.len() == 40_000), "{transport}");
    }
}
