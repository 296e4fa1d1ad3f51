//! Shared helpers of the grid-model tests: a tiny untrained grid network, the description a
//! run folder's `model.json` holds for it, and a surrogate around it.

use burn::backend::NdArray;
use minflow::data::Scaler;
use minflow::model::grid::{GridConfig, MemoryKind};
use minflow::model::store::{ModelMeta, Net, NetConfig, Surrogate};
use minflow::train::grid::initial_grid_model;

/// The grid network of the model tests, the in-process twin of [`crate::TINY_GRID_NET`]
/// (16 x 16 grid, two levels, widths 4 to 8), with velocity changes at a tenth of a unit
/// and the head's last layer drawn at random, so an untrained model moves its particles.
pub fn tiny_grid(memory: MemoryKind) -> GridConfig {
    GridConfig::new(memory)
        .with_grid(16)
        .with_levels(2)
        .with_unet_width(4)
        .with_latent(4)
        .with_hidden(4)
        .with_head_hidden(8)
        .with_dv_scale([0.1, 0.1])
        .with_head_zero_init(false)
}

/// A grid model's description: `config`, the default scaler, epoch 0, no constraints.
pub fn meta(config: GridConfig) -> ModelMeta {
    ModelMeta {
        net: NetConfig::Grid(config),
        scaler: Scaler::default(),
        epoch: 0,
        val_loss: 0.0,
        constraints: None,
    }
}

/// A surrogate around `config`'s model with fresh weights drawn from `seed`
/// ([`initial_grid_model`]), on the CPU.
pub fn surrogate(config: GridConfig, seed: u64) -> Surrogate<NdArray<f32>> {
    let device = Default::default();
    let model = initial_grid_model::<NdArray<f32>>(&config, seed, &device).unwrap();
    Surrogate::from_net(Net::Grid(model), meta(config), &device)
}
