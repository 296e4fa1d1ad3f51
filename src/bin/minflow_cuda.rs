//! The `minflow-cuda` binary (feature `cuda`): `minflow`'s `simulate`, `train`, `eval`,
//! `bench train`, `bench gemm`, `bench rollout` and `constraints` alone ([`TrainCli`]), so
//! that a stripped build with burn's CUDA backend stays small enough to carry to a GPU
//! machine (docs/cuda.md). Exit codes as `minflow`'s.
//!
//! [`TrainCli`]: minflow::cli::TrainCli

/// As in `minflow`: mimalloc reuses freed large host buffers.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    minflow::cli::ignore_file_size_signal();
    minflow::cli::flush_denormals();
    let cli: minflow::cli::TrainCli = minflow::cli::parse();
    minflow::cli::tune_allocator(minflow::cli::FreedMemory::Kept);
    minflow::cli::init_logging(cli.verbose);
    minflow::cli::exit_code(minflow::cli::run_train(cli))
}
