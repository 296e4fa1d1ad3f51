//! Loading trajectories from bags: frame order and bit-exact states, several scenes per bag
//! and one scene across bags, duplicates, gaps split into segments and reported, changed
//! particle counts and materials as errors naming scene and frame, truncated bags, topic
//! filtering, and `scan` agreeing with `load`.

use std::path::PathBuf;

use crate::data_support::{same_bits, simulate, state_of, synthetic, write_bag, TOPIC};
use minflow::bag::{BagWriter, PREDICTED_TOPIC};
use minflow::data::{self, DataError, Gap};

#[test]
fn frames_load_in_order_bit_for_bit() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let frames = simulate(0, 12);
    let bag = dir.path().join("a.mcap");
    write_bag(&bag, frames.iter().rev()); // written backwards: order comes from frame_index
    let (trajs, report) = data::load(&[bag], None).expect("load");
    assert_eq!(trajs.len(), 1);
    let t = &trajs[0];
    assert_eq!(
        (t.scene.as_str(), t.frames, t.n, t.start_index),
        (frames[0].scene.as_str(), 12, 2500, 0)
    );
    assert_eq!(t.dt.to_bits(), frames[0].dt.to_bits());
    assert_eq!(t.material, frames[0].material);
    assert_eq!(t.states.len(), 12 * 2500 * 4);
    for (k, f) in frames.iter().enumerate() {
        assert_eq!(t.frame_index(k), f.frame_index);
        assert!(same_bits(t.state(k), &state_of(f)), "frame {k} differs");
        let row = &t.state(k)[4 * 17..4 * 18]; // particle 17, by hand
        let expect = [
            f.position[34],
            f.position[35],
            f.velocity[34],
            f.velocity[35],
        ];
        assert!(same_bits(row, &expect));
    }
    assert_eq!((report.bags, report.frames, report.duplicates), (1, 12, 0));
    assert!(report.gaps.is_empty() && report.truncated.is_empty());
}

#[test]
fn scenes_interleaved_in_one_bag_and_one_scene_across_bags() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let (s1, s2, s3) = (simulate(1, 12), simulate(2, 12), simulate(3, 12));
    let interleaved: Vec<_> = s1.iter().zip(&s2).flat_map(|(a, b)| [a, b]).collect();
    write_bag(&dir.path().join("a.mcap"), interleaved);
    write_bag(&dir.path().join("b.mcap"), &s3[..6]);
    // The second half, with frame 5 again (a duplicate) and predicted frames on another topic.
    let mut writer = BagWriter::create(dir.path().join("c.mcap")).expect("create");
    for f in &s3[5..] {
        writer.write(TOPIC, f).expect("write");
        writer.write(PREDICTED_TOPIC, &s1[0]).expect("write");
    }
    writer.finish().expect("finish");

    let folder = vec![dir.path().to_path_buf()];
    let (trajs, report) = data::load(&folder, Some(TOPIC)).expect("load");
    let mut expected = [&s1, &s2, &s3];
    expected.sort_by(|a, b| a[0].scene.cmp(&b[0].scene));
    assert_eq!(trajs.len(), 3);
    for (t, frames) in trajs.iter().zip(expected) {
        assert_eq!(
            (&t.scene, t.frames, t.start_index),
            (&frames[0].scene, 12, 0)
        );
        for (k, f) in frames.iter().enumerate() {
            assert!(same_bits(t.state(k), &state_of(f)), "{} frame {k}", t.scene);
        }
    }
    assert_eq!((report.bags, report.frames, report.duplicates), (3, 36, 1));
    assert_eq!(report.skipped, 7, "the predicted frames are passed over");
    assert!(report.gaps.is_empty());

    // Without a topic filter the predicted frames (scene 1's frame 0) are duplicates of scene 1.
    let (all, report) = data::load(&folder, None).expect("load all topics");
    assert_eq!(all.len(), 3);
    assert_eq!((report.duplicates, report.skipped), (1 + 7, 0));

    let infos = data::scan(&folder, Some(TOPIC)).expect("scan");
    assert_eq!(infos.len(), 3);
    for (info, t) in infos.iter().zip(&trajs) {
        assert_eq!((&info.scene, info.frames, info.n), (&t.scene, 12, 2500));
        assert_eq!(info.segments, vec![0..12]);
        assert_eq!(info.dt, t.dt);
    }
    let s3_info = infos
        .iter()
        .find(|i| i.scene == s3[0].scene)
        .expect("scene 3");
    let names: Vec<_> = s3_info
        .bags
        .iter()
        .map(|p| p.file_name().expect("name"))
        .collect();
    assert_eq!(names, ["b.mcap", "c.mcap"]);
}

#[test]
fn missing_frames_split_a_scene_into_segments_and_are_reported() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let frames = simulate(4, 12);
    let kept: Vec<_> = frames
        .iter()
        .filter(|f| ![5, 8, 9].contains(&f.frame_index))
        .collect();
    let bag = dir.path().join("gaps.mcap");
    write_bag(&bag, kept);
    let (trajs, report) = data::load(std::slice::from_ref(&bag), None).expect("load");
    let segments: Vec<_> = trajs.iter().map(|t| (t.start_index, t.frames)).collect();
    assert_eq!(segments, [(0, 5), (6, 2), (10, 2)]);
    for t in &trajs {
        assert_eq!(t.scene, frames[0].scene);
        for k in 0..t.frames {
            let f = &frames[t.frame_index(k) as usize];
            assert!(same_bits(t.state(k), &state_of(f)));
        }
    }
    let scene = frames[0].scene.clone();
    assert_eq!(
        report.gaps,
        [
            Gap {
                scene: scene.clone(),
                missing: 5..6
            },
            Gap {
                scene: scene.clone(),
                missing: 8..10
            }
        ]
    );
    assert_eq!(
        report.gaps[1].to_string(),
        format!("scene {scene:?}: 2 frames 8..=9 missing")
    );
    let infos = data::scan(&[bag], None).expect("scan");
    assert_eq!(infos[0].segments, [0..5, 6..8, 10..12]);
    assert_eq!((infos[0].frames, infos[0].windows(2)), (9, 3));
}

#[test]
fn changed_particle_count_is_an_error_naming_scene_and_frame() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let mut frames = simulate(5, 12);
    let scene = frames[0].scene.clone();
    frames[7].material.pop();
    frames[7].position.truncate(2 * 2499);
    frames[7].velocity.truncate(2 * 2499);
    let bag = dir.path().join("count.mcap");
    write_bag(&bag, &frames);
    let err = data::load(std::slice::from_ref(&bag), None).expect_err("particle count changed");
    match &err {
        DataError::Inconsistent {
            scene: s,
            frame,
            reference,
            path,
            ..
        } => {
            assert_eq!((s, *frame, *reference, path), (&scene, 7, 0, &bag));
        }
        other => panic!("wrong error: {other:?}"),
    }
    let text = err.to_string();
    assert!(text.contains(&scene) && text.contains("frame 7"), "{text}");
    assert!(text.contains("2499") && text.contains("2500"), "{text}");
    let scan_err = data::scan(&[bag], None).expect_err("scan sees it too");
    assert!(matches!(scan_err, DataError::Inconsistent { frame: 7, .. }));

    let mut frames = simulate(5, 12);
    frames[3].material[10] = (frames[3].material[10] + 1) % 4;
    let bag = dir.path().join("material.mcap");
    write_bag(&bag, &frames);
    let text = data::load(&[bag], None)
        .expect_err("material changed")
        .to_string();
    assert!(
        text.contains("frame 3") && text.contains("particle 10"),
        "{text}"
    );
}

/// The bags are decoded on worker threads (`data::decode`); what they give must be a one-thread
/// read's: bag after bag in path order, so a duplicate keeps the first bag's copy and the
/// index lists the bags in order, and a bad bag stops the read with its own error.
#[test]
fn many_bags_read_in_path_order_on_worker_threads() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let frames: Vec<_> = (0..24).map(|k| synthetic("many/000", k, 50, 1)).collect();
    for (k, frame) in frames.iter().enumerate() {
        write_bag(&dir.path().join(format!("a{k:02}.mcap")), [frame]);
        // The same frame index again, later in path order, with other values.
        let mut other = synthetic("many/001", k as u32, 50, 1);
        other.scene = frame.scene.clone();
        write_bag(&dir.path().join(format!("b{k:02}.mcap")), [&other]);
    }
    let folder = vec![dir.path().to_path_buf()];
    let (trajs, report) = data::load(&folder, None).expect("load");
    assert_eq!((trajs.len(), trajs[0].frames), (1, 24));
    for (k, frame) in frames.iter().enumerate() {
        assert!(same_bits(trajs[0].state(k), &state_of(frame)), "frame {k}");
    }
    assert_eq!(
        (report.bags, report.frames, report.duplicates),
        (48, 24, 24)
    );
    let infos = data::scan(&folder, None).expect("scan");
    let names: Vec<String> = infos[0]
        .bags
        .iter()
        .map(|p| p.file_name().expect("name").to_string_lossy().into_owned())
        .collect();
    let expected: Vec<String> = (0..24)
        .map(|k| format!("a{k:02}.mcap"))
        .chain((0..24).map(|k| format!("b{k:02}.mcap")))
        .collect();
    assert_eq!(names, expected);

    std::fs::write(dir.path().join("a05x.mcap"), b"not a bag at all").expect("write");
    let err = data::load(&folder, None).expect_err("a bad bag among good ones");
    assert!(matches!(err, DataError::Bag(_)), "{err}");
    assert!(err.to_string().contains("a05x.mcap"), "{err}");
}

#[test]
fn truncated_bag_gives_what_was_read_and_is_reported() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let frames: Vec<_> = (0..40).map(|k| synthetic("cut/000", k, 3000, 2)).collect();
    let whole = dir.path().join("whole.mcap");
    write_bag(&whole, &frames);
    let bytes = std::fs::read(&whole).expect("read");
    let cut = dir.path().join("cut.mcap");
    std::fs::write(&cut, &bytes[..bytes.len() * 6 / 10]).expect("write");
    let intact: Vec<_> = (0..4).map(|k| synthetic("cut/001", k, 10, 0)).collect();
    let other = dir.path().join("other.mcap");
    write_bag(&other, &intact);

    let inputs: Vec<PathBuf> = vec![cut.clone(), other];
    let (trajs, report) = data::load(&inputs, None).expect("load a cut bag");
    assert_eq!(report.truncated.len(), 1);
    assert_eq!(report.truncated[0].0, cut);
    let read = trajs
        .iter()
        .find(|t| t.scene == "cut/000")
        .expect("frames before the cut");
    assert!(
        read.frames > 0 && read.frames < 40,
        "{} frames",
        read.frames
    );
    assert_eq!(read.start_index, 0);
    for (k, frame) in frames.iter().enumerate().take(read.frames) {
        assert!(same_bits(read.state(k), &state_of(frame)));
    }
    assert!(trajs.iter().any(|t| t.scene == "cut/001" && t.frames == 4));
}

#[test]
fn inputs_without_frames_are_an_error() {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let bag = dir.path().join("other-topic.mcap");
    let mut writer = BagWriter::create(&bag).expect("create");
    writer
        .write(PREDICTED_TOPIC, &synthetic("x/000", 0, 5, 0))
        .expect("write");
    writer.finish().expect("finish");
    let err = data::load(&[bag], Some(TOPIC)).expect_err("nothing on the topic");
    assert!(matches!(err, DataError::NoFrames { bags: 1, .. }), "{err}");
    assert!(err.to_string().contains(TOPIC));
    let missing = dir.path().join("nope");
    assert!(matches!(
        data::load(&[missing], None),
        Err(DataError::Bag(_))
    ));
}
