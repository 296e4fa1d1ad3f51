//! Training end to end on tiny networks: each of the five cores overfits a 4-frame dataset
//! (one test per core, each in a process of its own, so that two train at once)
//! to below 1e-4 of its starting loss (a synthetic trajectory made by the model's own
//! integrator, `v' = v + a dt`, `x' = x + v' dt`: on MLS-MPM frames a dv-only output leaves
//! an irreducible position residual, about 4e-3 of the starting loss); data with another particle count than the
//! model's N is a clear error; the stateful API's one-step prediction equals training's.

use burn::backend::NdArray;
use minflow::data::{Scaler, WindowIndex};
use minflow::model::store::Surrogate;
use minflow::model::CoreKind;
use minflow::train::{TrainOptions, Trainer};

use crate::train_support::{integrator_trajectory, options, tiny, trajectory, B};

/// One test per core: `core_overfits_four_frames!(test: core, ...)` defines each test (its
/// body in a process of its own) and [`OVERFIT_TESTS`], the cores they cover.
macro_rules! core_overfits_four_frames {
    ($($test:ident: $core:expr),* $(,)?) => {
        $(
            #[test]
            fn $test() {
                crate::isolated::run(concat!(module_path!(), "::", stringify!($test)), || {
                    overfits_four_frames($core)
                });
            }
        )*
        /// The cores that have an overfitting test.
        const OVERFIT_TESTS: &[CoreKind] = &[$($core),*];
    };
}

core_overfits_four_frames! {
    mlp_overfits_four_frames: CoreKind::Mlp,
    lstm_overfits_four_frames: CoreKind::Lstm,
    gru_overfits_four_frames: CoreKind::Gru,
    minlstm_overfits_four_frames: CoreKind::MinLstm,
    mingru_overfits_four_frames: CoreKind::MinGru,
}

/// Every core has its overfitting test (a core added to `CoreKind::ALL` needs one).
#[test]
fn every_core_has_an_overfitting_test() {
    assert_eq!(OVERFIT_TESTS, CoreKind::ALL.as_slice());
}

/// `core` trained on the 4-frame integrator trajectory reaches a training loss below 1e-4
/// of its first epoch's.
fn overfits_four_frames(core: CoreKind) {
    let traj = integrator_trajectory(32, 4);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj], 2, scaler).unwrap();
    assert_eq!(index.len(), 2);
    let dir = crate::tmp::tempdir().unwrap();
    // Each core's loss stays on a plateau, then falls through 1e-4 of its start within ~100
    // epochs: at epoch 1247 (mlp), 1267 (lstm), 1448 (gru), 1538 (minlstm) and 1514 (mingru).
    // 2,000 epochs leave a third more than the slowest needs.
    let opts = TrainOptions {
        lr: 1e-3,
        ..options(2000)
    };
    let trainer = Trainer::<B>::new(
        tiny(core, 32),
        opts,
        dir.path().to_path_buf(),
        Default::default(),
    );
    let history = trainer
        .fit(&index, None, &scaler, false, |_, _| {})
        .unwrap();
    let first = history[0].train_loss;
    let best = history
        .iter()
        .map(|r| r.train_loss)
        .fold(f64::INFINITY, f64::min);
    assert!(
        best < 1e-4 * first,
        "{}: loss {first:e} -> {best:e}",
        core.name()
    );
}

#[test]
fn particle_count_mismatch_is_a_clear_error() {
    crate::isolated::run(
        concat!(module_path!(), "::particle_count_mismatch_is_a_clear_error"),
        particle_count_mismatch_is_a_clear_error_alone,
    );
}

/// [`particle_count_mismatch_is_a_clear_error`]'s body, in a process of its own.
fn particle_count_mismatch_is_a_clear_error_alone() {
    let traj = trajectory(20, 4);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj], 2, scaler).unwrap();
    let dir = crate::tmp::tempdir().unwrap();
    let err = Trainer::<B>::new(
        tiny(CoreKind::MinGru, 32),
        options(1),
        dir.path().into(),
        Default::default(),
    )
    .fit(&index, None, &scaler, false, |_, _| {})
    .expect_err("N mismatch must fail");
    assert!(
        err.to_string().contains("N = 32") && err.to_string().contains("[20]"),
        "{err}"
    );
}

#[test]
fn stateful_step_equals_training_forward() {
    crate::isolated::run(
        concat!(module_path!(), "::stateful_step_equals_training_forward"),
        stateful_step_equals_training_forward_alone,
    );
}

/// [`stateful_step_equals_training_forward`]'s body, in a process of its own.
fn stateful_step_equals_training_forward_alone() {
    let traj = trajectory(32, 5);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj.clone()], 2, scaler).unwrap();
    for core in CoreKind::ALL {
        let dir = crate::tmp::tempdir().unwrap();
        Trainer::<B>::new(
            tiny(core, 32),
            options(3),
            dir.path().into(),
            Default::default(),
        )
        .fit(&index, None, &scaler, false, |_, _| {})
        .unwrap();
        let surrogate = Surrogate::<NdArray<f32>>::load(dir.path(), &Default::default()).unwrap();
        // Seeded with frames 0 and 1, the rollout's first frame predicts frame 2.
        let seed = vec![traj.state(0).to_vec(), traj.state(1).to_vec()];
        let rollout = surrogate
            .rollout(None, &seed, &traj.material, traj.dt, 1)
            .unwrap();
        let (model, meta) =
            minflow::model::store::load::<NdArray<f32>>(dir.path(), &Default::default()).unwrap();
        let batch = index.batches(1, None, 0).find(|b| b.ids[0].1 == 0).unwrap();
        let device = Default::default();
        let inputs = burn::tensor::Tensor::<NdArray<f32>, 4>::from_data(
            burn::tensor::TensorData::new(batch.inputs.clone(), [1, 2, 32, 5]),
            &device,
        );
        let dt = burn::tensor::Tensor::<NdArray<f32>, 1>::from_data(
            burn::tensor::TensorData::new(batch.dt.clone(), [1]),
            &device,
        );
        let scaled: Vec<f32> = model
            .forward(inputs, dt, &meta.scaling())
            .into_data()
            .to_vec()
            .unwrap();
        let scaling = meta.scaling();
        for (k, (&s, &r)) in scaled.iter().zip(&rollout[0]).enumerate() {
            let phys = s * scaling.range[k % 4] + scaling.min[k % 4];
            assert!(
                (phys - r).abs() <= 1e-5 * phys.abs().max(1.0),
                "{}: value {k}: {phys} vs {r}",
                core.name()
            );
        }
    }
}

/// A loss that turns NaN or infinite stops training with an error naming epoch and batch.
#[test]
fn non_finite_loss_is_a_clear_error() {
    crate::isolated::run(
        concat!(module_path!(), "::non_finite_loss_is_a_clear_error"),
        non_finite_loss_is_a_clear_error_alone,
    );
}

/// [`non_finite_loss_is_a_clear_error`]'s body, in a process of its own.
fn non_finite_loss_is_a_clear_error_alone() {
    let traj = trajectory(32, 8);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj], 2, scaler).unwrap();
    let dir = crate::tmp::tempdir().unwrap();
    let opts = TrainOptions {
        lr: 1e30,
        batch_size: 1,
        micro_batch: 1,
        ..options(20)
    };
    let err = Trainer::<B>::new(
        tiny(CoreKind::Gru, 32),
        opts,
        dir.path().into(),
        Default::default(),
    )
    .fit(&index, None, &scaler, false, |_, _| {})
    .expect_err("lr 1e30 must blow up");
    let text = err.to_string();
    assert!(
        matches!(err, minflow::train::TrainError::NonFinite { .. }),
        "{text}"
    );
    assert!(
        text.contains("non-finite loss") && text.contains("epoch") && text.contains("batch"),
        "{text}"
    );
}
