//! The box a grid model clamps its predicted positions into (`GridConfig::box_grid`, `train
//! --box-grid`): MPM's `[0.5 dx, 1 - 1.5 dx]` of the network's grid by default, of the grid
//! asked for otherwise, the same on the CPU's host pass and the tensor path, and kept in a
//! run folder's `model.json`.

use burn::backend::NdArray;
use burn::tensor::{Tensor, TensorData};
use minflow::model::grid::{one_hot, GridConfig, MemoryKind, MemoryState, StepInput};
use minflow::model::store::{parse_meta, NetConfig};
use minflow::train::grid::initial_grid_model;

use crate::model_support::{meta, tiny_grid};

type B = NdArray<f32>;

/// A small untrained grid model on 16 cells (its box's right edge at 1 - 1.5 / 16 =
/// 0.90625) that predicts constant velocity.
fn config(box_grid: usize) -> GridConfig {
    (tiny_grid(MemoryKind::MinGru))
        .with_head_zero_init(true)
        .with_box_grid(box_grid)
}

/// Four liquid particles at x = 0.9 moving right at 5 a time unit, and four at x = 0.1
/// moving left: after one frame of 0.016, x = 0.98 and 0.02 if nothing clamps them.
fn input() -> StepInput<B> {
    let device = Default::default();
    let rows: Vec<[f32; 4]> = (0..8)
        .map(|i| {
            let y = 0.3 + 0.1 * (i % 4) as f32;
            if i < 4 {
                [0.9, y, 5.0, 0.0]
            } else {
                [0.1, y, -5.0, 0.0]
            }
        })
        .collect();
    let flat = |f: fn(&[f32; 4]) -> [f32; 2]| -> Vec<f32> { rows.iter().flat_map(f).collect() };
    let pos = flat(|r| [r[0], r[1]]);
    let vel = flat(|r| [r[2], r[3]]);
    let vel = Tensor::<B, 3>::from_data(TensorData::new(vel, [1, 8, 2]), &device);
    StepInput {
        pos: Tensor::from_data(TensorData::new(pos, [1, 8, 2]), &device),
        vel: Tensor::cat(vec![vel.clone(), vel], 2),
        material: one_hot(&[0; 8], minflow::material::COUNT, 1, 8, &device),
        dt: Tensor::from_data(TensorData::new(vec![0.016f32], [1]), &device),
        reference: None,
        rest: None,
        deformation: None,
    }
}

/// The predicted x of the eight particles, by the host pass and by the tensor path.
fn predicted_x(box_grid: usize) -> [Vec<f32>; 2] {
    let model = initial_grid_model::<B>(&config(box_grid), 3, &Default::default()).unwrap();
    [true, false].map(|host_pass| {
        let model = model.clone().with_host_pass(host_pass);
        let (out, _) = model.step(input(), MemoryState::Empty);
        let pos: Vec<f32> = out.pos.into_data().to_vec().unwrap();
        pos.chunks_exact(2).map(|p| p[0]).collect()
    })
}

#[test]
fn predicted_positions_stay_in_the_box_of_the_grid_asked_for() {
    let near = |got: &[f32], right: f32, left: f32| {
        let want = [right; 4].into_iter().chain([left; 4]);
        got.iter().zip(want).all(|(g, w)| (g - w).abs() < 1e-5)
    };
    // The network's own box: [0.5 / 16, 1 - 1.5 / 16].
    for x in predicted_x(0) {
        assert!(near(&x, 1.0 - 1.5 / 16.0, 0.5 / 16.0), "{x:?}");
    }
    // The finest solver's box holds both moves.
    for x in predicted_x(256) {
        assert!(near(&x, 0.98, 0.02), "{x:?}");
    }
    // A box between: [0.5 / 64, 1 - 1.5 / 64] clamps the right move only.
    for x in predicted_x(64) {
        assert!(near(&x, 1.0 - 1.5 / 64.0, 0.02), "{x:?}");
    }
}

#[test]
fn the_box_grid_round_trips_through_model_json_and_defaults_to_the_network_grid() {
    let meta = meta(config(256));
    let box_grid = |json: &serde_json::Value| match parse_meta(&json.to_string()).unwrap().net {
        NetConfig::Grid(c) => c.box_grid,
        NetConfig::Paper(_) => unreachable!(),
    };
    let mut json = serde_json::to_value(&meta).unwrap();
    assert_eq!(box_grid(&json), 256);
    json.as_object_mut().unwrap().remove("box_grid");
    assert_eq!(box_grid(&json), 0, "a model.json from before the field");
    assert!(config(4).validate().is_err() && config(8).validate().is_ok());
}
