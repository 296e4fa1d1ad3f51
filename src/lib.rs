//! minflow: learned real-time surrogates for 2D MLS-MPM particle simulation.
//!
//! The library behind the `minflow` binary and the tests. Modules follow the pipeline
//! (`docs/design.md`, "Pipeline"):
//!
//! - [`material`]: the table of materials (id, name, colour) every module reads;
//! - [`bspline`]: MLS-MPM's quadratic B-spline weights, one definition for the solver, the
//!   grid models' transfers and the density constraint;
//! - [`geometry`]: the centre of mass of a set of particles, one definition for the
//!   constraint projection, `eval` and the solver's diagnostics;
//! - [`neighbours`]: the one neighbour search over a scene's particles (a cell list: k
//!   nearest and fixed radius), for eval's rest neighbours, the grid model's rest
//!   neighbourhoods and the constraint projection;
//! - [`sim`]: the MLS-MPM solver and its scenes, which make the ground truth;
//! - [`msgs`]: the `ParticleFrame` and `SurrogateStatus` messages and their CDR encoding;
//! - [`bag`]: MCAP bags: writer, reader (foreign and truncated bags), `info`, `check`;
//! - [`data`]: bags -> trajectories, split by scene, scaler, windows and batches;
//! - [`ops`]: the backend operations the networks need beyond burn's (fused dense layers,
//!   the recurrence scans, Adam, im2col, P2G/G2P): composed fallbacks, autodiff nodes, CPU
//!   kernels and cuBLAS products;
//! - [`model`]: the networks on [`ops`] (the grid architecture, the paper's encoder - core -
//!   decoder) and saved models;
//! - [`train`]: losses, the training loops, the optimizer, checkpoints;
//! - [`eval`]: rollouts, metrics, baselines, tables, curves and renders;
//! - [`interop`]: datasets for other tools (bags -> numpy `.npz`);
//! - [`plot`]: PNG line charts;
//! - [`transport`]: one publish / subscribe interface over zenoh, iceoryx2 and ROS 2;
//! - [`node`]: the surrogate node, the replay player and the recorder;
//! - [`launch`]: launch files, their nodes as supervised child processes;
//! - [`viz`]: frames as Foxglove point clouds, live over a WebSocket server or into bags;
//! - [`cli`]: the command layer of the `minflow` binary;
//! - [`switches`]: the environment variables minflow reads, in one typed place.

pub mod bag;
pub mod bspline;
pub mod cli;
pub mod data;
pub mod eval;
pub mod geometry;
pub mod interop;
pub mod launch;
pub mod material;
pub mod model;
pub mod msgs;
pub mod neighbours;
pub mod node;
pub mod ops;
pub mod plot;
pub mod sim;
pub mod switches;
pub mod train;
pub mod transport;
pub mod viz;
