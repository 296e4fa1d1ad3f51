//! The `minflow` binary: parses the command line, runs the subcommand, and maps the
//! outcome to an exit code (0 ok, 1 error, 2 usage, 3 finished but data was lost, such as
//! a truncated bag). Results go to stdout, logs and progress bars to stderr.

/// mimalloc reuses freed large buffers instead of returning them to the kernel, so the
/// model's per-step activations stop page-faulting (see `bench train`); the nodes give back
/// what stays unused for a second (`cli::FreedMemory`).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> std::process::ExitCode {
    minflow::cli::ignore_file_size_signal();
    minflow::cli::flush_denormals();
    let cli: minflow::cli::Cli = minflow::cli::parse();
    minflow::cli::tune_allocator(cli.freed_memory());
    minflow::cli::init_logging(cli.verbose);
    let outcome = {
        let _profile = minflow::cli::host_profile::HostProfile::start();
        minflow::cli::run(cli)
    };
    minflow::cli::exit_code(outcome)
}
