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

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::Sender;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use super::{
    topic_key, FramePublisher, Payload, Sample, StatusPublisher, Subscription, Transport,
    TransportError, TransportKind,
};
use crate::msgs::status::{decode_status, encode_status, SurrogateStatus};
use crate::msgs::{Header, ParticleFrame, Time};

const KIND: TransportKind = TransportKind::Iceoryx2;
type Svc = ipc_threadsafe::Service;
/// The frame service and its event service (wake-ups).
type Services = (
    PubSubFactory<Svc, [Particle], FrameHeader>,
    iceoryx2::service::port_factory::event::PortFactory<Svc>,
);

/// Largest scene id that fits [`FrameHeader::scene`] (63 UTF-8 bytes + NUL).
pub const MAX_SCENE_BYTES: usize = 63;
/// Slice length the data segment is first sized for (the paper's 2,500 particles); larger
/// frames grow the segment (power-of-two allocation strategy).
pub const INITIAL_PARTICLES: usize = 2_500;
/// Samples a subscriber may hold before a publisher has to wait.
const SUBSCRIBER_BUFFER: usize = 64;
/// How long a subscription thread blocks before checking whether it should stop.
const WAIT_SLICE: Duration = Duration::from_millis(100);

/// One particle of a frame as it lies in shared memory: 20 bytes, no padding.
/// Units as in `ParticleFrame`: domain units and domain units per time unit.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
#[type_name("minflow::Particle")]
pub struct Particle {
    /// Position x.
    pub x: f32,
    /// Position y.
    pub y: f32,
    /// Velocity x.
    pub vx: f32,
    /// Velocity y.
    pub vy: f32,
    /// Material id: 0 liquid, 1 jelly, 2 snow, 3 rope.
    pub material: u32,
}

/// The per-sample user header: everything of a `ParticleFrame` but the particles.
/// `header.frame_id` is always `"world"` (docs/design.md, "Topics and transports") and is
/// not carried.
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[repr(C)]
#[type_name("minflow::FrameHeader")]
pub struct FrameHeader {
    /// Scene id, UTF-8, NUL-padded (at most 63 bytes).
    pub scene: [u8; 64],
    /// Frame number from the start of the scene.
    pub frame_index: u32,
    /// Seconds (simulation time units) between frames.
    pub dt: f32,
    /// Stamp, whole seconds.
    pub stamp_sec: i32,
    /// Stamp, nanoseconds part.
    pub stamp_nanosec: u32,
    /// Number of particles in the slice that follows.
    pub particle_count: u32,
}

impl Default for FrameHeader {
    fn default() -> Self {
        FrameHeader {
            scene: [0; 64],
            frame_index: 0,
            dt: 0.0,
            stamp_sec: 0,
            stamp_nanosec: 0,
            particle_count: 0,
        }
    }
}

impl FrameHeader {
    /// The header of `frame`.
    ///
    /// # Errors
    /// [`TransportError::Unrepresentable`] for a scene id longer than 63 bytes or one with a
    /// NUL byte, or a frame_id other than `"world"`.
    pub fn from_frame(frame: &ParticleFrame) -> Result<Self, TransportError> {
        let unrep = |reason: String| TransportError::Unrepresentable {
            transport: KIND,
            reason,
        };
        let scene = frame.scene.as_bytes();
        if scene.len() > MAX_SCENE_BYTES {
            return Err(unrep(format!(
                "scene id {:?} is {} bytes; at most {MAX_SCENE_BYTES} fit",
                frame.scene,
                scene.len()
            )));
        }
        if scene.contains(&0) {
            return Err(unrep(format!(
                "scene id {:?} contains a NUL byte",
                frame.scene
            )));
        }
        if frame.header.frame_id != "world" {
            return Err(unrep(format!(
                "frame_id {:?}: iceoryx2 frames are in \"world\"",
                frame.header.frame_id
            )));
        }
        let mut header = FrameHeader {
            frame_index: frame.frame_index,
            dt: frame.dt,
            stamp_sec: frame.header.stamp.sec,
            stamp_nanosec: frame.header.stamp.nanosec,
            particle_count: u32::try_from(frame.len())
                .map_err(|_| unrep("too many particles".into()))?,
            ..FrameHeader::default()
        };
        header.scene[..scene.len()].copy_from_slice(scene);
        Ok(header)
    }

    /// The scene id.
    ///
    /// # Errors
    /// [`SampleError::SceneUnterminated`] or [`SampleError::SceneUtf8`].
    pub fn scene(&self) -> Result<&str, SampleError> {
        let end = self
            .scene
            .iter()
            .position(|&b| b == 0)
            .ok_or(SampleError::SceneUnterminated)?;
        std::str::from_utf8(&self.scene[..end]).map_err(SampleError::SceneUtf8)
    }
}

/// Writes `frame`'s particles into `out` (same length as the frame).
pub fn write_particles(frame: &ParticleFrame, out: &mut [std::mem::MaybeUninit<Particle>]) {
    for (i, p) in out.iter_mut().enumerate() {
        p.write(Particle {
            x: frame.position[2 * i],
            y: frame.position[2 * i + 1],
            vx: frame.velocity[2 * i],
            vy: frame.velocity[2 * i + 1],
            material: u32::from(frame.material[i]),
        });
    }
}

/// Why a received sample is not a frame.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SampleError {
    /// The header's particle count disagrees with the slice.
    #[error("header says {header} particles, sample carries {carried}")]
    Count {
        /// `particle_count` in the header.
        header: u32,
        /// Particles in the sample's slice.
        carried: usize,
    },
    /// The scene field has no NUL byte.
    #[error("scene id not NUL-terminated")]
    SceneUnterminated,
    /// The scene field is not UTF-8.
    #[error("scene id not UTF-8: {0}")]
    SceneUtf8(#[source] std::str::Utf8Error),
    /// A material id that does not fit the message's byte.
    #[error("material id {0} out of range")]
    Material(u32),
}

/// Rebuilds a `ParticleFrame` from a header and its particles.
///
/// # Errors
/// A [`SampleError`] if the header's count disagrees with the slice, the scene id is bad
/// or a material id does not fit a byte.
pub fn to_frame(
    header: &FrameHeader,
    particles: &[Particle],
) -> Result<ParticleFrame, SampleError> {
    if header.particle_count as usize != particles.len() {
        return Err(SampleError::Count {
            header: header.particle_count,
            carried: particles.len(),
        });
    }
    let mut position = Vec::with_capacity(2 * particles.len());
    let mut velocity = Vec::with_capacity(2 * particles.len());
    let mut material = Vec::with_capacity(particles.len());
    for p in particles {
        position.extend_from_slice(&[p.x, p.y]);
        velocity.extend_from_slice(&[p.vx, p.vy]);
        material.push(u8::try_from(p.material).map_err(|_| SampleError::Material(p.material))?);
    }
    Ok(ParticleFrame {
        header: Header {
            stamp: Time {
                sec: header.stamp_sec,
                nanosec: header.stamp_nanosec,
            },
            frame_id: "world".into(),
        },
        scene: header.scene()?.to_owned(),
        frame_index: header.frame_index,
        dt: header.dt,
        position,
        velocity,
        material,
    })
}

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
        let err = |reason: String| TransportError::Declare {
            transport: KIND,
            what,
            topic: topic.to_owned(),
            reason,
        };
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
        let err = |reason: String| TransportError::Declare {
            transport: KIND,
            what: "publisher",
            topic: topic.to_owned(),
            reason,
        };
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
        let err = |reason: String| TransportError::Declare {
            transport: KIND,
            what: "subscriber",
            topic: topic.to_owned(),
            reason,
        };
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
            .map_err(|e| TransportError::Declare {
                transport: KIND,
                what: "status publisher",
                topic: topic.to_owned(),
                reason: format!("{e:?}"),
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
        let subscriber =
            service
                .subscriber_builder()
                .create()
                .map_err(|e| TransportError::Declare {
                    transport: KIND,
                    what: "status subscriber",
                    topic: topic.to_owned(),
                    reason: format!("{e:?}"),
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
            .map_err(|e| TransportError::Declare {
                transport: KIND,
                what: "status subscriber",
                topic: topic.to_owned(),
                reason: e.to_string(),
            })?;
        Ok(Box::new(IceoryxSubscription {
            stop,
            thread: Some(thread),
        }))
    }
}

/// Status reports travel as their CDR bytes in a `[u8]` slice service named like the topic.
struct IceoryxStatusPublisher {
    topic: String,
    _service: iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>,
    publisher: iceoryx2::port::publisher::Publisher<Svc, [u8], ()>,
}

impl StatusPublisher for IceoryxStatusPublisher {
    fn publish(&mut self, status: &SurrogateStatus) -> Result<(), TransportError> {
        let err = |reason: String| TransportError::Publish {
            transport: KIND,
            topic: self.topic.clone(),
            reason,
        };
        let bytes = encode_status(status);
        let sample = self
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| err(format!("loan: {e:?}")))?;
        let sample = sample.write_from_slice(&bytes);
        sample.send().map_err(|e| err(format!("send: {e:?}")))?;
        Ok(())
    }
}

impl IceoryxTransport {
    fn status_service(
        &self,
        topic: &str,
        what: &'static str,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>,
        TransportError,
    > {
        let err = |reason: String| TransportError::Declare {
            transport: KIND,
            what,
            topic: topic.to_owned(),
            reason,
        };
        let name: ServiceName = topic_key(topic)?
            .try_into()
            .map_err(|e| err(format!("service name: {e:?}")))?;
        self.node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .history_size(1)
            .subscriber_max_buffer_size(8)
            .open_or_create()
            .map_err(|e| err(format!("{e:?}")))
    }
}

struct IceoryxPublisher {
    topic: String,
    service: PubSubFactory<Svc, [Particle], FrameHeader>,
    publisher: iceoryx2::port::publisher::Publisher<Svc, [Particle], FrameHeader>,
    notifier: iceoryx2::port::notifier::Notifier<Svc>,
}

impl FramePublisher for IceoryxPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        let header = FrameHeader::from_frame(frame)?;
        let err = |reason: String| TransportError::Publish {
            transport: KIND,
            topic: self.topic.clone(),
            reason,
        };
        let mut sample = self
            .publisher
            .loan_slice_uninit(frame.len())
            .map_err(|e| err(format!("loan: {e:?}")))?;
        *sample.user_header_mut() = header;
        write_particles(frame, sample.payload_mut());
        // SAFETY: every element was written by `write_particles` (slice length = frame.len()).
        let sample = unsafe { sample.assume_init() };
        sample.send().map_err(|e| err(format!("send: {e:?}")))?;
        self.notifier
            .notify()
            .map_err(|e| err(format!("notify: {e:?}")))?;
        Ok(())
    }

    fn subscriber_count(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }
}

struct IceoryxSubscription {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<()>>,
}

impl Subscription for IceoryxSubscription {}

impl Drop for IceoryxSubscription {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_is_packed() {
        assert_eq!(std::mem::size_of::<Particle>(), 20);
        assert_eq!(std::mem::size_of::<FrameHeader>(), 64 + 5 * 4);
    }

    /// A sample that disagrees with its header is refused with the reason, not truncated.
    #[test]
    fn bad_samples_name_what_is_wrong() {
        let particle = |material| Particle {
            x: 0.5,
            y: 0.5,
            vx: 0.0,
            vy: 0.0,
            material,
        };
        let frame = ParticleFrame {
            header: Header {
                frame_id: "world".into(),
                ..Header::default()
            },
            scene: "s".into(),
            position: vec![0.5, 0.5],
            velocity: vec![0.0, 0.0],
            material: vec![1],
            ..ParticleFrame::default()
        };
        let header = FrameHeader::from_frame(&frame).unwrap();
        assert_eq!(to_frame(&header, &[particle(1)]).unwrap().scene, "s");
        assert_eq!(
            to_frame(&header, &[]).unwrap_err(),
            SampleError::Count {
                header: 1,
                carried: 0
            }
        );
        assert_eq!(
            to_frame(&header, &[particle(300)]).unwrap_err(),
            SampleError::Material(300)
        );
        let mut full = header;
        full.scene = [b'a'; 64];
        assert_eq!(full.scene(), Err(SampleError::SceneUnterminated));
    }
}
