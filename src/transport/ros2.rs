//! ROS 2 transport with [`ros2-client`](https://docs.rs/ros2-client) 0.12: a real ROS 2 node
//! (pure Rust, no ROS installation needed) that publishes and subscribes
//! `minflow_msgs/msg/ParticleFrame` exactly as an `rclcpp`/`rclpy` node would
//! (docs/design.md, "Messages" and "Topics and transports").
//!
//! Two middlewares, chosen with [`Backend`]:
//!
//! - [`Backend::Dds`] (`--transport ros2`): DDS/RTPS with RustDDS, interoperable with
//!   `rmw_fastrtps_cpp`, `rmw_cyclonedds_cpp` and `rmw_connextdds`. ROS 2 topic `/mpm/frames`
//!   is the DDS topic `rt/mpm/frames` and the DDS type name is
//!   `minflow_msgs::msg::dds_::ParticleFrame_` (the mapping of the ROS 2 design article
//!   "Topic and Service name mapping to DDS",
//!   <https://design.ros2.org/articles/topic_and_service_names.html>). The domain is
//!   `ROS_DOMAIN_ID` (default 0, see [`domain_id_from_env`]).
//! - [`Backend::Zenoh`] (`--transport ros2-zenoh`): the `rmw_zenoh` wire protocol (key
//!   `<domain>/<topic>/<dds type>/<type hash>`, liveliness tokens for the ROS graph, an
//!   attachment with sequence number, source timestamp and GID per message). Like
//!   `rmw_zenoh`, processes find each other through a zenoh router on
//!   `tcp/localhost:7447` (`ros2 run rmw_zenoh_cpp rmw_zenohd`, or `zenohd`); the session
//!   config can be replaced with `ZENOH_SESSION_CONFIG_URI` and amended with
//!   `ZENOH_CONFIG_OVERRIDE`, as in `rmw_zenoh`. Limitation: ros2-client cannot compute the
//!   REP-2016 type hash of a custom message, so it *sends* with an all-zero placeholder
//!   hash; ros2-client receivers (and therefore minflow) accept any hash, but a C++
//!   `rmw_zenoh` subscriber expects the real `RIHS01_…` hash and will not receive minflow's
//!   frames. The other direction (C++ publisher → minflow) works.
//!
//! QoS: the ROS 2 default profile (`rmw_qos_profile_default`: reliable, volatile, keep last
//! 10, see [`QOS`]) for publishers and subscriptions.
//!
//! Serialization: serde into plain CDR little-endian (XCDR1) through the same serializer the
//! middleware uses; the bytes on the wire are the 4-byte encapsulation header `00 01 00 00`
//! followed by a body that is byte-identical to [`cdr::encode`] (unit-tested below).
//! Received messages are delivered as [`Payload::Cdr`] (the frame re-encoded with
//! [`cdr::encode`], i.e. the little-endian wire form), or [`Payload::Malformed`] when a
//! sample on the topic cannot be deserialized as a `ParticleFrame`.
//!
//! Threads: one spinner thread per [`Ros2Transport`] on DDS (ros2-client's `Spinner`, which
//! tracks matched subscriptions for [`FramePublisher::subscriber_count`]), and one delivery
//! thread per subscription, woken by the middleware (no polling). ros2-client's own types
//! never leave those threads or the `Send` wrappers here, so the caller's thread never runs
//! middleware code except for `publish`.

use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::mpsc::{self, Sender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use futures::channel::oneshot;
use futures::{FutureExt, Stream, StreamExt};
use ros2_client::qos::{History, QosProfile, Reliability, WhenFull};
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions, ReadError};
use serde::{Deserialize, Serialize};

use super::{
    topic_key, FramePublisher, Payload, Sample, StatusPublisher, Subscription, Transport,
    TransportError, TransportKind,
};
use crate::msgs::status::SurrogateStatus;
use crate::msgs::{cdr, Header, ParticleFrame, Time};

/// ROS 2 package of the message type (`minflow_msgs/msg/ParticleFrame`).
pub const PACKAGE: &str = "minflow_msgs";
/// ROS 2 message name within [`PACKAGE`].
pub const MESSAGE: &str = "ParticleFrame";

/// The ROS 2 default QoS profile (`rmw_qos_profile_default` in `rmw/qos_profiles.h`):
/// reliable, volatile, keep last 10, no deadline, no lifespan, automatic liveliness with an
/// infinite lease. A reliable `publish` waits up to 100 ms when the send window is full
/// (RustDDS's `max_blocking_time`, the DDS default), then fails.
pub const QOS: QosProfile = QosProfile::publisher_default()
    .reliability(Reliability::Reliable {
        when_full: WhenFull::Wait(Duration::from_millis(100)),
    })
    .history(History::KeepLast { depth: 10 });

/// The highest `ROS_DOMAIN_ID` ROS 2 accepts (DDS's UDP port mapping: 7400 + 250 x domain
/// must stay below 65536 with room for participants, see the ROS 2 documentation
/// "The ROS_DOMAIN_ID").
pub const MAX_DOMAIN_ID: u16 = 232;

/// Which middleware the ROS 2 node runs on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Backend {
    /// DDS/RTPS (RustDDS): any `rmw_*` DDS implementation on the same domain.
    Dds,
    /// The `rmw_zenoh` protocol over zenoh (ros2-client's zenoh backend).
    Zenoh,
}

impl Backend {
    /// The `--transport` value of this backend.
    pub fn kind(self) -> TransportKind {
        match self {
            Backend::Dds => TransportKind::Ros2,
            Backend::Zenoh => TransportKind::Ros2Zenoh,
        }
    }
}

/// `ROS_DOMAIN_ID` as ROS 2 reads it: unset or empty means 0, otherwise a decimal integer in
/// `0..=232`.
///
/// # Errors
/// A message naming the bad value (not a number, or above [`MAX_DOMAIN_ID`]).
pub fn domain_id_from_env() -> Result<u16, String> {
    match std::env::var("ROS_DOMAIN_ID") {
        Err(std::env::VarError::NotPresent) => Ok(0),
        Err(std::env::VarError::NotUnicode(v)) => {
            Err(format!("ROS_DOMAIN_ID={v:?} is not a number"))
        }
        Ok(v) => parse_domain_id(&v),
    }
}

fn parse_domain_id(v: &str) -> Result<u16, String> {
    if v.trim().is_empty() {
        return Ok(0);
    }
    match v.trim().parse::<u16>() {
        Ok(id) if id <= MAX_DOMAIN_ID => Ok(id),
        _ => Err(format!(
            "ROS_DOMAIN_ID={v:?} is not a domain id (an integer 0..={MAX_DOMAIN_ID})"
        )),
    }
}

/// The ROS 2 [`Name`] of an absolute topic such as `/mpm/frames`.
fn ros_name(topic: &str) -> Result<Name, TransportError> {
    topic_key(topic)?;
    Name::parse(topic).map_err(|_| TransportError::Topic(topic.to_owned()))
}

fn type_name() -> MessageTypeName {
    MessageTypeName::new(PACKAGE, MESSAGE)
}

/// A fresh node name per transport: `minflow_<pid>_<n>` in the root namespace.
fn node_name() -> NodeName {
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    NodeName::new("/", &format!("minflow_{}_{n}", std::process::id())).expect("valid node name")
}

fn node_options() -> NodeOptions {
    // No /rosout writer and no parameter services: fewer DDS endpoints to discover, so peers
    // match our publishers sooner. The node is still announced on ros_discovery_info.
    NodeOptions::new()
        .enable_rosout(false)
        .start_parameter_services(false)
}

// --- wire type -------------------------------------------------------------------------------

/// serde mirror of `builtin_interfaces/Time`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct WireTime {
    sec: i32,
    nanosec: u32,
}

/// serde mirror of `std_msgs/Header`.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct WireHeader {
    stamp: WireTime,
    frame_id: String,
}

/// serde mirror of `minflow_msgs/msg/ParticleFrame`, fields in `.msg` order. Serialized by a
/// CDR serializer it gives exactly [`cdr::encode`]'s body: structs add no padding, strings
/// are length (with NUL) + bytes + NUL, sequences are a u32 count + elements, each primitive
/// aligned to its size. `material` stays a plain sequence of u8 (not `serialize_bytes`, which
/// cdr-encoding 0.10, used by ros2-client's zenoh backend, writes without the count).
#[derive(Debug, Clone, Serialize, Deserialize)]
struct WireFrame {
    header: WireHeader,
    scene: String,
    frame_index: u32,
    dt: f32,
    position: Vec<f32>,
    velocity: Vec<f32>,
    material: Vec<u8>,
}

impl From<ParticleFrame> for WireFrame {
    fn from(f: ParticleFrame) -> Self {
        WireFrame {
            header: WireHeader {
                stamp: WireTime {
                    sec: f.header.stamp.sec,
                    nanosec: f.header.stamp.nanosec,
                },
                frame_id: f.header.frame_id,
            },
            scene: f.scene,
            frame_index: f.frame_index,
            dt: f.dt,
            position: f.position,
            velocity: f.velocity,
            material: f.material,
        }
    }
}

impl From<WireFrame> for ParticleFrame {
    fn from(w: WireFrame) -> Self {
        ParticleFrame {
            header: Header {
                stamp: Time {
                    sec: w.header.stamp.sec,
                    nanosec: w.header.stamp.nanosec,
                },
                frame_id: w.header.frame_id,
            },
            scene: w.scene,
            frame_index: w.frame_index,
            dt: w.dt,
            position: w.position,
            velocity: w.velocity,
            material: w.material,
        }
    }
}

// --- transport -------------------------------------------------------------------------------

/// A ROS 2 node (one per transport) that declares a publisher or subscription per call.
///
/// Open with [`Ros2Transport::open`]. Dropping it stops the node's spinner once every
/// publisher and subscription made from it is gone too (they keep the node alive).
pub struct Ros2Transport {
    backend: Backend,
    domain_id: u16,
    node: NodeRef,
}

#[derive(Clone)]
enum NodeRef {
    Dds(Arc<DdsNode>),
    Zenoh(Arc<ZenohNode>),
}

/// The DDS node and the thread running its `Spinner` (graph/discovery bookkeeping).
struct DdsNode {
    node: Mutex<Option<ros2_client::dds::Node>>,
    spinner: Option<JoinHandle<()>>,
    /// Keeps the DDS participant alive until the node's own writers (parameter events,
    /// rosout) are gone: ros2-client's `Node` drops its context before them, and a writer
    /// dropped after the participant logs "Cannot remove Writer ... Disconnected" as ERROR.
    _context: ros2_client::dds::Context,
}

impl DdsNode {
    fn with<R>(&self, f: impl FnOnce(&mut ros2_client::dds::Node) -> R) -> R {
        let mut guard = self.node.lock().unwrap_or_else(|e| e.into_inner());
        f(guard.as_mut().expect("node present until drop"))
    }
}

impl Drop for DdsNode {
    fn drop(&mut self) {
        // Dropping the Node signals its spinner to stop (ros2-client's Node::drop).
        let node = self.node.lock().unwrap_or_else(|e| e.into_inner()).take();
        drop(node);
        if let Some(spinner) = self.spinner.take() {
            let _ = spinner.join();
        }
    }
}

/// The zenoh-backend node (no spinner needed: its graph cache is fed by zenoh callbacks).
struct ZenohNode {
    node: ros2_client::zenoh::Node,
}

impl Ros2Transport {
    /// Opens a ROS 2 context and node on `backend`, in the domain given by `ROS_DOMAIN_ID`.
    ///
    /// DDS: creates a RustDDS participant (UDP multicast discovery plus unicast to the
    /// same-host SPDP ports, socket buffers of 8 MiB requested) and starts the spinner thread.
    /// Zenoh: opens a zenoh session configured like `rmw_zenoh`'s default (peer, connect to
    /// a router at `tcp/localhost:7447`, multicast scouting off, listen on loopback), or from
    /// `ZENOH_SESSION_CONFIG_URI`; `ZENOH_CONFIG_OVERRIDE` (`key=json5value;...`) applies on top.
    ///
    /// # Errors
    /// [`TransportError::Open`] with the middleware's message (bad `ROS_DOMAIN_ID`, sockets,
    /// zenoh config).
    pub fn open(backend: Backend) -> Result<Self, TransportError> {
        let kind = backend.kind();
        let open_err = |reason: String| TransportError::Open {
            transport: kind,
            reason,
        };
        let domain_id = domain_id_from_env().map_err(open_err)?;
        let node = match backend {
            Backend::Dds => NodeRef::Dds(Arc::new(open_dds(domain_id).map_err(open_err)?)),
            Backend::Zenoh => NodeRef::Zenoh(Arc::new(open_zenoh(domain_id).map_err(open_err)?)),
        };
        Ok(Ros2Transport {
            backend,
            domain_id,
            node,
        })
    }

    /// The backend this transport runs on.
    pub fn backend(&self) -> Backend {
        self.backend
    }

    /// The ROS domain id in use (from `ROS_DOMAIN_ID`).
    pub fn domain_id(&self) -> u16 {
        self.domain_id
    }
}

fn open_dds(domain_id: u16) -> Result<DdsNode, String> {
    use ros2_client::dds::{Context, ContextOptions};
    let context = Context::with_options(ContextOptions::new().domain_id(domain_id))
        .map_err(|e| format!("DDS participant in domain {domain_id}: {e}"))?;
    let mut node = context
        .new_node(node_name(), node_options())
        .map_err(|e| format!("ROS 2 node: {e}"))?;
    let spinner = node
        .spinner()
        .map_err(|e| format!("ROS 2 node spinner: {e}"))?;
    let thread = std::thread::Builder::new()
        .name("ros2-spinner".into())
        .spawn(move || {
            if let Err(e) = futures::executor::block_on(spinner.spin()) {
                tracing::warn!("ROS 2 spinner stopped: {e}");
            }
        })
        .map_err(|e| format!("spinner thread: {e}"))?;
    Ok(DdsNode {
        node: Mutex::new(Some(node)),
        spinner: Some(thread),
        _context: context,
    })
}

/// `rmw_zenoh`'s default session config (`DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5`, Jazzy):
/// a peer that connects to the router on `tcp/localhost:7447` and learns about other peers by
/// gossip; multicast scouting off. Listening on loopback with an OS-chosen port.
fn rmw_zenoh_default_config() -> Result<zenoh::Config, String> {
    let mut config = zenoh::Config::default();
    for (key, value) in [
        ("mode", r#""peer""#),
        ("connect/endpoints", r#"["tcp/localhost:7447"]"#),
        ("listen/endpoints", r#"["tcp/127.0.0.1:0"]"#),
        ("scouting/multicast/enabled", "false"),
        ("scouting/gossip/enabled", "true"),
    ] {
        config
            .insert_json5(key, value)
            .map_err(|e| format!("zenoh config {key}: {e}"))?;
    }
    if let Ok(overrides) = std::env::var("ZENOH_CONFIG_OVERRIDE") {
        for entry in overrides
            .split(';')
            .map(str::trim)
            .filter(|s| !s.is_empty())
        {
            let (key, value) = entry
                .split_once('=')
                .ok_or_else(|| format!("ZENOH_CONFIG_OVERRIDE entry {entry:?} is not key=value"))?;
            config
                .insert_json5(key.trim(), value.trim())
                .map_err(|e| format!("ZENOH_CONFIG_OVERRIDE {}: {e}", key.trim()))?;
        }
    }
    Ok(config)
}

fn open_zenoh(domain_id: u16) -> Result<ZenohNode, String> {
    use ros2_client::zenoh::{Context, ContextOptions};
    let mut options = ContextOptions::new().domain_id(domain_id);
    // With ZENOH_SESSION_CONFIG_URI set, ros2-client loads that file (and the override).
    let from_file = std::env::var("ZENOH_SESSION_CONFIG_URI").is_ok_and(|v| !v.trim().is_empty());
    if !from_file {
        options = options.zenoh_config(rmw_zenoh_default_config()?);
    }
    let context = Context::with_options(options).map_err(|e| format!("zenoh session: {e}"))?;
    let node = context
        .new_node(node_name(), node_options())
        .map_err(|e| format!("ROS 2 node: {e}"))?;
    Ok(ZenohNode { node })
}

impl Transport for Ros2Transport {
    fn kind(&self) -> TransportKind {
        self.backend.kind()
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError> {
        let name = ros_name(topic)?;
        let declare_err = |reason: String| TransportError::Declare {
            transport: self.backend.kind(),
            what: "publisher",
            topic: topic.to_owned(),
            reason,
        };
        match &self.node {
            NodeRef::Dds(dds) => {
                let publisher = dds
                    .with(|node| {
                        let t = node.create_topic(&name, type_name(), &QOS)?;
                        node.create_publisher::<WireFrame>(&t, Some(QOS))
                    })
                    .map_err(|e| declare_err(e.to_string()))?;
                Ok(Box::new(DdsPublisher {
                    topic: topic.to_owned(),
                    publisher,
                    node: Arc::clone(dds),
                }))
            }
            NodeRef::Zenoh(z) => {
                let t = z.node.create_topic(&name, type_name(), &QOS);
                let publisher = z
                    .node
                    .create_publisher::<WireFrame>(&t, Some(QOS))
                    .map_err(|e| declare_err(e.to_string()))?;
                Ok(Box::new(ZenohPublisher {
                    topic: topic.to_owned(),
                    publisher,
                    node: Arc::clone(z),
                }))
            }
        }
    }

    /// `minflow_msgs/msg/SurrogateStatus` on the topic (DDS type
    /// `minflow_msgs::msg::dds_::SurrogateStatus_`), default ROS 2 QoS.
    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        let name = ros_name(topic)?;
        let kind = self.backend.kind();
        let declare_err = |reason: String| TransportError::Declare {
            transport: kind,
            what: "status publisher",
            topic: topic.to_owned(),
            reason,
        };
        let type_name = MessageTypeName::new(PACKAGE, "SurrogateStatus");
        match &self.node {
            NodeRef::Dds(dds) => {
                let publisher = dds
                    .with(|node| {
                        let t = node.create_topic(&name, type_name, &QOS)?;
                        node.create_publisher::<SurrogateStatus>(&t, Some(QOS))
                    })
                    .map_err(|e| declare_err(e.to_string()))?;
                Ok(Box::new(Ros2StatusPublisher {
                    topic: topic.to_owned(),
                    kind,
                    send: Box::new(move |s| {
                        publisher.publish(s.clone()).map_err(|e| e.to_string())
                    }),
                }))
            }
            NodeRef::Zenoh(z) => {
                let t = z.node.create_topic(&name, type_name, &QOS);
                let publisher = z
                    .node
                    .create_publisher::<SurrogateStatus>(&t, Some(QOS))
                    .map_err(|e| declare_err(e.to_string()))?;
                Ok(Box::new(Ros2StatusPublisher {
                    topic: topic.to_owned(),
                    kind,
                    send: Box::new(move |s| {
                        publisher.publish(s.clone()).map_err(|e| e.to_string())
                    }),
                }))
            }
        }
    }

    fn subscribe(
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
            .map_err(|e| TransportError::Declare {
                transport: kind,
                what: "subscription",
                topic: topic.to_owned(),
                reason: format!("delivery thread: {e}"),
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
                Err(TransportError::Declare {
                    transport: kind,
                    what: "subscription",
                    topic: topic.to_owned(),
                    reason,
                })
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

// --- publishers ------------------------------------------------------------------------------

type SendStatus = Box<dyn FnMut(&SurrogateStatus) -> Result<(), String> + Send>;

struct Ros2StatusPublisher {
    topic: String,
    kind: TransportKind,
    send: SendStatus,
}

impl StatusPublisher for Ros2StatusPublisher {
    fn publish(&mut self, status: &SurrogateStatus) -> Result<(), TransportError> {
        (self.send)(status).map_err(|reason| TransportError::Publish {
            transport: self.kind,
            topic: self.topic.clone(),
            reason,
        })
    }
}

struct DdsPublisher {
    topic: String,
    publisher: ros2_client::dds::Publisher<WireFrame>,
    node: Arc<DdsNode>,
}

impl FramePublisher for DdsPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.publisher
            .publish(WireFrame::from(frame.clone()))
            .map_err(|e| TransportError::Publish {
                transport: TransportKind::Ros2,
                topic: self.topic.clone(),
                reason: e.to_string(),
            })
    }

    /// Reliable DDS retransmits what readers missed after the write returns: give it time
    /// before the writer goes away (ros2-client does not expose acknowledgement waits).
    fn flush(&mut self, timeout: Duration) {
        std::thread::sleep(timeout.min(Duration::from_secs(1)));
    }

    /// Matched DDS subscriptions (readers matched through SEDP with compatible QoS), as
    /// tracked by the node's spinner (`Publisher::get_subscription_count`).
    fn subscriber_count(&self) -> usize {
        self.node.with(|node| {
            // ros2-client logs an error for a writer that has never been matched, so ask only
            // once discovery has seen a reader on the topic at all.
            if node.subscription_count(&self.topic) == 0 {
                0
            } else {
                self.publisher.get_subscription_count(node)
            }
        })
    }
}

struct ZenohPublisher {
    topic: String,
    publisher: ros2_client::zenoh::Publisher<WireFrame>,
    node: Arc<ZenohNode>,
}

impl FramePublisher for ZenohPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.publisher
            .publish(WireFrame::from(frame.clone()))
            .map_err(|e| TransportError::Publish {
                transport: TransportKind::Ros2Zenoh,
                topic: self.topic.clone(),
                reason: e.to_string(),
            })
    }

    /// Subscriptions on the topic in the ROS graph (rmw_zenoh liveliness tokens).
    fn subscriber_count(&self) -> usize {
        self.publisher.get_subscription_count(&self.node.node)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ros2_client::dds::rustdds::no_key::SerializerAdapter;
    use ros2_client::dds::rustdds::serialization::deserialize_from_cdr_with_rep_id;
    use ros2_client::dds::rustdds::{CDRSerializerAdapter, RepresentationIdentifier};

    fn frame(n: usize, scene: &str) -> ParticleFrame {
        ParticleFrame {
            header: Header {
                stamp: Time {
                    sec: -3,
                    nanosec: 123_456_789,
                },
                frame_id: "world".into(),
            },
            scene: scene.into(),
            frame_index: 77,
            dt: 0.0025,
            position: (0..2 * n).map(|i| i as f32 * 0.001).collect(),
            velocity: (0..2 * n).map(|i| -(i as f32) * 0.5).collect(),
            material: (0..n).map(|i| (i % 4) as u8).collect(),
        }
    }

    /// The serializer ros2-client's DDS publisher uses (rustdds `CDRSerializerAdapter`,
    /// little-endian) gives cdr::encode's body; the encapsulation header is CDR_LE, options 0.
    #[test]
    fn serde_cdr_matches_encoder() {
        // Odd string lengths and particle counts exercise every alignment case.
        for (n, scene) in [(0, ""), (1, "a"), (3, "multi/rope+snow/007"), (2500, "ab")] {
            let f = frame(n, scene);
            let expected = cdr::encode(&f);
            let body = <CDRSerializerAdapter<WireFrame> as SerializerAdapter<WireFrame>>::to_bytes(
                &WireFrame::from(f.clone()),
            )
            .unwrap();
            assert_eq!(&expected[4..], &body[..], "n={n} scene={scene:?}");
            let rep =
                <CDRSerializerAdapter<WireFrame> as SerializerAdapter<WireFrame>>::output_encoding(
                );
            assert_eq!(rep, RepresentationIdentifier::CDR_LE);
            assert_eq!(rep.to_bytes(), [expected[0], expected[1]]);
            assert_eq!(&expected[2..4], &[0, 0]);

            let (back, _) = deserialize_from_cdr_with_rep_id::<WireFrame>(
                &expected[4..],
                RepresentationIdentifier::CDR_LE,
            )
            .unwrap();
            assert_eq!(ParticleFrame::from(back), f);
        }
    }

    #[test]
    fn truncated_cdr_is_an_error() {
        let bytes = cdr::encode(&frame(10, "s"));
        for cut in [0, 3, 9, 20, bytes.len() - 1] {
            let r = deserialize_from_cdr_with_rep_id::<WireFrame>(
                &bytes[4..cut.max(4)],
                RepresentationIdentifier::CDR_LE,
            );
            assert!(r.is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn ros2_name_mangling() {
        let node = NodeName::new("/", "n").unwrap();
        assert_eq!(
            ros_name("/mpm/frames")
                .unwrap()
                .to_dds_name("rt", &node, ""),
            "rt/mpm/frames"
        );
        assert_eq!(
            ros_name("/surrogate/frames")
                .unwrap()
                .to_dds_name("rt", &node, ""),
            "rt/surrogate/frames"
        );
        assert_eq!(
            ros_name("/frames").unwrap().to_dds_name("rt", &node, ""),
            "rt/frames"
        );
        assert_eq!(type_name().dds_msg_type(), crate::msgs::DDS_TYPE_NAME);
        assert!(ros_name("mpm/frames").is_err());
        assert!(ros_name("/mpm/").is_err());
    }

    #[test]
    fn domain_ids() {
        assert_eq!(parse_domain_id(""), Ok(0));
        assert_eq!(parse_domain_id(" 42 "), Ok(42));
        assert_eq!(parse_domain_id("232"), Ok(232));
        assert!(parse_domain_id("233").is_err());
        assert!(parse_domain_id("-1").is_err());
        assert!(parse_domain_id("x").is_err());
    }

    #[test]
    fn default_qos_is_ros2_default() {
        use ros2_client::qos::{Durability, Liveliness};
        assert!(matches!(QOS.reliability, Reliability::Reliable { .. }));
        assert_eq!(QOS.durability, Durability::Volatile);
        assert_eq!(QOS.history, History::KeepLast { depth: 10 });
        assert_eq!(QOS.liveliness, Liveliness::Automatic);
        assert_eq!(
            (QOS.deadline, QOS.lifespan, QOS.liveliness_lease),
            (None, None, None)
        );
    }
}
