//! The subscriber side of the ROS 2 transport: a subscription per topic, created and read
//! on its own delivery thread (woken by the middleware), which forwards every message to
//! the caller's channel as a [`Sample`] until the returned handle is dropped.

use std::sync::mpsc::{self, Sender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use futures::channel::oneshot;
use futures::{FutureExt, Stream, StreamExt};
use ros2_client::ReadError;

use super::names::{ros_name, type_name, QOS};
use super::wire::WireFrame;
use super::{NodeRef, Ros2Transport};
use crate::msgs::{cdr, ParticleFrame};
use crate::transport::{Payload, Sample, Subscription, TransportError};

impl Ros2Transport {
    /// Subscribes to `topic` ([`Transport::subscribe`](super::Transport::subscribe)): the
    /// subscription is created on a delivery thread of its own.
    pub(super) fn frame_subscription(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let name = ros_name(topic)?;
        let kind = self.backend.kind();
        let topic_owned = topic.to_owned();
        let (stop_tx, stop_rx) = oneshot::channel::<()>();
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<(), String>>(1);
        let node = self.node.clone();
        // The subscription is created on its delivery thread and never leaves it.
        let thread = std::thread::Builder::new()
            .name(format!("ros2-sub {topic}"))
            .spawn(move || match node {
                NodeRef::Dds(dds) => {
                    let created = dds.with(|node| {
                        let t = node.create_topic(&name, type_name(), &QOS)?;
                        node.create_subscription::<WireFrame>(&t, Some(QOS))
                    });
                    let sub = match created {
                        Ok(sub) => sub,
                        Err(e) => return drop(ready_tx.send(Err(e.to_string()))),
                    };
                    let _ = ready_tx.send(Ok(()));
                    let stream = sub.async_stream().map(|r| r.map(|(m, _info)| m));
                    futures::executor::block_on(pump(stream, stop_rx, sink, topic_owned));
                    drop(sub);
                    drop(dds);
                }
                NodeRef::Zenoh(z) => {
                    let t = z.node.create_topic(&name, type_name(), &QOS);
                    let sub = match z.node.create_subscription::<WireFrame>(&t, Some(QOS)) {
                        Ok(sub) => sub,
                        Err(e) => return drop(ready_tx.send(Err(e.to_string()))),
                    };
                    let _ = ready_tx.send(Ok(()));
                    let stream = sub.async_stream().map(|r| r.map(|(m, _info)| m));
                    futures::executor::block_on(pump(stream, stop_rx, sink, topic_owned));
                    drop(sub);
                    drop(z);
                }
            })
            .map_err(|e| {
                TransportError::declare(
                    kind,
                    "subscription",
                    topic.to_owned(),
                    format!("delivery thread: {e}"),
                )
            })?;
        let created = ready_rx
            .recv()
            .unwrap_or_else(|_| Err("delivery thread ended".into()));
        let handle = SubscriptionHandle {
            stop: Some(stop_tx),
            thread: Some(thread),
        };
        match created {
            Ok(()) => Ok(Box::new(handle)),
            Err(reason) => {
                drop(handle);
                Err(TransportError::declare(
                    kind,
                    "subscription",
                    topic.to_owned(),
                    reason,
                ))
            }
        }
    }
}

/// Forwards every message of `stream` into `sink` until `stop` fires (or its sender is
/// dropped), the sink's receiver is gone, or the middleware closes the subscription.
async fn pump<S>(stream: S, mut stop: oneshot::Receiver<()>, sink: Sender<Sample>, topic: String)
where
    S: Stream<Item = Result<WireFrame, ReadError>>,
{
    futures::pin_mut!(stream);
    loop {
        let item = futures::select! {
            _ = stop => return,
            item = stream.next().fuse() => item,
        };
        let payload = match item {
            None | Some(Err(ReadError::Closed)) => return,
            Some(Ok(wire)) => Payload::Cdr(cdr::encode(&ParticleFrame::from(wire))),
            Some(Err(ReadError::Deserialization { reason })) => Payload::Malformed(reason),
            Some(Err(ReadError::Malformed)) => {
                Payload::Malformed("malformed sample metadata".into())
            }
            Some(Err(e)) => {
                // Not about one sample (a middleware hiccup): report it, back off briefly.
                tracing::warn!("{topic}: ROS 2 read error: {e}");
                std::thread::sleep(Duration::from_millis(1));
                continue;
            }
        };
        let sample = Sample {
            topic: topic.clone(),
            payload,
            received: Instant::now(),
        };
        if sink.send(sample).is_err() {
            return;
        }
    }
}

/// Keeps a subscription's delivery thread running; dropping it stops and joins the thread.
struct SubscriptionHandle {
    stop: Option<oneshot::Sender<()>>,
    thread: Option<JoinHandle<()>>,
}

impl Drop for SubscriptionHandle {
    fn drop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
    }
}

impl Subscription for SubscriptionHandle {}
