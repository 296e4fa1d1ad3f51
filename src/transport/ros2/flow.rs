//! Flow control of minflow's DDS writers: after each large message, wait (briefly) until
//! at most [`WINDOW_BYTES`] worth of messages are unacknowledged by the matched reliable
//! readers, the way a TCP window keeps a receiver's buffer from overflowing.
//!
//! Why: a default ROS 2 subscriber (rclpy or rclcpp on Fast DDS) reads UDP through the
//! kernel's default socket buffer, `net.core.rmem_default` (208 KiB on Linux), which holds
//! about four 42 KB frames. `replay` at `--rate 1` sends the six bundled scenes' frames of
//! one instant back to back (375 frames a second in bursts of six); without a window a
//! burst overflows that buffer, and a reliable keep-last-10 reader that has to wait for a
//! repair drops the frames it withheld meanwhile (docs/ros2.md has the numbers). Fast DDS
//! acknowledges within its 5 ms heartbeat response delay, so the window costs a few
//! milliseconds per burst. A reader that does not acknowledge within [`WAIT`] (stalled, or
//! gone without saying so) turns the window off for [`BACKOFF`]: it costs the publisher at
//! most one [`WAIT`] pause per [`BACKOFF`] until DDS discovery drops it.

use std::time::{Duration, Instant};

/// Unacknowledged bytes allowed in flight (below the 208 KiB default receive buffer once
/// the kernel's per-datagram overhead is counted).
pub(super) const WINDOW_BYTES: usize = 128 * 1024;
/// Longest wait for acknowledgements after one message.
pub(super) const WAIT: Duration = Duration::from_millis(250);
/// How long the window stays off after a wait ran out.
pub(super) const BACKOFF: Duration = Duration::from_secs(1);

/// The window state of one writer.
#[derive(Debug, Default)]
pub(super) struct AckWindow {
    off_until: Option<Instant>,
}

impl AckWindow {
    /// After publishing a message of about `bytes` on `publisher` (`topic` for the log):
    /// waits until at most `WINDOW_BYTES / bytes` messages (at least one) are unacknowledged.
    pub(super) fn after_publish<M: serde::Serialize>(
        &mut self,
        publisher: &ros2_client::dds::Publisher<M>,
        bytes: usize,
        topic: &str,
    ) {
        if let Some(until) = self.off_until {
            if Instant::now() < until {
                return;
            }
            self.off_until = None;
        }
        let unacked = (WINDOW_BYTES / bytes.max(1)).max(1);
        if !matches!(publisher.wait_for_acked_within(unacked, WAIT), Ok(true)) {
            tracing::debug!("{topic}: readers did not acknowledge within {WAIT:?}; window off");
            self.off_until = Some(Instant::now() + BACKOFF);
        }
    }
}

/// About the CDR size of a frame of `particles` particles (positions, velocities,
/// materials; strings and header ignored).
pub(super) fn frame_bytes(particles: usize) -> usize {
    particles * 17 + 64
}
