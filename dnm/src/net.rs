//! A DNM on Zenoh: the routes the netlist needs between DNMs, and the DNM's answers to
//! Zenoh tools. Keys are in [`crate::keys`].
//!
//! - **Egress.** Every output of a local module that some task links to a module on another
//!   DNM is published on `<system>/port/<dnm>/<module>/<port>` by a thread that waits on the
//!   port's iceoryx2 event and forwards each new sample. Outputs no remote input needs are not
//!   published.
//! - **Ingress.** Every remote output that some task links to a local module is subscribed to
//!   and mirrored into a same-named port service in this DNM's shared memory, so the local
//!   module reads it exactly like a local output and a task switch stays a reference change.
//! - **Transparency.** Queryables answer for the DNM, its netlist, its modules (with the last
//!   value of every output) and its ports; liveliness tokens announce the DNM and each running
//!   module; a liveliness subscriber tracks the other DNMs of the system.
//!
//! Zenoh callbacks never touch DNM state: they queue what they receive and wake the DNM's loop,
//! which answers from its own thread.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver};
use std::sync::{Arc, Mutex};

use dnm_module::protocol::{DNM_EVENT, PortHeader, dnm_config, output_event, output_service};
use dnm_module::{event_service, port_service};
use dnm_netlist::{MessageType, Netlist};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use serde::{Deserialize, Serialize};
use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber as ZSubscriber;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Sample, SampleKind};

use crate::keys;
use crate::worker::{Control, Sets, Worker, dbg, err};

type Svc = ipc::Service;
type TsSvc = ipc_threadsafe::Service;

/// Event service that wakes a DNM's egress thread after its set of routes changed.
const EGRESS_EVENT: &str = "_dnm/egress";

/// Which of a DNM's queryables a query reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Target {
    Dnm,
    Netlist,
    Cmd,
    Module,
    Port,
}

/// What Zenoh callbacks hand to the DNM's loop.
#[derive(Debug)]
pub(crate) enum Inbound {
    Query(Target, Query),
    Peer { dnm: String, alive: bool },
}

/// How another DNM of the system looks from here.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PeerReport {
    pub dnm: String,
    /// `alive`, `lost` (was alive, its liveliness token went away) or `unseen`.
    pub state: String,
    /// How long it has been in that state, ms (absent while unseen).
    pub for_ms: Option<u64>,
}

/// Traffic of one route between DNMs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RouteReport {
    pub key: String,
    pub messages: u64,
    pub bytes: u64,
    /// Samples that could not be forwarded (too large, shared memory full).
    pub dropped: u64,
}

/// This DNM's routes, for reports.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct NetReport {
    /// Outputs published for other DNMs.
    pub published: Vec<RouteReport>,
    /// Remote outputs mirrored into this DNM's shared memory.
    pub mirrored: Vec<RouteReport>,
}

#[derive(Debug, Default)]
struct Counters {
    messages: AtomicU64,
    bytes: AtomicU64,
    dropped: AtomicU64,
}

impl Counters {
    fn count(&self, bytes: usize) {
        self.messages.fetch_add(1, Ordering::Relaxed);
        self.bytes.fetch_add(bytes as u64, Ordering::Relaxed);
    }

    fn report(&self, key: &str) -> RouteReport {
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
struct EgressRoute {
    service: String,
    event: String,
    key: String,
    message: MessageType,
    counters: Arc<Counters>,
}

/// A remote output mirrored into local shared memory.
struct Ingress {
    key: String,
    message: MessageType,
    counters: Arc<Counters>,
    _subscriber: ZSubscriber<()>,
}

struct Mirror {
    publisher: Publisher<TsSvc, [u8], PortHeader>,
    notifier: Notifier<TsSvc>,
    max_bytes: usize,
    counters: Arc<Counters>,
    _service: PubSubFactory<TsSvc, [u8], PortHeader>,
}

impl Mirror {
    fn forward(&self, sample: &Sample) {
        let payload = sample.payload().to_bytes();
        if payload.len() > self.max_bytes {
            self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        let header = sample
            .attachment()
            .and_then(|a| keys::decode_header(&a.to_bytes()))
            .unwrap_or_default();
        let sent = self
            .publisher
            .loan_slice_uninit(payload.len())
            .map_err(|e| format!("{e:?}"))
            .and_then(|s| {
                let mut s = s.write_from_slice(&payload);
                *s.user_header_mut() = header;
                s.send().map_err(|e| format!("{e:?}"))
            });
        match sent {
            Ok(_) => {
                self.counters.count(payload.len());
                let _ = self.notifier.notify();
            }
            Err(e) => {
                self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                tracing::debug!("mirror send failed: {e}");
            }
        }
    }
}

/// A sample's header and a copy of its bytes.
pub(crate) type LastSample = (PortHeader, Vec<u8>);

/// The last sample of an output, kept for queries.
struct Monitor {
    subscriber: Subscriber<Svc, [u8], PortHeader>,
    message: MessageType,
    last: Option<LastSample>,
}

impl Monitor {
    fn refresh(&mut self) {
        while let Ok(Some(s)) = self.subscriber.receive() {
            self.last = Some((*s.user_header(), s.payload().to_vec()));
        }
    }
}

/// A DNM's presence on Zenoh. Owned by the DNM's thread.
pub(crate) struct Net {
    session: zenoh::Session,
    system: String,
    dnm: String,
    inbox: Receiver<Inbound>,
    ts_node: Node<TsSvc>,
    _token: LivelinessToken,
    _queryables: Vec<Queryable<()>>,
    _peer_watch: ZSubscriber<()>,
    module_tokens: BTreeMap<String, LivelinessToken>,
    ingress: BTreeMap<String, Ingress>,
    egress: Vec<EgressRoute>,
    egress_worker: Worker<EgressRoute>,
    monitors: BTreeMap<String, Monitor>,
    peers: BTreeMap<String, (bool, std::time::Instant)>,
}

impl std::fmt::Debug for Net {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Net")
            .field("system", &self.system)
            .field("dnm", &self.dnm)
            .finish_non_exhaustive()
    }
}

impl Net {
    /// Declares the DNM on `session`: its liveliness token, queryables and the watch on the
    /// other DNMs. `prefix` is the DNM's shared-memory namespace.
    pub(crate) fn new(
        session: zenoh::Session,
        system: &str,
        dnm: &str,
        prefix: &str,
    ) -> Result<Self, String> {
        let config = dnm_config(prefix)?;
        let ts_node = NodeBuilder::new()
            .config(&config)
            .create::<TsSvc>()
            .map_err(dbg("zenoh bridge node"))?;
        let waker = Arc::new(Mutex::new(
            event_service(&ts_node, DNM_EVENT)
                .map_err(err("DNM event"))?
                .notifier_builder()
                .create()
                .map_err(dbg("DNM notifier"))?,
        ));
        let (tx, inbox) = mpsc::channel::<Inbound>();
        let deliver = {
            let tx = tx.clone();
            let waker = waker.clone();
            move |m: Inbound| {
                if tx.send(m).is_ok() {
                    if let Ok(n) = waker.lock() {
                        let _ = n.notify();
                    }
                }
            }
        };

        let mut queryables = Vec::new();
        for (target, key) in [
            (Target::Dnm, keys::dnm(system, dnm)),
            (Target::Netlist, keys::netlist(system, dnm)),
            (Target::Cmd, keys::cmd(system, dnm)),
            (Target::Module, keys::module(system, dnm, "*")),
            (Target::Port, keys::port(system, dnm, "*", "*")),
        ] {
            let deliver = deliver.clone();
            let q = session
                .declare_queryable(key.clone())
                .callback(move |q| deliver(Inbound::Query(target, q)))
                .wait()
                .map_err(err("declaring queryable"))?;
            queryables.push(q);
        }
        let token = session
            .liveliness()
            .declare_token(keys::dnm(system, dnm))
            .wait()
            .map_err(err("declaring liveliness token"))?;
        let peer_watch = {
            let system = system.to_string();
            let me = dnm.to_string();
            session
                .liveliness()
                .declare_subscriber(keys::all_dnms(&system))
                .history(true)
                .callback(move |s| {
                    let Some(name) = keys::dnm_of(&system, s.key_expr().as_str()) else {
                        return;
                    };
                    if name != me {
                        deliver(Inbound::Peer {
                            dnm: name,
                            alive: s.kind() == SampleKind::Put,
                        });
                    }
                })
                .wait()
                .map_err(err("watching DNMs"))?
        };

        let egress = {
            let session = session.clone();
            Worker::spawn(
                format!("egress-{dnm}"),
                prefix,
                EGRESS_EVENT,
                move |control| egress_loop(&session, &control),
            )?
        };
        drop(tx);
        Ok(Self {
            session,
            system: system.into(),
            dnm: dnm.into(),
            inbox,
            ts_node,
            _token: token,
            _queryables: queryables,
            _peer_watch: peer_watch,
            module_tokens: BTreeMap::new(),
            ingress: BTreeMap::new(),
            egress: Vec::new(),
            egress_worker: egress,
            monitors: BTreeMap::new(),
            peers: BTreeMap::new(),
        })
    }

    /// What the callbacks queued since the last call.
    pub(crate) fn take_inbound(&mut self) -> Vec<Inbound> {
        self.inbox.try_iter().collect()
    }

    pub(crate) fn set_peer(&mut self, dnm: String, alive: bool) {
        let changed = self.peers.get(&dnm).is_none_or(|(a, _)| *a != alive);
        if changed {
            if alive {
                tracing::info!(dnm = %self.dnm, peer = %dnm, "DNM joined");
            } else {
                tracing::warn!(dnm = %self.dnm, peer = %dnm, "DNM lost");
            }
            self.peers.insert(dnm, (alive, std::time::Instant::now()));
        }
    }

    /// Every other DNM of the netlist and how it looks from here.
    pub(crate) fn peer_reports(&self, netlist: Option<&Netlist>) -> Vec<PeerReport> {
        let mut names: BTreeSet<String> = self.peers.keys().cloned().collect();
        if let Some(n) = netlist {
            names.extend(n.dnms.iter().map(|d| d.name.clone()));
        }
        names.remove(&self.dnm);
        names
            .into_iter()
            .map(|name| match self.peers.get(&name) {
                Some((alive, since)) => PeerReport {
                    dnm: name,
                    state: if *alive { "alive" } else { "lost" }.into(),
                    for_ms: Some(since.elapsed().as_millis() as u64),
                },
                None => PeerReport {
                    dnm: name,
                    state: "unseen".into(),
                    for_ms: None,
                },
            })
            .collect()
    }

    /// Declares or drops module liveliness tokens to match the running set.
    pub(crate) fn sync_module_tokens<'a>(&mut self, running: impl Iterator<Item = &'a str>) {
        let running: BTreeSet<&str> = running.collect();
        self.module_tokens
            .retain(|m, _| running.contains(m.as_str()));
        for m in running {
            if self.module_tokens.contains_key(m) {
                continue;
            }
            match self
                .session
                .liveliness()
                .declare_token(keys::module(&self.system, &self.dnm, m))
                .wait()
            {
                Ok(t) => {
                    self.module_tokens.insert(m.to_string(), t);
                }
                Err(e) => tracing::warn!(module = m, "liveliness token: {e}"),
            }
        }
    }

    /// Before a revision is committed: every remote output any task links to a local module is
    /// mirrored into local shared memory, so plans can reference it. Only new mirrors are made
    /// here (returned, so a failed apply can drop them with [`Net::abort`]); a mirror whose
    /// key or type changed, or one replacing an output of a module still running here, is
    /// made at [`Net::commit`], when the old revision is gone.
    pub(crate) fn prepare_ingress(
        &mut self,
        netlist: &Netlist,
        local_outputs: &BTreeSet<String>,
    ) -> Result<Vec<String>, String> {
        let mut added = Vec::new();
        for (service, key, message) in self.wanted_ingress(netlist) {
            if self.ingress.contains_key(&service) || local_outputs.contains(&service) {
                continue;
            }
            match self.mirror(&service, &key, &message) {
                Ok(ingress) => {
                    self.ingress.insert(service.clone(), ingress);
                    added.push(service);
                }
                Err(e) => {
                    self.abort(&added);
                    return Err(e);
                }
            }
        }
        Ok(added)
    }

    /// Drops mirrors a failed apply prepared.
    pub(crate) fn abort(&mut self, prepared: &[String]) {
        for s in prepared {
            self.ingress.remove(s);
        }
    }

    fn mirror(&self, service: &str, key: &str, message: &MessageType) -> Result<Ingress, String> {
        let port = port_service(&self.ts_node, service, &message.payload)
            .map_err(err("mirror port service"))?;
        let publisher = port
            .publisher_builder()
            .initial_max_slice_len(message.payload.max_bytes())
            .create()
            .map_err(dbg("mirror publisher"))?;
        let (module, p) = service.split_once('/').unwrap_or((service, ""));
        let notifier = event_service(&self.ts_node, &output_event(module, p))
            .map_err(err("mirror event"))?
            .notifier_builder()
            .create()
            .map_err(dbg("mirror notifier"))?;
        let counters = Arc::new(Counters::default());
        let mirror = Mutex::new(Mirror {
            publisher,
            notifier,
            max_bytes: message.payload.max_bytes(),
            counters: counters.clone(),
            _service: port,
        });
        let subscriber = self
            .session
            .declare_subscriber(key.to_string())
            .callback(move |s| {
                if let Ok(m) = mirror.lock() {
                    m.forward(&s);
                }
            })
            .wait()
            .map_err(err("subscribing"))?;
        tracing::info!(dnm = %self.dnm, key, "mirroring remote output");
        Ok(Ingress {
            key: key.to_string(),
            message: message.clone(),
            counters,
            _subscriber: subscriber,
        })
    }

    /// After a revision is committed: publish exactly the outputs remote inputs need, drop
    /// mirrors no task uses any more, and keep a last-value monitor on every local output.
    pub(crate) fn commit(&mut self, netlist: &Netlist, node: &Node<Svc>) {
        let wanted = self.wanted_ingress(netlist);
        let names: BTreeSet<&String> = wanted.iter().map(|(s, _, _)| s).collect();
        self.ingress.retain(|s, _| names.contains(s));
        for (service, key, message) in &wanted {
            let current = self
                .ingress
                .get(service)
                .is_some_and(|i| i.key == *key && i.message == *message);
            if current {
                continue;
            }
            // Drop the old mirror first: one publisher per mirror port at a time.
            self.ingress.remove(service);
            match self.mirror(service, key, message) {
                Ok(i) => {
                    self.ingress.insert(service.clone(), i);
                }
                Err(e) => tracing::error!(key = %key, "cannot mirror: {e}"),
            }
        }

        let egress = self.wanted_egress(netlist);
        let same = egress.len() == self.egress.len()
            && egress
                .iter()
                .zip(&self.egress)
                .all(|(a, b)| a.key == b.key && a.message == b.message);
        if !same {
            // Keep the counters of routes that stay.
            let egress: Vec<EgressRoute> = egress
                .into_iter()
                .map(|mut r| {
                    if let Some(old) = self.egress.iter().find(|o| o.key == r.key) {
                        r.counters = old.counters.clone();
                    }
                    r
                })
                .collect();
            self.egress = egress.clone();
            self.egress_worker.send(egress);
        }

        let outputs: BTreeMap<String, MessageType> = netlist
            .modules_on(&self.dnm)
            .filter_map(|m| netlist.kind_of(&m.name).map(|k| (m, k)))
            .flat_map(|(m, k)| {
                k.outputs
                    .iter()
                    .map(|p| (output_service(&m.name, &p.name), p.message.clone()))
                    .collect::<Vec<_>>()
            })
            .collect();
        self.monitors
            .retain(|s, m| outputs.get(s).is_some_and(|t| *t == m.message));
        for (service, message) in outputs {
            if self.monitors.contains_key(&service) {
                continue;
            }
            let sub = port_service(node, &service, &message.payload)
                .map_err(err("port service"))
                .and_then(|p| p.subscriber_builder().create().map_err(dbg("monitor")));
            match sub {
                Ok(subscriber) => {
                    self.monitors.insert(
                        service,
                        Monitor {
                            subscriber,
                            message,
                            last: None,
                        },
                    );
                }
                Err(e) => tracing::warn!(port = %service, "no last-value monitor: {e}"),
            }
        }
    }

    /// (service, key, message type) of every remote output a local module may read.
    fn wanted_ingress(&self, netlist: &Netlist) -> Vec<(String, String, MessageType)> {
        let mut out = BTreeMap::new();
        for (link, from_dnm, to_dnm) in crate::crossing_links(netlist) {
            let Some(message) = output_message(netlist, &link.from).filter(|_| to_dnm == self.dnm)
            else {
                continue;
            };
            out.insert(
                output_service(&link.from.module, &link.from.port),
                (
                    keys::port(&self.system, &from_dnm, &link.from.module, &link.from.port),
                    message,
                ),
            );
        }
        out.into_iter().map(|(s, (k, m))| (s, k, m)).collect()
    }

    /// Every local output some task links to a module on another DNM, sorted by key.
    fn wanted_egress(&self, netlist: &Netlist) -> Vec<EgressRoute> {
        let mut out: BTreeMap<String, EgressRoute> = BTreeMap::new();
        for (link, from_dnm, _) in crate::crossing_links(netlist) {
            let Some(message) =
                output_message(netlist, &link.from).filter(|_| from_dnm == self.dnm)
            else {
                continue;
            };
            let key = keys::port(&self.system, &self.dnm, &link.from.module, &link.from.port);
            out.entry(key.clone()).or_insert(EgressRoute {
                service: output_service(&link.from.module, &link.from.port),
                event: output_event(&link.from.module, &link.from.port),
                key,
                message,
                counters: Arc::new(Counters::default()),
            });
        }
        out.into_values().collect()
    }

    pub(crate) fn report(&self) -> NetReport {
        NetReport {
            published: self
                .egress
                .iter()
                .map(|r| r.counters.report(&r.key))
                .collect(),
            mirrored: self
                .ingress
                .values()
                .map(|i| i.counters.report(&i.key))
                .collect(),
        }
    }

    /// The last sample of each local output whose key matches `query`.
    pub(crate) fn last_values(
        &mut self,
        query: &zenoh::key_expr::KeyExpr<'_>,
    ) -> Vec<(String, &MessageType, Option<&LastSample>)> {
        let (system, dnm) = (&self.system, &self.dnm);
        self.monitors
            .iter_mut()
            .filter_map(|(service, m)| {
                let (module, port) = service.split_once('/')?;
                let key = keys::port(system, dnm, module, port);
                let ke = zenoh::key_expr::KeyExpr::try_from(key.clone()).ok()?;
                if !ke.intersects(query) {
                    return None;
                }
                m.refresh();
                Some((key, &m.message, m.last.as_ref()))
            })
            .collect()
    }

    /// Last value of one output, as JSON, for module reports.
    pub(crate) fn last_value_json(&mut self, module: &str, port: &str) -> serde_json::Value {
        let Some(m) = self.monitors.get_mut(&output_service(module, port)) else {
            return serde_json::Value::Null;
        };
        m.refresh();
        match &m.last {
            None => serde_json::json!({ "schema": m.message.schema_name, "seq": null }),
            Some((h, bytes)) => serde_json::json!({
                "schema": m.message.schema_name,
                "seq": h.seq,
                "age_ms": dnm_module::protocol::monotonic_ns().saturating_sub(h.stamp_ns) / 1_000_000,
                "value": crate::values::decode(&m.message, bytes),
            }),
        }
    }
}

/// The message type of an output port.
fn output_message(netlist: &Netlist, port: &dnm_netlist::PortRef) -> Option<MessageType> {
    netlist
        .kind_of(&port.module)
        .and_then(|k| k.outputs.iter().find(|p| p.name == port.port))
        .map(|p| p.message.clone())
}

/// An egress route with its ports open.
struct OpenRoute {
    subscriber: Subscriber<Svc, [u8], PortHeader>,
    listener: Listener<Svc>,
    publisher: zenoh::pubsub::Publisher<'static>,
    counters: Arc<Counters>,
}

impl OpenRoute {
    fn open(node: &Node<Svc>, session: &zenoh::Session, r: &EgressRoute) -> Result<Self, String> {
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
            .encoding(keys::encoding(&r.message))
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

    fn forward(&self) {
        let _ = self.listener.try_wait(|_| ());
        while let Ok(Some(s)) = self.subscriber.receive() {
            let payload = s.payload();
            let header = keys::encode_header(s.user_header());
            match self
                .publisher
                .put(payload.to_vec())
                .attachment(header.to_vec())
                .wait()
            {
                Ok(()) => self.counters.count(payload.len()),
                Err(e) => {
                    self.counters.dropped.fetch_add(1, Ordering::Relaxed);
                    tracing::debug!("publish failed: {e}");
                }
            }
        }
    }
}

/// Forwards local samples of the routed outputs to Zenoh as they are sent. Reopens its ports
/// when the DNM sends a new route set; returns when the DNM drops its sender.
fn egress_loop(session: &zenoh::Session, control: &Control<EgressRoute>) -> Result<(), String> {
    let mut wanted: Vec<EgressRoute> = Vec::new();
    loop {
        let open: Vec<OpenRoute> = wanted
            .iter()
            .filter_map(|r| match OpenRoute::open(&control.node, session, r) {
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
            .create::<Svc>()
            .map_err(dbg("egress waitset"))?;
        let _control_guard = waitset
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
        // Sets sent before the waitset was attached count too.
        loop {
            match control.newest() {
                Sets::Closed => return Ok(()),
                Sets::New(set) => {
                    wanted = set;
                    break;
                }
                Sets::Same => {}
            }
            waitset
                .wait_and_process_once(|_| CallbackProgression::Continue)
                .map_err(dbg("egress wait"))?;
            for o in &open {
                o.forward();
            }
        }
    }
}

/// A command sent over Zenoh to `<system>/dnm/<dnm>/cmd`: an admin request plus an optional
/// id; a DNM applies each id once and answers a retry with the first answer.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ZenohCommand {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    #[serde(flatten)]
    pub request: crate::admin::Request,
}

/// The netlist a DNM has applied, as `<system>/dnm/<dnm>/netlist` answers it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NetlistState {
    pub system: String,
    pub dnm: String,
    pub revision: u64,
    pub digest: String,
    pub file: Option<String>,
    pub active_task: Option<String>,
    pub text: Option<String>,
}

/// The newest netlist the running DNMs of `system` hold, if any answers within `timeout`.
/// A DNM that (re)starts into a running system continues from it.
pub fn newest_netlist(
    session: &zenoh::Session,
    system: &str,
    timeout: std::time::Duration,
) -> Option<NetlistState> {
    let replies = session
        .get(keys::netlist(system, "*"))
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(timeout)
        .wait()
        .ok()?;
    let mut best: Option<NetlistState> = None;
    while let Ok(reply) = replies.recv() {
        let Ok(sample) = reply.result() else { continue };
        let Ok(state) = serde_json::from_slice::<NetlistState>(&sample.payload().to_bytes()) else {
            continue;
        };
        if state.text.is_some() && best.as_ref().is_none_or(|b| state.revision > b.revision) {
            best = Some(state);
        }
    }
    best
}
