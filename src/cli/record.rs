//! `minflow record`: the recorder (like `ros2 bag record`) over zenoh, iceoryx2 or ROS 2.
//! Logic in [`crate::node::record`].

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;

use super::transport::TransportArgs;
use super::Outcome;
use crate::node::{record, shutdown_flag};
use crate::transport::{self, Counters};

#[derive(Debug, Args)]
pub struct RecordArgs {
    #[command(flatten)]
    transport: TransportArgs,
    /// Topic to record (repeatable).
    #[arg(long = "topic", default_values_t = [crate::bag::FRAMES_TOPIC.to_string()])]
    topics: Vec<String>,
    /// Output folder: OUT/OUT_0.mcap, OUT/OUT_1.mcap ... and OUT/metadata.yaml.
    #[arg(short, long)]
    out: PathBuf,
    /// Split into a new file at this size, bytes.
    #[arg(long)]
    max_bag_size: Option<u64>,
    /// Split into a new file after this many seconds.
    #[arg(long, value_parser = super::flags::interval)]
    max_bag_duration: Option<f64>,
    /// Stop after this many seconds.
    #[arg(long, value_parser = super::flags::seconds)]
    duration: Option<f64>,
    /// Stop after this many frames.
    #[arg(long)]
    count: Option<u64>,
    /// Close and flush the current chunk every this many seconds (what SIGKILL can lose).
    #[arg(long, default_value_t = 1.0, value_parser = super::flags::seconds)]
    flush_interval: f64,
    /// Stop after this many seconds without a message (counted from the first one).
    #[arg(long, value_parser = super::flags::seconds)]
    idle_exit: Option<f64>,
    /// Delete the bags (and metadata.yaml) already in the output folder.
    #[arg(long)]
    overwrite: bool,
    /// Log the counters every this many seconds.
    #[arg(long, value_parser = super::flags::interval)]
    stats_interval: Option<f64>,
    /// Also write every frame as a foxglove.PointCloud (protobuf, coloured by material) on
    /// `<topic>/points`, so Foxglove's 3D panel plays the recording.
    #[arg(long)]
    points: bool,
}

pub fn run(args: RecordArgs) -> anyhow::Result<Outcome> {
    let secs = |s: f64| Duration::from_secs_f64(s.max(0.0));
    let options = record::RecordOptions {
        topics: args.topics,
        out: args.out,
        max_bag_size: args.max_bag_size,
        max_bag_duration: args.max_bag_duration.map(secs),
        duration: args.duration.map(secs),
        count: args.count,
        flush_interval: secs(args.flush_interval),
        overwrite: args.overwrite,
        idle_exit: args.idle_exit.map(secs),
        points: args.points,
    };
    let stop = shutdown_flag();
    let session = transport::open(&args.transport.options())?;
    let counters = Counters::default();
    let _stats = args
        .stats_interval
        .map(|s| counters.log_every("record", secs(s)));
    let bar = indicatif::ProgressBar::new_spinner();
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {pos} frames recorded {per_sec}",
        )
        .unwrap_or_else(|_| indicatif::ProgressStyle::default_spinner()),
    );
    bar.enable_steady_tick(Duration::from_millis(200));
    let report = record::record(&options, session.as_ref(), &counters, &stop, |n| {
        bar.set_position(n)
    })?;
    bar.finish_and_clear();
    for file in &report.files {
        println!("{}", file.display());
    }
    eprintln!(
        "record: {} frame(s) in {} file(s) ({}); {}",
        report.written,
        report.files.len(),
        report
            .per_topic
            .iter()
            .map(|(t, n)| format!("{t}: {n}"))
            .collect::<Vec<_>>()
            .join(", "),
        counters.get()
    );
    Ok(Outcome::Done)
}
