//! `--foxglove HOST:PORT`, flattened into `replay`, `node` and `simulate`: starts the live
//! view ([`crate::viz::LiveView`]) before any frame moves and says where to connect.

use anyhow::Context;
use clap::Args;

use crate::viz::{Endpoint, LiveView};

/// The live-view flag.
#[derive(Debug, Clone, Args)]
pub struct FoxgloveArgs {
    /// Serve every frame live to Foxglove as a foxglove.PointCloud on `<topic>/points`, from a
    /// WebSocket server on HOST:PORT (port 0: any free port; Foxglove: "Open connection",
    /// ws://HOST:PORT, then a 3D panel). A bare PORT binds to loopback (127.0.0.1) only; the
    /// server has no TLS and no authentication, so give a public HOST only on a trusted
    /// network. Off by default.
    #[arg(long, value_name = "[HOST:]PORT")]
    pub foxglove: Option<Endpoint>,
}

impl FoxgloveArgs {
    /// Starts the server when `--foxglove` was given; logs `foxglove: serving on ws://...` on
    /// stderr (with the real port when 0 was asked for).
    pub fn start(&self, name: &str) -> anyhow::Result<Option<LiveView>> {
        let Some(endpoint) = &self.foxglove else {
            return Ok(None);
        };
        let view =
            LiveView::start(endpoint, name).with_context(|| format!("--foxglove {endpoint}"))?;
        eprintln!("foxglove: serving on {}", view.url());
        Ok(Some(view))
    }
}
