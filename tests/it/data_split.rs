//! The train/val/test split by scene id: deterministic for a seed whatever the input order,
//! different across seeds, disjoint and complete, 80:10:10 with at least one val and one test
//! scene from 3 scenes on, configurable fractions, and segments of a scene kept together.

use std::collections::BTreeSet;

use minflow::data::{DataError, Part, Split, SplitFractions, Trajectory};

fn ids(n: usize) -> Vec<String> {
    (0..n).map(|i| format!("multi/rope+snow/{i:03}")).collect()
}

fn sizes(s: &Split) -> (usize, usize, usize) {
    (s.train.len(), s.val.len(), s.test.len())
}

#[test]
fn same_seed_same_split_whatever_the_order() {
    let scenes = ids(60);
    let a = Split::new(&scenes, 42);
    let mut reversed = scenes.clone();
    reversed.reverse();
    let doubled: Vec<_> = scenes.iter().chain(&scenes).collect();
    assert_eq!(a, Split::new(&reversed, 42));
    assert_eq!(a, Split::new(doubled, 42), "duplicate ids count once");
    assert_eq!(a, Split::new(&scenes, 42));
}

#[test]
fn different_seeds_differ() {
    let scenes = ids(60);
    let splits: Vec<_> = (0..8).map(|seed| Split::new(&scenes, seed)).collect();
    for (i, a) in splits.iter().enumerate() {
        for b in &splits[i + 1..] {
            assert_ne!(a.test, b.test);
        }
    }
    let ten = ids(10);
    let distinct: BTreeSet<_> = (0..20).map(|seed| Split::new(&ten, seed).test).collect();
    assert!(
        distinct.len() > 5,
        "only {} distinct test sets",
        distinct.len()
    );
}

#[test]
fn parts_are_disjoint_sorted_and_cover_everything() {
    for n in 0..=70 {
        let scenes = ids(n);
        let split = Split::new(&scenes, n as u64);
        let mut all: Vec<_> = [&split.train, &split.val, &split.test]
            .into_iter()
            .flatten()
            .cloned()
            .collect();
        for part in [&split.train, &split.val, &split.test] {
            assert!(part.windows(2).all(|w| w[0] < w[1]), "sorted, no repeats");
        }
        all.sort();
        assert_eq!(all, scenes, "n = {n}");
        for s in &scenes {
            let part = split.part_of(s).expect("every scene has a part");
            assert!(split.scenes(part).contains(s));
        }
        assert_eq!(split.part_of("not/a/scene"), None);
    }
}

#[test]
fn eighty_ten_ten() {
    assert_eq!(sizes(&Split::new(ids(10), 1)), (8, 1, 1));
    assert_eq!(sizes(&Split::new(ids(60), 1)), (48, 6, 6));
    assert_eq!(sizes(&Split::new(ids(100), 1)), (80, 10, 10));
    // From 3 scenes on, val and test get at least one each.
    assert_eq!(sizes(&Split::new(ids(3), 1)), (1, 1, 1));
    assert_eq!(sizes(&Split::new(ids(4), 1)), (2, 1, 1));
    assert_eq!(sizes(&Split::new(ids(14), 1)), (12, 1, 1));
    assert_eq!(sizes(&Split::new(ids(15), 1)), (11, 2, 2));
    // Fewer: all train.
    assert_eq!(sizes(&Split::new(ids(2), 1)), (2, 0, 0));
    assert_eq!(sizes(&Split::new(ids(0), 1)), (0, 0, 0));
}

#[test]
fn configurable_fractions() {
    let f = |train, val, test| SplitFractions { train, val, test };
    let split = Split::with_fractions(ids(20), 3, f(0.7, 0.15, 0.15)).expect("valid");
    assert_eq!(sizes(&split), (14, 3, 3));
    let split = Split::with_fractions(ids(20), 3, f(8.0, 1.0, 1.0)).expect("ratios");
    assert_eq!(sizes(&split), (16, 2, 2));
    let split = Split::with_fractions(ids(20), 3, f(0.9, 0.1, 0.0)).expect("no test");
    assert_eq!(sizes(&split), (18, 2, 0));
    for bad in [f(-0.1, 0.5, 0.6), f(0.0, 0.0, 0.0), f(f64::NAN, 0.1, 0.1)] {
        let err = Split::with_fractions(ids(20), 3, bad).expect_err("invalid fractions");
        assert!(matches!(err, DataError::Config { .. }), "{err}");
    }
}

#[test]
fn segments_of_a_scene_stay_in_one_part() {
    let segment = |scene: &str, start: u32| Trajectory {
        scene: scene.to_owned(),
        dt: 0.016,
        material: vec![0; 2],
        start_index: start,
        states: vec![0.0; 3 * 2 * 4],
        frames: 3,
        n: 2,
        solver_grid: None,
    };
    let trajs: Vec<_> = ids(10)
        .iter()
        .flat_map(|s| [segment(s, 0), segment(s, 5), segment(s, 9)])
        .collect();
    let split = Split::new(trajs.iter().map(|t| &t.scene), 9);
    assert_eq!(split, Split::new(ids(10), 9));
    assert_eq!(split.select(Part::Test, &trajs).len(), 3);
    let (train, val, test) = split.partition(trajs);
    assert_eq!((train.len(), val.len(), test.len()), (24, 3, 3));
    for (part, trajs) in [
        (Part::Train, &train),
        (Part::Val, &val),
        (Part::Test, &test),
    ] {
        assert!(trajs.iter().all(|t| split.part_of(&t.scene) == Some(part)));
    }
    assert!(test.iter().all(|t| t.scene == test[0].scene));
}
