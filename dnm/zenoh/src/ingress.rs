//! Ingress: remote outputs a local module reads, mirrored from Zenoh into same-named port
//! services of this DNM's shared memory.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use dnm_module::protocol::PortHeader;
use dnm_netlist::{MessageType, Netlist};

use crate::egress::Counters;
use crate::shared::TsSvc;
use crate::wire::from_wire;
use dnm_proto::keys;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use zenoh::pubsub::Subscriber as ZSubscriber;
use zenoh::sample::Sample;

/// A remote output mirrored into local shared memory.
pub(crate) struct Ingress {
    pub(crate) key: String,
    pub(crate) message: MessageType,
    pub(crate) counters: Arc<Counters>,
    /// Subscribers (and listeners) its mirror port was made for.
    pub(crate) slots: usize,
    pub(crate) _subscriber: ZSubscriber<()>,
}

pub(crate) struct Mirror {
    pub(crate) publisher: Publisher<TsSvc, [u8], PortHeader>,
    pub(crate) notifier: Notifier<TsSvc>,
    pub(crate) max_bytes: usize,
    pub(crate) counters: Arc<Counters>,
    pub(crate) _service: PubSubFactory<TsSvc, [u8], PortHeader>,
}

impl Mirror {
    /// Writes `sample` into a loaned shared-memory sample, straight from the slices Zenoh
    /// received it in (one copy, even for a message that came in fragments), and wakes the
    /// readers.
    pub(crate) fn forward(&self, sample: &Sample) {
        let payload = sample.payload();
        let len = payload.len();
        if len > self.max_bytes {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let header = sample
            .attachment()
            .and_then(|a| keys::decode_header(&a.to_bytes()))
            .map(from_wire)
            .unwrap_or_default();
        let sent = self
            .publisher
            .loan_slice_uninit(len)
            .map_err(|e| format!("{e:?}"))
            .and_then(|mut s| {
                let mut at = 0;
                for slice in payload.slices() {
                    s.payload_mut()[at..at + slice.len()].write_copy_of_slice(slice);
                    at += slice.len();
                }
                // SAFETY: the slices are the whole payload, `len` bytes, each byte written once
                // above.
                let mut s = unsafe { s.assume_init() };
                *s.user_header_mut() = header;
                s.send().map_err(|e| format!("{e:?}"))
            });
        match sent {
            Ok(_) => {
                self.counters.count(len);
                let _ = self.notifier.notify();
            }
            Err(e) => {
                self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                tracing::debug!("mirror send failed: {e}");
            }
        }
    }
}

/// The message type of an output port.
pub(crate) fn output_message(
    netlist: &Netlist,
    port: &dnm_netlist::PortRef,
) -> Option<MessageType> {
    netlist
        .kind_of(&port.module)
        .and_then(|k| k.outputs.iter().find(|p| p.name == port.port))
        .map(|p| p.message.clone())
}
