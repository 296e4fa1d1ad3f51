//! Which ROS 2 distribution minflow's ROS 2 nodes talk to (`--ros-distro`, else
//! `ROS_DISTRO`, else Kilted), and the REP-2016 type hashes its DDS endpoints announce.
//!
//! Jazzy and Kilted put the same bytes on the wire for everything minflow does (16-byte
//! GIDs, the type hash in each endpoint's USER_DATA as `typehash=RIHS01_<hex>;`), so the
//! choice only tells ros2-client what the program targets, which keeps it from warning that
//! `ROS_DISTRO` is not set (its check runs when the first node opens). A `ROS_DISTRO` naming
//! another distribution is left to ros2-client's own check, which says what differs.

use std::sync::atomic::{AtomicBool, Ordering};

use super::names::OpenError;
use crate::msgs::pointcloud2;
use crate::msgs::status::STATUS_TYPE_NAME;
use crate::msgs::type_hash::minflow_type_hash;
use crate::msgs::TYPE_NAME;

/// A ROS 2 distribution minflow is tested against (`--ros-distro`, `cli::transport`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RosDistro {
    /// ROS 2 Jazzy Jalisco (May 2024).
    Jazzy,
    /// ROS 2 Kilted Kaiju (May 2025); the default.
    Kilted,
}

impl RosDistro {
    /// Every distribution, oldest first.
    pub const ALL: [RosDistro; 2] = [RosDistro::Jazzy, RosDistro::Kilted];

    /// The distribution's name as `ROS_DISTRO` and `--ros-distro` write it.
    pub fn name(self) -> &'static str {
        match self {
            RosDistro::Jazzy => "jazzy",
            RosDistro::Kilted => "kilted",
        }
    }

    /// The distribution `ROS_DISTRO` names when it is `jazzy` or `kilted`.
    pub fn from_env_value(value: &str) -> Option<Self> {
        let value = value.trim();
        Self::ALL.into_iter().find(|d| d.name() == value)
    }

    fn to_client(self) -> ros2_client::RosDistro {
        match self {
            RosDistro::Jazzy => ros2_client::RosDistro::Jazzy,
            RosDistro::Kilted => ros2_client::RosDistro::Kilted,
        }
    }
}

/// Whether [`select`] ran in this process.
static SELECTED: AtomicBool = AtomicBool::new(false);

/// Tells ros2-client the distribution: `flag` when given, else `ROS_DISTRO` when it is
/// `jazzy` or `kilted`, else Kilted when `ROS_DISTRO` is unset; any other `ROS_DISTRO` is
/// left to ros2-client's check. Call before opening a node (`transport::open` does, with
/// `--ros-distro`; [`super::Ros2Transport::open`] selects from the environment otherwise).
pub fn select(flag: Option<RosDistro>) {
    SELECTED.store(true, Ordering::Relaxed);
    let env = crate::switches::ros_distro();
    let chosen = flag.or_else(|| match env.as_deref() {
        None | Some("") => Some(RosDistro::Kilted),
        Some(v) => RosDistro::from_env_value(v),
    });
    if let Some(distro) = chosen {
        ros2_client::select_ros_distro(distro.to_client());
    }
}

/// [`select`] from the environment, unless a selection was made already.
pub(super) fn select_if_unset() {
    if !SELECTED.load(Ordering::Relaxed) {
        select(None);
    }
}

/// (ROS 2 type, DDS type) of every message minflow publishes or subscribes on DDS.
fn announced_types() -> [(&'static str, &'static str); 3] {
    [
        (TYPE_NAME, crate::msgs::DDS_TYPE_NAME),
        (
            STATUS_TYPE_NAME,
            "minflow_msgs::msg::dds_::SurrogateStatus_",
        ),
        (
            pointcloud2::TYPE_NAME,
            "sensor_msgs::msg::dds_::PointCloud2_",
        ),
    ]
}

/// The USER_DATA rmw_fastrtps and rmw_cyclonedds give an endpoint of a type with hash
/// `rihs01` (rmw_dds_common's `encode_type_hash_for_user_data_qos`).
pub fn type_hash_user_data(rihs01: &str) -> String {
    format!("typehash={rihs01};")
}

/// Makes every DDS writer and reader of minflow's types announce its type hash in USER_DATA,
/// as ROS 2's DDS middlewares do (our vendored RustDDS's `set_endpoint_user_data`).
///
/// # Errors
/// [`OpenError::TypeHash`] if a hash cannot be computed from the `.msg` files.
pub(super) fn register_dds_type_hashes() -> Result<(), OpenError> {
    for (ros_type, dds_type) in announced_types() {
        let hash = if ros_type == pointcloud2::TYPE_NAME {
            pointcloud2::type_hash()
        } else {
            minflow_type_hash(ros_type)
        }
        .map_err(|e| OpenError::TypeHash {
            ros_type: ros_type.to_owned(),
            reason: e.to_string(),
        })?;
        ros2_client::dds::rustdds::discovery::set_endpoint_user_data(
            dds_type,
            type_hash_user_data(&hash).into_bytes(),
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn env_values() {
        assert_eq!(RosDistro::from_env_value("jazzy"), Some(RosDistro::Jazzy));
        assert_eq!(RosDistro::from_env_value("kilted"), Some(RosDistro::Kilted));
        assert_eq!(RosDistro::from_env_value("humble"), None);
    }

    #[test]
    fn dds_type_names_follow_the_mangling() {
        use ros2_client::MessageTypeName;
        for (ros, dds) in announced_types() {
            let parts: Vec<_> = ros.split('/').collect();
            assert_eq!(MessageTypeName::new(parts[0], parts[2]).dds_msg_type(), dds);
        }
        assert_eq!(
            type_hash_user_data("RIHS01_ab"),
            "typehash=RIHS01_ab;".to_owned()
        );
    }
}
