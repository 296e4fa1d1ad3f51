//! The min-max scaler: exact round trips over every value of a simulated trajectory, the
//! buffer forms agreeing with the per-value ones, fitting on the training split only (an
//! outlier in a test scene is ignored), constant features getting a range of 1, and serde.

use crate::data_support::{simulate, synthetic, write_bag};
use minflow::data::{self, Part, Scaler, Split, Trajectory, FEATURES};
use minflow::sim::{families, Family};

fn close(a: f32, v: f32) -> bool {
    (a - v).abs() <= 1e-6 * v.abs().max(1.0)
}

fn loaded(frames: &[minflow::msgs::ParticleFrame]) -> Trajectory {
    let dir = crate::tmp::tempdir().expect("tempdir");
    let bag = dir.path().join("s.mcap");
    write_bag(&bag, frames);
    let (mut trajs, _) = data::load(&[bag], None).expect("load");
    trajs.remove(0)
}

#[test]
fn round_trip_of_every_value_of_a_real_trajectory() {
    let traj = loaded(&simulate(1, 12));
    let scaler = Scaler::fit(&[&traj]);
    for f in 0..FEATURES {
        assert!(scaler.range(f) > 0.0 && scaler.min[f] < scaler.max[f]);
    }
    let mut worst = 0.0f32;
    for row in traj.states.chunks_exact(4) {
        for (f, &v) in row.iter().enumerate() {
            let s = scaler.scale(f, v);
            assert!(
                (0.0..=1.0).contains(&s),
                "training data scales into [0, 1]: {s}"
            );
            let back = scaler.unscale(f, s);
            assert!(close(back, v), "feature {f}: {v} -> {s} -> {back}");
            worst = worst.max((back - v).abs() / v.abs().max(1.0));
        }
    }
    for &m in &traj.material {
        let back = scaler.unscale(4, scaler.scale(4, f32::from(m)));
        assert_eq!(back, f32::from(m));
    }
    eprintln!("worst relative round-trip error {worst:e}");

    // Whole buffers: [N, 5] with materials, [N, 4] states, in place.
    let state = traj.state(11);
    let mut five = Vec::new();
    scaler.scale_into(state, &traj.material, &mut five);
    assert_eq!(five.len(), traj.n * 5);
    for (i, row) in five.chunks_exact(5).enumerate() {
        for f in 0..4 {
            assert_eq!(
                row[f].to_bits(),
                scaler.scale(f, state[4 * i + f]).to_bits()
            );
        }
        assert_eq!(row[4], scaler.scale(4, f32::from(traj.material[i])));
    }
    scaler.unscale_rows(&mut five, 5);
    let mut four = Vec::new();
    scaler.scale_state_into(state, &mut four);
    scaler.unscale_rows(&mut four, 4);
    for i in 0..traj.n {
        for f in 0..4 {
            let v = state[4 * i + f];
            assert!(close(five[5 * i + f], v) && close(four[4 * i + f], v));
        }
        assert_eq!(five[5 * i + 4], f32::from(traj.material[i]));
    }
    let mut rows = state.to_vec();
    scaler.scale_rows(&mut rows, 4);
    let mut scaled = Vec::new();
    scaler.scale_state_into(state, &mut scaled);
    assert_eq!(rows, scaled);
}

#[test]
fn fitted_on_training_scenes_only() {
    let ids: Vec<u32> = (0..10).collect();
    let names: Vec<String> = ids
        .iter()
        .map(|&i| families::scene(Family::Multi, i, 0).name)
        .collect();
    let split = Split::new(&names, 5);
    let outlier = &split.test[0];
    let dir = crate::tmp::tempdir().expect("tempdir");
    for &id in &ids {
        let mut frames = simulate(id, 6);
        if &frames[0].scene == outlier {
            frames[3].velocity[0] = 100.0; // vx of particle 0
            frames[3].velocity[1] = -100.0; // vy of particle 0
        }
        write_bag(&dir.path().join(format!("{id:03}.mcap")), &frames);
    }
    let (trajs, _) = data::load(&[dir.path().to_path_buf()], None).expect("load");
    let train = split.select(Part::Train, &trajs);
    assert_eq!(train.len(), 8);
    let scaler = Scaler::fit(&train);
    assert!(scaler.max[2] < 50.0 && scaler.min[3] > -50.0, "{scaler:?}");
    let everything: Vec<&Trajectory> = trajs.iter().collect();
    let all = Scaler::fit(&everything);
    assert_eq!(
        (all.max[2], all.min[3]),
        (100.0, -100.0),
        "the outlier is in the data"
    );
    // The training extremes are attained by training values.
    for f in 0..4 {
        let hit = |target: f32| {
            train
                .iter()
                .any(|t| t.states.chunks_exact(4).any(|r| r[f] == target))
        };
        assert!(hit(scaler.min[f]) && hit(scaler.max[f]), "feature {f}");
    }
}

#[test]
fn constant_features_get_a_range_of_one() {
    // All particles liquid (m = 0) and x = 0.5 everywhere.
    let mut frames: Vec<_> = (0..5).map(|k| synthetic("const/000", k, 50, 0)).collect();
    for f in &mut frames {
        f.position.iter_mut().step_by(2).for_each(|x| *x = 0.5);
    }
    let traj = loaded(&frames);
    let scaler = Scaler::fit(&[&traj]);
    assert_eq!(
        (scaler.min[0], scaler.max[0], scaler.range(0)),
        (0.5, 1.5, 1.0)
    );
    assert_eq!(
        (scaler.min[4], scaler.max[4], scaler.range(4)),
        (0.0, 1.0, 1.0)
    );
    let mut out = Vec::new();
    scaler.scale_into(traj.state(2), &traj.material, &mut out);
    assert!(out.iter().all(|v| v.is_finite()));
    assert!(out.chunks_exact(5).all(|r| r[0] == 0.0 && r[4] == 0.0));
    assert_eq!(scaler.unscale(0, 0.0), 0.5);
    // A scaler stored with max == min (hand-written) still never divides by zero.
    let degenerate = Scaler {
        min: [2.0; 5],
        max: [2.0; 5],
    };
    assert_eq!(degenerate.range(1), 1.0);
    assert_eq!(degenerate.scale(1, 3.0), 1.0);
    // No data at all: the identity.
    assert_eq!(Scaler::fit(&[]), Scaler::default());
}

#[test]
fn serde_round_trip() {
    let traj = loaded(&simulate(2, 4));
    let scaler = Scaler::fit(&[&traj]);
    let json = serde_json::to_string(&scaler).expect("serialize");
    assert!(json.contains("\"min\"") && json.contains("\"max\""));
    let back: Scaler = serde_json::from_str(&json).expect("deserialize");
    assert_eq!(back, scaler);
}
