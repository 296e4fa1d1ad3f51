//! The command layer: clap definitions of every subcommand and [`run`], which reads as the
//! table of contents of what `minflow` does. Each verb lives in its own file (`bench` and
//! `train` in folders of their own: `bench/mod.rs`, `train/mod.rs`): `demo`, `simulate`,
//! `train`, `eval`, `report`, `replay`, `record`, `node`, `launch`, `bag`, `export`,
//! `import`, `bench`, `constraints`, `average`. Shared by several: [`device`] (`--device`),
//! `flags` (range checks of numeric flags), `foxglove` (`--foxglove`), `transport`
//! (`--transport`, `--pointcloud2`) and `run_folder` (what a training run leaves in its
//! folder). This file also holds the `minflow-cuda` subset ([`TrainCli`]), exit codes, the
//! allocator setting and logging. Errors are `anyhow` with context here, structured error
//! types in the pipeline modules.

mod average;
mod bag;
mod bench;
mod constraints;
mod demo;
pub mod device;
pub mod eval;
mod export;
mod flags;
mod foxglove;
pub mod host_profile;
mod import;
mod launch;
mod node;
mod record;
mod replay;
mod report;
mod run_folder;
mod simulate;
#[cfg(feature = "cuda")]
mod simulate_gpu;
pub mod train;
mod transport;

use clap::{Parser, Subcommand};

pub use simulate::{bag_name, parse_ids};

/// minflow: MLS-MPM ground truth, MCAP bags and learned minGRU/minLSTM surrogates.
#[derive(Debug, Parser)]
#[command(name = "minflow", version, about, long_about = None)]
pub struct Cli {
    /// More log output on stderr (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// The main job on the bundled bags (see README): the shipped model in closed loop
    /// (replay -> node -> record -> eval), scored beside the baselines.
    Demo(demo::DemoArgs),
    /// Generate ground-truth scenes with MLS-MPM and write one MCAP bag per scene.
    Simulate(simulate::SimulateArgs),
    /// Train a surrogate on bags (the grid architecture, or `--arch paper`).
    Train(train::TrainArgs),
    /// Rollout metrics, tables, curves and renders of models and baselines (or of a bag of
    /// recorded predictions) against the ground truth.
    Eval(eval::EvalArgs),
    /// The paper's experiment end to end: train the five cores, evaluate, time, REPORT.md.
    Report(report::ReportArgs),
    /// Play bags of frames on a topic over zenoh, iceoryx2 or ROS 2 (like `ros2 bag play`).
    Replay(replay::ReplayArgs),
    /// Record topics into MCAP bags (like `ros2 bag record`).
    Record(record::RecordArgs),
    /// The surrogate node: predicts the next frame of every scene it receives.
    Node(node::NodeArgs),
    /// Start the nodes of a launch file (launch_configs/*.yaml) and supervise them.
    Launch(launch::LaunchArgs),
    /// Inspect and validate MCAP bags of ParticleFrames.
    #[command(subcommand)]
    Bag(bag::BagCommand),
    /// Write the trajectories of bags for other tools (numpy `.npz`, one file per trajectory).
    Export(export::ExportArgs),
    /// Convert datasets of other tools into bags, one per trajectory (LagrangeBench's HDF5
    /// layout, the paper's HDF5 layout).
    Import(import::ImportArgs),
    /// Benchmarks that print a table.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// A model's material constraints (projected onto after every predicted frame).
    #[command(subcommand)]
    Constraints(constraints::ConstraintsCommand),
    /// One model with the mean of several models' weights (weights of one run, averaged).
    Average(average::AverageArgs),
}

/// `minflow-cuda`: the subset of `minflow` a GPU machine needs (`simulate`, `train`, `eval`,
/// `bench sim`, `bench train`, `bench gemm`, `bench rollout`, `constraints`, `average`), the
/// same flags, without the transports, so that its stripped binary is small enough to carry
/// to the machine (docs/cuda.md). Built with `--features cuda`.
#[derive(Debug, Parser)]
#[command(name = "minflow-cuda", version, about, long_about = None)]
pub struct TrainCli {
    /// More log output on stderr (-v debug, -vv trace); RUST_LOG overrides.
    #[arg(short, long, global = true, action = clap::ArgAction::Count)]
    pub verbose: u8,
    #[command(subcommand)]
    command: TrainCommand,
}

#[derive(Debug, Subcommand)]
enum TrainCommand {
    /// Generate ground-truth scenes (as `minflow simulate`, without `--publish`).
    Simulate(simulate::SimulateArgs),
    /// Train a surrogate (as `minflow train`).
    Train(train::TrainArgs),
    /// Rollout metrics (as `minflow eval`).
    Eval(eval::EvalArgs),
    /// Benchmarks that print a table.
    #[command(subcommand)]
    Bench(TrainBenchCommand),
    /// A model's material constraints (as `minflow constraints`).
    #[command(subcommand)]
    Constraints(constraints::ConstraintsCommand),
    /// Average models' weights (as `minflow average`).
    Average(average::AverageArgs),
}

#[derive(Debug, Subcommand)]
enum TrainBenchCommand {
    /// Simulator speed, on the CPU and batched on a GPU (as `minflow bench sim`).
    Sim(bench::sim::SimBenchArgs),
    /// Training speed per core (as `minflow bench train`).
    Train(bench::train::TrainBenchArgs),
    /// GPU dense-layer products per kernel (as `minflow bench gemm`).
    Gemm(bench::gemm::GemmBenchArgs),
    /// Rollout cost per frame against the MPM solver (as `minflow bench rollout`).
    Rollout(bench::rollout::RolloutBenchArgs),
}

/// Runs a parsed [`TrainCli`] command.
pub fn run_train(cli: TrainCli) -> anyhow::Result<Outcome> {
    match cli.command {
        TrainCommand::Simulate(args) => simulate::run_offline(args),
        TrainCommand::Train(args) => train::run(args),
        TrainCommand::Eval(args) => eval::run(args),
        TrainCommand::Bench(TrainBenchCommand::Sim(args)) => bench::sim::run(args),
        TrainCommand::Bench(TrainBenchCommand::Train(args)) => bench::train::run(args),
        TrainCommand::Bench(TrainBenchCommand::Gemm(args)) => bench::gemm::run(args),
        TrainCommand::Bench(TrainBenchCommand::Rollout(args)) => bench::rollout::run(args),
        TrainCommand::Constraints(cmd) => constraints::run(cmd),
        TrainCommand::Average(args) => average::run(args),
    }
}

/// Parses the process's command line into `P` as `P::parse()` does (errors and `--help` exit
/// through clap, usage errors with code 2), except that a flag's value may be a negative
/// number: `--lr -1` reaches the flag's range check, whose message names the flag, instead of
/// clap's "unexpected argument '-1' found".
pub fn parse<P: clap::Parser>() -> P {
    fn negatives(cmd: clap::Command) -> clap::Command {
        cmd.mut_args(|a| a.allow_negative_numbers(true))
            .mut_subcommands(negatives)
    }
    let mut matches = negatives(P::command()).get_matches();
    P::from_arg_matches_mut(&mut matches).unwrap_or_else(|e| e.exit())
}

/// A flag or file value found out of range after parsing (it needs another flag or the data
/// to judge): exit code 2, like clap's own usage errors. Return it inside an `anyhow::Error`.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

/// The process exit code of a command's result: 0 done, 3 data lost (also an error whose
/// cause is a write that ran out of room, [`out_of_room`]: what the command produced after its
/// last complete file is lost), 2 a [`UsageError`] anywhere in the error chain, 1 any other
/// error (printed to stderr with its causes).
pub fn exit_code(result: anyhow::Result<Outcome>) -> std::process::ExitCode {
    use std::process::ExitCode;
    match result {
        Ok(Outcome::Done) => ExitCode::SUCCESS,
        Ok(Outcome::DataLost) => ExitCode::from(3),
        Err(err) => {
            eprintln!("error: {}", error_text(&err));
            if err.chain().any(|e| e.is::<UsageError>()) {
                ExitCode::from(2)
            } else if out_of_room(&err) {
                ExitCode::from(3)
            } else {
                ExitCode::FAILURE
            }
        }
    }
}

/// Whether a cause in `err`'s chain is an OS error of a write that ran out of room: no
/// space left on the device (ENOSPC), a file over the size limit (EFBIG, `RLIMIT_FSIZE`) or
/// a disk quota exceeded (EDQUOT).
pub fn out_of_room(err: &anyhow::Error) -> bool {
    err.chain().any(|cause| {
        cause
            .downcast_ref::<std::io::Error>()
            .and_then(std::io::Error::raw_os_error)
            .is_some_and(|code| [libc::ENOSPC, libc::EFBIG, libc::EDQUOT].contains(&code))
    })
}

/// The error and its causes joined by ": ", as `{:#}` prints them, but leaving out a cause
/// whose text the message before it already ends with (library errors that print their
/// source themselves, such as `StoreError::Io` and `BagError::Io`).
fn error_text(err: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in err.chain() {
        let text = cause.to_string();
        if out.ends_with(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    out
}

#[cfg(test)]
mod error_text_tests {
    /// A full disk, however deep in the chain, exits 3; other OS errors exit 1.
    #[test]
    fn a_write_out_of_room_is_data_lost() {
        let full = std::io::Error::from_raw_os_error(libc::ENOSPC);
        let store = crate::model::store::io(std::path::Path::new("m/model.mpk"), full);
        let err = anyhow::Error::new(store).context("training");
        assert!(super::out_of_room(&err));
        assert!(super::error_text(&err).contains("No space left on device"));
        let gone = std::io::Error::from_raw_os_error(libc::ENOENT);
        assert!(!super::out_of_room(&anyhow::Error::new(gone)));
    }

    /// A cause already printed by the error above it appears once; context is kept.
    #[test]
    fn a_cause_is_printed_once() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "gone");
        let store = crate::model::store::io(std::path::Path::new("m/model.json"), io);
        let err = anyhow::Error::new(store).context("loading the model");
        assert_eq!(
            super::error_text(&err),
            "loading the model: m/model.json: gone"
        );
    }
}

/// How a command finished.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Everything asked for was done.
    Done,
    /// Finished, but some input was lost (for example a truncated bag); exit code 3.
    DataLost,
}

/// The outcome of a command that read `truncated` bags to the damage and used what came
/// before it: each is logged as a warning, and any makes the outcome [`Outcome::DataLost`]
/// (exit code 3, the same rule as `bag info` and `replay`).
pub(crate) fn read_to_damage(
    truncated: &[(std::path::PathBuf, crate::bag::Truncation)],
) -> Outcome {
    for (path, truncation) in truncated {
        tracing::warn!("{}: {truncation}", path.display());
    }
    match truncated.is_empty() {
        true => Outcome::Done,
        false => Outcome::DataLost,
    }
}

/// Runs the parsed command.
pub fn run(cli: Cli) -> anyhow::Result<Outcome> {
    match cli.command {
        Command::Demo(args) => demo::run(args),
        Command::Simulate(args) => simulate::run(args),
        Command::Bag(cmd) => bag::run(cmd),
        Command::Export(args) => export::run(args),
        Command::Import(args) => import::run(args),
        Command::Replay(args) => replay::run(args),
        Command::Record(args) => record::run(args),
        Command::Node(args) => node::run(args),
        Command::Launch(args) => launch::run(args),
        Command::Train(args) => train::run(args),
        Command::Constraints(cmd) => constraints::run(cmd),
        Command::Average(args) => average::run(args),
        Command::Eval(args) => eval::run(args),
        Command::Report(args) => report::run(args),
        Command::Bench(cmd) => bench::run(cmd),
    }
}

/// How long mimalloc (the binaries' global allocator) keeps freed memory committed before
/// returning it to the kernel (`mi_option_purge_delay`, ms; -1 never; mimalloc's own default
/// is 10 ms).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FreedMemory {
    /// Never returned (-1): for batch work. Training frees and reallocates activations of
    /// tens of MB every step; returned pages come back zero-filled by page faults, which cost
    /// ~10 % of a CPU training step (`bench train`). The price: the process keeps its peak.
    Kept,
    /// Returned after 1 s unused: for the long-running nodes (`node`, `replay`, `record`,
    /// `launch`). Buffers reused every frame or call stay committed, while what a burst
    /// or a queue left behind goes back. Kept forever, the node's resident memory crept
    /// up ~2 MB every 5 s over a 30 s soak on a loaded machine (113 -> 120 MB; 10 ms and
    /// 1 s held it flat at 92-105 MB: `tests/it/soak.rs`).
    ReturnedAfterOneSecond,
}

impl Cli {
    /// The allocator setting for this command: [`FreedMemory::ReturnedAfterOneSecond`] for
    /// the nodes that run until stopped, [`FreedMemory::Kept`] for the rest.
    pub fn freed_memory(&self) -> FreedMemory {
        match self.command {
            Command::Node(_) | Command::Replay(_) | Command::Record(_) | Command::Launch(_) => {
                FreedMemory::ReturnedAfterOneSecond
            }
            _ => FreedMemory::Kept,
        }
    }
}

/// Sets mimalloc's purge delay to `freed` (see [`FreedMemory`]); the environment's
/// `MIMALLOC_PURGE_DELAY` still wins when set.
pub fn tune_allocator(freed: FreedMemory) {
    // mimalloc v2's `mi_option_t` value of `mi_option_purge_delay` (include/mimalloc.h).
    const MI_OPTION_PURGE_DELAY: std::ffi::c_int = 15;
    extern "C" {
        fn mi_option_set(option: std::ffi::c_int, value: std::ffi::c_long);
    }
    let delay_ms = match freed {
        FreedMemory::Kept => -1,
        FreedMemory::ReturnedAfterOneSecond => 1000,
    };
    if !crate::switches::mimalloc_purge_delay_set() {
        // SAFETY: sets a process-wide integer option; mimalloc reads it on later frees.
        unsafe { mi_option_set(MI_OPTION_PURGE_DELAY, delay_ms) };
    }
}

/// Ignores SIGXFSZ, so that a write past the file size limit (`ulimit -f`, `RLIMIT_FSIZE`)
/// fails with EFBIG ("File too large"), which the command reports naming the file (exit 3),
/// instead of the signal killing the process with a core dump mid-write.
pub fn ignore_file_size_signal() {
    // SAFETY: sets the disposition of one signal to "ignore"; no handler runs.
    unsafe {
        libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
    }
}

/// Flushes subnormal floats to zero (x86 MXCSR FTZ and DAZ bits) on the calling thread and
/// on every thread of rayon's global pool, which this builds (call it first thing in `main`).
/// Training drives some gradients through products of many gates below 1 (minGRU's
/// recurrence over 32 steps), which pass through the subnormal range on their way to zero;
/// each subnormal operand costs a microcode assist of ~100 cycles on x86, and a CPU epoch
/// got 2x slower once they appeared. Values below 1.2e-38 become 0, as on GPUs.
pub fn flush_denormals() {
    fn set() {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: sets the FTZ (bit 15) and DAZ (bit 6) bits of this thread's MXCSR, which
        // only changes how subnormal results and operands are rounded.
        unsafe {
            let mut csr: u32 = 0;
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack));
            csr |= 0x8040;
            std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack, readonly));
        }
    }
    set();
    // Ignored if the pool already exists (then its threads keep the default mode).
    let _ = rayon::ThreadPoolBuilder::new()
        .start_handler(|_| set())
        .build_global();
}

/// Logs to stderr; `RUST_LOG` wins over `-v`.
pub fn init_logging(verbose: u8) {
    // The middleware crates are chatty at info (every session open/close, scouting);
    // their warnings still show.
    let default = match verbose {
        0 => "info,zenoh=warn,rustdds=warn,ros2_client=warn",
        1 => "debug,zenoh=info,rustdds=info,ros2_client=info",
        _ => "trace",
    };
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    // Colour codes only on a terminal: a log redirected to a file or read by `launch` (a
    // pipe) stays plain text.
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_ansi(ansi)
        .try_init();
}

/// A progress bar on stderr (hidden when stderr is not a terminal).
pub(crate) fn progress(len: u64, what: &str) -> indicatif::ProgressBar {
    let bar = indicatif::ProgressBar::new(len);
    let style = indicatif::ProgressStyle::with_template(
        "{msg:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} {per_sec} eta {eta}",
    )
    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar());
    bar.set_style(style);
    bar.set_message(what.to_string());
    bar
}

/// Train and validation loss per epoch as a PNG (log scale).
pub(crate) fn loss_plot(
    path: &std::path::Path,
    history: &[crate::train::EpochRecord],
) -> anyhow::Result<()> {
    use crate::plot::{line_chart, Series};
    let series = [
        Series {
            name: "train".into(),
            points: history
                .iter()
                .map(|r| (r.epoch as f64, r.train_loss))
                .collect(),
        },
        Series {
            name: "validation".into(),
            points: history
                .iter()
                .map(|r| (r.epoch as f64, r.val_loss))
                .collect(),
        },
    ];
    line_chart(path, "loss", "epoch", "loss", &series, true, (800, 500))?;
    Ok(())
}
