//! The surrogate node's loop (`minflow node`): declare the output and status publishers,
//! wait for the output's subscribers, join the shard group (`--shard`), subscribe to the
//! input (its samples decoded on a thread of their own), then repeat { periodic status and
//! counters, gather the decoded samples into per-scene queues ([`super::intake`]), publish
//! the rollout frames that are due ([`super::closed`]) and the pipelined calls' frames the
//! lander thread has landed ([`super::lander`]), and when a batch is due step it
//! ([`super::batcher`]) }. The totals come back as a [`NodeReport`].

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};

use crate::model::store::Surrogate;
use crate::ops::NetOps;
use crate::transport::{FramePublisher, StatusPublisher, Transport, TransportError};

use super::intake::spawn_decoder;
use super::lander::Lander;
use super::node_loop::NodeLoop;
use super::options::{NodeOptions, NodeReport};
use super::report::log_start;
use super::shard::Shard;

/// Runs the node until `stop` turns true (or `max_published` is reached). Returns totals.
///
/// Reads as its steps: declare the output (and status) publishers, wait for the output's
/// subscribers, join the shard group, subscribe to the input, then loop { status, gather,
/// publish due rollout frames, step a batch when one is due }.
///
/// # Errors
/// Declaring the subscription, publishers or shard token fails ([`TransportError`]);
/// `--shard` over a transport without a zenoh session.
pub fn run<B: NetOps>(
    options: &NodeOptions,
    surrogate: &Surrogate<B>,
    transport: &dyn Transport,
    stop: &AtomicBool,
) -> Result<NodeReport, TransportError> {
    let publisher = transport.publisher(&options.output)?;
    let status_pub = open_status_publisher(options, transport);
    if !wait_for_output_subscribers(options, publisher.as_ref(), stop) {
        return Ok(NodeReport {
            node: options.name.clone(),
            ..NodeReport::default()
        });
    }
    let shard = join_shard(options, transport)?;
    let (tx, rx) = channel();
    let _subscription = transport.subscribe(&options.input, tx)?;
    log_start(options, surrogate, transport);
    // The lander thread of pipelined calls (`super::lander`) lives as long as the loop.
    std::thread::scope(|scope| {
        let mut node = NodeLoop::new(options, surrogate, publisher, status_pub);
        node.shard = shard;
        if options.pipeline {
            let (outlet, busy) = (node.outlet(), node.times.land.clone());
            node.lander = Some(Lander::start(scope, surrogate, outlet, busy));
        }
        let (rx, decoder) = spawn_decoder(
            rx,
            (options.max_frame_bytes, node.model_n, node.view.is_some()),
            node.shard.as_ref().map(|s| s.owners()),
            node.times.decode.clone(),
        );
        while !stop.load(Ordering::Relaxed) && !node.done() {
            node.periodic();
            if !node.gather(&rx) {
                // The decoder ended: the transport closed the subscription, or it panicked
                // (then so does the node, not a clean stop).
                if let Err(panic) = decoder.join() {
                    std::panic::resume_unwind(panic);
                }
                break;
            }
            node.publish_due_rollouts();
            node.publish_landed(usize::MAX);
            if node.batch_due(Instant::now()).is_now() {
                node.step_batch();
            }
        }
        node.publish_landed(0);
        Ok(node.finish())
    })
}

/// Joins `options.shard`'s group on the transport's zenoh session (None without `--shard`).
fn join_shard(
    options: &NodeOptions,
    transport: &dyn Transport,
) -> Result<Option<Shard>, TransportError> {
    let Some(group) = &options.shard else {
        return Ok(None);
    };
    let Some(session) = transport.zenoh_session() else {
        return Err(TransportError::declare(
            transport.kind(),
            "shard group",
            group.clone(),
            "--shard needs --transport zenoh (zenoh liveliness tokens)",
        ));
    };
    let shard = Shard::join(&session, group, &options.name)?;
    tracing::info!(
        "{}: shard group {group:?}: {} node(s) alive",
        options.name,
        shard.members()
    );
    Ok(Some(shard))
}

/// The status publisher if `options.status` names a topic; a failure to declare it is
/// logged and the node runs without status reports.
fn open_status_publisher(
    options: &NodeOptions,
    transport: &dyn Transport,
) -> Option<Box<dyn StatusPublisher>> {
    let topic = options.status.as_ref()?;
    match transport.status_publisher(topic) {
        Ok(p) => Some(p),
        Err(e) => {
            tracing::warn!("no status reports: {e}");
            None
        }
    }
}

/// Waits until the output has `options.wait_for_subscribers` subscribers. False when `stop`
/// turned true first.
fn wait_for_output_subscribers(
    options: &NodeOptions,
    publisher: &dyn FramePublisher,
    stop: &AtomicBool,
) -> bool {
    if options.wait_for_subscribers == 0 {
        return true;
    }
    tracing::info!(
        "{}: waiting for {} subscriber(s) on {}",
        options.name,
        options.wait_for_subscribers,
        options.output
    );
    while publisher.subscriber_count() < options.wait_for_subscribers {
        if stop.load(Ordering::Relaxed) {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    true
}
