//! A DNM on Zenoh: the routes the netlist needs between DNMs, and the DNM's answers to
//! Zenoh tools. Keys are in [`dnm_proto::keys`].
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
//! - **Commands.** `<system>/dnm/<dnm>/cmd` takes [`dnm_proto::RemoteCommand`]s.
//!
//! Nothing here runs on the DNM's thread but the [`Plugin`] calls, which only swap route sets.
//! Queries are answered by a query thread from the DNM's latest [`Snapshot`] and the bridge's
//! own last-value readers; commands by a command thread that hands them to the DNM through its
//! [`Commander`] and replies when the DNM answers. Each thread takes at most a bounded number
//! of queries at a time; beyond that, queries are dropped (the querier sees no reply from this
//! DNM) and counted, so a flood of queries costs the DNM's thread nothing.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_core::worker::{Control, Sets, Worker, dbg, err};
use dnm_core::{
    Command, CommandKey, Commander, Context, Decision, DnmReport, Plugin, Reply, Snapshot, Txn,
};
use dnm_module::protocol::{PortHeader, dnm_config, output_event, output_service};
use dnm_module::{event_service, event_service_for, port_service, port_service_for};
use dnm_netlist::{MessageType, Netlist, Wiring};

use crate::lease::{Lease, lease_loop};
use crate::watch::{WATCH_EVENT, WatchPort, watch_loop};
use crate::wire::{encoding, from_wire, to_wire, traffic_class};
use dnm_proto::keys;
use dnm_proto::station::Beat;
use dnm_proto::{
    NetReport, NetlistState, PeerReport, RemoteCommand, Request, Response, RouteReport,
};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use zenoh::Wait;
use zenoh::bytes::Encoding;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber as ZSubscriber;
use zenoh::qos::CongestionControl;
use zenoh::query::{Query, Queryable};
use zenoh::sample::{Sample, SampleKind};

type Svc = ipc::Service;
type TsSvc = ipc_threadsafe::Service;

/// Event service that wakes a DNM's egress thread after its set of routes changed.
const EGRESS_EVENT: &str = "_dnm/egress";
/// Queries the query thread holds at most (queued or being answered).
pub const QUERY_QUEUE: usize = 256;
/// Commands the command thread holds at most (queued, at the DNM, or being answered).
pub const COMMAND_QUEUE: usize = 32;
/// Applies among them at most: applies take seconds, and must leave room for switches.
pub const APPLIES_IN_FLIGHT: usize = 4;

/// Parses and validates a netlist sent in a command (`file` names it in errors).
pub type ParseNetlist = Arc<dyn Fn(&Path, &str) -> Result<Netlist, String> + Send + Sync>;

/// Which of a DNM's queryables a query reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Target {
    Dnm,
    Netlist,
    Wiring,
    Module,
    Port,
}

/// What the bridge's threads and callbacks share.
#[derive(Default)]
struct Shared {
    snapshot: Mutex<Option<Arc<Snapshot>>>,
    peers: Mutex<BTreeMap<String, (bool, Instant)>>,
    /// Local outputs and their types, for last-value readers (set at each commit).
    outputs: Mutex<Option<Vec<(String, MessageType)>>>,
    /// The wiring of the revision committed last.
    wiring: Mutex<Option<Wiring>>,
    /// The kinds that revision could use (built in and the executables it declares).
    kinds: Mutex<Option<Arc<dnm_netlist::Catalog>>>,
    queries_in_flight: AtomicUsize,
    commands_in_flight: AtomicUsize,
    applies_in_flight: Arc<AtomicUsize>,
    refused: AtomicU64,
    answered: AtomicU64,
    /// Set when the bridge is dropped: its threads end.
    stop: std::sync::atomic::AtomicBool,
    /// The system's authority, when it has one: switches and applies then come only from it
    /// (as transactions); a direct one would put this DNM on a task the others are not on.
    authority: std::sync::OnceLock<String>,
    /// The DNM's lease on that authority.
    lease: Mutex<Lease>,
}

impl Shared {
    fn snapshot(&self) -> Option<Arc<Snapshot>> {
        self.snapshot.lock().ok().and_then(|s| s.clone())
    }
}

/// A DNM's presence on Zenoh, plugged into the DNM (see the module docs).
pub struct Bridge {
    session: zenoh::Session,
    system: String,
    dnm: String,
    shared: Arc<Shared>,
    ts_node: Node<TsSvc>,
    _token: LivelinessToken,
    _queryables: Vec<Queryable<()>>,
    _peer_watch: ZSubscriber<()>,
    ingress: BTreeMap<String, Ingress>,
    /// Mirrors made by the apply being prepared.
    prepared: Vec<String>,
    egress: Vec<EgressRoute>,
    egress_worker: Worker<EgressRoute>,
    watch: Vec<WatchPort>,
    watch_worker: Worker<WatchPort>,
    declared_dnms: Vec<String>,
    query_thread: Option<std::thread::JoinHandle<()>>,
    command_thread: Option<std::thread::JoinHandle<()>>,
    query_tx: Option<SyncSender<(Target, Query)>>,
    command_tx: Option<SyncSender<CommandJob>>,
    /// For the lease: it makes the DNM safe.
    commander: Commander,
    _beats: Option<ZSubscriber<()>>,
    lease_thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for Bridge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bridge")
            .field("system", &self.system)
            .field("dnm", &self.dnm)
            .finish_non_exhaustive()
    }
}

enum CommandJob {
    Query(Query),
    Answer(Query, Response),
}

impl Bridge {
    /// Takes switches and applies only from the system's authority `dnm` (see
    /// `dnm-authority`); other clients are told to go through a ground station. Keeps a lease
    /// on it (see [`crate::lease`]): the DNM makes itself safe when it must, whoever is down.
    pub fn follow_authority(mut self, dnm: &str) -> Result<Self, String> {
        let _ = self.shared.authority.set(dnm.to_string());
        let beats = {
            let shared = self.shared.clone();
            let authority = dnm.to_string();
            self.session
                .declare_subscriber(keys::authority_beat(&self.system))
                .callback(move |sample| {
                    let Ok(beat) = serde_json::from_slice::<Beat>(&sample.payload().to_bytes())
                    else {
                        return;
                    };
                    if let Ok(mut l) = shared.lease.lock() {
                        l.heard(&authority, beat);
                    }
                })
                .wait()
                .map_err(err("subscribing to the authority's beat"))?
        };
        let thread = {
            let shared = self.shared.clone();
            let commander = self.commander.clone();
            let (me, authority) = (self.dnm.clone(), dnm.to_string());
            std::thread::Builder::new()
                .name(format!("lease-{me}"))
                .spawn(move || {
                    lease_loop(
                        &me,
                        &authority,
                        &shared.lease,
                        &|| shared.snapshot(),
                        &commander,
                        &shared.stop,
                    )
                })
                .map_err(err("spawning the lease thread"))?
        };
        self._beats = Some(beats);
        self.lease_thread = Some(thread);
        Ok(self)
    }

    /// Declares the DNM on `session`: its liveliness token, queryables, the watch on the other
    /// DNMs, and the threads that answer queries and commands. `commander` reaches the DNM;
    /// `parse` validates netlists sent in `apply` commands.
    pub fn new(
        session: zenoh::Session,
        system: &str,
        dnm: &str,
        prefix: &str,
        commander: Commander,
        parse: ParseNetlist,
    ) -> Result<Self, String> {
        let config = dnm_config(prefix)?;
        let ts_node = NodeBuilder::new()
            .config(&config)
            .create::<TsSvc>()
            .map_err(dbg("zenoh bridge node"))?;
        let shared = Arc::new(Shared::default());

        let (query_tx, query_rx) = mpsc::sync_channel::<(Target, Query)>(QUERY_QUEUE);
        let query_thread = {
            let shared = shared.clone();
            let session = session.clone();
            let (system, dnm, prefix) = (system.to_string(), dnm.to_string(), prefix.to_string());
            std::thread::Builder::new()
                .name(format!("zenoh-queries-{dnm}"))
                .spawn(move || query_loop(&session, &system, &dnm, &prefix, &shared, &query_rx))
                .map_err(err("spawning the query thread"))?
        };
        let (command_tx, command_rx) = mpsc::sync_channel::<CommandJob>(COMMAND_QUEUE * 2);
        let lease_commander = commander.clone();
        let command_thread = {
            let shared = shared.clone();
            let tx = command_tx.clone();
            let (system, dnm) = (system.to_string(), dnm.to_string());
            std::thread::Builder::new()
                .name(format!("zenoh-commands-{dnm}"))
                .spawn(move || {
                    command_loop(&system, &dnm, &shared, &commander, &parse, &tx, &command_rx)
                })
                .map_err(err("spawning the command thread"))?
        };

        let mut queryables = Vec::new();
        for (target, key) in [
            (Target::Dnm, keys::dnm(system, dnm)),
            (Target::Netlist, keys::netlist(system, dnm)),
            (Target::Wiring, keys::wiring(system, dnm)),
            (Target::Module, keys::module(system, dnm, "*")),
            (Target::Port, keys::port(system, dnm, "*", "*")),
        ] {
            let tx = query_tx.clone();
            let shared = shared.clone();
            let q = session
                .declare_queryable(key.clone())
                .callback(move |q| {
                    if admit(&shared.queries_in_flight, QUERY_QUEUE, &shared.refused)
                        && tx.try_send((target, q)).is_err()
                    {
                        shared.queries_in_flight.fetch_sub(1, Ordering::Relaxed);
                        shared.refused.fetch_add(1, Ordering::Relaxed);
                    }
                })
                .wait()
                .map_err(err("declaring queryable"))?;
            queryables.push(q);
        }
        {
            let tx = command_tx.clone();
            let shared = shared.clone();
            let q = session
                .declare_queryable(keys::cmd(system, dnm))
                .callback(move |q| {
                    if admit(&shared.commands_in_flight, COMMAND_QUEUE, &shared.refused)
                        && tx.try_send(CommandJob::Query(q)).is_err()
                    {
                        shared.commands_in_flight.fetch_sub(1, Ordering::Relaxed);
                        shared.refused.fetch_add(1, Ordering::Relaxed);
                    }
                })
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
            let shared = shared.clone();
            session
                .liveliness()
                .declare_subscriber(keys::all_dnms(&system))
                .history(true)
                .callback(move |s| {
                    let Some(name) = keys::dnm_of(&system, s.key_expr().as_str()) else {
                        return;
                    };
                    if name == me {
                        return;
                    }
                    let alive = s.kind() == SampleKind::Put;
                    let Ok(mut peers) = shared.peers.lock() else {
                        return;
                    };
                    if peers.get(&name).is_none_or(|(a, _)| *a != alive) {
                        if alive {
                            tracing::info!(dnm = %me, peer = %name, "DNM joined");
                        } else {
                            tracing::warn!(dnm = %me, peer = %name, "DNM lost");
                        }
                        peers.insert(name, (alive, Instant::now()));
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
        let watch_worker = {
            let session = session.clone();
            let (system, dnm, p) = (system.to_string(), dnm.to_string(), prefix.to_string());
            Worker::spawn(
                format!("watch-{dnm}"),
                prefix,
                WATCH_EVENT,
                move |control| watch_loop(&session, &system, &dnm, &p, &control),
            )?
        };
        Ok(Self {
            session,
            system: system.into(),
            dnm: dnm.into(),
            shared,
            ts_node,
            _token: token,
            _queryables: queryables,
            _peer_watch: peer_watch,
            ingress: BTreeMap::new(),
            prepared: Vec::new(),
            egress: Vec::new(),
            egress_worker: egress,
            watch: Vec::new(),
            watch_worker,
            declared_dnms: Vec::new(),
            query_thread: Some(query_thread),
            command_thread: Some(command_thread),
            query_tx: Some(query_tx),
            command_tx: Some(command_tx),
            commander: lease_commander,
            _beats: None,
            lease_thread: None,
        })
    }

    /// Every other DNM of the netlist and how it looks from here.
    fn peer_reports(&self) -> Vec<PeerReport> {
        let peers = self
            .shared
            .peers
            .lock()
            .map(|p| p.clone())
            .unwrap_or_default();
        let mut names: BTreeSet<String> = peers.keys().cloned().collect();
        names.extend(self.declared_dnms.iter().cloned());
        names.remove(&self.dnm);
        names
            .into_iter()
            .map(|name| match peers.get(&name) {
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

    fn mirror(
        &self,
        netlist: &Netlist,
        service: &str,
        key: &str,
        message: &MessageType,
    ) -> Result<Ingress, String> {
        let (module, p) = service.split_once('/').unwrap_or((service, ""));
        // As many subscribers as the port has readers here, like a local port; a service that
        // outlived its last mirror (a reader still holds it) is opened as it was made.
        let payload = &message.payload;
        let subscribers = payload.subscribers_for(netlist.readers(module, p, &self.dnm));
        let port = port_service_for(&self.ts_node, service, payload, subscribers)
            .or_else(|_| {
                port_service_for(&self.ts_node, service, payload, payload.subscribers_for(0))
            })
            .map_err(err("mirror port service"))?;
        let publisher = port
            .publisher_builder()
            .initial_max_slice_len(message.payload.max_bytes())
            .create()
            .map_err(dbg("mirror publisher"))?;
        let event_name = output_event(module, p);
        let event = event_service_for(
            &self.ts_node,
            &event_name,
            subscribers.max(dnm_module::protocol::MAX_PORT_SUBSCRIBERS),
        )
        .or_else(|_| {
            event_service_for(
                &self.ts_node,
                &event_name,
                dnm_module::protocol::MAX_PORT_SUBSCRIBERS,
            )
        })
        .map_err(err("mirror event"))?;
        let slots = port
            .static_config()
            .max_subscribers()
            .min(event.static_config().max_listeners());
        room(service, &self.dnm, netlist, slots)?;
        let notifier = event
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
            slots,
            _subscriber: subscriber,
        })
    }

    /// (service, key, message type) of every remote output a local module may read.
    fn wanted_ingress(&self, netlist: &Netlist) -> Vec<(String, String, MessageType)> {
        let mut out = BTreeMap::new();
        for (link, from_dnm, to_dnm) in dnm_core::crossing_links(netlist) {
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

    /// Every output of a local module, for watchers.
    fn watchable(&self, netlist: &Netlist) -> Vec<WatchPort> {
        netlist
            .modules_on(&self.dnm)
            .filter_map(|m| netlist.kind_of(&m.name).map(|k| (m, k)))
            .flat_map(|(m, k)| {
                k.outputs.iter().map(|p| WatchPort {
                    module: m.name.clone(),
                    port: p.name.clone(),
                    service: output_service(&m.name, &p.name),
                    event: output_event(&m.name, &p.name),
                    message: p.message.clone(),
                })
            })
            .collect()
    }

    /// Every local output some task links to a module on another DNM, sorted by key.
    fn wanted_egress(&self, netlist: &Netlist) -> Vec<EgressRoute> {
        let mut out: BTreeMap<String, EgressRoute> = BTreeMap::new();
        for (link, from_dnm, _) in dnm_core::crossing_links(netlist) {
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
}

impl Plugin for Bridge {
    fn name(&self) -> &'static str {
        "zenoh"
    }

    /// Every remote output any task links to a local module is mirrored into local shared
    /// memory before plans reference it. Only new mirrors are made here; a mirror whose key or
    /// type changed, or one replacing an output of a module still running here, is made at the
    /// commit, when the old revision is gone.
    fn prepare(
        &mut self,
        ctx: &Context<'_>,
        netlist: &Netlist,
        _revision: u64,
    ) -> Result<(), String> {
        self.prepared.clear();
        for (service, key, message) in self.wanted_ingress(netlist) {
            if let Some(kept) = self.ingress.get(&service) {
                // A mirror kept across the apply must have room for its readers in this one.
                if let Err(e) = room(&service, &self.dnm, netlist, kept.slots) {
                    for s in self.prepared.drain(..) {
                        self.ingress.remove(&s);
                    }
                    return Err(e);
                }
                continue;
            }
            if ctx.local_outputs.contains(&service) {
                continue;
            }
            match self.mirror(netlist, &service, &key, &message) {
                Ok(ingress) => {
                    self.ingress.insert(service.clone(), ingress);
                    self.prepared.push(service);
                }
                Err(e) => {
                    for s in self.prepared.drain(..) {
                        self.ingress.remove(&s);
                    }
                    return Err(e);
                }
            }
        }
        Ok(())
    }

    fn abort(&mut self, _ctx: &Context<'_>, _revision: u64) {
        for s in self.prepared.drain(..) {
            self.ingress.remove(&s);
        }
    }

    /// Publishes exactly the outputs remote inputs need, drops mirrors no task uses any more,
    /// and gives the query thread the outputs to keep last values of.
    fn commit(&mut self, _ctx: &Context<'_>, netlist: &Netlist, revision: u64) {
        self.prepared.clear();
        if let Ok(mut l) = self.shared.lease.lock() {
            l.committed(
                netlist
                    .on_link_loss
                    .as_ref()
                    .map(|l| (Duration::from_millis(l.after_ms), l.task.clone())),
            );
        }
        self.declared_dnms = netlist.dnms.iter().map(|d| d.name.clone()).collect();
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
            match self.mirror(netlist, service, key, message) {
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

        let outputs: Vec<(String, MessageType)> = netlist
            .modules_on(&self.dnm)
            .filter_map(|m| netlist.kind_of(&m.name).map(|k| (m, k)))
            .flat_map(|(m, k)| {
                k.outputs
                    .iter()
                    .map(|p| (output_service(&m.name, &p.name), p.message.clone()))
                    .collect::<Vec<_>>()
            })
            .collect();
        if let Ok(mut o) = self.shared.outputs.lock() {
            *o = Some(outputs);
        }
        if let Ok(mut w) = self.shared.wiring.lock() {
            *w = Some(Wiring::of(netlist, &self.dnm, revision, None));
        }
        if let Ok(mut k) = self.shared.kinds.lock() {
            *k = Some(Arc::new(netlist.catalog.without_bodies()));
        }

        let watch = self.watchable(netlist);
        if watch != self.watch {
            self.watch = watch.clone();
            self.watch_worker.send(watch);
        }
    }

    fn report(&self, report: &mut DnmReport) {
        report.peers = self.peer_reports();
        if let Some(a) = self.shared.authority.get() {
            report.lease = self.shared.lease.lock().ok().map(|l| l.report(a));
        }
        report.routes = NetReport {
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
            queries_refused: self.shared.refused.load(Ordering::Relaxed),
            queries_answered: self.shared.answered.load(Ordering::Relaxed),
        };
    }

    fn published(&mut self, snapshot: &Arc<Snapshot>) {
        if let Ok(mut s) = self.shared.snapshot.lock() {
            *s = Some(snapshot.clone());
        }
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        // Queryables first, so nothing new arrives; then the threads end.
        self._queryables.clear();
        self.shared.stop.store(true, Ordering::Relaxed);
        self.query_tx.take();
        self.command_tx.take();
        if let Some(t) = self.query_thread.take() {
            let _ = t.join();
        }
        if let Some(t) = self.lease_thread.take() {
            let _ = t.join();
        }
        if let Some(t) = self.command_thread.take() {
            let _ = t.join();
        }
    }
}

/// Takes one slot of a bounded in-flight count; counts a refusal when none is left.
fn admit(in_flight: &AtomicUsize, limit: usize, refused: &AtomicU64) -> bool {
    let taken = in_flight
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (n < limit).then_some(n + 1)
        })
        .is_ok();
    if !taken {
        refused.fetch_add(1, Ordering::Relaxed);
    }
    taken
}

fn reply_json(query: &Query, key: String, body: &impl serde::Serialize) {
    let bytes = serde_json::to_vec(body).unwrap_or_default();
    if let Err(e) = query
        .reply(key, bytes)
        .encoding(Encoding::APPLICATION_JSON)
        .wait()
    {
        tracing::debug!("zenoh reply: {e}");
    }
}

/// A sample's header and a copy of its bytes.
type LastSample = (PortHeader, Vec<u8>);

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

    fn json(&mut self) -> serde_json::Value {
        self.refresh();
        match &self.last {
            None => serde_json::json!({ "schema": self.message.schema_name, "seq": null }),
            Some((h, bytes)) => serde_json::json!({
                "schema": self.message.schema_name,
                "seq": h.seq,
                "age_ms": dnm_module::protocol::monotonic_ns().saturating_sub(h.stamp_ns) / 1_000_000,
                "value": dnm_netlist::values::decode(&self.message, bytes),
            }),
        }
    }
}

/// Answers the DNM's queries from its snapshot and the last-value readers; keeps the module
/// liveliness tokens in step with the running modules.
fn query_loop(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    prefix: &str,
    shared: &Shared,
    queries: &Receiver<(Target, Query)>,
) {
    let node = match dnm_config(prefix).and_then(|c| {
        NodeBuilder::new()
            .config(&c)
            .create::<Svc>()
            .map_err(|e| format!("{e:?}"))
    }) {
        Ok(n) => n,
        Err(e) => {
            tracing::error!(dnm, "query thread has no shared memory: {e}");
            return;
        }
    };
    let mut monitors: BTreeMap<String, Monitor> = BTreeMap::new();
    let mut tokens: BTreeMap<String, LivelinessToken> = BTreeMap::new();
    let mut last_snapshot: Option<Arc<Snapshot>> = None;
    loop {
        let job = queries.recv_timeout(Duration::from_millis(100));
        if matches!(job, Err(mpsc::RecvTimeoutError::Disconnected))
            || shared.stop.load(Ordering::Relaxed)
        {
            return;
        }
        // Outputs changed at a commit: readers follow.
        if let Some(outputs) = shared.outputs.lock().ok().and_then(|mut o| o.take()) {
            let wanted: BTreeMap<String, MessageType> = outputs.into_iter().collect();
            monitors.retain(|s, m| wanted.get(s).is_some_and(|t| *t == m.message));
            for (service, message) in wanted {
                if monitors.contains_key(&service) {
                    continue;
                }
                let sub = port_service(&node, &service, &message.payload)
                    .map_err(err("port service"))
                    .and_then(|p| p.subscriber_builder().create().map_err(dbg("monitor")));
                match sub {
                    Ok(subscriber) => {
                        monitors.insert(
                            service,
                            Monitor {
                                subscriber,
                                message,
                                last: None,
                            },
                        );
                    }
                    Err(e) => tracing::warn!(port = %service, "no last-value reader: {e}"),
                }
            }
        }
        let snapshot = shared.snapshot();
        if snapshot.as_ref().map(Arc::as_ptr) != last_snapshot.as_ref().map(Arc::as_ptr) {
            last_snapshot = snapshot.clone();
            if let Some(s) = &snapshot {
                sync_tokens(session, system, dnm, &mut tokens, &s.report);
            }
        }
        let Ok((target, query)) = job else { continue };
        answer(
            system,
            dnm,
            target,
            &query,
            snapshot.as_deref(),
            shared,
            &mut monitors,
        );
        drop(query);
        shared.queries_in_flight.fetch_sub(1, Ordering::Relaxed);
        shared.answered.fetch_add(1, Ordering::Relaxed);
    }
}

fn sync_tokens(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    tokens: &mut BTreeMap<String, LivelinessToken>,
    report: &DnmReport,
) {
    let running: BTreeSet<&str> = report
        .modules
        .iter()
        .filter(|m| m.state == dnm_proto::ModuleRunState::Running)
        .map(|m| m.name.as_str())
        .collect();
    tokens.retain(|m, _| running.contains(m.as_str()));
    for m in running {
        if tokens.contains_key(m) {
            continue;
        }
        match session
            .liveliness()
            .declare_token(keys::module(system, dnm, m))
            .wait()
        {
            Ok(t) => {
                tokens.insert(m.to_string(), t);
            }
            Err(e) => tracing::warn!(module = m, "liveliness token: {e}"),
        }
    }
}

fn answer(
    system: &str,
    dnm: &str,
    target: Target,
    query: &Query,
    snapshot: Option<&Snapshot>,
    shared: &Shared,
    monitors: &mut BTreeMap<String, Monitor>,
) {
    match target {
        Target::Dnm => {
            if let Some(s) = snapshot {
                // `?brief`: only what a DNM is running, for the authority's checks across a
                // slow link.
                if query.parameters().contains_key("glance") {
                    reply_json(
                        query,
                        keys::dnm(system, dnm),
                        &dnm_proto::DnmGlance::of(&s.report),
                    );
                } else if query.parameters().contains_key("brief") {
                    reply_json(
                        query,
                        keys::dnm(system, dnm),
                        &dnm_proto::DnmBrief::of(&s.report),
                    );
                } else {
                    reply_json(query, keys::dnm(system, dnm), &s.report);
                }
            }
        }
        Target::Netlist => {
            if let Some(s) = snapshot {
                reply_json(query, keys::netlist(system, dnm), &s.netlist);
            }
        }
        Target::Wiring => {
            // `?kinds`: every kind this DNM can run (ports, message types, parameters), for
            // editors that compose netlists away from the rover.
            if query.parameters().contains_key("kinds") {
                let kinds = shared.kinds.lock().ok().and_then(|k| k.clone());
                if let Some(k) = kinds {
                    reply_json(query, keys::wiring(system, dnm), &*k);
                }
            } else if let Some(mut w) = shared.wiring.lock().ok().and_then(|w| w.clone()) {
                // The task in force now (switches do not commit a new revision).
                if let Some(s) = snapshot.filter(|s| s.report.revision == w.revision) {
                    w.active_task = s.report.active_task.clone();
                }
                reply_json(query, keys::wiring(system, dnm), &w);
            }
        }
        Target::Module => {
            let Some(s) = snapshot else { return };
            for m in &s.report.modules {
                let key = keys::module(system, dnm, &m.name);
                let matches = zenoh::key_expr::KeyExpr::try_from(key.as_str())
                    .is_ok_and(|k| k.intersects(query.key_expr()));
                if !matches {
                    continue;
                }
                let mut outputs = serde_json::Map::new();
                let prefix = format!("{}/", m.name);
                for (service, monitor) in monitors.range_mut(prefix.clone()..) {
                    let Some(port) = service.strip_prefix(&prefix) else {
                        break;
                    };
                    outputs.insert(port.to_string(), monitor.json());
                }
                let mut v = serde_json::to_value(m).unwrap_or_default();
                if let Some(o) = v.as_object_mut() {
                    o.insert("dnm".into(), dnm.into());
                    o.insert("outputs".into(), serde_json::Value::Object(outputs));
                }
                reply_json(query, key, &v);
            }
        }
        Target::Port => {
            for (service, m) in monitors.iter_mut() {
                let Some((module, port)) = service.split_once('/') else {
                    continue;
                };
                let key = keys::port(system, dnm, module, port);
                let matches = zenoh::key_expr::KeyExpr::try_from(key.as_str())
                    .is_ok_and(|k| k.intersects(query.key_expr()));
                if !matches {
                    continue;
                }
                m.refresh();
                let Some((header, bytes)) = &m.last else {
                    continue;
                };
                if let Err(e) = query
                    .reply(key, bytes.clone())
                    .encoding(encoding(&m.message))
                    .attachment(keys::encode_header(&to_wire(header)).to_vec())
                    .wait()
                {
                    tracing::debug!("zenoh reply: {e}");
                }
            }
        }
    }
}

/// Takes commands from Zenoh, hands switches and applies to the DNM, and replies when it
/// answers. Status and netlist requests are answered from the snapshot.
fn command_loop(
    system: &str,
    dnm: &str,
    shared: &Shared,
    commander: &Commander,
    parse: &ParseNetlist,
    jobs_tx: &SyncSender<CommandJob>,
    jobs: &Receiver<CommandJob>,
) {
    let c = Commands {
        system,
        dnm,
        shared,
        commander,
        parse,
        jobs_tx,
    };
    loop {
        match jobs.recv_timeout(Duration::from_millis(100)) {
            Ok(CommandJob::Answer(query, response)) => c.finish(query, &response),
            Ok(CommandJob::Query(query)) => c.take(query),
            Err(mpsc::RecvTimeoutError::Timeout) if !shared.stop.load(Ordering::Relaxed) => {}
            Err(_) => return,
        }
    }
}

/// What the command thread works with; one method per phase of a command and per request.
struct Commands<'a> {
    system: &'a str,
    dnm: &'a str,
    shared: &'a Shared,
    commander: &'a Commander,
    parse: &'a ParseNetlist,
    jobs_tx: &'a SyncSender<CommandJob>,
}

/// A query's bytes as a command, or why they are none.
fn read_command(query: &Query) -> Result<RemoteCommand, String> {
    const EXAMPLE: &str = r#"{"client":"me","id":"42","cmd":"switch","task":"auto"}"#;
    match query.payload().map(|p| p.to_bytes()) {
        Some(b) => serde_json::from_slice(&b)
            .map_err(|e| format!("bad command: {e}; send JSON such as {EXAMPLE}")),
        None => Err(format!("empty command; send JSON such as {EXAMPLE}")),
    }
}

impl Commands<'_> {
    /// Answers a command's query (and frees its place).
    fn finish(&self, query: Query, response: &Response) {
        let key = keys::cmd(self.system, self.dnm);
        let bytes = serde_json::to_vec(response).unwrap_or_default();
        let sent = if response.ok {
            query
                .reply(key, bytes)
                .encoding(Encoding::APPLICATION_JSON)
                .wait()
        } else {
            query
                .reply_err(bytes)
                .encoding(Encoding::APPLICATION_JSON)
                .wait()
        };
        if let Err(e) = sent {
            tracing::debug!("zenoh reply: {e}");
        }
        self.shared
            .commands_in_flight
            .fetch_sub(1, Ordering::Relaxed);
        self.shared.answered.fetch_add(1, Ordering::Relaxed);
    }

    /// Hands a command to the DNM; if it cannot take it, its query is answered here.
    fn hand(&self, command: Command, slot: Arc<Mutex<Option<Query>>>) {
        if let Err(e) = self.commander.send(command)
            && let Some(q) = slot.lock().ok().and_then(|mut s| s.take())
        {
            self.finish(q, &Response::error(format!("DNM `{}`: {e}", self.dnm)));
        }
    }

    /// Why a command must not come from its sender, if it must not: in a system commanded
    /// through its authority, transactions, switches and applies come from it alone.
    fn refusal(&self, cmd: &RemoteCommand) -> Option<String> {
        let system = self.system;
        let authority = self.shared.authority.get()?;
        let from_authority = cmd.client.as_deref() == Some(&format!("authority-{authority}"));
        if from_authority {
            return None;
        }
        match cmd.request {
            Request::Prepare { .. } | Request::Decide { .. } | Request::Adopt { .. } => {
                Some(format!(
                    "transactions of system `{system}` come from its authority, DNM `{authority}`"
                ))
            }
            Request::Switch { .. } | Request::Apply { .. } => Some(format!(
                "system `{system}` is commanded through its authority, DNM `{authority}`: \
                 send switches and applies through a ground station (`dnm ground switch TASK`), \
                 which has every DNM take them together"
            )),
            _ => None,
        }
    }

    /// One command: read, checked against its sender, then handed on.
    fn take(&self, query: Query) {
        let cmd = match read_command(&query) {
            Ok(c) => c,
            Err(e) => return self.finish(query, &Response::error(e)),
        };
        if let Some(why) = self.refusal(&cmd) {
            return self.finish(query, &Response::error(why));
        }
        let key = cmd.id.map(|id| CommandKey {
            client: cmd.client.unwrap_or_default(),
            id,
        });
        match cmd.request {
            Request::Status | Request::Netlist => self.state(query, &cmd.request),
            Request::Switch { task } => self.switch(query, task, key),
            Request::Apply { file, text } => self.apply(query, &file, &text, key),
            Request::Prepare {
                txn,
                revision,
                task,
                file,
                text,
            } => self.prepare(query, txn, revision, task, file, text),
            Request::Decide {
                txn,
                commit,
                at_unix_ns,
                revision,
                task,
            } => self.decide(
                query,
                Decision {
                    id: txn,
                    commit,
                    at_unix_ns,
                    revision,
                    task,
                },
            ),
            Request::Adopt {
                revision,
                task,
                file,
                text,
            } => self.adopt(query, revision, task, &file, &text),
        }
    }

    /// The DNM's report or its netlist, from the latest snapshot.
    fn state(&self, query: Query, request: &Request) {
        let r = match (self.shared.snapshot(), request) {
            (None, _) => Response::error(format!("DNM `{}` is starting", self.dnm)),
            (Some(s), Request::Status) => Response {
                ok: true,
                dnms: vec![s.report.clone()],
                ..Response::default()
            },
            (Some(s), _) => Response {
                ok: true,
                revision: Some(s.netlist.revision),
                netlist: s.netlist.text.clone(),
                ..Response::default()
            },
        };
        self.finish(query, &r);
    }

    fn switch(&self, query: Query, task: String, key: Option<CommandKey>) {
        let dnm = self.dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<dnm_proto::SwitchRecord, String>| match r {
                Ok(s) => Response {
                    ok: true,
                    revision: Some(s.revision),
                    switches: vec![s],
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm}`: {e}")),
            },
        );
        self.hand(Command::Switch { task, key, reply }, slot);
    }

    fn apply(&self, query: Query, file: &str, text: &str, key: Option<CommandKey>) {
        let (system, dnm) = (self.system, self.dnm);
        let applies = self.shared.applies_in_flight.clone();
        if !admit(&applies, APPLIES_IN_FLIGHT, &self.shared.refused) {
            return self.finish(
                query,
                &Response::error(format!(
                    "DNM `{dnm}` is busy with {APPLIES_IN_FLIGHT} applies; send it again later (same id)"
                )),
            );
        }
        let release = {
            let applies = applies.clone();
            move || {
                applies.fetch_sub(1, Ordering::AcqRel);
            }
        };
        let netlist = match (self.parse)(Path::new(file), text) {
            Err(e) => {
                release();
                return self.finish(
                    query,
                    &Response::error(format!("netlist refused, nothing changed:\n{e}")),
                );
            }
            Ok(n) if n.system != system => {
                release();
                return self.finish(
                    query,
                    &Response::error(format!(
                        "netlist is for system `{}`, this is `{system}`; nothing changed",
                        n.system
                    )),
                );
            }
            Ok(n) => n,
        };
        let dnm_name = dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<u64, String>| {
                release();
                match r {
                    Ok(revision) => Response {
                        ok: true,
                        revision: Some(revision),
                        ..Response::default()
                    },
                    Err(e) => Response::error(format!("DNM `{dnm_name}`: {e}")),
                }
            },
        );
        if let Err(e) = self.commander.send(Command::Apply {
            netlist: Box::new(netlist),
            key,
            reply,
        }) {
            // The command (with its reply) came back unsent: free its apply slot here.
            applies.fetch_sub(1, Ordering::AcqRel);
            if let Some(q) = slot.lock().ok().and_then(|mut s| s.take()) {
                self.finish(q, &Response::error(format!("DNM `{dnm}`: {e}")));
            }
        }
    }

    fn prepare(
        &self,
        query: Query,
        txn: u64,
        revision: u64,
        task: Option<String>,
        file: Option<String>,
        text: Option<String>,
    ) {
        let dnm = self.dnm;
        // A DNM whose clock is off would put the decision in force at the wrong moment.
        let clock = self
            .shared
            .lease
            .lock()
            .ok()
            .and_then(|l| l.clock_refusal(dnm));
        if let Some(why) = clock {
            tracing::warn!(dnm, txn, "transaction refused: {why}");
            return self.finish(query, &Response::error(why));
        }
        let netlist = match text.map(|t| {
            let file = file.unwrap_or_else(|| "netlist.toml".into());
            parse_here(self.parse, self.system, &file, &t)
        }) {
            None => None,
            Some(Ok(n)) => Some(Box::new(n)),
            Some(Err(e)) => return self.finish(query, &Response::error(e)),
        };
        let dnm_name = dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<(), String>| match r {
                Ok(()) => Response {
                    ok: true,
                    revision: Some(revision),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm_name}`: {e}")),
            },
        );
        let txn = Txn {
            id: txn,
            revision,
            task,
            netlist,
        };
        self.hand(Command::Prepare { txn, reply }, slot);
    }

    fn decide(&self, query: Query, decision: Decision) {
        // A decision is sent shortly before its instant; one far ahead would keep the DNM
        // waiting (and its supervision quiet) for nothing.
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as u64);
        if decision.commit && decision.at_unix_ns > now + MAX_DECISION_AHEAD.as_nanos() as u64 {
            return self.finish(
                query,
                &Response::error(format!(
                    "decision {} is for {:.0} s from now; at most {} s ahead is taken \
                     (are the clocks synchronised?)",
                    decision.id,
                    (decision.at_unix_ns - now) as f64 / 1e9,
                    MAX_DECISION_AHEAD.as_secs()
                )),
            );
        }
        let (dnm, revision) = (self.dnm.to_string(), decision.revision);
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<Option<dnm_proto::SwitchRecord>, String>| match r {
                Ok(s) => Response {
                    ok: true,
                    revision: Some(revision),
                    switches: s.into_iter().collect(),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm}`: {e}")),
            },
        );
        self.hand(Command::Decide { decision, reply }, slot);
    }

    fn adopt(&self, query: Query, revision: u64, task: Option<String>, file: &str, text: &str) {
        let netlist = match parse_here(self.parse, self.system, file, text) {
            Ok(n) => n,
            Err(e) => return self.finish(query, &Response::error(e)),
        };
        let dnm = self.dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<u64, String>| match r {
                Ok(revision) => Response {
                    ok: true,
                    revision: Some(revision),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm}`: {e}")),
            },
        );
        let adopt = Command::Adopt {
            revision,
            task,
            netlist: Box::new(netlist),
            reply,
        };
        self.hand(adopt, slot);
    }
}

/// A netlist sent in a transaction, validated here and for this system.
fn parse_here(
    parse: &ParseNetlist,
    system: &str,
    file: &str,
    text: &str,
) -> Result<Netlist, String> {
    match parse(Path::new(file), text) {
        Ok(n) if n.system == system => Ok(n),
        Ok(n) => Err(format!(
            "netlist is for system `{}`, this is `{system}`",
            n.system
        )),
        Err(e) => Err(format!("netlist refused:\n{e}")),
    }
}

/// How far ahead of now a decided instant may be.
const MAX_DECISION_AHEAD: Duration = Duration::from_secs(60);

/// A reply for the DNM that hands the query back to the command thread with the response. The
/// query waits in a slot, so it can be answered here if the DNM never takes the command.
#[allow(clippy::type_complexity)]
fn answer_slot<T: Send + 'static>(
    tx: SyncSender<CommandJob>,
    query: Query,
    to_response: impl FnOnce(T) -> Response + Send + 'static,
) -> (Reply<T>, Arc<Mutex<Option<Query>>>) {
    let slot = Arc::new(Mutex::new(Some(query)));
    let held = slot.clone();
    let reply = Reply::new(move |v: T| {
        if let Some(q) = held.lock().ok().and_then(|mut s| s.take()) {
            // Never full: the channel has room for twice the commands admitted.
            let _ = tx.try_send(CommandJob::Answer(q, to_response(v)));
        }
    });
    (reply, slot)
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
    /// Subscribers (and listeners) its mirror port was made for.
    slots: usize,
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
            .map(from_wire)
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

    fn forward(&self) {
        let _ = self.listener.try_wait(|_| ());
        while let Ok(Some(s)) = self.subscriber.receive() {
            let payload = s.payload();
            let header = keys::encode_header(&to_wire(s.user_header()));
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

/// The newest netlist the running DNMs of `system` hold, if any answers within `timeout`.
/// A DNM that (re)starts into a running system continues from it.
pub(crate) fn newest_netlist_impl(
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

/// Whether mirror port `service` on `dnm`, made for `slots` subscribers, holds the readers
/// `netlist` gives it there beside the DNM's own subscribers.
fn room(service: &str, dnm: &str, netlist: &Netlist, slots: usize) -> Result<(), String> {
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
