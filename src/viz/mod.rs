//! Live view and recorded view of frames in Foxglove: every `ParticleFrame` as a
//! `foxglove.PointCloud` (protobuf, the schema Foxglove publishes) on a topic named after
//! the frame topic (`/mpm/frames` -> `/mpm/frames/points`), coloured by material or, for
//! predictions, by their error against the ground truth.
//!
//! - [`cloud`]: frame -> point cloud, colours;
//! - [`live`]: the Foxglove WebSocket server (`--foxglove HOST:PORT` on `replay`, `node` and
//!   `simulate --publish`), the publisher wrapper and the node's prediction view.

pub mod cloud;
pub mod live;

pub use live::{points_topic, LiveView, PointsChannel, PredictionView, VizPublisher};

/// Where the live view listens: a host name or IP address and a TCP port (0: any free).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    /// Host name or IP address to bind, e.g. `127.0.0.1`, `0.0.0.0`, `localhost`.
    pub host: String,
    /// TCP port; 0 lets the system pick one.
    pub port: u16,
}

impl std::fmt::Display for Endpoint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.host.contains(':') {
            write!(f, "[{}]:{}", self.host, self.port)
        } else {
            write!(f, "{}:{}", self.host, self.port)
        }
    }
}

impl std::str::FromStr for Endpoint {
    type Err = String;

    /// `HOST:PORT`, IPv6 hosts in brackets (`[::1]:8765`).
    fn from_str(s: &str) -> Result<Self, String> {
        // A bare port binds to loopback only: other machines see the frames only when a
        // host is given (`0.0.0.0:8765`).
        if let Ok(port) = s.parse::<u16>() {
            return Ok(Endpoint {
                host: "127.0.0.1".to_owned(),
                port,
            });
        }
        let (host, port) = s
            .rsplit_once(':')
            .ok_or_else(|| format!("{s:?} is not HOST:PORT"))?;
        let host = host.trim_start_matches('[').trim_end_matches(']');
        if host.is_empty() {
            return Err(format!("{s:?} has no host (try 127.0.0.1:{port})"));
        }
        let port = port
            .parse::<u16>()
            .map_err(|e| format!("port {port:?} of {s:?}: {e}"))?;
        Ok(Endpoint {
            host: host.to_owned(),
            port,
        })
    }
}

/// Errors of the live view.
#[derive(Debug, thiserror::Error)]
pub enum VizError {
    /// The WebSocket server could not start (address in use, host not resolvable).
    #[error("cannot start the Foxglove server on {endpoint}: {source}")]
    Start {
        /// `HOST:PORT` asked for.
        endpoint: String,
        /// The SDK's reason.
        #[source]
        source: foxglove::FoxgloveError,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_parse() {
        let e: Endpoint = "127.0.0.1:8765".parse().unwrap();
        assert_eq!((e.host.as_str(), e.port), ("127.0.0.1", 8765));
        let e: Endpoint = "[::1]:0".parse().unwrap();
        assert_eq!(
            (e.host.as_str(), e.port, e.to_string()),
            ("::1", 0, "[::1]:0".into())
        );
        let e: Endpoint = "8765".parse().unwrap();
        assert_eq!((e.host.as_str(), e.port), ("127.0.0.1", 8765));
        for bad in ["70000", ":8765", "localhost:", "localhost:70000", "h:-1"] {
            assert!(bad.parse::<Endpoint>().is_err(), "{bad}");
        }
        assert_eq!(points_topic("/mpm/frames"), "/mpm/frames/points");
    }
}
