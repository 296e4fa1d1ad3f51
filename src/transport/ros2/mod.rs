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
//!   `ZENOH_CONFIG_OVERRIDE`, as in `rmw_zenoh`. The type hash in keys and liveliness tokens
//!   is the REP-2016 `RIHS01_…` hash of the message, computed from `msgs/*.msg` as rosidl
//!   does ([`crate::msgs::type_hash`]) and handed to ros2-client through the one hook of
//!   our vendored copy (`vendor/README.md`; upstream sends an all-zero placeholder for
//!   custom types, which C++ `rmw_zenoh` subscribers do not match). Subscriptions accept
//!   any hash (ros2-client listens with a wildcard in the hash slot).
//!
//! QoS: the ROS 2 default profile (`rmw_qos_profile_default`: reliable, volatile, keep last
//! 10, see [`QOS`]) for publishers and subscriptions.
//!
//! Serialization: serde into plain CDR little-endian (XCDR1) through the same serializer the
//! middleware uses; the bytes on the wire are the 4-byte encapsulation header `00 01 00 00`
//! followed by a body that is byte-identical to
//! [`cdr::encode`](crate::msgs::cdr::encode) (unit-tested in `wire.rs`). Received messages
//! are delivered as [`Payload::Cdr`](super::Payload::Cdr) (the frame re-encoded with
//! `cdr::encode`, i.e. the little-endian wire form), or
//! [`Payload::Malformed`](super::Payload::Malformed) when a sample on the topic cannot be
//! deserialized as a `ParticleFrame`.
//!
//! Threads: one spinner thread per [`Ros2Transport`] on DDS (ros2-client's `Spinner`, which
//! tracks matched subscriptions for [`FramePublisher::subscriber_count`]), and one delivery
//! thread per subscription, woken by the middleware (no polling). ros2-client's own types
//! never leave those threads or the `Send` wrappers here, so the caller's thread never runs
//! middleware code except for `publish`.
//!
//! Distribution: Jazzy or Kilted (`--ros-distro`, else `ROS_DISTRO`, default Kilted; the
//! same wire format). Every DDS endpoint announces its type's REP-2016 hash in USER_DATA
//! (`typehash=RIHS01_...;`), as `rmw_fastrtps_cpp` does (`distro.rs`).
//!
//! Delivery: `flush` waits (bounded) until every matched reliable reader acknowledged what
//! was published (`wait_for_all_acked`). A peer on this host that advertises its LAN
//! address gets loopback-sized datagrams (a 42 KB frame is one UDP datagram, not ~33), a
//! change in our vendored RustDDS (`vendor/README.md`, docs/ros2.md).
//!
//! Files: `names.rs` (type names, topic names, QoS, `ROS_DOMAIN_ID`), `wire.rs` (the serde
//! mirror of the message), `dds.rs` and `rmw_zenoh.rs` (opening a node on each backend),
//! `distro.rs` (distribution, type hashes on DDS), `publish.rs` (frame and status
//! publishers), `flow.rs` (the DDS writers' flow-control window), `subscribe.rs`
//! (subscriptions and their delivery threads), `cloud.rs` (`sensor_msgs/PointCloud2` beside
//! the frames); this file holds [`Ros2Transport`] and its [`Transport`] impl.

mod cloud;
mod dds;
mod distro;
mod flow;
mod names;
mod publish;
mod rmw_zenoh;
mod subscribe;
mod wire;

use std::sync::mpsc::Sender;
use std::sync::Arc;

use super::{
    FramePublisher, Sample, StatusPublisher, Subscription, Transport, TransportError, TransportKind,
};
pub use cloud::{open_with_pointcloud2, with_pointcloud2, CloudPublisher};
use dds::{open_dds, DdsNode};
pub use distro::{select as select_distro, type_hash_user_data, RosDistro};
pub use names::{domain_id_from_env, OpenError, MAX_DOMAIN_ID, MESSAGE, PACKAGE, QOS};
use rmw_zenoh::{open_zenoh, ZenohNode};

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
        let open_err = |e: OpenError| TransportError::Open {
            transport: kind,
            reason: e.to_string(),
        };
        let domain_id = domain_id_from_env().map_err(open_err)?;
        distro::select_if_unset();
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

impl Transport for Ros2Transport {
    fn kind(&self) -> TransportKind {
        self.backend.kind()
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError> {
        self.frame_publisher(topic)
    }

    /// `minflow_msgs/msg/SurrogateStatus` on the topic (DDS type
    /// `minflow_msgs::msg::dds_::SurrogateStatus_`), default ROS 2 QoS.
    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        self.surrogate_status_publisher(topic)
    }

    fn subscribe(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        self.frame_subscription(topic, sink)
    }
}
