//! Issue 46, structure by construction: a surrogate whose `model.json` has material
//! constraints projects every predicted frame onto them. On bundled bags the shipped
//! small model, with constraints fitted on those bags' truth, rolls out with its jelly body
//! whole and its rope within the fitted stretch, which it does not keep without them;
//! `--constraints off` predicts what the same model without constraints does, to the bit;
//! batched equals unbatched with the projection on; `constraints fit` leaves the truth's
//! own liquid frames nearly in place; `eval` reports the projection's moves and the kinetic
//! energy.

use std::path::{Path, PathBuf};

use burn::backend::NdArray;
use minflow::data::Trajectory;
use minflow::model::constraints::{self, Constraints, Parts};
use minflow::model::store::{parse_meta, Predict, SceneStep, Surrogate};

fn repo(p: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(p)
}

/// The bundled bag `name`'s trajectory.
fn bag(name: &str) -> Trajectory {
    let (mut trajs, _) = minflow::data::load(
        &[repo(&format!("bags/{name}.mcap"))],
        Some(minflow::bag::FRAMES_TOPIC),
    )
    .unwrap();
    trajs.remove(0)
}

/// A copy of the shipped `model` with `constraints` in its model.json (None: without).
fn with_constraints(model: &str, constraints: Option<&Constraints>) -> tempfile::TempDir {
    let dir = crate::tmp::tempdir().unwrap();
    let from = repo(&format!("models/{model}"));
    std::fs::copy(from.join("model.mpk"), dir.path().join("model.mpk")).unwrap();
    let mut meta = parse_meta(&std::fs::read_to_string(from.join("model.json")).unwrap()).unwrap();
    meta.constraints = constraints.cloned();
    std::fs::write(
        dir.path().join("model.json"),
        serde_json::to_string(&meta).unwrap(),
    )
    .unwrap();
    dir
}

/// Constraints fitted on the bundled bags' truth.
fn fitted() -> Constraints {
    let trajs: Vec<Trajectory> = [
        "multi_rope+snow_001",
        "multi_jelly+liquid_002",
        "fluid_circle_000",
    ]
    .iter()
    .map(|n| bag(n))
    .collect();
    constraints::fit(&trajs, &Constraints::defaults()).0
}

/// `steps` frames rolled out from frame 1 of `traj` (seed frames 0 and 1, frame 0 the rest).
fn rollout(s: &Surrogate<NdArray<f32>>, traj: &Trajectory, steps: usize) -> Vec<Vec<f32>> {
    let seed = vec![traj.state(0).to_vec(), traj.state(1).to_vec()];
    s.rollout(Some(traj.state(0)), &seed, &traj.material, traj.dt, steps)
        .unwrap()
}

/// The largest link stretch of the rope (material 3, consecutive particles) in `frame`.
fn rope_stretch(rest: &[f32], frame: &[f32], material: &[u8]) -> f32 {
    let d = |f: &[f32], i: usize| (f[4 * i + 4] - f[4 * i]).hypot(f[4 * i + 5] - f[4 * i + 1]);
    (0..material.len() - 1)
        .filter(|&i| material[i] == 3 && material[i + 1] == 3)
        .map(|i| d(frame, i) / d(rest, i))
        .fold(0.0, f32::max)
}

#[test]
fn projected_rollouts_keep_the_rope_within_its_stretch_and_the_jelly_whole() {
    let c = fitted();
    let stretch = c.rope.unwrap().stretch;
    assert!(
        (1.0..1.6).contains(&stretch),
        "fitted rope stretch {stretch}"
    );
    let on = with_constraints("all-grid-mingru-small", Some(&c));
    let s = Surrogate::<NdArray<f32>>::load(on.path(), &Default::default()).unwrap();
    let rope = bag("multi_rope+snow_001");
    let frames = rollout(&s, &rope, 40);
    for (k, f) in frames.iter().enumerate() {
        let worst = rope_stretch(rope.state(0), f, &rope.material);
        // Gauss-Seidel sweeps along a chain leave a link a little past the limit at most.
        assert!(
            worst <= stretch * 1.1,
            "step {k}: rope link at {worst}x its rest length (limit {stretch})"
        );
        assert!(f.iter().all(|v| v.is_finite()));
    }
    let moved = s.take_corrections();
    assert!(
        moved.mean(3).is_some_and(|m| m > 0.0),
        "the rope was projected"
    );
    // The jelly: every rest-neighbour pair intact (shape matching keeps the body rigid).
    let jelly = bag("multi_jelly+liquid_002");
    let neighbours = minflow::eval::plausibility::Neighbours::new(jelly.state(0), &jelly.material);
    let frames = rollout(&s, &jelly, 40);
    let intact = neighbours.intact_fraction(&frames[39], 1).unwrap();
    assert!(intact >= 0.999, "jelly intact {intact} with the projection");
    // The same model without constraints does not keep the rope within the stretch.
    let off = with_constraints("all-grid-mingru-small", None);
    let plain = Surrogate::<NdArray<f32>>::load(off.path(), &Default::default()).unwrap();
    let frames = rollout(&plain, &rope, 40);
    let worst = frames
        .iter()
        .map(|f| rope_stretch(rope.state(0), f, &rope.material))
        .fold(0.0, f32::max);
    assert!(
        worst > stretch * 1.5,
        "without the projection: {worst} (limit {stretch})"
    );
}

#[test]
fn constraints_off_predicts_what_the_model_without_them_does() {
    let c = fitted();
    let on = with_constraints("all-grid-mingru-small-k4", Some(&c));
    let none = with_constraints("all-grid-mingru-small-k4", None);
    let traj = bag("multi_jelly+liquid_002");
    let off = Surrogate::<NdArray<f32>>::load(on.path(), &Default::default())
        .unwrap()
        .with_constraints(Parts::NONE);
    let plain = Surrogate::<NdArray<f32>>::load(none.path(), &Default::default()).unwrap();
    assert!(off.constraints().is_none());
    assert_eq!(rollout(&off, &traj, 9), rollout(&plain, &traj, 9));
    // And on, the rollout differs.
    let projected = Surrogate::<NdArray<f32>>::load(on.path(), &Default::default()).unwrap();
    assert_ne!(rollout(&projected, &traj, 9), rollout(&plain, &traj, 9));
}

#[test]
fn batched_projected_steps_equal_steps_one_scene_at_a_time() {
    let c = fitted();
    let on = with_constraints("all-grid-mingru-small", Some(&c));
    let s = Surrogate::<NdArray<f32>>::load(on.path(), &Default::default()).unwrap();
    let scenes: Vec<Trajectory> = [
        "multi_rope+snow_001",
        "multi_jelly+liquid_002",
        "fluid_splash_002",
    ]
    .iter()
    .map(|n| bag(n))
    .collect();
    let alone: Vec<Vec<Vec<f32>>> = scenes
        .iter()
        .map(|t| {
            let mut state = s.init_state();
            let mut outs = Vec::new();
            for k in 0..5 {
                let (out, st) = s.step(t.state(k), &t.material, &[t.dt], state).unwrap();
                state = st;
                outs.push(out);
            }
            outs
        })
        .collect();
    let mut states: Vec<_> = scenes.iter().map(|_| Some(s.init_state())).collect();
    for k in 0..5 {
        let steps = scenes
            .iter()
            .zip(states.iter_mut())
            .map(|(t, st)| SceneStep {
                rows: t.state(k).to_vec(),
                material: &t.material,
                dt: t.dt,
                state: st.take().unwrap(),
            })
            .collect();
        let batch = s.step_scenes(steps, Predict::Next);
        assert_eq!(batch.calls, [3]);
        for (i, result) in batch.results.into_iter().enumerate() {
            let (out, st) = result.unwrap();
            let worst = out[0]
                .iter()
                .zip(&alone[i][k])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f32::max);
            assert!(worst <= 1e-5, "scene {i} frame {k}: {worst}");
            states[i] = Some(st);
        }
    }
}

#[test]
fn the_fitted_liquid_density_leaves_the_truth_in_place() {
    let trajs = vec![bag("fluid_circle_000"), bag("fluid_splash_002")];
    let base = Constraints {
        liquid: Some(constraints::DensityParams::LOOSE),
        ..Constraints::default()
    };
    let (c, report) = constraints::fit(&trajs, &base);
    let rest = c.liquid.unwrap().rest;
    let &(tried, moved) = report.liquid_moves.last().unwrap();
    assert_eq!(tried, rest);
    assert!(
        moved < constraints::fit::TRUTH_MOVE,
        "{moved} spacings a frame"
    );
    // A lower rest density than the fitted one moves the truth more.
    if report.liquid_moves.len() > 1 {
        let (_, before) = report.liquid_moves[report.liquid_moves.len() - 2];
        assert!(before >= constraints::fit::TRUTH_MOVE);
    }
}

/// The pressure part's threshold, fitted per solver grid on bags that record it (the bundled
/// ones), moves the truth's own liquid less than 0.02 spacings a frame on each grid, and a
/// tighter one moves it more (the check: the truth stays in place).
#[test]
fn the_fitted_pressure_threshold_leaves_the_truth_in_place() {
    let trajs: Vec<_> = [
        "fluid_circle_000",
        "fluid_splash_002",
        "multi_jelly+liquid_002",
    ]
    .into_iter()
    .map(bag)
    .collect();
    assert!(
        trajs.iter().all(|t| t.solver_grid.is_some()),
        "the bags record their grid"
    );
    let base = Constraints {
        pressure: Constraints::defaults().pressure,
        ..Constraints::default()
    };
    let (c, report) = constraints::fit(&trajs, &base);
    let p = c.pressure.unwrap();
    assert_eq!(
        report.pressure_by_grid.len(),
        2,
        "the 64 x 64 and 128 x 128 scenes"
    );
    for (grid, moves, met) in &report.pressure_by_grid {
        assert!(*met, "grid {grid}: {moves:?}");
        let &(tried, moved) = moves.last().unwrap();
        assert_eq!(tried, p.rest_for(Some(*grid)));
        assert!(moved < constraints::fit::TRUTH_MOVE, "grid {grid}: {moved}");
        if moves.len() > 1 {
            assert!(
                moves[moves.len() - 2].1 >= constraints::fit::TRUTH_MOVE,
                "{moves:?}"
            );
        }
    }
}

#[test]
fn fit_writes_model_json_and_eval_reports_moves_and_energy() {
    let dir = with_constraints("all-grid-mingru-small-k4", None);
    let model = dir.path().to_str().unwrap();
    let bags = repo("bags");
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_minflow"))
            .args(args)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned();
        assert!(
            out.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        text
    };
    // The shipped folder's split names scenes of the full dataset: none is bundled, so
    // this folder's split is the seeded split of the bundled bags.
    std::fs::remove_file(dir.path().join("split.json")).ok();
    let printed = run(&[
        "constraints",
        "fit",
        "--model",
        model,
        "--data",
        bags.to_str().unwrap(),
    ]);
    assert!(printed.contains("rope: stretch"), "{printed}");
    let meta =
        parse_meta(&std::fs::read_to_string(dir.path().join("model.json")).unwrap()).unwrap();
    let fitted = meta.constraints.unwrap();
    assert!(
        fitted.rope.is_some()
            && fitted.pressure.is_some()
            && fitted.liquid.is_none()
            && fitted.momentum.is_some()
            && fitted.rebound.is_some()
    );
    // The bundled bags carry their solver grid, so the walls are fitted in solver cells too:
    // the solver's boundary nodes (index < 3) stop its particles short of 3 cells.
    let cells = fitted.walls.unwrap().cells.expect("walls in solver cells");
    assert!((1.0..3.0).contains(&cells), "{cells}");
    // Fitting one part rewrites that part and keeps the others as they were.
    let mut edited = fitted.clone();
    edited.walls.as_mut().unwrap().lo = 0.25;
    let path = dir.path().join("model.json");
    let mut json = crate::json(&path);
    json["constraints"] = serde_json::to_value(&edited).unwrap();
    std::fs::write(&path, json.to_string()).unwrap();
    let args = [
        "constraints",
        "fit",
        "--model",
        model,
        "--parts",
        "walls",
        "--max-scenes",
        "2",
    ];
    run(&[&args[..], &["--data", bags.to_str().unwrap()]].concat());
    let refit = parse_meta(&std::fs::read_to_string(&path).unwrap())
        .unwrap()
        .constraints
        .unwrap();
    assert_ne!(refit.walls, edited.walls, "the walls were not fitted again");
    assert_eq!(
        (refit.rope, refit.jelly, refit.contact, &refit.pressure),
        (fitted.rope, fitted.jelly, fitted.contact, &fitted.pressure)
    );
    assert_eq!(
        (refit.momentum, refit.rebound),
        (fitted.momentum, fitted.rebound)
    );
    let out = crate::tmp::tempdir().unwrap();
    let bag = repo("bags/multi_jelly+liquid_002.mcap");
    run(&[
        "eval",
        "--model",
        model,
        "--data",
        bag.to_str().unwrap(),
        "--split",
        "all",
        "--horizon",
        "10",
        "--no-render",
        "--constraints",
        "off",
        "--constraints",
        "on",
        "-o",
        out.path().to_str().unwrap(),
    ]);
    let table = std::fs::read_to_string(out.path().join("table.md")).unwrap();
    let name = dir
        .path()
        .file_name()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    assert!(table.contains(&format!("| {name}[on] |")), "{table}");
    assert!(table.contains(&format!("| {name}[off] |")));
    assert!(table.contains("Constraint projection"), "{table}");
    let csv = std::fs::read_to_string(out.path().join("plausibility.csv")).unwrap();
    let header: Vec<&str> = csv.lines().next().unwrap().split(',').collect();
    let col = header.iter().position(|h| *h == "energy").unwrap();
    let energy: Vec<f64> = csv
        .lines()
        .skip(1)
        .filter(|l| l.contains(",persist,") && l.contains(",liquid,"))
        .map(|l| l.split(',').nth(col).unwrap().parse().unwrap())
        .collect();
    // persist keeps the seed frame's velocities: some energy, not the truth's.
    assert!(!energy.is_empty() && energy.iter().all(|e| e.is_finite() && *e > 0.0));
}

#[test]
fn momentum_and_rebound_leave_the_solvers_frames_in_place_and_correct_a_slowed_body() {
    use minflow::model::constraints::{MomentumParams, ReboundParams, SceneShape};
    use minflow::sim::scene::Scene;
    // Two jelly disks thrown at each other (the held-out `collide` kind, fewer particles and
    // a third of its speed), 30 frames: they fly free, clear of the walls, apart until
    // frame 7, in contact from frame 9 and apart again.
    let mut scene = Scene::from_toml(
        &std::fs::read_to_string(repo("launch_configs/scenes/heldout/collide.toml")).unwrap(),
    )
    .unwrap();
    for body in &mut scene.bodies {
        body.count = 300;
        body.velocity[0] /= 3.0;
    }
    scene.frames = 30;
    let frames: Vec<Vec<f32>> = minflow::sim::run::SceneRun::new(scene.clone())
        .unwrap()
        .map(|f| {
            let f = f.unwrap();
            let mut state = Vec::new();
            for (x, v) in f.position.chunks_exact(2).zip(f.velocity.chunks_exact(2)) {
                state.extend([x[0], x[1], v[0], v[1]]);
            }
            state
        })
        .collect();
    let material = vec![1u8; frames[0].len() / 4];
    let c = Constraints {
        momentum: Some(MomentumParams::DEFAULT),
        rebound: Some(ReboundParams::DEFAULT),
        ..Default::default()
    };
    let dt = scene.frame_dt();
    let mut shape = SceneShape::new(&frames[0], 4, &material, &c);
    let mean_vx = |f: &[f32], r: std::ops::Range<usize>| {
        r.clone().map(|i| f[4 * i + 2]).sum::<f32>() / r.len() as f32
    };
    // The largest difference of `a` and `b` over the columns `cols` of their rows.
    let worst = |a: &[f32], b: &[f32], cols: std::ops::Range<usize>| {
        a.chunks_exact(4)
            .zip(b.chunks_exact(4))
            .flat_map(|(a, b)| cols.clone().map(move |c| (a[c] - b[c]).abs()))
            .fold(0.0, f32::max)
    };
    for k in 1..frames.len() {
        // The truth's own transition: moved by f32 rounding alone (positions by 2e-6 while
        // the disks fly free, less than the gravity term's 1/S share of 5e-5).
        let mut frame = frames[k].clone();
        shape.project(&c, (Some(&frames[k - 1]), &mut frame), &material, dt);
        let moved = worst(&frame, &frames[k], 0..4);
        assert!(
            moved < 2e-4,
            "frame {k}: the truth moved by {moved} (left disk vx {} -> {})",
            mean_vx(&frames[k], 0..300),
            mean_vx(&frame, 0..300)
        );
        if k <= 6 {
            let moved = worst(&frame, &frames[k], 0..2);
            assert!(moved < 2e-6, "frame {k}: positions moved {moved}");
        }
    }
    // The same scene with the left disk slowed by a third each frame while it flies free:
    // its momentum comes back.
    let mut shape = SceneShape::new(&frames[0], 4, &material, &c);
    for k in 1..7 {
        let mut slowed = frames[k].clone();
        for (row, old) in slowed
            .chunks_exact_mut(4)
            .zip(frames[k - 1].chunks_exact(4))
            .take(300)
        {
            row[0] = old[0] + (row[0] - old[0]) * 2.0 / 3.0;
            row[2] *= 2.0 / 3.0;
        }
        shape.project(&c, (Some(&frames[k - 1]), &mut slowed), &material, dt);
        let off = worst(&slowed, &frames[k], 0..4);
        assert!(off < 2e-4, "frame {k}: the slowed disk is off by {off}");
    }
}
