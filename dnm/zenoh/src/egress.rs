//! Egress: local outputs that a remote input needs, forwarded from shared memory to Zenoh by
//! the egress thread (each sample lent to Zenoh without a copy), and the room a port's service
//! has for its readers.

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use bytes::Bytes;
use dnm_core::worker::{Control, Sets, dbg, err};
use dnm_module::protocol::PortHeader;
use dnm_module::{event_service, port_service};
use dnm_netlist::{MessageType, Netlist};

use crate::shared::TsSvc;
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

/// An egress route with its ports open.
pub(crate) struct OpenRoute {
    subscriber: Subscriber<TsSvc, [u8], PortHeader>,
    listener: Listener<TsSvc>,
    publisher: zenoh::pubsub::Publisher<'static>,
    counters: Arc<Counters>,
}

/// A received sample lent to Zenoh as the bytes it publishes, without a copy. Zenoh gives it
/// back when the put returns (copied into its batches, or by a mirror of this process).
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
        Ok(Self {
            subscriber,
            listener,
            publisher,
            counters: r.counters.clone(),
        })
    }

    /// Publishes the samples waiting, each lent to Zenoh from shared memory, [`PER_WAKE`] at
    /// most. Whether some may be left.
    fn forward(&self) -> bool {
        let _ = self.listener.try_wait(|_| ());
        for _ in 0..PER_WAKE {
            let s = match self.subscriber.receive() {
                Ok(Some(s)) => s,
                Ok(None) => return false,
                Err(e) => {
                    tracing::debug!("egress receive: {e:?}");
                    return false;
                }
            };
            let header = keys::encode_header(&to_wire(s.user_header()));
            let len = s.payload().len();
            match self
                .publisher
                .put(Bytes::from_owner(Lent(s)))
                .attachment(header.to_vec())
                .wait()
            {
                Ok(()) => self.counters.count(len),
                Err(e) => {
                    self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!("publish failed: {e}");
                }
            }
        }
        true
    }
}

/// Samples of one route forwarded per wake-up at most: a module publishing without pause (a
/// loop gone wrong) shares the thread with the other routes and the DNM's route sets, and
/// never takes it from them.
const PER_WAKE: usize = 32;

/// Forwards local samples of the routed outputs to Zenoh as they are sent. Reopens its ports
/// when the DNM sends a new route set; returns when the DNM drops its sender.
///
/// The puts stay on this thread, not on Zenoh's transmission runtime (which would save the
/// wake-up of this thread per sample): a put may wait for one of the link's batches, and with
/// the runtime's only thread waiting, nothing would write the batches out, for up to Zenoh's
/// `wait_before_close` (5 s) behind another thread's blocking put on the same link.
pub(crate) fn egress_loop(
    session: &zenoh::Session,
    control: &Control<EgressRoute>,
) -> Result<(), String> {
    let node = NodeBuilder::new()
        .config(control.node.config())
        .create::<TsSvc>()
        .map_err(dbg("egress node"))?;
    let mut wanted: Vec<EgressRoute> = Vec::new();
    loop {
        let open: Vec<OpenRoute> = wanted
            .iter()
            .filter_map(|r| match OpenRoute::open(&node, session, r) {
                Ok(o) => Some(o),
                Err(e) => {
                    tracing::error!(key = %r.key, "cannot publish: {e}");
                    None
                }
            })
            .collect();
        // Termination signals are the DNM thread's to take (iceoryx2 hands each to one waiter).
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<TsSvc>()
            .map_err(dbg("egress waitset"))?;
        let control_guard = waitset
            .attach_notification(&control.listener)
            .map_err(dbg("attach"))?;
        let mut guards = Vec::new();
        for o in &open {
            guards.push(
                waitset
                    .attach_notification(&o.listener)
                    .map_err(dbg("attach"))?,
            );
        }
        // Which routes woke it: only theirs are forwarded, a wake-up costs one port, not all.
        let mut fired = vec![false; open.len()];
        // Sets sent before the waitset was attached count too; after that, a set comes with a
        // notification of the control listener (and so does the DNM dropping the worker), and
        // only then is it looked at: a sample's wake-up costs no read of the control's socket.
        let mut control_fired = true;
        loop {
            if std::mem::take(&mut control_fired) {
                match control.newest() {
                    Sets::Closed => return Ok(()),
                    Sets::New(set) => {
                        // A route's samples left from its last turn get one more before its
                        // port is opened anew (what is older is skipped then).
                        for (o, f) in open.iter().zip(&fired) {
                            if *f {
                                o.forward();
                            }
                        }
                        wanted = set;
                        break;
                    }
                    Sets::Same => {}
                }
            }
            let leftover = fired.iter().any(|f| *f);
            let on_event = |id: WaitSetAttachmentId<TsSvc>| {
                if id.has_event_from(&control_guard) {
                    control_fired = true;
                } else if let Some(i) = guards.iter().position(|g| id.has_event_from(g)) {
                    fired[i] = true;
                }
                CallbackProgression::Continue
            };
            // A route with samples left from its last turn: the others' events are looked at
            // without waiting, then it goes on.
            if leftover {
                waitset.wait_and_process_once_with_timeout(on_event, Duration::ZERO)
            } else {
                waitset.wait_and_process_once(on_event)
            }
            .map_err(dbg("egress wait"))?;
            for (o, f) in open.iter().zip(fired.iter_mut()) {
                if std::mem::take(f) {
                    *f = o.forward();
                }
            }
        }
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

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use std::sync::atomic::AtomicBool;

    /// Samples the module publishes at most: a turn that never ends while it publishes ends
    /// when it stops.
    const BOUND: u64 = 20_000_000;

    /// A module publishing without pause does not keep the egress thread to its route: a turn
    /// forwards [`PER_WAKE`] samples at most, and says that more may be waiting.
    #[test]
    fn a_module_publishing_without_pause_gets_turns_not_the_thread() {
        let name = format!("dnm_egress_turns_{}", std::process::id());
        let node = NodeBuilder::new().create::<TsSvc>().unwrap();
        let message = MessageType {
            schema_name: "dnm_msgs/Tick".into(),
            encoding: dnm_netlist::POD_ENCODING.into(),
            schema: "uint64 seq\n".into(),
            payload: dnm_netlist::Payload::Fixed { size_bytes: 8 },
            standard: None,
        };
        let service = format!("{name}/out");
        let event = format!("{name}/out/ev");
        let mut c = zenoh::Config::default();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5("listen/endpoints", "[]").unwrap();
        let session = zenoh::open(c).wait().unwrap();
        let route = EgressRoute {
            service: service.clone(),
            event: event.clone(),
            key: format!("{name}/key"),
            message: message.clone(),
            counters: Arc::default(),
        };
        // A reader in this process, as another DNM's mirror is, slower than the module: each
        // put waits for it.
        let _reader = session
            .declare_subscriber(route.key.clone())
            .callback(|_| std::thread::sleep(std::time::Duration::from_micros(50)))
            .wait()
            .unwrap();
        let open = OpenRoute::open(&node, &session, &route).unwrap();
        // The module: publishes and notifies as fast as it can, until told to stop or a bound
        // (reached only if a turn never ends while it publishes).
        let stop = Arc::new(AtomicBool::new(false));
        let module = {
            let (stop, service, event) = (stop.clone(), service.clone(), event.clone());
            std::thread::spawn(move || {
                let node = NodeBuilder::new().create::<TsSvc>().unwrap();
                let publisher = port_service(&node, &service, &message.payload)
                    .unwrap()
                    .publisher_builder()
                    .initial_max_slice_len(8)
                    .create()
                    .unwrap();
                let notifier = event_service(&node, &event)
                    .unwrap()
                    .notifier_builder()
                    .create()
                    .unwrap();
                let mut n = 0u64;
                while !stop.load(Ordering::Relaxed) && n < BOUND {
                    let s = publisher.loan_slice_uninit(8).unwrap();
                    let s = s.write_from_slice(&n.to_le_bytes());
                    s.send().unwrap();
                    let _ = notifier.notify();
                    n += 1;
                }
                n
            })
        };
        let forwarded = || route.counters.messages.load(Ordering::Relaxed);
        // (A hang guard, not a performance limit.)
        let guard = std::time::Instant::now() + std::time::Duration::from_secs(60);
        // Turns while it publishes: none forwards more than its share, and turns that find
        // more waiting than that end with their share, saying so (until five have).
        let mut full_turns = 0;
        while full_turns < 5 {
            assert!(
                std::time::Instant::now() < guard,
                "no turn ever found its share waiting"
            );
            let before = forwarded();
            let more = open.forward();
            let took = forwarded() - before;
            assert!(took <= PER_WAKE as u64, "{took}");
            if took == PER_WAKE as u64 {
                assert!(more);
                full_turns += 1;
            }
        }
        stop.store(true, Ordering::Relaxed);
        let published = module.join().unwrap();
        assert!(
            published < BOUND,
            "a turn lasted as long as the module published"
        );
        // Drained once the module stops: a turn that finds nothing says so.
        while open.forward() {}
        assert!(!open.forward());
    }
}
