//! `minflow replay`: the ground-truth player (like `ros2 bag play`) over zenoh, iceoryx2 or
//! ROS 2. Logic in [`crate::node::replay`].

use std::path::PathBuf;
use std::time::Duration;

use anyhow::Context;
use clap::Args;

use super::transport::{PointCloud2Args, TransportArgs};
use super::Outcome;
use crate::bag::FRAMES_TOPIC;
use crate::node::{replay, shutdown_flag};
use crate::transport::Counters;
use crate::viz::VizPublisher;

#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// Bag files or folders of bags; several are merged by log time.
    #[arg(required = true)]
    inputs: Vec<PathBuf>,
    #[command(flatten)]
    transport: TransportArgs,
    /// Topic the frames are published on.
    #[arg(long, default_value = FRAMES_TOPIC)]
    topic: String,
    /// Topic read from the bags.
    #[arg(long, default_value = FRAMES_TOPIC)]
    input_topic: String,
    /// Playback speed factor; 0 plays as fast as the transport accepts frames.
    #[arg(long, default_value_t = 1.0, value_parser = super::flags::rate)]
    rate: f64,
    /// Play again from the start when done, until Ctrl-C.
    #[arg(long = "loop")]
    looped: bool,
    /// Start this many seconds (log time) into the bags.
    #[arg(long, default_value_t = 0.0, value_parser = super::flags::seconds)]
    start_offset: f64,
    /// Play only scenes matching this glob (repeatable), e.g. `multi/rope*`.
    #[arg(long)]
    scene: Vec<String>,
    /// Wait for this many subscribers before the first frame (0: don't wait).
    #[arg(long, default_value_t = 1)]
    wait_for_subscribers: usize,
    /// Seconds to wait for subscribers before giving up.
    #[arg(long, default_value_t = 30.0, value_parser = super::flags::seconds)]
    wait_timeout: f64,
    /// Log the counters every this many seconds.
    #[arg(long, value_parser = super::flags::interval)]
    stats_interval: Option<f64>,
    #[command(flatten)]
    foxglove: super::foxglove::FoxgloveArgs,
    #[command(flatten)]
    pointcloud2: PointCloud2Args,
}

pub fn run(args: ReplayArgs) -> anyhow::Result<Outcome> {
    let scenes = args
        .scene
        .iter()
        .map(|s| glob::Pattern::new(s).with_context(|| format!("--scene {s:?}")))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let options = replay::ReplayOptions {
        inputs: args.inputs,
        input_topic: args.input_topic,
        rate: args.rate,
        looped: args.looped,
        start_offset: args.start_offset,
        scenes,
        wait_for_subscribers: args.wait_for_subscribers,
        wait_timeout: Duration::from_secs_f64(args.wait_timeout.max(0.0)),
    };
    let stop = shutdown_flag();
    let session = args.pointcloud2.open(&args.transport)?;
    let mut publisher = session.publisher(&args.topic)?;
    if let Some(view) = args.foxglove.start("minflow replay")? {
        // A Foxglove client watching the points counts as a subscriber (docs/design.md).
        publisher = Box::new(VizPublisher::new(publisher, view.points(&args.topic)));
    }
    let counters = Counters::default();
    let _stats = args
        .stats_interval
        .map(|s| counters.log_every("replay", Duration::from_secs_f64(s)));
    // Frames on the input topic, for the progress bar (a full scan; bags are small next to
    // the time they take to play).
    let total = crate::bag::inspect::info(&crate::bag::bag_paths(&options.inputs)?)
        .map(|info| {
            let on_topic = |t: &crate::bag::inspect::TopicInfo| t.topic == options.input_topic;
            info.files
                .iter()
                .flat_map(|f| f.topics.iter().filter(|t| on_topic(t)))
                .map(|t| t.count)
                .sum::<u64>()
        })
        .unwrap_or(0);
    let bar = super::progress(total, "frames");
    let report = replay::play(&options, publisher.as_mut(), &counters, &stop, |n| {
        bar.set_position(n)
    })?;
    bar.finish_and_clear();
    eprintln!(
        "replay: {} frame(s) on {} over {} in {:.2} s ({} filtered){}; {}",
        report.published,
        args.topic,
        session.kind(),
        report.elapsed.as_secs_f64(),
        report.filtered,
        if report.interrupted {
            ", interrupted"
        } else {
            ""
        },
        counters.get()
    );
    Ok(if report.truncated.is_empty() {
        Outcome::Done
    } else {
        Outcome::DataLost
    })
}
