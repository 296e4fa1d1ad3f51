//! Nodes: long-running processes around a transport. [`surrogate`] is the surrogate node
//! (`minflow node`): one hidden state per scene, the next frame predicted for every frame
//! that arrives, closed-loop rollouts, dynamic batching of many scenes into one network call
//! and sharding of the scenes over a group of nodes. [`replay`] plays the ground truth from
//! bags (like `ros2 bag play`), [`record`] writes what arrives on topics into bags (like
//! `ros2 bag record`). All three count what they handle ([`crate::transport::Counters`] for
//! replay and record, the surrogate's status message and counters) and stop cleanly on
//! SIGINT/SIGTERM ([`shutdown_flag`]).

pub mod record;
pub mod replay;
pub mod surrogate;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, OnceLock};

static SHUTDOWN: OnceLock<Arc<AtomicBool>> = OnceLock::new();

/// A flag that turns true on SIGINT, SIGTERM or SIGHUP (the handler is installed on first
/// call; later calls return the same flag). A second signal exits at once with code 130.
pub fn shutdown_flag() -> Arc<AtomicBool> {
    SHUTDOWN
        .get_or_init(|| {
            let flag = Arc::new(AtomicBool::new(false));
            let seen = Arc::clone(&flag);
            let installed = ctrlc::set_handler(move || {
                if seen.swap(true, Ordering::SeqCst) {
                    std::process::exit(130);
                }
                tracing::info!("signal received: finishing");
            });
            if let Err(e) = installed {
                tracing::warn!("cannot install the SIGINT/SIGTERM handler: {e}");
            }
            flag
        })
        .clone()
}
