//! How frames enter the surrogate node. A decoder thread ([`spawn_decoder`]) takes the
//! transport's samples in arrival order, decodes each and applies [`check_frame`], off the
//! loop's thread (at 16,000 frames/s of 2,500 particles this was 37-46 % of the loop's
//! wall time on an H100 machine, `docs/scale.md`); [`NodeLoop::gather`] takes what it has
//! decoded (blocking only until the next thing is due: a batch, a rollout frame, the
//! status), and [`NodeLoop::accept`] counts bad input, passes over the scenes another
//! shard member owns, notes the scene's activity and queues the frame (the scene's oldest
//! pending frame dropped past `queue_depth`; [`super::schedule`]). A sharded node's decoder
//! reads only the scene of a frame another member owns (`cdr::scene_of`): N nodes sharing
//! the streams each decode their own share, not every frame. Used by `run.rs`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{channel, Receiver, RecvTimeoutError};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::msgs::{cdr, state_rows, ParticleFrame};
use crate::ops::NetOps;
use crate::transport::{Payload, Sample};

use super::admission::{check_frame, Rejection};
use super::frames::payload_bytes;
use super::node_loop::NodeLoop;
use super::schedule::{Due, Pending};
use super::shard::Owners;

/// The longest the loop blocks on the transport with nothing due.
const MAX_WAIT: Duration = Duration::from_millis(100);

/// The longest the loop blocks on the transport while pipelined calls are landing
/// (`super::lander`): how late their frames may be published.
const LANDING_POLL: Duration = Duration::from_millis(1);

/// One sample as the decoder thread hands it to the loop.
pub(super) struct Arrival {
    /// When the transport received it.
    received: Instant,
    decoded: Decoded,
}

/// What the decoder made of a sample.
enum Decoded {
    /// Larger than `--max-frame-bytes`: the reason.
    Oversize(String),
    /// Not a frame: the reason.
    Malformed(String),
    /// A frame, its `[N, 4]` rows, and whether [`check_frame`] lets it be predicted on
    /// (rows only then; the frame's own arrays emptied unless the loop keeps them).
    Frame(ParticleFrame, Vec<f32>, Result<(), Rejection>),
    /// A frame of a scene another shard member owns (only its scene was read).
    Others,
}

/// Starts the decoder thread: every sample of `samples`, in order, decoded and checked
/// (`max_frame_bytes`, the model's fixed particle count `model_n`) and laid out as the
/// model's rows onto the returned channel, or, with `owners` (sharded), passed over when
/// another member owns its scene; its busy time is added to `busy_ns`. A frame keeps its
/// position and velocity arrays only with `keep_arrays` (a live view draws them). The
/// thread ends when `samples` closes (the subscription is dropped) or the returned
/// channel's receiver is dropped; the returned channel closes when it ends (or panics:
/// join the handle to tell).
///
/// # Panics
/// When the thread cannot be spawned (as `std::thread::spawn`).
pub(super) fn spawn_decoder(
    samples: Receiver<Sample>,
    (max_frame_bytes, model_n, keep_arrays): (usize, Option<usize>, bool),
    owners: Option<Owners>,
    busy_ns: Arc<AtomicU64>,
) -> (Receiver<Arrival>, JoinHandle<()>) {
    let (tx, rx) = channel();
    let decode = move || {
        for sample in samples {
            let start = Instant::now();
            let others = owners.as_ref().is_some_and(|o| others_own(o, &sample));
            let arrival = Arrival {
                received: sample.received,
                decoded: match others {
                    true => Decoded::Others,
                    false => decode(&sample, max_frame_bytes, model_n, keep_arrays),
                },
            };
            busy_ns.fetch_add(start.elapsed().as_nanos() as u64, Ordering::Relaxed);
            if tx.send(arrival).is_err() {
                return;
            }
        }
    };
    let handle = std::thread::Builder::new()
        .name("minflow-decode".into())
        .spawn(decode)
        .expect("spawning the node's decoder thread");
    (rx, handle)
}

/// Whether another shard member owns the scene of `sample`, read without decoding the rest
/// of a CDR payload; a payload whose scene does not read is not passed over (its full decode
/// reports why).
fn others_own(owners: &Owners, sample: &Sample) -> bool {
    match &sample.payload {
        Payload::Cdr(bytes) => cdr::scene_of(bytes).is_ok_and(|s| !owners.mine(s)),
        Payload::Frame(frame) => !owners.mine(&frame.scene),
        Payload::Malformed(_) => false,
    }
}

/// The decoder's work on one sample: size limit, CDR decode, [`check_frame`], the rows
/// (off the loop's thread: 256 of them a call), the arrays dropped unless `keep_arrays`.
fn decode(
    sample: &Sample,
    max_frame_bytes: usize,
    model_n: Option<usize>,
    keep_arrays: bool,
) -> Decoded {
    let bytes = payload_bytes(&sample.payload);
    if bytes > max_frame_bytes {
        return Decoded::Oversize(format!(
            "payload of {bytes} bytes over --max-frame-bytes {max_frame_bytes}"
        ));
    }
    match sample.decode() {
        Ok(mut frame) => {
            let checked = check_frame(&frame, model_n);
            let rows = match checked {
                Ok(()) => state_rows(&frame),
                Err(_) => Vec::new(),
            };
            if !keep_arrays {
                (frame.position, frame.velocity) = (Vec::new(), Vec::new());
            }
            Decoded::Frame(frame, rows, checked)
        }
        Err(reason) => Decoded::Malformed(format!("malformed payload: {reason}")),
    }
}

impl<B: NetOps> NodeLoop<'_, B> {
    /// Takes every decoded sample waiting in `rx` into the per-scene queues; blocks until
    /// the next batch, rollout frame or status is due (at most 100 ms) for the first one.
    /// False when the decoder thread has ended (the transport is gone, or it panicked).
    pub(super) fn gather(&mut self, rx: &Receiver<Arrival>) -> bool {
        let now = Instant::now();
        let mut wait = match self.batch_due(now) {
            Due::Now => Duration::ZERO,
            Due::At(t) => t.saturating_duration_since(now),
            Due::Nothing => MAX_WAIT,
        };
        wait = wait.min(self.next_status.saturating_duration_since(now));
        if let Some(t) = self.schedule.rollouts.next_due() {
            wait = wait.min(t.saturating_duration_since(now));
        }
        if self.lander.as_ref().is_some_and(|l| l.landing > 0) {
            // Calls are landing: their frames are published within LANDING_POLL.
            wait = wait.min(LANDING_POLL);
        }
        let blocked = Instant::now();
        let first = if wait.is_zero() {
            None
        } else {
            match rx.recv_timeout(wait.min(MAX_WAIT)) {
                Ok(s) => Some(s),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => return false,
            }
        };
        let taking = Instant::now();
        self.times.wait += taking - blocked;
        for arrival in first.into_iter().chain(rx.try_iter()) {
            self.accept(arrival);
        }
        self.times.intake += taking.elapsed();
        true
    }

    /// Counts bad input and the frames of scenes another shard member owns (the decoder
    /// passed them over) and queues the rest (dropping the scene's oldest pending frame past
    /// `queue_depth`).
    fn accept(&mut self, arrival: Arrival) {
        let (frame, rows, checked) = match arrival.decoded {
            Decoded::Frame(frame, rows, checked) => (frame, rows, checked),
            Decoded::Oversize(reason) => {
                self.tally.report.received += 1;
                self.tally.report.rejected += 1;
                self.tally.note("?", reason);
                return;
            }
            Decoded::Malformed(reason) => {
                self.tally.report.received += 1;
                self.tally.report.malformed += 1;
                self.tally.note("?", reason);
                return;
            }
            Decoded::Others => {
                self.others += 1;
                return;
            }
        };
        self.tally.report.received += 1;
        if let Err(reason) = checked {
            self.tally.report.rejected += 1;
            self.tally.note(&frame.scene.clone(), reason.to_string());
            return;
        }
        if let Some(view) = self.view.as_mut() {
            view.truth(&frame);
        }
        // Closed loop: a scene already rolled out waits for its next start (frame 0).
        if self.options.rollout.is_some()
            && frame.frame_index != 0
            && self.scenes.rolled_out(&frame.scene)
        {
            return;
        }
        let idle = self.scenes.touch(&frame.scene, self.options.idle_timeout);
        self.note_idle(u64::from(idle));
        self.note_takeover(&frame.scene, frame.frame_index);
        let pending = Pending {
            frame,
            rows,
            arrived: arrival.received,
        };
        if self.schedule.queue(pending, self.options.queue_depth) {
            self.tally.report.dropped += 1;
        }
    }

    /// Sharded: counts and logs a scene this node meets mid-stream (it owns it now: a
    /// member left, or this node joined), whose state starts again from this frame.
    fn note_takeover(&mut self, scene: &str, index: u32) {
        let fresh = index != 0 && !self.scenes.contains(scene) && !self.schedule.has_pending(scene);
        if self.shard.is_none() || !fresh {
            return;
        }
        self.adopted += 1;
        // The first ten, then every 100th: a node joining many streams must not flood the log.
        if self.adopted <= 10 || self.adopted % 100 == 0 {
            tracing::info!(
                "{}: took scene {scene:?} over at frame {index}; its state starts again here \
                 ({} so far)",
                self.options.name,
                self.adopted
            );
        }
    }
}
