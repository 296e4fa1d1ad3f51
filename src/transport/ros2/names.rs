//! ROS 2 names and settings of minflow's node: the message type name
//! (`minflow_msgs/msg/ParticleFrame`), topic names (`/mpm/frames` -> DDS `rt/mpm/frames`),
//! the node name, the default QoS profile and the domain id from `ROS_DOMAIN_ID`.

use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;

use ros2_client::qos::{History, QosProfile, Reliability, WhenFull};
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions};

use crate::transport::{topic_key, TransportError};

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

/// Why a ROS 2 node could not be opened (becomes [`TransportError::Open`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum OpenError {
    /// `ROS_DOMAIN_ID` is not an integer in `0..=232`.
    #[error("ROS_DOMAIN_ID={value:?} is not a domain id (an integer 0..={MAX_DOMAIN_ID})")]
    DomainId {
        /// The variable's value as set.
        value: String,
    },
    /// A zenoh session setting (rmw_zenoh's defaults or `ZENOH_CONFIG_OVERRIDE`) was refused.
    #[error("zenoh config {key}: {reason}")]
    ZenohConfig { key: String, reason: String },
    /// A `ZENOH_CONFIG_OVERRIDE` entry without `=`.
    #[error("ZENOH_CONFIG_OVERRIDE entry {entry:?} is not key=value")]
    Override { entry: String },
    /// A message's REP-2016 type hash could not be computed or registered.
    #[error("type hash of {ros_type}: {reason}")]
    TypeHash { ros_type: String, reason: String },
    /// The middleware failed to make one of the node's parts (`what`).
    #[error("{what}: {reason}")]
    Middleware { what: String, reason: String },
}

impl OpenError {
    /// [`OpenError::Middleware`] for `what`, with `error`'s message.
    pub(super) fn middleware(what: impl Into<String>, error: impl std::fmt::Display) -> Self {
        Self::Middleware {
            what: what.into(),
            reason: error.to_string(),
        }
    }
}

/// `ROS_DOMAIN_ID` as ROS 2 reads it: unset or empty means 0, otherwise a decimal integer in
/// `0..=232`.
///
/// # Errors
/// [`OpenError::DomainId`] naming the bad value (not a number, or above [`MAX_DOMAIN_ID`]).
pub fn domain_id_from_env() -> Result<u16, OpenError> {
    match crate::switches::ros_domain_id() {
        Err(std::env::VarError::NotPresent) => Ok(0),
        Err(std::env::VarError::NotUnicode(v)) => Err(OpenError::DomainId {
            value: v.to_string_lossy().into_owned(),
        }),
        Ok(v) => parse_domain_id(&v),
    }
}

fn parse_domain_id(v: &str) -> Result<u16, OpenError> {
    if v.trim().is_empty() {
        return Ok(0);
    }
    match v.trim().parse::<u16>() {
        Ok(id) if id <= MAX_DOMAIN_ID => Ok(id),
        _ => Err(OpenError::DomainId {
            value: v.to_owned(),
        }),
    }
}

/// The ROS 2 [`Name`] of an absolute topic such as `/mpm/frames`.
pub(super) fn ros_name(topic: &str) -> Result<Name, TransportError> {
    topic_key(topic)?;
    Name::parse(topic).map_err(|_| TransportError::Topic(topic.to_owned()))
}

pub(super) fn type_name() -> MessageTypeName {
    MessageTypeName::new(PACKAGE, MESSAGE)
}

/// `minflow_msgs/msg/SurrogateStatus` (DDS type `minflow_msgs::msg::dds_::SurrogateStatus_`).
pub(super) fn status_type_name() -> MessageTypeName {
    MessageTypeName::new(PACKAGE, "SurrogateStatus")
}

/// A fresh node name per transport: `minflow_<pid>_<n>` in the root namespace.
pub(super) fn node_name() -> NodeName {
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    NodeName::new("/", &format!("minflow_{}_{n}", std::process::id())).expect("valid node name")
}

pub(super) fn node_options() -> NodeOptions {
    // No /rosout writer and no parameter services: fewer DDS endpoints to discover, so peers
    // match our publishers sooner. The node is still announced on ros_discovery_info.
    NodeOptions::new()
        .enable_rosout(false)
        .start_parameter_services(false)
}

#[cfg(test)]
mod tests {
    use super::*;

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
