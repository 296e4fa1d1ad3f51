//! iceoryx2 transport: zero-copy shared-memory publish-subscribe of a slice of
//! `#[repr(C)]` [`Particle`]s with a `#[repr(C)]` [`FrameHeader`] user header
//! (docs/design.md, "Topics and transports"). Same host only.
//!
//! Service name = topic without the leading slash (`mpm/frames`). Each publish-subscribe
//! service has an event service of the same name: publishers notify it after every sample,
//! and each subscription waits on it in a blocking call on its own thread (iceoryx2 has no
//! async API), so delivery costs no polling and no sleeping.
//!
//! Nothing is lost: the subscriber buffer does not overwrite (`safe_overflow` off) and
//! publishers retry until delivered, while the subscription thread drains samples into the
//! caller's unbounded channel as fast as they come. A crashed node must not wedge the next
//! run: opening the transport removes the stale resources of every dead iceoryx2 node
//! (iceoryx2's `Node::list` + `DeadNodeView::try_remove_stale_resources`).
//!
//! Files: `sample.rs` (the shared-memory layout and its conversions), `ports.rs` (publishers
//! and the subscription handle); this file opens the node and services and holds the
//! [`Transport`] impl with the subscription threads.

mod ports;
mod sample;

use ports::{IceoryxPublisher, IceoryxStatusPublisher, IceoryxSubscription};

pub use sample::{to_frame, write_particles, FrameHeader, Particle, SampleError, MAX_SCENE_BYTES};

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Sender;
use std::sync::Arc;
use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use super::{
    topic_key, FramePublisher, Payload, Sample, StatusPublisher, Subscription, Transport,
    TransportError, TransportKind,
};
use crate::msgs::status::{decode_status, SurrogateStatus};

const KIND: TransportKind = TransportKind::Iceoryx2;
type Svc = ipc_threadsafe::Service;
/// The frame service and its event service (wake-ups).
type Services = (
    PubSubFactory<Svc, [Particle], FrameHeader>,
    iceoryx2::service::port_factory::event::PortFactory<Svc>,
);

/// Slice length the data segment is first sized for (the paper's 2,500 particles); larger
/// frames grow the segment (power-of-two allocation strategy).
pub const INITIAL_PARTICLES: usize = 2_500;
/// Samples a subscriber may hold before a publisher has to wait.
const SUBSCRIBER_BUFFER: usize = 64;
/// How long a subscription thread blocks before checking whether it should stop.
const WAIT_SLICE: Duration = Duration::from_millis(100);

/// An iceoryx2 node.
pub struct IceoryxTransport {
    node: Node<Svc>,
}

/// Removes the stale resources (shared memory, ports) of every dead iceoryx2 node; returns
/// how many dead nodes were found.
pub fn clean_up_dead_nodes() -> usize {
    let mut dead = 0;
    let _ = Node::<Svc>::list(Config::global_config(), |state| {
        if let NodeState::<Svc>::Dead(view) = state {
            dead += 1;
            if let Err(e) = view.try_remove_stale_resources() {
                tracing::warn!("iceoryx2: cannot remove resources of a dead node: {e:?}");
            }
        }
        CallbackProgression::Continue
    });
    dead
}

impl IceoryxTransport {
    /// Cleans up after dead nodes, then creates a node (no signal handlers: the caller's
    /// SIGINT/SIGTERM handling stays in charge).
    ///
    /// # Errors
    /// [`TransportError::Open`] if the node cannot be created.
    pub fn open() -> Result<Self, TransportError> {
        set_log_level_from_env_or(LogLevel::Error);
        let dead = clean_up_dead_nodes();
        if dead > 0 {
            tracing::info!("iceoryx2: removed stale resources of {dead} dead node(s)");
        }
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Svc>()
            .map_err(|e| TransportError::Open {
                transport: KIND,
                reason: format!("{e:?}"),
            })?;
        Ok(IceoryxTransport { node })
    }

    fn services(&self, topic: &str, what: &'static str) -> Result<Services, TransportError> {
        let err = |reason: String| TransportError::declare(KIND, what, topic.to_owned(), reason);
        let name: ServiceName = topic_key(topic)?
            .try_into()
            .map_err(|e| err(format!("service name: {e:?}")))?;
        let pubsub = self
            .node
            .service_builder(&name)
            .publish_subscribe::<[Particle]>()
            .user_header::<FrameHeader>()
            .enable_safe_overflow(false)
            .history_size(0)
            .subscriber_max_buffer_size(SUBSCRIBER_BUFFER)
            .open_or_create()
            .map_err(|e| err(format!("{e:?}")))?;
        let event = self
            .node
            .service_builder(&name)
            .event()
            .open_or_create()
            .map_err(|e| err(format!("event: {e:?}")))?;
        Ok((pubsub, event))
    }
}

impl Transport for IceoryxTransport {
    fn kind(&self) -> TransportKind {
        KIND
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError> {
        let err =
            |reason: String| TransportError::declare(KIND, "publisher", topic.to_owned(), reason);
        let (service, event) = self.services(topic, "publisher")?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(INITIAL_PARTICLES)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .backpressure_strategy(BackpressureStrategy::RetryUntilDelivered)
            .create()
            .map_err(|e| err(format!("{e:?}")))?;
        let notifier = event
            .notifier_builder()
            .create()
            .map_err(|e| err(format!("notifier: {e:?}")))?;
        Ok(Box::new(IceoryxPublisher {
            topic: topic.to_owned(),
            service,
            publisher,
            notifier,
        }))
    }

    fn subscribe(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let err =
            |reason: String| TransportError::declare(KIND, "subscriber", topic.to_owned(), reason);
        let (service, event) = self.services(topic, "subscriber")?;
        let subscriber = service
            .subscriber_builder()
            .create()
            .map_err(|e| err(format!("{e:?}")))?;
        let listener = event
            .listener_builder()
            .create()
            .map_err(|e| err(format!("listener: {e:?}")))?;
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = Arc::clone(&stop);
        let name = topic.to_owned();
        let thread = std::thread::Builder::new()
            .name(format!("iox2 {topic}"))
            .spawn(move || {
                let _service = service;
                while !stopping.load(Ordering::Relaxed) {
                    // Drain first: samples may have arrived before the listener existed.
                    loop {
                        match subscriber.receive() {
                            Ok(Some(sample)) => {
                                let received = Instant::now();
                                let payload = match to_frame(sample.user_header(), sample.payload())
                                {
                                    Ok(frame) => Payload::Frame(frame),
                                    Err(reason) => Payload::Malformed(reason.to_string()),
                                };
                                drop(sample);
                                if sink
                                    .send(Sample {
                                        topic: name.clone(),
                                        payload,
                                        received,
                                    })
                                    .is_err()
                                {
                                    return;
                                }
                            }
                            Ok(None) => break,
                            Err(e) => {
                                tracing::warn!("iceoryx2: receive on {name} failed: {e:?}");
                                break;
                            }
                        }
                    }
                    if let Err(e) = listener.timed_wait(|_| {}, WAIT_SLICE) {
                        tracing::warn!("iceoryx2: wait on {name} failed: {e:?}");
                        std::thread::sleep(WAIT_SLICE);
                    }
                }
            })
            .map_err(|e| err(e.to_string()))?;
        Ok(Box::new(IceoryxSubscription {
            stop,
            thread: Some(thread),
        }))
    }

    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        let service = self.status_service(topic, "status publisher")?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(512)
            .allocation_strategy(AllocationStrategy::PowerOfTwo)
            .create()
            .map_err(|e| {
                TransportError::declare(
                    KIND,
                    "status publisher",
                    topic.to_owned(),
                    format!("{e:?}"),
                )
            })?;
        Ok(Box::new(IceoryxStatusPublisher {
            topic: topic.to_owned(),
            _service: service,
            publisher,
        }))
    }

    fn subscribe_status(
        &self,
        topic: &str,
        sink: Sender<SurrogateStatus>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let service = self.status_service(topic, "status subscriber")?;
        let subscriber = service.subscriber_builder().create().map_err(|e| {
            TransportError::declare(
                KIND,
                "status subscriber",
                topic.to_owned(),
                format!("{e:?}"),
            )
        })?;
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = Arc::clone(&stop);
        let name = topic.to_owned();
        let thread = std::thread::Builder::new()
            .name(format!("iox2 {topic}"))
            .spawn(move || {
                let _service = service;
                // Status is a 1 Hz report: polling every 20 ms is plenty.
                while !stopping.load(Ordering::Relaxed) {
                    while let Ok(Some(sample)) = subscriber.receive() {
                        match decode_status(sample.payload()) {
                            Ok(status) => {
                                if sink.send(status).is_err() {
                                    return;
                                }
                            }
                            Err(reason) => tracing::warn!("{name}: undecodable status: {reason}"),
                        }
                    }
                    std::thread::sleep(Duration::from_millis(20));
                }
            })
            .map_err(|e| {
                TransportError::declare(KIND, "status subscriber", topic.to_owned(), e.to_string())
            })?;
        Ok(Box::new(IceoryxSubscription {
            stop,
            thread: Some(thread),
        }))
    }
}
