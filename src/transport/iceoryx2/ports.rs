//! The iceoryx2 transport's ports: the frame publisher (sample, then a wake-up on the event
//! service), the status publisher (CDR bytes in a `[u8]` slice service) and the
//! subscription handle that stops its delivery thread when dropped.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;

use iceoryx2::prelude::*;

use super::{write_particles, FrameHeader, IceoryxTransport, Particle, PubSubFactory, Svc, KIND};
use crate::msgs::status::{encode_status, SurrogateStatus};
use crate::msgs::ParticleFrame;
use crate::transport::{topic_key, FramePublisher, StatusPublisher, Subscription, TransportError};

/// Status reports travel as their CDR bytes in a `[u8]` slice service named like the topic.
pub(super) struct IceoryxStatusPublisher {
    pub(super) topic: String,
    pub(super) _service:
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>,
    pub(super) publisher: iceoryx2::port::publisher::Publisher<Svc, [u8], ()>,
}

impl StatusPublisher for IceoryxStatusPublisher {
    fn publish(&mut self, status: &SurrogateStatus) -> Result<(), TransportError> {
        let err = |reason: String| TransportError::Publish {
            transport: KIND,
            topic: self.topic.clone(),
            reason,
        };
        let bytes = encode_status(status);
        let sample = self
            .publisher
            .loan_slice_uninit(bytes.len())
            .map_err(|e| err(format!("loan: {e:?}")))?;
        let sample = sample.write_from_slice(&bytes);
        sample.send().map_err(|e| err(format!("send: {e:?}")))?;
        Ok(())
    }
}

impl IceoryxTransport {
    pub(super) fn status_service(
        &self,
        topic: &str,
        what: &'static str,
    ) -> Result<
        iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>,
        TransportError,
    > {
        let err = |reason: String| TransportError::declare(KIND, what, topic.to_owned(), reason);
        let name: ServiceName = topic_key(topic)?
            .try_into()
            .map_err(|e| err(format!("service name: {e:?}")))?;
        self.node
            .service_builder(&name)
            .publish_subscribe::<[u8]>()
            .history_size(1)
            .subscriber_max_buffer_size(8)
            .open_or_create()
            .map_err(|e| err(format!("{e:?}")))
    }
}

pub(super) struct IceoryxPublisher {
    pub(super) topic: String,
    pub(super) service: PubSubFactory<Svc, [Particle], FrameHeader>,
    pub(super) publisher: iceoryx2::port::publisher::Publisher<Svc, [Particle], FrameHeader>,
    pub(super) notifier: iceoryx2::port::notifier::Notifier<Svc>,
}

impl FramePublisher for IceoryxPublisher {
    fn publish(&mut self, frame: &ParticleFrame) -> Result<(), TransportError> {
        let header = FrameHeader::from_frame(frame)?;
        let err = |reason: String| TransportError::Publish {
            transport: KIND,
            topic: self.topic.clone(),
            reason,
        };
        let mut sample = self
            .publisher
            .loan_slice_uninit(frame.len())
            .map_err(|e| err(format!("loan: {e:?}")))?;
        *sample.user_header_mut() = header;
        write_particles(frame, sample.payload_mut());
        // SAFETY: every element was written by `write_particles` (slice length = frame.len()).
        let sample = unsafe { sample.assume_init() };
        sample.send().map_err(|e| err(format!("send: {e:?}")))?;
        self.notifier
            .notify()
            .map_err(|e| err(format!("notify: {e:?}")))?;
        Ok(())
    }

    fn subscriber_count(&self) -> usize {
        self.service.dynamic_config().number_of_subscribers()
    }
}

pub(super) struct IceoryxSubscription {
    pub(super) stop: Arc<AtomicBool>,
    pub(super) thread: Option<JoinHandle<()>>,
}

impl Subscription for IceoryxSubscription {}

impl Drop for IceoryxSubscription {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
