//! The live view: a Foxglove WebSocket server (the Foxglove SDK's, subprotocol
//! `foxglove.sdk.v1`, the protocol once named `foxglove.websocket.v1`) with one
//! `foxglove.PointCloud` channel per frame topic, named `<topic>/points` ([`points_topic`]).
//! `replay` and `simulate --publish` wrap their frame publisher in a [`VizPublisher`]; `node`
//! shows its input and, through [`PredictionView`], its predictions coloured by their error
//! once the ground truth of the same frame arrives.
//!
//! A cloud is built only while a client subscribes to its channel ([`PointsChannel::watched`]):
//! with nothing connected a frame costs one lock-free check.

use std::collections::{BTreeMap, HashMap};
use std::sync::Arc;
use std::time::Duration;

use foxglove::messages::PointCloud;
use foxglove::{Channel, Context, WebSocketServer, WebSocketServerHandle};

use super::{cloud, Endpoint, VizError};
use crate::msgs::ParticleFrame;
use crate::transport::{FramePublisher, TransportError};

/// The Foxglove channel of a frame topic: `/mpm/frames` -> `/mpm/frames/points`.
pub fn points_topic(frame_topic: &str) -> String {
    format!("{}/points", frame_topic.trim_end_matches('/'))
}

/// A running Foxglove WebSocket server with its own channel context (cheap to clone; the
/// server stops when the last clone is dropped).
#[derive(Clone)]
pub struct LiveView {
    inner: Arc<Served>,
}

struct Served {
    context: Arc<Context>,
    handle: WebSocketServerHandle,
    host: String,
}

impl std::fmt::Debug for LiveView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "LiveView({})", self.url())
    }
}

impl LiveView {
    /// Starts the server on `endpoint` (port 0: any free port, see [`LiveView::port`]) on the
    /// SDK's own tokio runtime. Call from a thread that is not inside an async runtime.
    ///
    /// # Errors
    /// [`VizError::Start`]: the address cannot be bound.
    pub fn start(endpoint: &Endpoint, name: &str) -> Result<Self, VizError> {
        let context = Context::new();
        let handle = WebSocketServer::new()
            .name(name)
            .bind(endpoint.host.clone(), endpoint.port)
            .context(&context)
            .start_blocking()
            .map_err(|source| VizError::Start {
                endpoint: endpoint.to_string(),
                source,
            })?;
        Ok(LiveView {
            inner: Arc::new(Served {
                context,
                handle,
                host: endpoint.host.clone(),
            }),
        })
    }

    /// The port the server listens on.
    pub fn port(&self) -> u16 {
        self.inner.handle.port()
    }

    /// `ws://HOST:PORT`, what Foxglove's "Open connection" asks for.
    pub fn url(&self) -> String {
        format!("ws://{}:{}", self.inner.host, self.port())
    }

    /// Connected clients.
    pub fn clients(&self) -> usize {
        self.inner.handle.client_count()
    }

    /// The point-cloud channel of `frame_topic` ([`points_topic`]).
    pub fn points(&self, frame_topic: &str) -> PointsChannel {
        let channel = self
            .inner
            .context
            .channel_builder(points_topic(frame_topic))
            .build::<PointCloud>();
        PointsChannel {
            channel,
            _view: self.clone(),
        }
    }
}

/// One `foxglove.PointCloud` channel (keeps its server alive).
pub struct PointsChannel {
    channel: Channel<PointCloud>,
    _view: LiveView,
}

impl PointsChannel {
    /// Whether a client subscribes to this channel now.
    pub fn watched(&self) -> bool {
        self.channel.has_sinks()
    }

    /// Sends `frame` coloured by material, if watched.
    pub fn show(&self, frame: &ParticleFrame) {
        if self.watched() {
            self.channel.log(&cloud::by_material(frame));
        }
    }

    /// Sends `predicted` coloured by its error against `truth`, if watched.
    pub fn show_error(&self, predicted: &ParticleFrame, truth: &ParticleFrame) {
        if self.watched() {
            self.channel.log(&cloud::by_error(predicted, truth));
        }
    }
}

/// A frame publisher that also shows every frame it publishes on a points channel. Its
/// subscriber count adds one while a Foxglove client watches, so `--wait-for-subscribers`
/// is met by Foxglove alone.
pub struct VizPublisher {
    inner: Box<dyn FramePublisher>,
    points: PointsChannel,
}

impl VizPublisher {
    /// Wraps `inner`; frames go to `points` after `inner` took them.
    pub fn new(inner: Box<dyn FramePublisher>, points: PointsChannel) -> Self {
        VizPublisher { inner, points }
    }
}

impl FramePublisher for VizPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.inner.publish(frame)?;
        self.points.show(frame);
        Ok(())
    }

    fn publish_cdr(&mut self, bytes: &[u8], frame: &ParticleFrame) -> Result<(), TransportError> {
        self.inner.publish_cdr(bytes, frame)?;
        self.points.show(frame);
        Ok(())
    }

    fn flush(&mut self, timeout: Duration) {
        self.inner.flush(timeout);
    }

    fn subscriber_count(&self) -> usize {
        self.inner.subscriber_count() + usize::from(self.points.watched())
    }
}

/// Most predictions held per scene waiting for their ground truth; past it the oldest is
/// shown by material.
const HELD_PER_SCENE: usize = 64;

/// The surrogate node's view: its input on `<input>/points`, and each prediction on
/// `<output>/points`, coloured by its error when the ground truth of the same scene and
/// frame index arrives, by material when that frame is skipped or never comes.
pub struct PredictionView {
    truth: PointsChannel,
    predicted: PointsChannel,
    held: HashMap<String, BTreeMap<u32, ParticleFrame>>,
    /// The ground-truth frames per scene that no prediction has passed yet (at most
    /// [`HELD_PER_SCENE`]), kept while predictions are watched: a prediction made after its
    /// truth arrived (the node accepts frames before it predicts on them, and lags behind
    /// under load) is shown by error at once.
    truths: HashMap<String, BTreeMap<u32, ParticleFrame>>,
}

impl PredictionView {
    /// Channels for the node's `input` and `output` topics on `view`.
    pub fn new(view: &LiveView, input: &str, output: &str) -> Self {
        PredictionView {
            truth: view.points(input),
            predicted: view.points(output),
            held: HashMap::new(),
            truths: HashMap::new(),
        }
    }

    /// A ground-truth frame arrived: show it, and the predictions of its scene up to its
    /// index (the one of the same index by error, older ones by material).
    pub fn truth(&mut self, frame: &ParticleFrame) {
        self.truth.show(frame);
        if !self.predicted.watched() {
            self.truths.clear();
            self.held.clear();
            return;
        }
        let truths = self.truths.entry(frame.scene.clone()).or_default();
        truths.insert(frame.frame_index, frame.clone());
        if truths.len() > HELD_PER_SCENE {
            truths.pop_first();
        }
        let Some(held) = self.held.get_mut(&frame.scene) else {
            return;
        };
        while let Some(entry) = held.first_entry() {
            if *entry.key() > frame.frame_index {
                break;
            }
            let predicted = entry.remove();
            if predicted.frame_index == frame.frame_index {
                self.predicted.show_error(&predicted, frame);
            } else {
                self.predicted.show(&predicted);
            }
        }
    }

    /// A prediction was published: shown by error if its ground truth is already here,
    /// else held for it (nothing when unwatched).
    pub fn prediction(&mut self, frame: &ParticleFrame) {
        if !self.predicted.watched() {
            return;
        }
        if let Some(truths) = self.truths.get_mut(&frame.scene) {
            // Truths up to this index are passed: predictions come in index order.
            let later = truths.split_off(&frame.frame_index.saturating_add(1));
            let passed = std::mem::replace(truths, later);
            if let Some(truth) = passed.get(&frame.frame_index) {
                self.predicted.show_error(frame, truth);
                return;
            }
        }
        let held = self.held.entry(frame.scene.clone()).or_default();
        held.insert(frame.frame_index, frame.clone());
        if held.len() > HELD_PER_SCENE {
            if let Some((_, oldest)) = held.pop_first() {
                self.predicted.show(&oldest);
            }
        }
    }

    /// Shows every held prediction by material (the node is stopping).
    pub fn finish(&mut self) {
        for (_, held) in self.held.drain() {
            for frame in held.into_values() {
                self.predicted.show(&frame);
            }
        }
    }
}
