//! The integration tests, as one test binary (ripgrep keeps one integration-test crate the
//! same way): each module below was its own binary before, and linking the whole stack
//! (zenoh, burn, iceoryx2, ros2-client) once instead of 22 times is most of the build's
//! time saved. The training tests that need burn's per-process CPU generator to themselves
//! (`train_loop`, `train_resume`, `train_parallel`) and the ros2-zenoh tests of
//! `transport_ros2` and `transport_type_hash` (they set a process-wide environment variable
//! that spawned nodes would inherit) run each test body in a child process of this binary
//! (`isolated`).

mod bag_bad_input;
mod bag_damage;
mod bag_python_interop;
mod bag_roundtrip;
mod cli_bundle;
mod cli_constraints;
mod cli_simulate;
mod cli_train;
mod cli_train_grid;
mod cli_train_init;
mod data_load;
mod data_scaler;
mod data_split;
mod data_streaming;
mod data_windows;
mod eval_metrics;
mod eval_render;
mod eval_replay;
mod eval_report;
mod fault_full_disk;
mod fault_input;
mod fault_network;
mod fault_peers;
mod interop_import;
mod interop_import_h5py;
mod interop_npz;
mod many_streams;
mod model_average;
mod model_box;
mod model_bundle;
mod model_cells;
mod model_constraints;
mod model_device_projection;
mod model_grid;
mod model_structure;
mod models_shipped;
mod msgs_cdr;
mod node_batching;
mod node_large_frames;
mod node_shard;
mod node_surrogate;
mod plot_png;
mod ros2_rclpy;
mod scenes_heldout;
mod sim_scenes;
mod sim_validation;
mod soak;
mod tidy;
mod train_calls;
mod train_loop;
mod train_parallel;
mod train_resume;
mod train_validate;
mod transport_nodes;
mod transport_ros2;
mod transport_type_hash;
mod viz_foxglove;

#[allow(dead_code)]
mod data_support;
mod isolated;
mod python_support;
mod tmp;
mod unavailable;

/// The grid network of the command-line tests (16 x 16 grid, two levels, widths 4 to 8:
/// seconds per epoch on a CPU).
pub const TINY_GRID_NET: [&str; 12] = [
    "--grid",
    "16",
    "--levels",
    "2",
    "--unet-width",
    "4",
    "--latent",
    "4",
    "--hidden",
    "4",
    "--head-hidden",
    "8",
];

/// The schedule of the command-line grid trainings (2-step rollouts, batches of 4, 8 samples
/// an epoch, one 3-frame validation rollout per scene): with [`TINY_GRID_NET`], seconds.
pub const TINY_GRID_SCHEDULE: [&str; 12] = [
    "--rollout-steps",
    "2",
    "--batch-size",
    "4",
    "--samples-per-epoch",
    "8",
    "--val-starts",
    "1",
    "--val-horizon",
    "3",
    "--noise",
    "0.1",
];

/// The JSON file `path` (a run's `model.json`, `split.json`, `run.json`, ...); panics naming
/// the path when it cannot be read.
pub fn json(path: &std::path::Path) -> serde_json::Value {
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[allow(dead_code)]
mod model_support;
#[allow(dead_code)]
mod train_support;
#[allow(dead_code)]
mod transport_support;
