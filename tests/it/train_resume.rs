//! A training run killed after 2 epochs and resumed from its checkpoint reproduces the
//! uninterrupted run's weights bit for bit (same seed, CPU backend, dropout on). Its own test
//! binary: burn's NdArray RNG is process-wide, so trainings running concurrently in one
//! process (as other tests would) interleave their dropout masks.

use burn::backend::NdArray;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::Tensor;
use minflow::data::{Scaler, WindowIndex};
use minflow::model::CoreKind;
use minflow::train::Trainer;

/// Every weight of the run's last checkpoint, in module order.
fn weights(dir: &std::path::Path) -> Vec<f32> {
    struct Collect(Vec<f32>);
    impl ModuleVisitor<NdArray<f32>> for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<NdArray<f32>, D>>) {
            self.0
                .extend(param.val().into_data().to_vec::<f32>().unwrap());
        }
    }
    let (model, _) = minflow::model::store::load::<NdArray<f32>>(dir, &Default::default()).unwrap();
    let mut c = Collect(Vec::new());
    model.visit(&mut c);
    c.0
}

use crate::train_support::{options, tiny, trajectory, B};

#[test]
fn resumed_run_equals_uninterrupted_run() {
    crate::isolated::run(
        concat!(module_path!(), "::resumed_run_equals_uninterrupted_run"),
        resumed_run_equals_uninterrupted_run_alone,
    );
}

/// [`resumed_run_equals_uninterrupted_run`]'s body, in a process of its own.
fn resumed_run_equals_uninterrupted_run_alone() {
    let traj = trajectory(32, 6);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj], 2, scaler).unwrap();
    let config = || tiny(CoreKind::MinGru, 32).with_dropout(0.2);
    let (a, b) = (
        crate::tmp::tempdir().unwrap(),
        crate::tmp::tempdir().unwrap(),
    );
    let full = Trainer::<B>::new(config(), options(4), a.path().into(), Default::default())
        .fit(&index, None, &scaler, false, |_, _| {})
        .unwrap();
    // "Killed" after 2 epochs, then resumed to 4.
    Trainer::<B>::new(config(), options(2), b.path().into(), Default::default())
        .fit(&index, None, &scaler, false, |_, _| {})
        .unwrap();
    let history = Trainer::<B>::new(config(), options(4), b.path().into(), Default::default())
        .fit(&index, None, &scaler, true, |_, _| {})
        .unwrap();
    assert_eq!(history.len(), 4);
    for (x, y) in full.iter().zip(&history) {
        assert_eq!(
            x.train_loss.to_bits(),
            y.train_loss.to_bits(),
            "epoch {}",
            x.epoch
        );
    }
    // The files also hold random parameter ids, so compare the weights themselves.
    let wa = weights(a.path());
    let wb = weights(b.path());
    assert_eq!(wa.len(), wb.len());
    assert!(
        wa.iter().zip(&wb).all(|(x, y)| x.to_bits() == y.to_bits()),
        "weights differ after resume"
    );
}
