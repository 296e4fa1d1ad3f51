//! Issue 35, the bad input that was still accepted silently: a scene file whose `position`
//! (or `size`, `velocity`, `gravity`) has three values, and a bag whose frames have an empty
//! scene name (`bag check` passed it; the node, eval and train key scenes by that name).

use std::time::Duration;

use minflow::bag::{BagWriter, FRAMES_TOPIC};
use minflow::sim::scene::Scene;

use crate::transport_support::*;

#[test]
fn a_scene_vector_with_three_values_is_refused() {
    let body = |position: &str, size: &str| {
        format!(
            "frames = 10\nname = \"x\"\n[[body]]\nshape = \"disk\"\nmaterial = \"jelly\"\n\
             position = {position}\nsize = {size}\ncount = 10\n"
        )
    };
    let ok = body("[0.5, 0.5]", "[0.2, 0.2]");
    assert!(Scene::from_toml(&ok).is_ok());
    for text in [
        body("[0.5, 0.5, 0.5]", "[0.2, 0.2]"),
        body("[0.5, 0.5]", "[0.2, 0.2, 0.2]"),
        body("[0.5]", "[0.2, 0.2]"),
        format!("gravity = [0.0, -9.8, 0.0]\n{ok}"),
    ] {
        let err = Scene::from_toml(&text).unwrap_err().to_string();
        assert!(err.contains("expected 2 values"), "{text:?} -> {err}");
    }
}

#[test]
fn bag_check_fails_frames_with_an_empty_scene_name() {
    let dir = crate::tmp::tempdir().unwrap();
    let bag = dir.path().join("nameless.mcap");
    let source = source_bag();
    let frames = raw_messages(&source, Some(FRAMES_TOPIC));
    let mut writer = BagWriter::create(&bag).unwrap();
    for bytes in frames.iter().take(5) {
        let mut frame = minflow::msgs::decode(bytes).unwrap();
        frame.scene = String::new();
        writer.write(FRAMES_TOPIC, &frame).unwrap();
    }
    writer.finish().unwrap();
    let o = Node::spawn("bag check", &["bag", "check", bag.to_str().unwrap()])
        .wait(Duration::from_secs(30));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(o.status.code(), Some(1), "{text}");
    assert!(text.contains("empty scene name"), "{text}");
    // The source bag itself still passes.
    let o = Node::spawn("bag check", &["bag", "check", source.to_str().unwrap()])
        .wait(Duration::from_secs(30));
    ok(&o, "bag check of the source");
}
