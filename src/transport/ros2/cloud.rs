//! `sensor_msgs/msg/PointCloud2` beside the frames, for RViz (`--pointcloud2 TOPIC`; the
//! encoding is [`crate::msgs::pointcloud2`]).
//!
//! [`with_pointcloud2`] wraps any open transport: every frame publisher it makes then also
//! publishes each frame's cloud on the cloud topic, through a ROS 2 node of its own (DDS, or
//! rmw_zenoh when the frames go over `ros2-zenoh`). QoS is `ros2 bag play`'s default for a
//! topic it has no recorded profile for, the ROS 2 default (reliable, volatile, keep last
//! 10): reliable and best-effort subscriptions (RViz offers both) match it.

use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use super::dds::DdsNode;
use super::flow::AckWindow;
use super::names::{ros_name, QOS};
use super::publish::wait_for_all_acked;
use super::rmw_zenoh::ZenohNode;
use super::{Backend, NodeRef, Ros2Transport};
use crate::msgs::pointcloud2::PointCloud2;
use crate::msgs::status::SurrogateStatus;
use crate::msgs::ParticleFrame;
use crate::transport::{
    FramePublisher, Sample, StatusPublisher, Subscription, Transport, TransportError, TransportKind,
};

/// A `sensor_msgs/msg/PointCloud2` publisher on one topic.
pub struct CloudPublisher {
    topic: String,
    sink: CloudSink,
    window: AckWindow,
    _transport: Ros2Transport,
}

enum CloudSink {
    Dds(ros2_client::dds::Publisher<PointCloud2>, Arc<DdsNode>),
    Zenoh(ros2_client::zenoh::Publisher<PointCloud2>, Arc<ZenohNode>),
}

impl CloudPublisher {
    /// Opens a ROS 2 node on `backend` and declares a PointCloud2 publisher on `topic`.
    ///
    /// # Errors
    /// [`TransportError::Open`], [`TransportError::Declare`] or [`TransportError::Topic`].
    pub fn open(backend: Backend, topic: &str) -> Result<Self, TransportError> {
        let transport = Ros2Transport::open(backend)?;
        let name = ros_name(topic)?;
        let type_name = ros2_client::MessageTypeName::new("sensor_msgs", "PointCloud2");
        let declare_err = |reason: String| {
            TransportError::declare(
                backend.kind(),
                "PointCloud2 publisher",
                topic.to_owned(),
                reason,
            )
        };
        let sink = match &transport.node {
            NodeRef::Dds(dds) => {
                let publisher = dds
                    .with(|node| {
                        let t = node.create_topic(&name, type_name, &QOS)?;
                        node.create_publisher::<PointCloud2>(&t, Some(QOS))
                    })
                    .map_err(|e| declare_err(e.to_string()))?;
                CloudSink::Dds(publisher, Arc::clone(dds))
            }
            NodeRef::Zenoh(z) => {
                let t = z.node.create_topic(&name, type_name, &QOS);
                let publisher = z
                    .node
                    .create_publisher::<PointCloud2>(&t, Some(QOS))
                    .map_err(|e| declare_err(e.to_string()))?;
                CloudSink::Zenoh(publisher, Arc::clone(z))
            }
        };
        Ok(CloudPublisher {
            topic: topic.to_owned(),
            sink,
            window: AckWindow::default(),
            _transport: transport,
        })
    }

    /// Publishes the cloud of `frame`.
    ///
    /// # Errors
    /// [`TransportError::Publish`] with the middleware's message.
    pub fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        let cloud = PointCloud2::from_frame(frame);
        let bytes = cloud.data.len() + 128;
        let (kind, result) = match &self.sink {
            CloudSink::Dds(p, _) => {
                let sent = p.publish(cloud).map_err(|e| e.to_string());
                if sent.is_ok() {
                    self.window.after_publish(p, bytes, &self.topic);
                }
                (TransportKind::Ros2, sent)
            }
            CloudSink::Zenoh(p, _) => (
                TransportKind::Ros2Zenoh,
                p.publish(cloud).map_err(|e| e.to_string()),
            ),
        };
        result.map_err(|reason| TransportError::Publish {
            transport: kind,
            topic: self.topic.clone(),
            reason,
        })
    }

    /// Matched subscriptions (DDS: as the node's spinner tracks them; rmw_zenoh: in the graph).
    pub fn subscriber_count(&self) -> usize {
        use futures::FutureExt;
        match &self.sink {
            CloudSink::Dds(p, node) => {
                node.with(|n| match p.wait_for_subscription(n).now_or_never() {
                    Some(()) => p.get_subscription_count(n),
                    None => 0,
                })
            }
            CloudSink::Zenoh(p, node) => p.get_subscription_count(&node.node),
        }
    }

    /// DDS: waits (at most `timeout`) until every reader acknowledged every cloud.
    pub fn flush(&self, timeout: Duration) {
        if let CloudSink::Dds(p, _) = &self.sink {
            wait_for_all_acked(p, &self.topic, timeout);
        }
    }
}

/// `session` with every frame publisher it makes also publishing PointCloud2 on `topic`.
/// The cloud's node runs on rmw_zenoh when `session` is `ros2-zenoh`, on DDS otherwise.
///
/// # Errors
/// As [`CloudPublisher::open`].
pub fn with_pointcloud2(
    session: Box<dyn Transport>,
    topic: &str,
) -> Result<Box<dyn Transport>, TransportError> {
    let backend = match session.kind() {
        TransportKind::Ros2Zenoh => Backend::Zenoh,
        _ => Backend::Dds,
    };
    let cloud = Arc::new(Mutex::new(CloudPublisher::open(backend, topic)?));
    Ok(Box::new(CloudTransport {
        inner: session,
        cloud,
    }))
}

struct CloudTransport {
    inner: Box<dyn Transport>,
    cloud: SharedCloud,
}

/// The cloud publisher, shared by every frame publisher of a [`CloudTransport`] (a
/// `simulate --publish` publishes from several threads).
type SharedCloud = Arc<Mutex<CloudPublisher>>;

impl Transport for CloudTransport {
    fn kind(&self) -> TransportKind {
        self.inner.kind()
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError> {
        Ok(Box::new(FrameAndCloud {
            inner: self.inner.publisher(topic)?,
            cloud: Arc::clone(&self.cloud),
        }))
    }

    fn subscribe(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        self.inner.subscribe(topic, sink)
    }

    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        self.inner.status_publisher(topic)
    }

    fn zenoh_session(&self) -> Option<zenoh::Session> {
        self.inner.zenoh_session()
    }

    fn subscribe_status(
        &self,
        topic: &str,
        sink: Sender<SurrogateStatus>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        self.inner.subscribe_status(topic, sink)
    }
}

/// A frame publisher that also publishes each frame's cloud (after the frame).
struct FrameAndCloud {
    inner: Box<dyn FramePublisher>,
    cloud: SharedCloud,
}

impl FrameAndCloud {
    fn with_cloud<R>(&self, f: impl FnOnce(&mut CloudPublisher) -> R) -> R {
        f(&mut self.cloud.lock().unwrap_or_else(|e| e.into_inner()))
    }

    fn cloud(&self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.with_cloud(|c| c.publish(frame))
    }
}

impl FramePublisher for FrameAndCloud {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.inner.publish(frame)?;
        self.cloud(frame)
    }

    fn publish_cdr(&mut self, bytes: &[u8], frame: &ParticleFrame) -> Result<(), TransportError> {
        self.inner.publish_cdr(bytes, frame)?;
        self.cloud(frame)
    }

    fn flush(&mut self, timeout: Duration) {
        self.inner.flush(timeout);
        self.with_cloud(|c| c.flush(timeout));
    }

    /// Frame subscribers plus cloud subscribers (an RViz watching counts, as a Foxglove
    /// client does for the Foxglove view).
    fn subscriber_count(&self) -> usize {
        self.inner.subscriber_count() + self.with_cloud(|c| c.subscriber_count())
    }
}

/// Opens the transport `options` names, wrapped by [`with_pointcloud2`] when `pointcloud2`
/// names a cloud topic (the `--pointcloud2 TOPIC` flag of `replay`, `node` and `simulate
/// --publish`, `cli::transport::PointCloud2Args`): the frames go over whatever
/// `options.transport` is, the clouds over ROS 2 (DDS, or rmw_zenoh with `ros2-zenoh`).
///
/// # Errors
/// As [`crate::transport::open`] and [`CloudPublisher::open`].
pub fn open_with_pointcloud2(
    options: &crate::transport::TransportOptions,
    pointcloud2: Option<&str>,
) -> Result<Box<dyn Transport>, TransportError> {
    let session = crate::transport::open(options)?;
    match pointcloud2 {
        Some(topic) => {
            if !matches!(options.transport, TransportKind::Ros2Zenoh) {
                super::distro::select(options.ros_distro);
            }
            with_pointcloud2(session, topic)
        }
        None => Ok(session),
    }
}
