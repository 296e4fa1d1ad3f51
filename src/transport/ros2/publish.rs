//! The publisher side of the ROS 2 transport: declaring frame publishers
//! (`minflow_msgs/msg/ParticleFrame`) and status publishers
//! (`minflow_msgs/msg/SurrogateStatus`) on either backend, and the [`FramePublisher`] /
//! [`StatusPublisher`] impls that send them.

use std::sync::Arc;
use std::time::Duration;

use super::dds::DdsNode;
use super::flow::{frame_bytes, AckWindow};
use super::names::{ros_name, status_type_name, type_name, QOS};
use super::rmw_zenoh::ZenohNode;
use super::wire::WireFrame;
use super::{NodeRef, Ros2Transport};
use crate::msgs::status::SurrogateStatus;
use crate::msgs::ParticleFrame;
use crate::transport::{FramePublisher, StatusPublisher, TransportError, TransportKind};

impl Ros2Transport {
    /// Declares a frame publisher on `topic` ([`Transport::publisher`](super::Transport::publisher)).
    pub(super) fn frame_publisher(
        &self,
        topic: &str,
    ) -> Result<Box<dyn FramePublisher>, TransportError> {
        let name = ros_name(topic)?;
        let declare_err = |reason: String| {
            TransportError::declare(self.backend.kind(), "publisher", topic.to_owned(), reason)
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
                    window: AckWindow::default(),
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
    pub(super) fn surrogate_status_publisher(
        &self,
        topic: &str,
    ) -> Result<Box<dyn StatusPublisher>, TransportError> {
        let name = ros_name(topic)?;
        let kind = self.backend.kind();
        let declare_err = |reason: String| {
            TransportError::declare(kind, "status publisher", topic.to_owned(), reason)
        };
        let type_name = status_type_name();
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
}

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
    window: AckWindow,
}

impl FramePublisher for DdsPublisher {
    /// Publishes, then waits (briefly) for the readers' acknowledgements to keep at most
    /// 128 KiB unacknowledged (`flow.rs`).
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.publisher
            .publish(WireFrame::from(frame.clone()))
            .map_err(|e| TransportError::Publish {
                transport: TransportKind::Ros2,
                topic: self.topic.clone(),
                reason: e.to_string(),
            })?;
        let bytes = frame_bytes(frame.material.len());
        self.window
            .after_publish(&self.publisher, bytes, &self.topic);
        Ok(())
    }

    /// Reliable DDS retransmits what readers missed after the write returns: wait until
    /// every matched reader acknowledged everything (rclcpp's `wait_for_all_acked`), at most
    /// `timeout`; a reader that did not in time is logged.
    fn flush(&mut self, timeout: Duration) {
        wait_for_all_acked(&self.publisher, &self.topic, timeout);
    }

    /// Matched DDS subscriptions (readers matched through SEDP with compatible QoS), as
    /// tracked by the node's spinner (`Publisher::get_subscription_count`).
    fn subscriber_count(&self) -> usize {
        use futures::FutureExt;
        self.node.with(|node| {
            // ros2-client logs an ERROR when asked to count for a writer its spinner has not
            // yet matched to any reader, and the spinner learns of a match after discovery
            // does, so a reader discovered on the topic is not enough. Its "wait for a
            // subscription" future is ready exactly when the spinner has matched one.
            match self.publisher.wait_for_subscription(node).now_or_never() {
                Some(()) => self.publisher.get_subscription_count(node),
                None => 0,
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

/// Waits until every matched reliable reader of `publisher` acknowledged all it published, at
/// most `timeout`; warns when they did not.
pub(super) fn wait_for_all_acked<M: serde::Serialize>(
    publisher: &ros2_client::dds::Publisher<M>,
    topic: &str,
    timeout: Duration,
) {
    match publisher.wait_for_all_acked(timeout) {
        Ok(true) => {}
        Ok(false) => tracing::warn!("{topic}: not every reader acknowledged within {timeout:?}"),
        Err(e) => tracing::warn!("{topic}: waiting for acknowledgements: {e}"),
    }
}
