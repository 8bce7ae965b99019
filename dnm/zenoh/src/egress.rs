//! Egress: local outputs that a remote input needs, forwarded from shared memory to Zenoh on
//! Zenoh's own transmission runtime (the egress thread only opens and closes the routes), and
//! the room a port's service has for its readers.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use std::os::fd::{AsRawFd, RawFd};

use bytes::Bytes;
use dnm_core::worker::{Control, Sets, dbg, err};
use dnm_module::protocol::PortHeader;
use dnm_module::{event_service, port_service};
use dnm_netlist::{MessageType, Netlist};
use tokio::io::Interest;
use tokio::io::unix::AsyncFd;
use zenoh_runtime::ZRuntime;

use crate::shared::{Svc, TsSvc};
use crate::wire::{encoding, to_wire, traffic_class};
use dnm_proto::RouteReport;
use dnm_proto::keys;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use zenoh::Wait;
use zenoh::qos::CongestionControl;

/// Event service that wakes a DNM's egress thread after its set of routes changed.
pub(crate) const EGRESS_EVENT: &str = "_dnm/egress";

#[derive(Debug, Default)]
pub(crate) struct Counters {
    pub(crate) messages: AtomicU64,
    pub(crate) bytes: AtomicU64,
    pub(crate) dropped: AtomicU64,
}

impl Counters {
    pub(crate) fn count(&self, bytes: usize) {
        self.messages.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    pub(crate) fn report(&self, key: &str) -> RouteReport {
        RouteReport {
            key: key.to_string(),
            messages: self.messages.load(Ordering::Relaxed),
            bytes: self.bytes.load(Ordering::Relaxed),
            dropped: self.dropped.load(Ordering::Relaxed),
        }
    }
}

/// An output this DNM publishes for other DNMs.
#[derive(Debug, Clone)]
pub(crate) struct EgressRoute {
    pub(crate) service: String,
    pub(crate) event: String,
    pub(crate) key: String,
    pub(crate) message: MessageType,
    pub(crate) counters: Arc<Counters>,
}

/// An egress route with its ports open. It is served on Zenoh's transmission runtime
/// ([`serve`]): the thread the module's notification wakes is the one that then writes to the
/// link, so a crossing sample costs one wake-up in this process, not two (this thread's and
/// then Zenoh's transmission task's).
pub(crate) struct OpenRoute {
    subscriber: Subscriber<TsSvc, [u8], PortHeader>,
    listener: AsyncFd<Woken>,
    publisher: zenoh::pubsub::Publisher<'static>,
    counters: Arc<Counters>,
}

/// The largest payload published straight from the transmission runtime's thread: well
/// within one of Zenoh's batches (64 KiB), so that it never waits for the transmission task.
const DIRECT_PUT_MAX: usize = 16 * 1024;

/// A listener whose file descriptor Zenoh's runtime waits on.
struct Woken(Listener<TsSvc>);

impl AsRawFd for Woken {
    fn as_raw_fd(&self) -> RawFd {
        // SAFETY: the listener's descriptor, valid for as long as the listener (reading it has
        // no other precondition).
        unsafe { self.0.file_descriptor().native_handle() }
    }
}

/// A received sample lent to Zenoh as the bytes it publishes, without a copy. Zenoh gives it
/// back once the sample is written to the link (or copied for a subscriber in this process).
struct Lent(Sample<TsSvc, [u8], PortHeader>);

impl AsRef<[u8]> for Lent {
    fn as_ref(&self) -> &[u8] {
        self.0.payload()
    }
}

impl OpenRoute {
    fn open(node: &Node<TsSvc>, session: &zenoh::Session, r: &EgressRoute) -> Result<Self, String> {
        let subscriber = port_service(node, &r.service, &r.message.payload)
            .map_err(err("port service"))?
            .subscriber_builder()
            .create()
            .map_err(dbg("egress subscriber"))?;
        let listener = event_service(node, &r.event)
            .map_err(err("port event"))?
            .listener_builder()
            .create()
            .map_err(dbg("egress listener"))?;
        let publisher = session
            .declare_publisher(r.key.clone())
            .encoding(encoding(&r.message))
            .priority(traffic_class(&r.message))
            .congestion_control(CongestionControl::Drop)
            .express(true)
            .wait()
            .map_err(err("declaring publisher"))?;
        // What is already there was published before (or predates the route): skip it.
        while let Ok(Some(_)) = subscriber.receive() {}
        // Registered with the runtime's reactor, so it must be made inside the runtime.
        let listener = {
            let _inside = ZRuntime::TX.enter();
            // SAFETY: the descriptor is the listener's own; `Woken` owns the listener, so the
            // descriptor stays open and the same for as long as the `AsyncFd` lives.
            unsafe { AsyncFd::register_with_interest(Woken(listener), Interest::READABLE) }
                .map_err(|e| format!("waiting on the port's event: {e}"))?
        };
        Ok(Self {
            subscriber,
            listener,
            publisher,
            counters: r.counters.clone(),
        })
    }

    /// The next sample waiting, if any.
    fn next(&self) -> Option<Sample<TsSvc, [u8], PortHeader>> {
        match self.subscriber.receive() {
            Ok(s) => s,
            Err(e) => {
                // Samples still lent to Zenoh (held by a subscriber of this process) count
                // against the port's borrow limit: the rest waits for the next event.
                tracing::debug!("egress receive: {e:?}");
                None
            }
        }
    }

    /// Publishes `s`.
    fn forward(&self, s: Sample<TsSvc, [u8], PortHeader>) {
        let header = keys::encode_header(&to_wire(s.user_header()));
        let len = s.payload().len();
        let put = || {
            self.publisher
                .put(Bytes::from_owner(Lent(s)))
                .attachment(header.to_vec())
                .wait()
        };
        // A sample Zenoh sends in fragments needs batches the transmission task frees while
        // the put waits: that task must be able to run on another thread meanwhile.
        let put = if len <= DIRECT_PUT_MAX {
            put()
        } else {
            tokio::task::block_in_place(put)
        };
        match put {
            Ok(()) => self.counters.count(len),
            Err(e) => {
                self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                tracing::debug!("publish failed: {e}");
            }
        }
    }
}

/// Serves one route on Zenoh's transmission runtime until it is aborted: each time the port's
/// event fires, publishes what the port holds, one sample at a time, letting the transmission
/// task write each before the next is put (a publication that finds the link's queue full waits
/// for room at most Zenoh's `wait_before_drop` once, then the link counts as congested and
/// further samples are dropped at once until it drains).
async fn serve(route: OpenRoute) {
    loop {
        let mut ready = match route.listener.readable().await {
            Ok(r) => r,
            Err(e) => {
                tracing::error!("egress: waiting on a port's event failed: {e}");
                return;
            }
        };
        // Take every notification, then say so: one that comes after is a new readiness.
        let _ = route.listener.get_ref().0.try_wait(|_| ());
        ready.clear_ready();
        let mut first = true;
        while let Some(s) = route.next() {
            if !std::mem::take(&mut first) {
                // Several waiting: the transmission task writes the last one first.
                tokio::task::yield_now().await;
            }
            route.forward(s);
        }
    }
}

/// The routes being served, stopped (and their ports closed) when dropped.
struct Serving(Vec<tokio::task::JoinHandle<()>>);

impl Drop for Serving {
    fn drop(&mut self) {
        for h in &self.0 {
            h.abort();
        }
        // Wait until each has let go of its ports, so that routes opened next find the ports'
        // subscriber slots free.
        for h in self.0.drain(..) {
            let _ = ZRuntime::TX.block_on(h);
        }
    }
}

/// Keeps the DNM's routes served: opens the ports of each new set the DNM sends and serves them
/// on Zenoh's transmission runtime; returns when the DNM drops its sender.
pub(crate) fn egress_loop(
    session: &zenoh::Session,
    control: &Control<EgressRoute>,
) -> Result<(), String> {
    let node = NodeBuilder::new()
        .config(control.node.config())
        .create::<TsSvc>()
        .map_err(dbg("egress node"))?;
    // Termination signals are the DNM thread's to take (iceoryx2 hands each to one waiter).
    let waitset = WaitSetBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Svc>()
        .map_err(dbg("egress waitset"))?;
    let _control_guard = waitset
        .attach_notification(&control.listener)
        .map_err(dbg("attach"))?;
    let mut serving = Serving(Vec::new());
    loop {
        match control.newest() {
            Sets::Closed => return Ok(()),
            Sets::New(set) => {
                drop(std::mem::replace(&mut serving, Serving(Vec::new())));
                for r in &set {
                    match OpenRoute::open(&node, session, r) {
                        Ok(o) => serving.0.push(ZRuntime::TX.spawn(serve(o))),
                        Err(e) => tracing::error!(key = %r.key, "cannot publish: {e}"),
                    }
                }
            }
            Sets::Same => {}
        }
        waitset
            .wait_and_process_once(|_| CallbackProgression::Continue)
            .map_err(dbg("egress wait"))?;
    }
}

/// Whether mirror port `service` on `dnm`, made for `slots` subscribers, holds the readers
/// `netlist` gives it there beside the DNM's own subscribers.
pub(crate) fn room(
    service: &str,
    dnm: &str,
    netlist: &Netlist,
    slots: usize,
) -> Result<(), String> {
    let (module, port) = service.split_once('/').unwrap_or((service, ""));
    let readers = netlist.readers(module, port, dnm);
    let needed = readers + dnm_netlist::DNM_SUBSCRIBERS;
    if needed <= slots {
        return Ok(());
    }
    Err(format!(
        "the mirror of remote output `{module}.{port}` on DNM `{dnm}` was made for {slots} \
         subscribers and this netlist needs {needed} ({readers} readers here and {} of the \
         DNM's own): remove its readers on `{dnm}` in one apply and add them back in the next, \
         so that the mirror is made anew",
        dnm_netlist::DNM_SUBSCRIBERS
    ))
}
