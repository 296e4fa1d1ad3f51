//! Data-parallel training (`Trainer::data_parallel`) against a one-device run. Its own test
//! binary: burn's CPU random generator is one per process, and two runs can only start from
//! the same initial weights when no other test draws from it at the same time.

use minflow::data::{Layout, Scaler, WindowIndex};
use minflow::model::CoreKind;
use minflow::train::{EpochRecord, TrainOptions, Trainer};

use crate::train_support::{options, tiny, trajectory, B};

/// The paper trainer data-parallel (a persistent replica of the model and of Adam on the
/// second device through each epoch's two steps, the gradients summed by the group's
/// all-reduce: a host rendezvous on the CPU), on two CPU "devices" (the same ndarray device
/// twice): with dropout off the gradient of the summed shares is the batch gradient and the
/// replica takes the main model's step, so the losses of every epoch equal a one-device
/// run's up to float summation order. (On GPUs the same code runs with `--device
/// cuda:0,cuda:1`.)
#[test]
fn data_parallel_equals_one_device() {
    crate::isolated::run(
        concat!(module_path!(), "::data_parallel_equals_one_device"),
        data_parallel_equals_one_device_alone,
    );
}

/// [`data_parallel_equals_one_device`]'s body, in a process of its own.
fn data_parallel_equals_one_device_alone() {
    let traj = trajectory(32, 10);
    let scaler = Scaler::fit(&[&traj]);
    let index = WindowIndex::new(vec![traj], 2, scaler).unwrap();
    let opts = TrainOptions {
        batch_size: 4,
        micro_batch: 4,
        ..options(4)
    };
    let run = |devices: Vec<_>| {
        let dir = crate::tmp::tempdir().unwrap();
        let trainer = Trainer::<B>::data_parallel(
            tiny(CoreKind::MinGru, 32),
            opts.clone(),
            dir.path().to_path_buf(),
            devices,
        );
        trainer
            .fit(&index, None, &scaler, false, |_, _| {})
            .unwrap()
    };
    let one = run(vec![Default::default()]);
    let two = run(vec![Default::default(), Default::default()]);
    assert_same_losses(&one, &two);
    // Training moved: the check is not of four identical untouched epochs.
    assert!(one[3].train_loss < 0.9 * one[0].train_loss, "{one:?}");
}

/// The grid trainer data-parallel (`GridTrainer::replicas`: each batch cut into one share
/// per device, each share's gradient weighted by its share of the batch, summed by the
/// group's all-reduce) on two CPU "devices" against one: without input noise the losses of every
/// epoch equal a one-device run's up to float summation order. Each epoch's last batch has
/// one window: the second device takes a padding share that counts 0 (before it had none,
/// and both ranks waited for each other forever). (On GPUs the same code runs with
/// `--device cuda:0,cuda:1,...`; docs/training.md has those runs.)
#[test]
fn grid_data_parallel_equals_one_device() {
    crate::isolated::run(
        concat!(module_path!(), "::grid_data_parallel_equals_one_device"),
        grid_data_parallel_equals_one_device_alone,
    );
}

/// [`grid_data_parallel_equals_one_device`]'s body, in a process of its own.
fn grid_data_parallel_equals_one_device_alone() {
    use minflow::model::grid::{GridConfig, MemoryKind};
    use minflow::train::grid::{fit_stats, GridTrainOptions, GridTrainer};
    let traj = trajectory(64, 14);
    let stats = fit_stats(&[&traj]);
    let config = GridConfig {
        grid: 16,
        unet_width: 4,
        levels: 2,
        latent: 4,
        hidden: 4,
        head_hidden: 8,
        ..GridConfig::new(MemoryKind::MinGru)
            .with_window(2)
            .with_vel_scale(stats.vel_scale)
            .with_dv_mean(stats.dv_mean)
            .with_dv_scale(stats.dv_scale)
    };
    let opts = GridTrainOptions {
        epochs: 4,
        // 9 windows: batches of 4, 4 and 1.
        batch_size: 4,
        steps: 2,
        chunks: 2,
        clip: 1.0,
        lr: 3e-3,
        seed: 4,
        ..GridTrainOptions::default()
    };
    // The grid trainer's layout, as `train --arch grid` builds it for the devices: two
    // devices' batches written straight into their shares.
    let index = |devices| {
        WindowIndex::new(vec![traj.clone()], 2 + 2 * 2 - 1, Scaler::default())
            .unwrap()
            .with_layout(Layout::frames_for(devices))
    };
    let run = |replicas: Vec<_>| {
        let index = index(replicas.len() + 1);
        let dir = crate::tmp::tempdir().unwrap();
        let trainer = GridTrainer::<B> {
            config: config.clone(),
            opts: opts.clone(),
            out: dir.path().to_path_buf(),
            device: Default::default(),
            replicas,
            init_from: None,
            share: Default::default(),
            dataset: Default::default(),
        };
        let quiet = &mut minflow::train::Quiet;
        (trainer.fit(&mut &index, &[], &Scaler::default(), false, quiet)).unwrap()
    };
    let one = run(Vec::new());
    let two = run(vec![Default::default()]);
    assert_eq!((one.len(), two.len()), (4, 4));
    assert_same_losses(&one, &two);
    assert!(one[3].train_loss < 0.95 * one[0].train_loss, "{one:?}");
}

/// Every epoch's training loss of a two-device run within 1e-4 (relative) of the one-device
/// run's: the same gradients up to float summation order.
fn assert_same_losses(one: &[EpochRecord], two: &[EpochRecord]) {
    assert_eq!(one.len(), two.len());
    for (a, b) in one.iter().zip(two) {
        let rel = (a.train_loss - b.train_loss).abs() / a.train_loss;
        assert!(
            rel < 1e-4,
            "epoch {}: {:e} vs {:e}",
            a.epoch,
            a.train_loss,
            b.train_loss
        );
    }
}
