//! `eval` metrics (issue 4): an oracle that returns the ground truth scores exactly 0 through
//! the same scoring code as the models; `persist` and `constvel` give the values computed by
//! hand on a 3-frame synthetic trajectory; missing steps are not scores; the density map and
//! the start offsets behave as documented.

use indicatif::ProgressBar;
use minflow::data::{Scaler, Trajectory};
use minflow::eval::{
    density_map, evaluate, frame_metrics, start_offsets, ConstVel, EvalError, Persist, Predictor,
    RolloutOptions,
};

/// Returns the true future frames: the perfect model.
struct Oracle;

impl Predictor for Oracle {
    fn name(&self) -> &str {
        "oracle"
    }
    fn window(&self) -> usize {
        2
    }
    fn rollout(
        &self,
        traj: &Trajectory,
        first: usize,
        steps: usize,
    ) -> Result<Vec<Vec<f32>>, EvalError> {
        Ok((first..first + steps)
            .map(|k| traj.state(k).to_vec())
            .collect())
    }
}

fn traj(frames: Vec<[[f32; 4]; 2]>) -> Trajectory {
    let n = frames.len();
    Trajectory {
        scene: "test/hand/000".into(),
        dt: 0.5,
        material: vec![0, 1],
        start_index: 0,
        states: frames.iter().flatten().flatten().copied().collect(),
        frames: n,
        n: 2,
        solver_grid: None,
    }
}

/// The 3-frame trajectory of the hand computation; 2 particles (liquid, jelly), dt = 0.5.
fn three_frames() -> Trajectory {
    traj(vec![
        [[0.1, 0.2, 0.0, 0.0], [0.5, 0.5, 0.0, 0.0]],
        [[0.2, 0.2, 0.2, 0.0], [0.5, 0.6, 0.0, 0.2]],
        [[0.35, 0.2, 0.3, 0.0], [0.5, 0.65, 0.0, 0.1]],
    ])
}

/// x, y in [0, 1] (range 1), vx, vy in [-1, 1] (range 2): scaled velocity errors are halved.
fn scaler() -> Scaler {
    Scaler {
        min: [0.0, 0.0, -1.0, -1.0, 0.0],
        max: [1.0, 1.0, 1.0, 1.0, 3.0],
    }
}

fn close(a: f64, b: f64) {
    // f32 inputs: differences of ~0.05 between values ~0.5 carry ~1e-6 relative rounding.
    assert!((a - b).abs() <= 2e-5 * b.abs().max(1e-3), "{a} != {b}");
}

fn opts(horizon: usize) -> RolloutOptions {
    RolloutOptions {
        horizon,
        starts: 1,
        window: 2,
        density_grid: 8,
        snapshots: true,
        ..RolloutOptions::default()
    }
}

#[test]
fn baselines_match_the_hand_computation() {
    let t = three_frames();
    let preds: [&dyn Predictor; 2] = [&Persist, &ConstVel];
    let eval = evaluate(
        &[t],
        &preds,
        &scaler(),
        "hand",
        &opts(1),
        &ProgressBar::hidden(),
    )
    .unwrap();
    assert_eq!(eval.predictors, ["persist", "constvel"]);
    let scene = &eval.scenes[0];
    assert_eq!(scene.rollouts, 1);
    // persist predicts frame 1 for frame 2. Errors p0: dx -0.15, dvx -0.1 (scaled -0.05);
    // p1: dy -0.05, dvy 0.1 (scaled 0.05). Squares 0.0225 + 0.0025 + 0.0025 + 0.0025 = 0.03
    // over 8 values: 0.00375.
    let p = scene.curves[0].last().unwrap();
    close(p.mse, 0.00375);
    close(p.mse_pos, (0.0225 + 0.0025) / 4.0);
    close(p.mse_vel, (0.0025 + 0.0025) / 4.0);
    close(p.mse_material[0].unwrap(), (0.0225 + 0.0025) / 4.0); // liquid p0
    close(p.mse_material[1].unwrap(), (0.0025 + 0.0025) / 4.0); // jelly p1
    assert_eq!(p.mse_material[2], None);
    close(p.phys_pos, (0.0225 + 0.0025) / 4.0);
    close(p.phys_vel, (0.01 + 0.01) / 4.0);
    // KE = 1/2 mean |v|^2: predicted (0.04 + 0.04) / 2 / 2 = 0.02, true (0.09 + 0.01) / 4 = 0.025.
    close(p.ke_err, 0.005);
    // Centres of mass (0.35, 0.4) and (0.425, 0.425).
    close(p.com_err, (0.075f64.powi(2) + 0.025f64.powi(2)).sqrt());
    assert_eq!(p.outside, 0.0);
    // constvel: p0 (0.2 + 0.2 * 0.5, 0.2) = (0.3, 0.2), p1 (0.5, 0.6 + 0.2 * 0.5) = (0.5, 0.7).
    // Errors p0: dx -0.05, dvx -0.1 (scaled -0.05); p1: dy 0.05, dvy 0.1 (scaled 0.05):
    // four squares of 0.0025 over 8 values: 0.00125.
    let c = scene.curves[1].last().unwrap();
    close(c.mse, 0.00125);
    close(c.mse_pos, 0.0025 / 2.0);
    close(c.phys_vel, 0.005);
    // One step only: avg1 = f1.
    assert_eq!(scene.curves[0].avg(), scene.curves[0].last());
}

#[test]
fn an_oracle_scores_zero_everywhere() {
    let t = three_frames();
    let preds: [&dyn Predictor; 3] = [&Oracle, &Persist, &ConstVel];
    let eval = evaluate(
        &[t],
        &preds,
        &scaler(),
        "hand",
        &opts(1),
        &ProgressBar::hidden(),
    )
    .unwrap();
    let m = eval.scenes[0].curves[0].avg().unwrap();
    for (name, v) in minflow::eval::metric_names().iter().zip(m.values()) {
        if !v.is_nan() {
            assert_eq!(v, 0.0, "{name}");
        }
    }
    // ...and the baselines do not.
    assert!(eval.scenes[0].curves[1].avg().unwrap().mse > 1e-3);
}

#[test]
fn short_trajectories_leave_later_steps_unscored_not_zero() {
    let t = three_frames();
    let preds: [&dyn Predictor; 1] = [&Persist];
    let eval = evaluate(
        &[t],
        &preds,
        &scaler(),
        "hand",
        &opts(3),
        &ProgressBar::hidden(),
    )
    .unwrap();
    let curve = &eval.scenes[0].curves[0];
    assert_eq!(curve.steps.len(), 3);
    assert_eq!(curve.scored(), 1);
    assert_eq!(curve.last(), None, "f3 does not exist for a 1-step rollout");
    close(curve.avg().unwrap().mse, 0.00375);
    assert!(
        eval.notes.iter().any(|n| n.contains("only 1 of 3 steps")),
        "{:?}",
        eval.notes
    );
    let table = minflow::eval::table::markdown(&eval);
    assert!(table.contains("n/a"), "{table}");
}

#[test]
fn particles_outside_the_box_are_counted() {
    let truth = [0.5f32, 0.5, 0.0, 0.0, 0.2, 0.2, 0.0, 0.0];
    let pred = [1.2f32, 0.5, 0.0, 0.0, 0.2, -0.01, 0.0, 0.0];
    let m = frame_metrics(&pred, &truth, &[0, 0], &scaler(), 0);
    assert_eq!(m.outside, 2.0);
    assert_eq!(m.outside_truth, 0.0);
}

#[test]
fn density_map_is_normalised_and_matches_the_tent_kernel() {
    // A particle at a cell centre lands in that cell only, with weight G^2 / N.
    let g = 4;
    let map = density_map(&[0.375, 0.625, 0.0, 0.0], g);
    assert_eq!(map[g + 2], 16.0);
    assert_eq!(map.iter().sum::<f64>(), 16.0);
    // Half way between two centres along x: split 50:50.
    let map = density_map(&[0.5, 0.625, 0.0, 0.0], g);
    assert_eq!((map[g + 2], map[2 * g + 2]), (8.0, 8.0));
    // Interior particles: the map sums to G^2 (mean 1).
    let state: Vec<f32> = (0..100)
        .flat_map(|i| [0.2 + 0.006 * i as f32, 0.7 - 0.005 * i as f32, 0.0, 0.0])
        .collect();
    close(density_map(&state, 8).iter().sum::<f64>(), 64.0);
}

#[test]
fn start_offsets_are_evenly_spaced() {
    assert_eq!(start_offsets(25, 2, 20, 1), vec![0]);
    assert_eq!(start_offsets(25, 2, 20, 3), vec![0, 2, 3]);
    assert_eq!(start_offsets(122, 2, 20, 5), vec![0, 25, 50, 75, 100]);
    assert_eq!(start_offsets(10, 2, 20, 4), vec![0]);
    assert!(start_offsets(2, 2, 20, 1).is_empty());
}

#[test]
fn recorded_one_step_predictions_get_one_step_baselines() {
    use minflow::eval::replay::ScenePredictions;
    use minflow::eval::{score_predictions, Predictions, ReplayOptions};
    let mut t = three_frames();
    // A fourth frame.
    t.states
        .extend_from_slice(&[0.5, 0.2, 0.3, -0.1, 0.5, 0.7, 0.05, 0.1]);
    t.frames = 4;
    // Perfect predictions of frames 2 and 3.
    let mut preds = Predictions::default();
    preds.scenes.insert(
        t.scene.clone(),
        ScenePredictions {
            material: t.material.clone(),
            frames: [(2, t.state(2).to_vec()), (3, t.state(3).to_vec())].into(),
            duplicates: 0,
        },
    );
    let baselines: [&dyn Predictor; 1] = [&Persist];
    let score = |one_step| {
        let opts = ReplayOptions {
            horizon: 2,
            one_step,
            density_grid: 0,
            snapshots: false,
        };
        score_predictions(
            &preds,
            "pred",
            &[t.clone()],
            &baselines,
            &scaler(),
            "s",
            &opts,
        )
        .unwrap()
    };
    let direct = |pred: usize, truth: usize| {
        frame_metrics(t.state(pred), t.state(truth), &t.material, &scaler(), 0).mse
    };
    for one_step in [false, true] {
        let eval = score(one_step);
        let scene = &eval.scenes[0];
        assert_eq!(scene.missing, [0, 0]);
        assert_eq!(
            scene.curves[0].avg().unwrap().mse,
            0.0,
            "the oracle scores 0"
        );
        // Step 1 is predicted from frame 1 either way; step 2 from frame 1 (rollout) or 2.
        close(scene.curves[1].steps[0].unwrap().mse, direct(1, 2));
        let seed = if one_step { 2 } else { 1 };
        close(scene.curves[1].steps[1].unwrap().mse, direct(seed, 3));
    }
}
