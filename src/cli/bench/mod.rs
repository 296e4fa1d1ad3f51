//! `minflow bench`: the subcommands, one file or folder each: [`sim`] (the MPM solver's
//! speed), [`train`] (training speed, both architectures), [`transport`] (latency and
//! throughput between two processes), [`node`] (a surrogate node's latency and throughput),
//! [`gemm`] (the GPU's dense-layer products), [`rollout`] (a model's rollout cost against the
//! solver, with `roofline.rs`'s table under each row), [`transfer`] (the GPU's particle-grid
//! transfers); [`common`] holds the helpers they share. This file holds the subcommand list
//! and the dispatch.

pub(crate) mod common;
pub mod gemm;
pub mod node;
pub mod rollout;
mod roofline;
pub mod sim;
#[cfg(feature = "cuda")]
mod sim_gpu;
pub mod train;
pub mod transfer;
pub mod transport;

use crate::cli::Outcome;
use clap::Subcommand;

/// `minflow bench SUBCOMMAND`.
#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Simulator speed: ms per saved frame, one thread and all threads.
    Sim(sim::SimBenchArgs),
    /// Training speed per core (the paper's Table 4): parameters, s/epoch, us/sample, memory.
    Train(train::TrainBenchArgs),
    /// Transport latency between two processes (p50/p99/max) and burst throughput.
    Transport(transport::TransportBenchArgs),
    /// Surrogate node latency and throughput per core and transport (two processes).
    Node(node::NodeBenchArgs),
    /// GPU dense-layer products: cubecl vs cuBLAS TF32 / FP32, ms, TFLOP/s, difference.
    Gemm(gemm::GemmBenchArgs),
    /// Closed-loop rollout cost per frame of models against the MPM solver, as a ratio.
    Rollout(rollout::RolloutBenchArgs),
    /// GPU particle-grid transfers (P2G, G2P): sparse kernels vs dense products, checked
    /// against the host, ms.
    Transfer(transfer::TransferBenchArgs),
}

/// Runs a `minflow bench` subcommand.
///
/// # Errors
/// The subcommand's.
pub fn run(cmd: BenchCommand) -> anyhow::Result<Outcome> {
    match cmd {
        BenchCommand::Sim(args) => sim::run(args),
        BenchCommand::Train(args) => train::run(args),
        BenchCommand::Transport(args) => transport::run(args),
        BenchCommand::Node(args) => node::run(args),
        BenchCommand::Gemm(args) => gemm::run(args),
        BenchCommand::Rollout(args) => rollout::run(args),
        BenchCommand::Transfer(args) => transfer::run(args),
    }
}
