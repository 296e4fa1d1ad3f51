//! zenoh transport: key = ROS 2 topic without the leading slash, payload = the frame's CDR
//! bytes (the zenoh-bridge-ros2dds mapping, docs/design.md "Topics and transports"), so the
//! bridge, rmw_zenoh tools and any zenoh client in any language can read and write frames.
//!
//! The default session is an embedded peer (multicast scouting, no router needed); a
//! standard zenoh JSON5 config file can replace it (`--zenoh-config`). zenoh runs its own
//! multi-threaded tokio runtime inside; this module uses its synchronous `Wait` API, so no
//! caller needs a runtime. Publishers are reliable, `Block` congestion control (nothing is
//! dropped at the sender) and `express` (no batching: lowest latency).
//!
//! Counting subscribers: zenoh itself only says whether *any* subscriber matches a
//! publisher. Every minflow subscription also declares a liveliness token
//! `minflow/subscribers/<key>/<id>`, and publishers count those tokens; the count is the
//! larger of the two.

use std::collections::HashSet;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use zenoh::qos::CongestionControl;
use zenoh::sample::SampleKind;
use zenoh::Wait;

use super::{
    topic_key, FramePublisher, Payload, Sample, StatusPublisher, Subscription, Transport,
    TransportError, TransportKind,
};
use crate::msgs::status::{decode_status, encode_status, SurrogateStatus};
use crate::msgs::{cdr, ParticleFrame};

const KIND: TransportKind = TransportKind::Zenoh;
static NEXT_SUBSCRIPTION: AtomicU64 = AtomicU64::new(0);

fn liveliness_prefix(key: &str) -> String {
    format!("minflow/subscribers/{key}")
}

/// An open zenoh session.
pub struct ZenohTransport {
    session: zenoh::Session,
}

impl ZenohTransport {
    /// Opens a session: an embedded peer with zenoh's default config, or the config in
    /// `config_file` (JSON5, zenoh's own format and semantics).
    ///
    /// # Errors
    /// [`TransportError::Open`] if the file cannot be parsed or the session cannot start.
    pub fn open(config_file: Option<&Path>) -> Result<Self, TransportError> {
        let open_err = |reason: String| TransportError::Open {
            transport: KIND,
            reason,
        };
        let config = match config_file {
            Some(path) => zenoh::Config::from_file(path)
                .map_err(|e| open_err(format!("zenoh config {}: {e}", path.display())))?,
            None => zenoh::Config::default(),
        };
        let session = zenoh::open(config)
            .wait()
            .map_err(|e| open_err(e.to_string()))?;
        Ok(ZenohTransport { session })
    }

    /// The underlying session (for callers that need zenoh features beyond frames).
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }
}

impl Transport for ZenohTransport {
    fn kind(&self) -> TransportKind {
        KIND
    }

    fn zenoh_session(&self) -> Option<zenoh::Session> {
        Some(self.session.clone())
    }

    fn publisher(&self, topic: &str) -> Result<Box<dyn FramePublisher>, TransportError> {
        let key = topic_key(topic)?.to_owned();
        let declare_err =
            |reason: String| TransportError::declare(KIND, "publisher", topic.to_owned(), reason);
        let publisher = self
            .session
            .declare_publisher(key.clone())
            .congestion_control(CongestionControl::Block)
            .express(true)
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        let tokens = Arc::new(Mutex::new(HashSet::new()));
        let seen = Arc::clone(&tokens);
        let liveliness = self
            .session
            .liveliness()
            .declare_subscriber(format!("{}/*", liveliness_prefix(&key)))
            .history(true)
            .callback(move |sample| {
                let mut seen = seen.lock().expect("token set poisoned");
                let token = sample.key_expr().as_str().to_owned();
                match sample.kind() {
                    SampleKind::Put => seen.insert(token),
                    SampleKind::Delete => seen.remove(&token),
                };
            })
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        Ok(Box::new(ZenohPublisher {
            topic: topic.to_owned(),
            publisher,
            tokens,
            _liveliness: liveliness,
            buffer: Vec::new(),
        }))
    }

    fn subscribe(
        &self,
        topic: &str,
        sink: Sender<Sample>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let key = topic_key(topic)?.to_owned();
        let declare_err =
            |reason: String| TransportError::declare(KIND, "subscriber", topic.to_owned(), reason);
        let name = topic.to_owned();
        let subscriber = self
            .session
            .declare_subscriber(key.clone())
            .callback(move |sample| {
                let received = Instant::now();
                let bytes = sample.payload().to_bytes().into_owned();
                // A closed receiver means the owner is shutting down; nothing to do.
                let _ = sink.send(Sample {
                    topic: name.clone(),
                    payload: Payload::Cdr(bytes),
                    received,
                });
            })
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        let id = format!(
            "{}_{}_{}",
            self.session.zid(),
            std::process::id(),
            NEXT_SUBSCRIPTION.fetch_add(1, Ordering::Relaxed)
        );
        let token = self
            .session
            .liveliness()
            .declare_token(format!("{}/{id}", liveliness_prefix(&key)))
            .wait()
            .map_err(|e| declare_err(e.to_string()))?;
        Ok(Box::new(ZenohSubscription {
            _subscriber: subscriber,
            _token: Some(token),
        }))
    }

    fn status_publisher(&self, topic: &str) -> Result<Box<dyn StatusPublisher>, TransportError> {
        let key = topic_key(topic)?.to_owned();
        let publisher = self.session.declare_publisher(key).wait().map_err(|e| {
            TransportError::declare(KIND, "status publisher", topic.to_owned(), e.to_string())
        })?;
        Ok(Box::new(ZenohStatusPublisher {
            topic: topic.to_owned(),
            publisher,
        }))
    }

    fn subscribe_status(
        &self,
        topic: &str,
        sink: Sender<SurrogateStatus>,
    ) -> Result<Box<dyn Subscription>, TransportError> {
        let key = topic_key(topic)?.to_owned();
        let name = topic.to_owned();
        let subscriber = self
            .session
            .declare_subscriber(key)
            .callback(
                move |sample| match decode_status(&sample.payload().to_bytes()) {
                    Ok(status) => {
                        let _ = sink.send(status);
                    }
                    Err(reason) => tracing::warn!("{name}: undecodable status: {reason}"),
                },
            )
            .wait()
            .map_err(|e| {
                TransportError::declare(KIND, "status subscriber", topic.to_owned(), e.to_string())
            })?;
        Ok(Box::new(ZenohSubscription {
            _subscriber: subscriber,
            _token: None,
        }))
    }
}

struct ZenohStatusPublisher {
    topic: String,
    publisher: zenoh::pubsub::Publisher<'static>,
}

impl StatusPublisher for ZenohStatusPublisher {
    fn publish(&mut self, status: &SurrogateStatus) -> Result<(), TransportError> {
        self.publisher
            .put(encode_status(status))
            .wait()
            .map_err(|e| TransportError::Publish {
                transport: KIND,
                topic: self.topic.clone(),
                reason: e.to_string(),
            })
    }
}

struct ZenohPublisher {
    topic: String,
    publisher: zenoh::pubsub::Publisher<'static>,
    tokens: Arc<Mutex<HashSet<String>>>,
    _liveliness: zenoh::pubsub::Subscriber<()>,
    buffer: Vec<u8>,
}

impl ZenohPublisher {
    fn put(&self, bytes: Vec<u8>) -> Result<(), TransportError> {
        self.publisher
            .put(bytes)
            .wait()
            .map_err(|e| TransportError::Publish {
                transport: KIND,
                topic: self.topic.clone(),
                reason: e.to_string(),
            })
    }
}

impl FramePublisher for ZenohPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        self.buffer.clear();
        cdr::encode_into(frame, &mut self.buffer);
        let bytes = self.buffer.clone();
        self.put(bytes)
    }

    fn publish_cdr(&mut self, bytes: &[u8], _frame: &ParticleFrame) -> Result<(), TransportError> {
        self.put(bytes.to_vec())
    }

    fn subscriber_count(&self) -> usize {
        let tokens = self.tokens.lock().expect("token set poisoned").len();
        let matching = self
            .publisher
            .matching_status()
            .wait()
            .map(|s| s.matching())
            .unwrap_or(false);
        tokens.max(usize::from(matching))
    }
}

struct ZenohSubscription {
    _subscriber: zenoh::pubsub::Subscriber<()>,
    _token: Option<zenoh::liveliness::LivelinessToken>,
}

impl Subscription for ZenohSubscription {}
