//! Scene generation: every scene id of both families passes the per-frame sanity checks of
//! `docs/mpm.md` ("Validation checks", check 6) over its first 100 frames; the families have the sizes the
//! paper gives; scene files parse, run, and fail with clear errors.

use minflow::sim::families::{self, Family, FLUID_KINDS, PAIRINGS};
use minflow::sim::{Material, Scene, SceneRun};

fn first_frames_are_sane(family: Family, seed: u64, ids: impl IntoIterator<Item = u32>) {
    let mut failures = Vec::new();
    for id in ids {
        let mut scene = families::scene(family, id, seed);
        scene.frames = 100;
        let name = scene.name.clone();
        let mut run = SceneRun::new(scene).unwrap();
        let mut count = 0;
        while let Some(frame) = run.next_frame() {
            match frame {
                Ok(_) => count += 1,
                Err(err) => {
                    failures.push(format!("{name} (seed {seed}): {err}"));
                    break;
                }
            }
        }
        assert!(count == 100 || !failures.is_empty());
        assert_eq!(
            run.solver().escaped,
            0,
            "{name} (seed {seed}): particles left the interpolation band"
        );
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

#[test]
fn every_multi_scene_is_sane_for_100_frames() {
    first_frames_are_sane(Family::Multi, 0, 0..Family::Multi.scene_count());
}

/// Issue 16's seed sweep: other seeds once failed 3 of 420 multi scenes ("liquid J = 0" at
/// frames 43-61, e.g. `multi/liquid+snow/007` with seed 2; seed 9001 scene 51 at frame 63)
/// before the liquid's J was floored (`sim::material::project`). Those two, and every third
/// multi scene holding liquid for seeds 1-7 (the whole 7 x 60 sweep runs with `simulate`).
#[test]
fn other_seeds_are_sane_for_100_frames() {
    first_frames_are_sane(Family::Multi, 2, [7]);
    first_frames_are_sane(Family::Multi, 9001, [51]);
    let liquid: Vec<u32> = (0..Family::Multi.scene_count())
        .filter(|&id| families::multi_materials(id).contains(&Material::Liquid))
        .collect();
    for seed in 1..=7u64 {
        let ids = liquid.iter().copied().skip(seed as usize % 3).step_by(3);
        first_frames_are_sane(Family::Multi, seed, ids);
    }
}

#[test]
fn every_fluid_scene_is_sane_for_100_frames() {
    first_frames_are_sane(Family::Fluid, 0, 0..Family::Fluid.scene_count());
}

#[test]
fn families_have_the_papers_sizes() {
    let mut pairs = [0; 6];
    for id in 0..60 {
        let s = families::scene(Family::Multi, id, 0);
        assert_eq!(s.particle_count(), 2500, "{}", s.name);
        assert_eq!((s.grid, s.substeps, s.frames), (64, 20, 625));
        assert!(s.name.starts_with("multi/") && s.name.ends_with(&format!("/{id:03}")));
        let ropes: usize = s
            .bodies
            .iter()
            .filter(|b| b.material == Material::Rope)
            .map(|b| b.count)
            .sum();
        assert!(ropes == 0 || (100..=300).contains(&ropes));
        let mats: Vec<Material> = s.bodies.iter().map(|b| b.material).collect();
        if let Some(k) = PAIRINGS.iter().position(|&(a, b)| mats == [a, b]) {
            pairs[k] += 1;
        }
        for b in &s.bodies {
            assert!(b.velocity[0].hypot(b.velocity[1]) <= 2.0 + 1e-6);
        }
    }
    assert_eq!(pairs, [8; 6], "8 scenes per pairing");
    for id in 0..40 {
        let s = families::scene(Family::Fluid, id, 0);
        assert_eq!((s.grid, s.substeps, s.particle_count()), (128, 80, 2500));
        assert!(
            (313..=1563).contains(&s.frames),
            "{}: {} frames",
            s.name,
            s.frames
        );
        assert!(s.name.contains(FLUID_KINDS[(id % 3) as usize]));
        assert!(s.bodies.iter().all(|b| b.material == Material::Liquid));
    }
    // Frames are 0.016 time units apart in both families.
    for f in [Family::Multi, Family::Fluid] {
        assert!((families::scene(f, 0, 0).frame_dt() - 0.016).abs() < 1e-7);
    }
}

#[test]
fn scenes_depend_on_id_and_seed_only() {
    assert_eq!(
        families::scene(Family::Multi, 9, 3),
        families::scene(Family::Multi, 9, 3)
    );
    assert_ne!(
        families::scene(Family::Multi, 9, 3),
        families::scene(Family::Multi, 9, 4)
    );
    assert_ne!(
        families::scene(Family::Fluid, 1, 0),
        families::scene(Family::Fluid, 4, 0)
    );
}

#[test]
fn the_example_scene_file_runs() {
    let text = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/launch_configs/scenes/example.toml"
    ))
    .unwrap();
    let mut scene = Scene::from_toml(&text).unwrap();
    assert_eq!(scene.bodies.len(), 3);
    assert_eq!(scene.particle_count(), 2500);
    scene.frames = 20;
    let frames: Vec<_> = SceneRun::new(scene)
        .unwrap()
        .collect::<Result<_, _>>()
        .unwrap();
    assert_eq!(frames.len(), 20);
    assert_eq!(frames[19].frame_index, 19);
    assert_eq!(frames[19].header.stamp.as_nanos(), 19 * 16_000_000);
}

#[test]
fn bad_scene_files_give_clear_errors() {
    let body = |count: u64| {
        format!("[[body]]\nshape = \"disk\"\nmaterial = \"jelly\"\nposition = [0.5, 0.5]\nsize = [0.2, 0.2]\ncount = {count}\n")
    };
    let overflowing = format!(
        "frames = 10\nname = \"x\"\n{}{}{}",
        body(i64::MAX as u64),
        body(i64::MAX as u64),
        body(3)
    );
    let named = |name: &str| format!("frames = 10\nname = {name:?}\n{}", body(10));
    let (empty_name, hidden_name, control_name) = (named(""), named(".x"), named("a\nb"));
    let cases = [
        ("frames = 10\n[[body]]\nshape = \"cube\"", "cube"),
        ("frames = 10\nname = \"x\"\nbody = []", "particles"),
        (
            "frames = 10\nname = \"x\"\n[[body]]\nshape = \"disk\"\nmaterial = \"jelly\"\nposition = [0.0, 0.5]\nsize = [0.2, 0.2]\ncount = 10",
            "outside",
        ),
        (
            "frames = 10\nname = \"x\"\n[[body]]\nshape = \"line\"\nmaterial = \"rope\"\nposition = [0.5, 0.5]\nsize = [0.4, 0.0]\ncount = 10",
            "spacing",
        ),
        ("frames = 10\nname = \"x\"\ncolour = 3\nbody = []", "colour"),
        // Counts whose sum wraps to 1 in usize arithmetic.
        (overflowing.as_str(), "particles"),
        // The name is the bag's file name: empty, hidden or with a control character.
        (empty_name.as_str(), "name \"\": must be non-empty"),
        (hidden_name.as_str(), "must not start with '.'"),
        (control_name.as_str(), "control characters"),
    ];
    for (text, needle) in cases {
        let err = Scene::from_toml(text).unwrap_err().to_string();
        assert!(err.contains(needle), "{text:?} -> {err}");
    }
}
