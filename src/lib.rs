//! minflow: learned real-time surrogates for 2D MLS-MPM particle simulation.
//!
//! The library behind the `minflow` binary and the tests. Modules follow the pipeline
//! (`../shared/DESIGN.md`): [`sim`] makes the ground truth, [`msgs`] defines the
//! `ParticleFrame` message and its CDR encoding, [`bag`] reads and writes MCAP bags, and
//! [`cli`] is the command layer of the `minflow` binary.

pub mod bag;
pub mod cli;
pub mod data;
pub mod eval;
pub mod launch;
pub mod model;
pub mod msgs;
pub mod node;
pub mod ops;
pub mod plot;
pub mod sim;
pub mod train;
pub mod transport;
