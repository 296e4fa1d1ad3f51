//! Transports: one small interface to publish and subscribe `ParticleFrame`s on a named
//! topic, with three real implementations (docs/design.md, "Topics and transports").
//!
//! - [`zenoh`](self::zenoh): key = topic without the leading slash, payload = the CDR bytes
//!   (the zenoh-bridge-ros2dds mapping); embedded peer session by default, or a standard
//!   zenoh JSON5 config file.
//! - [`iceoryx2`](self::iceoryx2): zero-copy shared memory, a `#[repr(C)]` user header and a
//!   slice of `#[repr(C)]` particles; stale resources of dead nodes are removed on open.
//! - [`ros2`](self::ros2): ROS 2 over DDS with `ros2-client` (`rt/mpm/frames`,
//!   `minflow_msgs::msg::dds_::ParticleFrame_`, default ROS 2 QoS, `ROS_DOMAIN_ID`), and the
//!   same crate's rmw_zenoh-compatible backend as `ros2-zenoh`.
//!
//! Every subscription delivers [`Sample`]s into a channel owned by the caller, from the
//! transport's own I/O thread: the caller's thread never runs transport code, and a slow
//! consumer never blocks a publisher. [`counters`] holds the node counters (received,
//! published, dropped, malformed) the nodes share between their threads.

pub mod counters;
pub mod iceoryx2;
pub mod ros2;
pub mod zenoh;

use std::path::PathBuf;
use std::sync::mpsc::Sender;
use std::time::{Duration, Instant};

use crate::msgs::status::SurrogateStatus;
use crate::msgs::{cdr, FrameError, ParticleFrame};

pub use counters::Counters;

/// Which middleware carries the frames. Named as [`std::fmt::Display`] writes it (`zenoh`,
/// `iceoryx2`, `ros2`, `ros2-zenoh`) on the command line (`--transport`, `cli::transport`)
/// and in launch files.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum TransportKind {
    /// zenoh 1.x: key = topic without the leading '/', payload = CDR bytes.
    Zenoh,
    /// iceoryx2 zero-copy shared memory (same host only).
    Iceoryx2,
    /// ROS 2 over DDS (RTPS) with ros2-client; honours ROS_DOMAIN_ID.
    Ros2,
    /// ROS 2 over rmw_zenoh's wire protocol (ros2-client's zenoh backend).
    Ros2Zenoh,
}

impl TransportKind {
    /// Every middleware, in the order `--help` lists them.
    pub const ALL: [TransportKind; 4] = [
        TransportKind::Zenoh,
        TransportKind::Iceoryx2,
        TransportKind::Ros2,
        TransportKind::Ros2Zenoh,
    ];

    /// The middleware's name on the command line and in launch files.
    pub fn name(self) -> &'static str {
        match self {
            TransportKind::Zenoh => "zenoh",
            TransportKind::Iceoryx2 => "iceoryx2",
            TransportKind::Ros2 => "ros2",
            TransportKind::Ros2Zenoh => "ros2-zenoh",
        }
    }
}

impl std::fmt::Display for TransportKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Options shared by every node that opens a transport (the command line's `--transport`
/// flag group, `cli::transport::TransportArgs`).
#[derive(Debug, Clone)]
pub struct TransportOptions {
    /// Middleware to use.
    pub transport: TransportKind,
    /// A standard zenoh JSON5 config file (routers, endpoints, scouting, TLS, access
    /// control, shared memory); without it, an embedded peer session that needs no router.
    pub zenoh_config: Option<PathBuf>,
    /// With `ros2` or `ros2-zenoh`: the ROS 2 distribution of the peers; None: `ROS_DISTRO`
    /// when it names one minflow knows, else Kilted ([`ros2::select_distro`]).
    pub ros_distro: Option<ros2::RosDistro>,
}

impl TransportOptions {
    /// Options for `kind` with the default zenoh session.
    pub fn new(kind: TransportKind) -> Self {
        TransportOptions {
            transport: kind,
            zenoh_config: None,
            ros_distro: None,
        }
    }
}

/// Errors of opening a transport, declaring a publisher/subscriber or sending.
#[derive(Debug, thiserror::Error)]
pub enum TransportError {
    /// The middleware could not be opened (session, node or context creation).
    #[error("cannot open {transport}: {reason}")]
    Open {
        transport: TransportKind,
        reason: String,
    },
    /// A publisher or subscriber could not be declared on `topic`.
    #[error("cannot declare {what} on {topic} over {transport}: {reason}")]
    Declare {
        transport: TransportKind,
        what: &'static str,
        topic: String,
        reason: String,
    },
    /// Sending one frame failed.
    #[error("cannot publish on {topic} over {transport}: {reason}")]
    Publish {
        transport: TransportKind,
        topic: String,
        reason: String,
    },
    /// The frame cannot be carried by this transport (for example a scene id longer than
    /// iceoryx2's 63-byte header field, or more particles than the service allows).
    #[error("frame not representable on {transport}: {reason}")]
    Unrepresentable {
        transport: TransportKind,
        reason: String,
    },
    /// The topic is not a valid ROS 2 topic name (`/a/b`, no trailing '/').
    #[error("invalid topic {0:?}: expected an absolute ROS 2 name such as /mpm/frames")]
    Topic(String),
}

impl TransportError {
    /// [`TransportError::Declare`]: `what` (a publisher, a subscriber, ...) could not be
    /// declared on `topic` over `transport`, because `reason`. Every transport builds its
    /// declaration errors through this.
    pub fn declare(
        transport: TransportKind,
        what: &'static str,
        topic: impl Into<String>,
        reason: impl Into<String>,
    ) -> Self {
        TransportError::Declare {
            transport,
            what,
            topic: topic.into(),
            reason: reason.into(),
        }
    }
}

/// Why a received message is not a usable frame ([`Sample::frame`], [`Sample::decode`],
/// [`Sample::cdr`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MalformedFrame {
    /// The CDR bytes do not decode (the field and byte offset are in the error).
    #[error(transparent)]
    Cdr(#[from] cdr::CdrError),
    /// The frame decodes but is not valid (lengths, finiteness, material ids).
    #[error(transparent)]
    Invalid(#[from] FrameError),
    /// The transport delivered something that is not a frame; its reason as it gave it
    /// ([`Payload::Malformed`]).
    #[error("{0}")]
    Transport(String),
}

/// What arrived on a subscription.
#[derive(Debug, Clone)]
pub enum Payload {
    /// Serialized bytes as they travelled (zenoh, ROS 2): CDR with encapsulation header.
    Cdr(Vec<u8>),
    /// A frame rebuilt from a zero-copy sample (iceoryx2).
    Frame(ParticleFrame),
    /// Something arrived that is not a valid frame; the reason says why.
    Malformed(String),
}

/// One received message with the topic it came on and when it arrived.
#[derive(Debug, Clone)]
pub struct Sample {
    /// ROS 2 topic name (`/mpm/frames`).
    pub topic: String,
    /// The message.
    pub payload: Payload,
    /// Arrival time on the transport's I/O thread (for latency measurements).
    pub received: Instant,
}

impl Sample {
    /// The frame, decoding CDR if needed.
    ///
    /// # Errors
    /// The reason a payload is malformed (CDR decode error, failed validation).
    pub fn frame(&self) -> Result<ParticleFrame, MalformedFrame> {
        let frame = self.decode()?;
        frame.validate()?;
        Ok(frame)
    }

    /// The frame as it arrived, decoded but not validated (lengths, finiteness and material
    /// ids unchecked: see [`ParticleFrame::validate`]).
    ///
    /// # Errors
    /// The reason the payload does not decode.
    pub fn decode(&self) -> Result<ParticleFrame, MalformedFrame> {
        match &self.payload {
            Payload::Cdr(bytes) => Ok(cdr::decode(bytes)?),
            Payload::Frame(frame) => Ok(frame.clone()),
            Payload::Malformed(reason) => Err(MalformedFrame::Transport(reason.clone())),
        }
    }

    /// The CDR bytes of the message, encoding a zero-copy frame if needed; validated.
    ///
    /// # Errors
    /// As [`Sample::frame`].
    pub fn cdr(&self) -> Result<Vec<u8>, MalformedFrame> {
        match &self.payload {
            Payload::Cdr(bytes) => {
                cdr::decode(bytes)?.validate()?;
                Ok(bytes.clone())
            }
            _ => self.frame().map(|f| cdr::encode(&f)),
        }
    }
}

/// A publisher of frames on one topic.
pub trait FramePublisher: Send {
    /// Publishes one frame.
    ///
    /// # Errors
    /// [`TransportError::Publish`] or [`TransportError::Unrepresentable`].
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError>;

    /// Publishes a frame given as its CDR bytes (replay: the bag's bytes go out unchanged
    /// where the transport carries CDR). The default decodes and calls [`publish`].
    ///
    /// [`publish`]: FramePublisher::publish
    ///
    /// # Errors
    /// As [`publish`](FramePublisher::publish); malformed bytes give `Unrepresentable`.
    fn publish_cdr(&mut self, bytes: &[u8], frame: &ParticleFrame) -> Result<(), TransportError> {
        let _ = bytes;
        self.publish(frame)
    }

    /// Waits (at most `timeout`) until what was published has been delivered to the matched
    /// subscribers as far as the middleware can tell (DDS: acknowledged by reliable readers;
    /// zenoh: the session's queues drained). Call before dropping a publisher whose last
    /// messages matter. The default returns at once.
    fn flush(&mut self, timeout: Duration) {
        let _ = timeout;
    }

    /// Number of subscribers currently matched (a lower bound where the middleware only
    /// tells whether any is matched: zenoh gives 0 or 1).
    fn subscriber_count(&self) -> usize;
}

/// A publisher of [`SurrogateStatus`] reports (`/surrogate/status`).
pub trait StatusPublisher: Send {
    /// Publishes one report.
    ///
    /// # Errors
    /// [`TransportError::Publish`].
    fn publish(&mut self, status: &SurrogateStatus) -> Result<(), TransportError>;
}

/// Keeps a subscription alive; dropping it stops delivery and joins its thread.
pub trait Subscription: Send {}

/// An open middleware session: the factory of publishers and subscriptions.
pub trait Transport: Send + Sync {
    /// Which middleware this is.
    fn kind(&self) -> TransportKind;

    /// Declares a publisher on `topic` (a ROS 2 name such as `/mpm/frames`).
    ///
    /// # Errors
    /// [`TransportError::Declare`] or [`TransportError::Topic`].
    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError>;

    /// Subscribes to `topic`; every message is sent to `sink` from the transport's I/O
    /// thread, in arrival order. Delivery stops when the returned handle is dropped or the
    /// receiver is gone.
    ///
    /// # Errors
    /// [`TransportError::Declare`] or [`TransportError::Topic`].
    fn subscribe(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError>;

    /// Declares a publisher of status reports on `topic`.
    ///
    /// # Errors
    /// [`TransportError::Declare`]; the default says the transport has none.
    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        Err(TransportError::declare(
            self.kind(),
            "status publisher",
            topic.to_owned(),
            "not supported by this transport",
        ))
    }

    /// The zenoh session under this transport, for callers that need zenoh beyond frames
    /// (the node's `--shard` liveliness tokens); None for other middleware.
    fn zenoh_session(&self) -> Option<::zenoh::Session> {
        None
    }

    /// Subscribes to status reports on `topic`; undecodable ones are logged and skipped.
    ///
    /// # Errors
    /// [`TransportError::Declare`]; the default says the transport has none.
    fn subscribe_status(
        &self,
        topic: &str,
        sink: Sender<SurrogateStatus>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let _ = sink;
        Err(TransportError::declare(
            self.kind(),
            "status subscriber",
            topic.to_owned(),
            "not supported by this transport",
        ))
    }
}

/// Opens the middleware named by `options`.
///
/// # Errors
/// [`TransportError::Open`] with the middleware's own message.
pub fn open(options: &TransportOptions) -> Result<Box<dyn Transport>, TransportError> {
    match options.transport {
        TransportKind::Zenoh => Ok(Box::new(zenoh::ZenohTransport::open(
            options.zenoh_config.as_deref(),
        )?)),
        TransportKind::Iceoryx2 => Ok(Box::new(iceoryx2::IceoryxTransport::open()?)),
        TransportKind::Ros2 | TransportKind::Ros2Zenoh => {
            ros2::select_distro(options.ros_distro);
            let backend = match options.transport {
                TransportKind::Ros2 => ros2::Backend::Dds,
                _ => ros2::Backend::Zenoh,
            };
            Ok(Box::new(ros2::Ros2Transport::open(backend)?))
        }
    }
}

/// Checks a ROS 2 topic name (absolute, segments of `[A-Za-z0-9_]`, no trailing '/') and
/// returns it without the leading slash: the zenoh key and iceoryx2 service name.
///
/// # Errors
/// [`TransportError::Topic`].
pub fn topic_key(topic: &str) -> Result<&str, TransportError> {
    let key = topic
        .strip_prefix('/')
        .ok_or_else(|| TransportError::Topic(topic.to_owned()))?;
    let ok = !key.is_empty()
        && key.split('/').all(|seg| {
            !seg.is_empty()
                && seg.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                && !seg.starts_with(|c: char| c.is_ascii_digit())
        });
    if ok {
        Ok(key)
    } else {
        Err(TransportError::Topic(topic.to_owned()))
    }
}

/// Waits until `publisher` has at least `n` subscribers, or `timeout` passes.
/// Returns whether the count was reached.
pub fn wait_for_subscribers(publisher: &dyn FramePublisher, n: usize, timeout: Duration) -> bool {
    let deadline = Instant::now() + timeout;
    loop {
        if publisher.subscriber_count() >= n {
            return true;
        }
        if Instant::now() >= deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topic_names() {
        assert_eq!(topic_key("/mpm/frames").unwrap(), "mpm/frames");
        assert!(topic_key("mpm/frames").is_err());
        assert!(topic_key("/mpm/").is_err());
        assert!(topic_key("/mpm//frames").is_err());
        assert!(topic_key("/mpm/fr ames").is_err());
        assert!(topic_key("/1mpm").is_err());
    }
}
