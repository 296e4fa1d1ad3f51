//! Opening a ROS 2 node on the `rmw_zenoh` wire protocol (ros2-client's zenoh backend),
//! with a session configured like `rmw_zenoh`'s default or from `ZENOH_SESSION_CONFIG_URI`,
//! amended by `ZENOH_CONFIG_OVERRIDE`, after registering the REP-2016 type hashes of
//! minflow's messages with ros2-client (the key `<domain>/<topic>/<dds type>/<RIHS01 hash>`
//! and the liveliness tokens of our publishers and subscriptions carry them, so C++
//! `rmw_zenoh` peers match).

use super::names::{node_name, node_options, status_type_name, type_name, OpenError};
use crate::msgs::status::STATUS_TYPE_NAME;
use crate::msgs::type_hash::minflow_type_hash;
use crate::msgs::TYPE_NAME;

/// The zenoh-backend node (no spinner needed: its graph cache is fed by zenoh callbacks).
pub(super) struct ZenohNode {
    pub(super) node: ros2_client::zenoh::Node,
}

/// `rmw_zenoh`'s default session config (`DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5`, Jazzy):
/// a peer that connects to the router on `tcp/localhost:7447` and learns about other peers by
/// gossip; multicast scouting off. Listening on loopback with an OS-chosen port.
fn rmw_zenoh_default_config() -> Result<zenoh::Config, OpenError> {
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
            .map_err(|e| OpenError::ZenohConfig {
                key: key.to_owned(),
                reason: e.to_string(),
            })?;
    }
    if let Some(overrides) = crate::switches::zenoh_config_override() {
        for entry in overrides
            .split(';')
            .map(str::trim)
            .filter(|s| !s.is_empty())
        {
            let (key, value) = entry.split_once('=').ok_or_else(|| OpenError::Override {
                entry: entry.to_owned(),
            })?;
            config
                .insert_json5(key.trim(), value.trim())
                .map_err(|e| OpenError::ZenohConfig {
                    key: format!("ZENOH_CONFIG_OVERRIDE {}", key.trim()),
                    reason: e.to_string(),
                })?;
        }
    }
    Ok(config)
}

/// Registers the RIHS01 hashes of `ParticleFrame` and `SurrogateStatus`, computed from
/// `msgs/*.msg` ([`crate::msgs::type_hash`]), with ros2-client (the one hook our vendored copy
/// adds, `vendor/README.md`): without them it sends an all-zero placeholder hash.
fn register_type_hashes() -> Result<(), OpenError> {
    for (ros_type, dds_type) in [
        (TYPE_NAME, type_name()),
        (STATUS_TYPE_NAME, status_type_name()),
    ] {
        let err = |reason: String| OpenError::TypeHash {
            ros_type: ros_type.to_owned(),
            reason,
        };
        let hash = minflow_type_hash(ros_type).map_err(|e| err(e.to_string()))?;
        ros2_client::zenoh::register_type_hash(&dds_type.dds_msg_type(), &hash).map_err(err)?;
    }
    // `--pointcloud2`'s sensor_msgs/msg/PointCloud2.
    let cloud = crate::msgs::pointcloud2::type_hash().map_err(|e| OpenError::TypeHash {
        ros_type: crate::msgs::pointcloud2::TYPE_NAME.to_owned(),
        reason: e.to_string(),
    })?;
    ros2_client::zenoh::register_type_hash("sensor_msgs::msg::dds_::PointCloud2_", &cloud)
        .map_err(|reason| OpenError::TypeHash {
            ros_type: crate::msgs::pointcloud2::TYPE_NAME.to_owned(),
            reason,
        })?;
    Ok(())
}

/// A zenoh-backend node in `domain_id`.
pub(super) fn open_zenoh(domain_id: u16) -> Result<ZenohNode, OpenError> {
    use ros2_client::zenoh::{Context, ContextOptions};
    register_type_hashes()?;
    let mut options = ContextOptions::new().domain_id(domain_id);
    // With ZENOH_SESSION_CONFIG_URI set, ros2-client loads that file (and the override).
    let from_file =
        crate::switches::zenoh_session_config_uri().is_some_and(|v| !v.trim().is_empty());
    if !from_file {
        options = options.zenoh_config(rmw_zenoh_default_config()?);
    }
    let context =
        Context::with_options(options).map_err(|e| OpenError::middleware("zenoh session", e))?;
    let node = context
        .new_node(node_name(), node_options())
        .map_err(|e| OpenError::middleware("ROS 2 node", e))?;
    Ok(ZenohNode { node })
}
