//! A DNM on Zenoh: the routes the netlist needs between DNMs, and the DNM's answers to
//! Zenoh tools. Keys are in [`dnm_proto::keys`].
//!
//! - **Egress.** Every output of a local module that some task links to a module on another
//!   DNM is published on `<system>/port/<dnm>/<module>/<port>` by a thread that waits on the
//!   port's iceoryx2 event and lends each new sample to Zenoh without a copy. Outputs no remote
//!   input needs are not published.
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
use std::sync::atomic::Ordering;
use std::sync::mpsc::{self, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use std::thread::JoinHandle;

use dnm_core::worker::{Worker, WorkerStartError, dbg, err};
use dnm_core::{Commander, Context, DnmReport, Plugin, PluginPrepareError, Snapshot};
use dnm_module::protocol::{DnmConfigError, dnm_config, output_event, output_service};
use dnm_module::{event_service_for, port_service_for};
use dnm_netlist::{MessageType, Netlist, NetlistDoor, Wiring};

use crate::command::{CommandJob, command_loop};
use crate::egress::{Counters, EGRESS_EVENT, EgressRoute, egress_loop, room};
use crate::ingress::{Ingress, Mirror, output_message};
use crate::lease::lease_loop;
use crate::query::{QueryJob, Target, admit, query_loop};
use crate::shared::{COMMAND_QUEUE, QUERY_QUEUE, Shared, TsSvc};
use crate::watch::{WATCH_EVENT, WatchPort, watch_loop};
use dnm_proto::keys;
use dnm_proto::station::Beat;
use dnm_proto::{NetReport, NetlistState, PeerReport};
use iceoryx2::prelude::*;
use zenoh::Wait;
use zenoh::liveliness::LivelinessToken;
use zenoh::pubsub::Subscriber as ZSubscriber;
use zenoh::query::Queryable;
use zenoh::sample::SampleKind;

/// A DNM's presence on Zenoh, plugged into the DNM (see the module docs).
pub struct Bridge {
    pub(crate) session: zenoh::Session,
    pub(crate) system: String,
    pub(crate) dnm: String,
    pub(crate) shared: Arc<Shared>,
    pub(crate) ts_node: Node<TsSvc>,
    pub(crate) _token: LivelinessToken,
    /// Declared as the DNM stops in order; dropped after its presence token (fields drop in
    /// this order), so the others hear that it leaves before it is gone.
    pub(crate) leaving: Option<LivelinessToken>,
    pub(crate) _queryables: Vec<Queryable<()>>,
    pub(crate) _peer_watch: ZSubscriber<()>,
    pub(crate) ingress: BTreeMap<String, Ingress>,
    /// Mirrors made by the apply being prepared.
    pub(crate) prepared: Vec<String>,
    pub(crate) egress: Vec<EgressRoute>,
    pub(crate) egress_worker: Worker<EgressRoute>,
    pub(crate) watch: Vec<WatchPort>,
    pub(crate) watch_worker: Worker<WatchPort>,
    pub(crate) declared_dnms: Vec<String>,
    pub(crate) query_thread: Option<std::thread::JoinHandle<()>>,
    pub(crate) command_thread: Option<std::thread::JoinHandle<()>>,
    pub(crate) query_tx: Option<SyncSender<QueryJob>>,
    pub(crate) command_tx: Option<SyncSender<CommandJob>>,
    /// For the lease: it makes the DNM safe.
    pub(crate) commander: Commander,
    pub(crate) _beats: Option<ZSubscriber<()>>,
    pub(crate) lease_thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for Bridge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bridge")
            .field("system", &self.system)
            .field("dnm", &self.dnm)
            .finish_non_exhaustive()
    }
}

impl Bridge {
    /// Takes switches and applies only from the system's authority `dnm` (see
    /// `dnm-authority`); other clients are told to go through a ground station. Keeps a lease
    /// on it (see [`crate::lease`]): the DNM makes itself safe when it must, whoever is down.
    pub fn follow_authority(mut self, dnm: &str) -> Result<Self, BridgeStartError> {
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
                .map_err(zenoh_err("subscribing to the authority's beat"))?
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
                .map_err(thread_err("lease"))?
        };
        self._beats = Some(beats);
        self.lease_thread = Some(thread);
        Ok(self)
    }

    /// Declares the DNM on `session`: its liveliness token, queryables, the watch on the other
    /// DNMs, and the threads that answer queries and commands. `commander` reaches the DNM;
    /// `door` takes the netlists sent in commands.
    pub fn new(
        session: zenoh::Session,
        system: &str,
        dnm: &str,
        prefix: &str,
        commander: Commander,
        door: NetlistDoor,
    ) -> Result<Self, BridgeStartError> {
        let config = dnm_config(prefix)?;
        let ts_node = NodeBuilder::new()
            .config(&config)
            .create::<TsSvc>()
            .map_err(BridgeStartError::Node)?;
        let shared = Arc::new(Shared::default());
        let (query_thread, query_tx) =
            spawn_query_thread(&session, system, dnm, prefix, &shared, commander.clone())?;
        let lease_commander = commander.clone();
        let (command_thread, command_tx) =
            spawn_command_thread(system, dnm, &shared, commander, door)?;
        let queryables =
            declare_queryables(&session, system, dnm, &shared, &query_tx, &command_tx)?;
        let token = session
            .liveliness()
            .declare_token(keys::dnm(system, dnm))
            .wait()
            .map_err(zenoh_err("declaring liveliness token"))?;
        let peer_watch = watch_peers(&session, system, dnm, &shared)?;
        let (egress_worker, watch_worker) = start_workers(&session, system, dnm, prefix)?;
        Ok(Self {
            session,
            system: system.into(),
            dnm: dnm.into(),
            shared,
            ts_node,
            _token: token,
            leaving: None,
            _queryables: queryables,
            _peer_watch: peer_watch,
            ingress: BTreeMap::new(),
            prepared: Vec::new(),
            egress: Vec::new(),
            egress_worker,
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

    /// Wakes the query thread to follow the running modules and the local outputs: one `Look`
    /// queued at a time, in a slot of its own beyond the queries' (a queued one is enough: the
    /// thread reads the newest state when it takes it).
    fn tell_query_thread(&self) {
        if self.shared.look_pending.swap(true, Ordering::AcqRel) {
            return;
        }
        if let Some(tx) = &self.query_tx
            && tx.try_send(QueryJob::Look).is_err()
        {
            self.shared.look_pending.store(false, Ordering::Release);
        }
    }

    /// Every other DNM of the netlist and how it looks from here.
    fn peer_reports(&self) -> Vec<PeerReport> {
        let peers = self
            .shared
            .peers
            .lock()
            .map(|p| p.clone())
            .unwrap_or_default();
        let left = self
            .shared
            .leaving
            .lock()
            .map(|l| l.clone())
            .unwrap_or_default();
        let mut names: BTreeSet<String> = peers.keys().cloned().collect();
        names.extend(self.declared_dnms.iter().cloned());
        names.remove(&self.dnm);
        names
            .into_iter()
            .map(|name| match peers.get(&name) {
                Some((alive, since)) => PeerReport {
                    state: match (*alive, left.contains(&name)) {
                        (true, _) => "alive",
                        // It said it stopped in order.
                        (false, true) => "left",
                        (false, false) => "lost",
                    }
                    .into(),
                    dnm: name,
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

/// Why a DNM could not go on Zenoh: which part of its bridge failed.
#[derive(Debug, thiserror::Error)]
pub enum BridgeStartError {
    #[error(transparent)]
    Config(#[from] DnmConfigError),
    #[error("zenoh bridge node: {0}")]
    Node(#[source] iceoryx2::node::NodeCreationFailure),
    #[error("spawning the {what} thread: {source}")]
    Thread {
        what: &'static str,
        #[source]
        source: std::io::Error,
    },
    #[error("{what}: {source}")]
    Zenoh {
        what: &'static str,
        #[source]
        source: zenoh::Error,
    },
    #[error(transparent)]
    Worker(#[from] WorkerStartError),
}

fn zenoh_err(what: &'static str) -> impl FnOnce(zenoh::Error) -> BridgeStartError {
    move |source| BridgeStartError::Zenoh { what, source }
}

fn thread_err(what: &'static str) -> impl FnOnce(std::io::Error) -> BridgeStartError {
    move |source| BridgeStartError::Thread { what, source }
}

/// Where queryables hand the query thread their queries.
type QueryQueue = SyncSender<QueryJob>;

/// The query thread and the queue its queryables feed.
fn spawn_query_thread(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    prefix: &str,
    shared: &Arc<Shared>,
    commander: Commander,
) -> Result<(JoinHandle<()>, QueryQueue), BridgeStartError> {
    let (query_tx, query_rx) = mpsc::sync_channel::<QueryJob>(QUERY_QUEUE + 1);
    let shared = shared.clone();
    let session = session.clone();
    let (system, dnm, prefix) = (system.to_string(), dnm.to_string(), prefix.to_string());
    let thread = std::thread::Builder::new()
        .name(format!("zenoh-queries-{dnm}"))
        .spawn(move || {
            query_loop(
                &session, &system, &dnm, &prefix, &shared, &commander, &query_rx,
            )
        })
        .map_err(thread_err("query"))?;
    Ok((thread, query_tx))
}

/// The command thread and the queue its queryable (and the DNM's answers) feed.
fn spawn_command_thread(
    system: &str,
    dnm: &str,
    shared: &Arc<Shared>,
    commander: Commander,
    door: NetlistDoor,
) -> Result<(JoinHandle<()>, SyncSender<CommandJob>), BridgeStartError> {
    let (command_tx, command_rx) = mpsc::sync_channel::<CommandJob>(COMMAND_QUEUE * 2);
    let shared = shared.clone();
    let tx = command_tx.clone();
    let (system, dnm) = (system.to_string(), dnm.to_string());
    let thread = std::thread::Builder::new()
        .name(format!("zenoh-commands-{dnm}"))
        .spawn(move || command_loop(&system, &dnm, &shared, &commander, &door, &tx, &command_rx))
        .map_err(thread_err("command"))?;
    Ok((thread, command_tx))
}

/// The DNM's queryables: its state, netlist, wiring, modules and ports for the query thread,
/// its commands for the command thread. Beyond their queues, queries are refused and counted.
fn declare_queryables(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    shared: &Arc<Shared>,
    query_tx: &SyncSender<QueryJob>,
    command_tx: &SyncSender<CommandJob>,
) -> Result<Vec<Queryable<()>>, BridgeStartError> {
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
                    && tx.try_send(QueryJob::Answer(target, q)).is_err()
                {
                    shared.queries_in_flight.fetch_sub(1, Ordering::Relaxed);
                    shared.refused.fetch_add(1, Ordering::Relaxed);
                }
            })
            .wait()
            .map_err(zenoh_err("declaring queryable"))?;
        queryables.push(q);
    }
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
        .map_err(zenoh_err("declaring queryable"))?;
    queryables.push(q);
    Ok(queryables)
}

/// Follows the other DNMs of the system by their liveliness tokens.
fn watch_peers(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    shared: &Arc<Shared>,
) -> Result<ZSubscriber<()>, BridgeStartError> {
    let system = system.to_string();
    let me = dnm.to_string();
    let shared = shared.clone();
    session
        .liveliness()
        .declare_subscriber(keys::dnms_coming_and_going(&system))
        .history(true)
        .callback(move |s| {
            let Some((name, leaving_token)) = keys::presence_of(&system, s.key_expr().as_str())
            else {
                return;
            };
            if name == me {
                return;
            }
            let put = s.kind() == SampleKind::Put;
            let Ok(mut leaving) = shared.leaving.lock() else {
                return;
            };
            if leaving_token {
                // Its presence goes next: that is a DNM stopping in order.
                if put && leaving.len() < MAX_PEERS {
                    leaving.insert(name);
                }
                return;
            }
            let left = !put && leaving.contains(&name);
            if put {
                leaving.remove(&name);
            }
            drop(leaving);
            let Ok(mut peers) = shared.peers.lock() else {
                return;
            };
            if peers.get(&name).is_none_or(|(a, _)| *a != put) {
                match (put, left) {
                    (true, _) => tracing::info!(dnm = %me, peer = %name, "DNM joined"),
                    (false, true) => tracing::info!(dnm = %me, peer = %name, "DNM left"),
                    (false, false) => tracing::warn!(dnm = %me, peer = %name, "DNM lost"),
                }
                if peers.contains_key(&name) || make_room(&mut peers) {
                    peers.insert(name, (put, Instant::now()));
                }
            }
        })
        .wait()
        .map_err(zenoh_err("watching DNMs"))
}

/// DNMs of the system a DNM keeps track of, at most (a netlist names far fewer; tokens of
/// other names past it are not followed).
const MAX_PEERS: usize = 256;

/// Whether `peers` has room for one more, after forgetting the DNM gone longest ago if full.
fn make_room(peers: &mut BTreeMap<String, (bool, Instant)>) -> bool {
    if peers.len() < MAX_PEERS {
        return true;
    }
    let oldest_gone = peers
        .iter()
        .filter(|(_, (alive, _))| !alive)
        .min_by_key(|(_, (_, since))| *since)
        .map(|(name, _)| name.clone());
    oldest_gone.is_some_and(|name| peers.remove(&name).is_some())
}

/// The egress thread and the watch thread, each serving the set of ports it is sent.
fn start_workers(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    prefix: &str,
) -> Result<(Worker<EgressRoute>, Worker<WatchPort>), BridgeStartError> {
    let egress = {
        let session = session.clone();
        Worker::spawn(
            format!("egress-{dnm}"),
            prefix,
            EGRESS_EVENT,
            move |control| egress_loop(&session, &control),
        )?
    };
    let watch = {
        let session = session.clone();
        let (system, dnm, p) = (system.to_string(), dnm.to_string(), prefix.to_string());
        Worker::spawn(
            format!("watch-{dnm}"),
            prefix,
            WATCH_EVENT,
            move |control| watch_loop(&session, &system, &dnm, &p, &control),
        )?
    };
    Ok((egress, watch))
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
    ) -> Result<(), PluginPrepareError> {
        self.prepared.clear();
        for (service, key, message) in self.wanted_ingress(netlist) {
            if let Some(kept) = self.ingress.get(&service) {
                // A mirror kept across the apply must have room for its readers in this one.
                if let Err(e) = room(&service, &self.dnm, netlist, kept.slots) {
                    for s in self.prepared.drain(..) {
                        self.ingress.remove(&s);
                    }
                    return Err(e.into());
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
                    return Err(e.into());
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
        self.tell_query_thread();
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
        let before = self.shared.set_snapshot(snapshot);
        // The query thread follows the running modules: told when they change.
        fn running(s: &Snapshot) -> impl Iterator<Item = &str> {
            s.report
                .modules
                .iter()
                .filter(|m| m.state == dnm_proto::ModuleRunState::Running)
                .map(|m| m.name.as_str())
        }
        if before.is_none_or(|b| !running(&b).eq(running(snapshot))) {
            self.tell_query_thread();
        }
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        // Stopping in order: the others hear it before this DNM's presence goes.
        let leaving = self
            .session
            .liveliness()
            .declare_token(keys::dnm_leaving(&self.system, &self.dnm))
            .wait();
        self.leaving = leaving.ok();
        // Queryables first, so nothing new arrives; then the threads end.
        self._queryables.clear();
        self.shared.stop.store(true, Ordering::Relaxed);
        // A question waiting for a snapshot this DNM will no longer make is answered now.
        {
            let _held = self.shared.snapshot.lock();
            self.shared.fresh.notify_all();
        }
        self.query_tx.take();
        if let Some(tx) = self.command_tx.take() {
            let _ = tx.try_send(CommandJob::Stop);
        }
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

#[cfg(test)]
mod peer_tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn the_peers_kept_are_bounded_and_the_longest_gone_make_room() {
        let mut peers = BTreeMap::new();
        let t0 = Instant::now();
        for i in 0..MAX_PEERS {
            let since = t0 + Duration::from_millis(i as u64);
            // Every tenth is gone; the first of them went longest ago.
            peers.insert(format!("dnm{i}"), (i % 10 != 0, since));
        }
        assert!(make_room(&mut peers));
        assert!(!peers.contains_key("dnm0"));
        assert!(peers.contains_key("dnm10"));
        assert_eq!(peers.len(), MAX_PEERS - 1);
        // All alive: no room is made, nobody is forgotten.
        for (_, (alive, _)) in peers.iter_mut() {
            *alive = true;
        }
        peers.insert("another".into(), (true, t0));
        assert!(!make_room(&mut peers));
        assert_eq!(peers.len(), MAX_PEERS);
    }
}
