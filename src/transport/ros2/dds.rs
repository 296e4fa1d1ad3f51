//! Opening a ROS 2 node on DDS/RTPS (RustDDS through ros2-client), and the node shared by
//! the publishers and subscriptions of one [`Ros2Transport`](super::Ros2Transport) with the
//! thread running its spinner (discovery and graph bookkeeping).

use std::sync::Mutex;
use std::thread::JoinHandle;

use super::names::{node_name, node_options, OpenError};

/// The DDS node and the thread running its `Spinner` (graph/discovery bookkeeping).
pub(super) struct DdsNode {
    node: Mutex<Option<ros2_client::dds::Node>>,
    spinner: Option<JoinHandle<()>>,
    /// Keeps the DDS participant alive until the node's own writers (parameter events,
    /// rosout) are gone: ros2-client's `Node` drops its context before them, and a writer
    /// dropped after the participant logs "Cannot remove Writer ... Disconnected" as ERROR.
    _context: ros2_client::dds::Context,
}

impl DdsNode {
    pub(super) fn with<R>(&self, f: impl FnOnce(&mut ros2_client::dds::Node) -> R) -> R {
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

/// A DDS node in `domain_id` with its spinner thread started.
pub(super) fn open_dds(domain_id: u16) -> Result<DdsNode, OpenError> {
    use ros2_client::dds::{Context, ContextOptions};
    super::distro::register_dds_type_hashes()?;
    let context = Context::with_options(ContextOptions::new().domain_id(domain_id))
        .map_err(|e| OpenError::middleware(format!("DDS participant in domain {domain_id}"), e))?;
    let mut node = context
        .new_node(node_name(), node_options())
        .map_err(|e| OpenError::middleware("ROS 2 node", e))?;
    let spinner = node
        .spinner()
        .map_err(|e| OpenError::middleware("ROS 2 node spinner", e))?;
    let thread = std::thread::Builder::new()
        .name("ros2-spinner".into())
        .spawn(move || {
            if let Err(e) = futures::executor::block_on(spinner.spin()) {
                tracing::warn!("ROS 2 spinner stopped: {e}");
            }
        })
        .map_err(|e| OpenError::middleware("spinner thread", e))?;
    Ok(DdsNode {
        node: Mutex::new(Some(node)),
        spinner: Some(thread),
        _context: context,
    })
}
