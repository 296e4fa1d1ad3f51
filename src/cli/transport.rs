//! The transport flags of the node commands (`node`, `replay`, `record`, `simulate
//! --publish`; `bench` has its own repeatable `--transport`): the `--transport` group
//! ([`TransportArgs`], read into the library's [`TransportOptions`]), `--pointcloud2`
//! ([`PointCloud2Args`]) and the command-line values of the library's [`TransportKind`] and
//! [`RosDistro`] (their `clap::ValueEnum`, here so that `transport` stays free of clap).

use std::path::PathBuf;

use clap::builder::PossibleValue;

use crate::transport::ros2::{open_with_pointcloud2, RosDistro};
use crate::transport::{Transport, TransportError, TransportKind, TransportOptions};

/// Options shared by every node that opens a transport (the `--transport` flag group).
#[derive(Debug, Clone, clap::Args)]
pub struct TransportArgs {
    /// Middleware to use.
    #[arg(long, value_enum, default_value_t = TransportKind::Zenoh)]
    pub transport: TransportKind,
    /// A standard zenoh JSON5 config file (routers, endpoints, scouting, TLS, access
    /// control, shared memory); without it, an embedded peer session that needs no router.
    #[arg(long, value_name = "FILE")]
    pub zenoh_config: Option<PathBuf>,
    /// With --transport ros2 or ros2-zenoh: the ROS 2 distribution of the peers, jazzy or
    /// kilted (the same wire format; type hashes on DDS endpoints either way). Default:
    /// $ROS_DISTRO when it names one of them, else kilted.
    #[arg(long, value_enum, value_name = "DISTRO")]
    pub ros_distro: Option<RosDistro>,
}

impl TransportArgs {
    /// The flags as the library's options.
    pub fn options(&self) -> TransportOptions {
        TransportOptions {
            transport: self.transport,
            zenoh_config: self.zenoh_config.clone(),
            ros_distro: self.ros_distro,
        }
    }
}

/// The `--pointcloud2 TOPIC` flag of `replay`, `node` and `simulate --publish`.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct PointCloud2Args {
    /// Also publish every frame this process publishes as sensor_msgs/PointCloud2 on TOPIC
    /// (one point per particle: x, y, z = 0 and rgb by material, packed as PCL does), for
    /// RViz; over ROS 2 (DDS, or rmw_zenoh with --transport ros2-zenoh) whatever
    /// --transport carries the frames; default ROS 2 QoS.
    #[arg(long, value_name = "TOPIC")]
    pub pointcloud2: Option<String>,
}

impl PointCloud2Args {
    /// Opens the transport `transport` names, with PointCloud2 beside the frames when the
    /// flag is given ([`open_with_pointcloud2`]).
    ///
    /// # Errors
    /// As [`open_with_pointcloud2`].
    pub fn open(&self, transport: &TransportArgs) -> Result<Box<dyn Transport>, TransportError> {
        open_with_pointcloud2(&transport.options(), self.pointcloud2.as_deref())
    }
}

/// `--transport`'s values: [`TransportKind::name`], each with its help line.
impl clap::ValueEnum for TransportKind {
    fn value_variants<'a>() -> &'a [Self] {
        &TransportKind::ALL
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        let help = match self {
            TransportKind::Zenoh => {
                "zenoh 1.x: key = topic without the leading '/', payload = CDR bytes"
            }
            TransportKind::Iceoryx2 => "iceoryx2 zero-copy shared memory (same host only)",
            TransportKind::Ros2 => "ROS 2 over DDS (RTPS) with ros2-client; honours ROS_DOMAIN_ID",
            TransportKind::Ros2Zenoh => {
                "ROS 2 over rmw_zenoh's wire protocol (ros2-client's zenoh backend)"
            }
        };
        Some(PossibleValue::new(self.name()).help(help))
    }
}

/// `--ros-distro`'s values: [`RosDistro::name`], each with its help line.
impl clap::ValueEnum for RosDistro {
    fn value_variants<'a>() -> &'a [Self] {
        &RosDistro::ALL
    }

    fn to_possible_value(&self) -> Option<PossibleValue> {
        let help = match self {
            RosDistro::Jazzy => "ROS 2 Jazzy Jalisco (May 2024)",
            RosDistro::Kilted => "ROS 2 Kilted Kaiju (May 2025); the default",
        };
        Some(PossibleValue::new(self.name()).help(help))
    }
}
