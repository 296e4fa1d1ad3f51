//! The grid run's validation score (`validation_rollout`): the rollouts of several scenes
//! packed into one batch score each scene as a call of its own would, scenes of another
//! particle count go into a call of their own, and the structure factor only adds.

use minflow::data::{Scaler, Trajectory};
use minflow::model::grid::MemoryKind;
use minflow::train::grid::validation_rollout;

use crate::model_support::{surrogate, tiny_grid};
use crate::train_support::trajectory;

/// `traj` without its first `skip` frames: another scene of the same particles.
fn later(traj: &Trajectory, skip: usize) -> Trajectory {
    let row = traj.n * 4;
    Trajectory {
        scene: format!("{}-later", traj.scene),
        states: traj.states[skip * row..].to_vec(),
        frames: traj.frames - skip,
        start_index: traj.start_index + skip as u32,
        ..traj.clone()
    }
}

#[test]
fn packed_validation_rollouts_score_each_scene_as_its_own_call() {
    // A small untrained grid model predicting 2 frames a call.
    let s = surrogate(tiny_grid(MemoryKind::MinGru).with_bundle(2), 4);
    let (a, c) = (trajectory(40, 30), trajectory(24, 30));
    let b = later(&a, 6);
    let scaler = Scaler::fit(&[&a, &b, &c]);
    let score = |trajs: &[Trajectory], structure| {
        validation_rollout(&s, trajs, &scaler, (2, 8), structure).unwrap()
    };
    let (one_a, one_b, one_c) = (
        score(&[a.clone()], false),
        score(&[b.clone()], false),
        score(&[c.clone()], false),
    );
    assert!(one_a.is_finite() && one_a > 0.0 && (one_a - one_b).abs() > 1e-3 * one_a);
    // a and b (40 particles, 2 rollouts each) go into one call; c (24) into another.
    let packed = score(&[a.clone(), c.clone(), b.clone()], false);
    let expected = (one_a * 40.0 + one_b * 40.0 + one_c * 24.0) / 104.0;
    assert!(
        (packed - expected).abs() <= 1e-6 * expected,
        "packed {packed} against the scenes' own calls {expected}"
    );
    let with_structure = score(&[a, c, b], true);
    assert!(with_structure >= packed, "{with_structure} < {packed}");
}
