//! One DNM: hosts its modules as processes, holds the netlist, prepares every reference a
//! defined task needs when a netlist is applied, and switches tasks with one store into the
//! shared task word.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::Child;
use std::sync::mpsc::{Receiver, SyncSender};
use std::time::{Duration, Instant};

use dnm_module::protocol::*;
use dnm_module::{event_service, plan_service_factory, port_service, status_service_factory};
use dnm_netlist::{KindSource, KindSpec, Netlist, RestartMode};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::port::writer::{EntryHandleMut, Writer};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::blackboard::PortFactory as BlackboardFactory;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;
use iceoryx2::waitset::WaitSetRunResult;
use serde::{Deserialize, Serialize};

use crate::net::{Inbound, Net, NetReport, PeerReport, Target, ZenohCommand};
use crate::plan::{module_plan, task_slots};
use crate::procfs::{self, CpuMeter, Memory};

type Svc = ipc::Service;

/// Failures of DNM operations. Each leaves the running system as it was.
#[derive(Debug, thiserror::Error)]
pub enum DnmError {
    #[error("shared memory: {0}")]
    Ipc(String),
    #[error(
        "DNM `{dnm}` of system `{system}` is already running on this machine (its task word exists); stop it first"
    )]
    AlreadyRunning { system: String, dnm: String },
    #[error("unknown task `{task}`; defined tasks: {known}")]
    UnknownTask { task: String, known: String },
    #[error("no netlist applied yet")]
    NoNetlist,
    #[error(
        "netlist does not declare DNM `{0}`, which this process hosts; keep it or stop this DNM first"
    )]
    DnmMissing(String),
    #[error(
        "modules did not prepare revision {revision} within {timeout_ms} ms: {modules}; the previous revision stays active"
    )]
    PrepareTimeout {
        revision: u64,
        timeout_ms: u128,
        modules: String,
    },
    #[error("zenoh: {0}")]
    Zenoh(String),
    #[error("cannot start module `{module}` ({exec}): {why}")]
    Spawn {
        module: String,
        exec: String,
        why: String,
    },
}

fn ipc<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> DnmError {
    move |e| DnmError::Ipc(format!("{what}: {e:?}"))
}

/// Set when this process was asked to terminate; every DNM loop of the process stops.
static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Asks every DNM loop of this process to stop (as SIGTERM does).
pub(crate) fn request_stop() {
    STOP.store(true, std::sync::atomic::Ordering::Relaxed);
}

/// How a DNM runs its modules.
#[derive(Debug, Clone)]
pub struct DnmOptions {
    /// Executable that runs built-in kinds (`dnm-module-host`).
    pub module_host: PathBuf,
    /// How long modules get to prepare a new revision.
    pub prepare_timeout: Duration,
    /// Supervision period: exits, restarts, CPU readings.
    pub tick: Duration,
    /// Record every output port to MCAP (see [`crate::record`]); `None`: no recording.
    pub record: Option<crate::record::RecordOptions>,
}

/// Lifecycle of a hosted module, as the DNM sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModuleRunState {
    Starting,
    Running,
    /// Exited or crashed; restarts per its policy.
    Failed,
    /// Stopped on purpose, or failed past its restart budget.
    Stopped,
}

/// What the DNM knows about one module.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleReport {
    pub name: String,
    pub kind: String,
    pub state: ModuleRunState,
    pub pid: Option<u32>,
    pub restarts: u32,
    pub last_exit: Option<String>,
    pub plan_revision: u64,
    pub steps: u64,
    pub sent: u64,
    pub step_errors: u64,
    /// Steps per second over the last second.
    pub rate_hz: f64,
    /// Time since the module's last step, ms.
    pub last_step_age_ms: Option<u64>,
    pub cpu_percent: f64,
    pub memory: Option<Memory>,
}

/// A task switch, as performed.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SwitchRecord {
    /// The DNM that switched.
    #[serde(default)]
    pub dnm: String,
    pub revision: u64,
    pub from: Option<String>,
    pub to: String,
    /// Time to perform the switch inside the DNM (lookup and the store), ns.
    pub duration_ns: u64,
    /// CLOCK_MONOTONIC time of the switch, ns.
    pub at_ns: u64,
}

/// The state of one DNM, for operators and tools.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DnmReport {
    pub system: String,
    pub dnm: String,
    pub pid: u32,
    pub revision: u64,
    pub netlist_digest: String,
    pub netlist_file: Option<String>,
    pub active_task: Option<String>,
    pub tasks: Vec<String>,
    pub cpu_percent: f64,
    pub memory: Option<Memory>,
    pub modules: Vec<ModuleReport>,
    pub switches: Vec<SwitchRecord>,
    /// Shared-memory leftovers of dead processes removed so far.
    pub cleaned_dead_nodes: u64,
    /// The other DNMs of the system, as seen over Zenoh (empty without Zenoh).
    #[serde(default)]
    pub peers: Vec<PeerReport>,
    /// Traffic of the routes to and from other DNMs.
    #[serde(default)]
    pub routes: NetReport,
    /// The recorder's progress, when recording.
    #[serde(default)]
    pub recording: Option<crate::record::RecordReport>,
}

/// Commands a DNM's loop takes from other threads.
#[derive(Debug)]
pub enum Command {
    Status(SyncSender<DnmReport>),
    Switch(String, SyncSender<Result<SwitchRecord, String>>),
    Apply(Box<Netlist>, SyncSender<Result<u64, String>>),
    Netlist(SyncSender<crate::net::NetlistState>),
}

struct ModuleSlot {
    decl: dnm_netlist::Module,
    spec: KindSpec,
    source: KindSource,
    plan_pub: Publisher<Svc, [u8], ()>,
    wake: Notifier<Svc>,
    status_sub: Subscriber<Svc, Status, ()>,
    child: Option<Child>,
    state: ModuleRunState,
    restarts: u32,
    restart_at: Option<Instant>,
    last_exit: Option<String>,
    status: Status,
    rate: (Instant, u64, f64),
    cpu: CpuMeter,
}

impl ModuleSlot {
    fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }
}

/// Keeps an output port's services alive while the DNM runs, so they outlive module restarts.
#[allow(dead_code)]
struct PortServices {
    data: PubSubFactory<Svc, [u8], PortHeader>,
    event: EventFactory<Svc>,
}

/// A database node module.
pub struct Dnm {
    system: String,
    name: String,
    prefix: String,
    options: DnmOptions,
    node: Node<Svc>,
    _board: BlackboardFactory<Svc, u64>,
    _writer: Writer<Svc, u64>,
    word: EntryHandleMut<Svc, u64, u64>,
    _dnm_event: EventFactory<Svc>,
    ports: BTreeMap<String, PortServices>,
    modules: BTreeMap<String, ModuleSlot>,
    netlist: Option<Netlist>,
    revision: u64,
    tasks: Vec<String>,
    active: Option<String>,
    switches: Vec<SwitchRecord>,
    cpu: CpuMeter,
    cleaned: u64,
    net: Option<Net>,
    recorder: Option<crate::record::Recorder>,
    /// Answers to the last Zenoh commands, by id, so a retried command is applied once.
    answered: std::collections::VecDeque<(String, crate::admin::Response)>,
}

impl std::fmt::Debug for Dnm {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Dnm")
            .field("system", &self.system)
            .field("name", &self.name)
            .field("revision", &self.revision)
            .finish_non_exhaustive()
    }
}

impl Dnm {
    /// Opens this DNM's shared-memory namespace, removing leftovers of dead processes in it.
    pub fn new(system: &str, name: &str, options: DnmOptions) -> Result<Self, DnmError> {
        let prefix = dnm_prefix(system, name);
        let config = dnm_config(&prefix).map_err(DnmError::Ipc)?;
        let node_name: NodeName = format!("dnm-{name}")
            .as_str()
            .try_into()
            .map_err(ipc("node name"))?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .create::<Svc>()
            .map_err(ipc("node"))?;
        let cleaned = node.try_cleanup_dead_nodes().cleanups;
        if cleaned > 0 {
            tracing::info!(
                dnm = name,
                cleaned,
                "removed shared memory of dead processes"
            );
        }
        let board_name: ServiceName = TASK_SERVICE.try_into().map_err(ipc("service name"))?;
        let board = node
            .service_builder(&board_name)
            .blackboard_creator::<u64>()
            .max_readers(MAX_MODULES)
            .max_nodes(MAX_MODULES)
            .add::<u64>(0, task_word(0, NO_TASK))
            .create()
            .map_err(|e| {
                tracing::debug!("blackboard create: {e:?}");
                DnmError::AlreadyRunning {
                    system: system.into(),
                    dnm: name.into(),
                }
            })?;
        let writer = board
            .writer_builder()
            .create()
            .map_err(ipc("task writer"))?;
        let word = writer.entry::<u64>(&0).map_err(ipc("task entry"))?;
        let dnm_event =
            event_service(&node, DNM_EVENT).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let options_record = options.record.clone();
        let prefix_for_recorder = prefix.clone();
        Ok(Self {
            system: system.into(),
            name: name.into(),
            prefix,
            options,
            node,
            _board: board,
            _writer: writer,
            word,
            _dnm_event: dnm_event,
            ports: BTreeMap::new(),
            modules: BTreeMap::new(),
            netlist: None,
            revision: 0,
            tasks: Vec::new(),
            active: None,
            switches: Vec::new(),
            cpu: CpuMeter::default(),
            cleaned,
            net: None,
            recorder: match &options_record {
                Some(r) => Some(
                    crate::record::Recorder::start(name, &prefix_for_recorder, r.clone())
                        .map_err(DnmError::Ipc)?,
                ),
                None => None,
            },
            answered: std::collections::VecDeque::new(),
        })
    }

    /// Puts this DNM on Zenoh: it answers queries, announces itself and its modules, and
    /// routes the links that cross to other DNMs. Call before the first [`Dnm::apply`].
    pub fn attach_zenoh(&mut self, session: zenoh::Session) -> Result<(), DnmError> {
        self.net = Some(
            Net::new(session, &self.system, &self.name, &self.prefix).map_err(DnmError::Zenoh)?,
        );
        Ok(())
    }

    /// Continues a running system: the next apply yields `revision + 1` and starts in `task`
    /// (if its netlist defines it) instead of the netlist's initial task.
    pub fn continue_from(&mut self, revision: u64, task: Option<&str>) {
        self.revision = self.revision.max(revision);
        if self.netlist.is_none() {
            self.active = task.map(str::to_string);
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    /// The iceoryx2 file prefix of this DNM's namespace.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// A listener for module status notifications; the caller owns it so it can be attached to
    /// a WaitSet while the DNM is borrowed mutably.
    pub fn status_listener(&self) -> Result<Listener<Svc>, DnmError> {
        event_service(&self.node, DNM_EVENT)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .listener_builder()
            .create()
            .map_err(ipc("status listener"))
    }

    /// Applies a netlist: starts added modules, prepares every reference of every task in
    /// all modules, then commits the new revision with one store. Modules it drops are stopped
    /// and changed ones replaced after the commit. On error nothing running changes.
    pub fn apply(&mut self, netlist: &Netlist, events: &Listener<Svc>) -> Result<u64, DnmError> {
        if netlist.dnm(&self.name).is_none() {
            return Err(DnmError::DnmMissing(self.name.clone()));
        }
        let revision = self.revision + 1;
        let me = self.name.clone();
        let wanted: BTreeMap<&str, &dnm_netlist::Module> = netlist
            .modules_on(&me)
            .map(|m| (m.name.as_str(), m))
            .collect();
        let removed: Vec<String> = self
            .modules
            .keys()
            .filter(|m| !wanted.contains_key(m.as_str()))
            .cloned()
            .collect();
        let replaced: Vec<String> = self
            .modules
            .iter()
            .filter(|(name, slot)| wanted.get(name.as_str()).is_some_and(|m| **m != slot.decl))
            .map(|(n, _)| n.clone())
            .collect();
        let added: Vec<&str> = wanted
            .keys()
            .filter(|m| !self.modules.contains_key(**m))
            .copied()
            .collect();

        // 1. Output services of new and replaced modules exist before anyone subscribes.
        for name in added
            .iter()
            .copied()
            .chain(replaced.iter().map(String::as_str))
        {
            let spec = netlist
                .kind_of(name)
                .ok_or_else(|| DnmError::Ipc(format!("no kind for {name}")))?;
            for port in &spec.outputs {
                self.ensure_port(name, &port.name, &port.message.payload)?;
            }
        }
        // Remote outputs any task links here are mirrored into this namespace.
        let local_outputs: std::collections::BTreeSet<String> = self
            .modules
            .values()
            .flat_map(|m| {
                m.spec
                    .outputs
                    .iter()
                    .map(|p| output_service(&m.decl.name, &p.name))
            })
            .collect();
        let prepared = match self.net.as_mut() {
            Some(net) => net
                .prepare_ingress(netlist, &local_outputs)
                .map_err(DnmError::Zenoh)?,
            None => Vec::new(),
        };
        let result = self.apply_prepared(netlist, revision, removed, replaced, added, events);
        // Mirrors are dropped only if the revision was not committed (a replacement failing
        // after the commit leaves the new revision, and its routes, in force).
        if result.is_err() && self.revision != revision {
            if let Some(net) = self.net.as_mut() {
                net.abort(&prepared);
            }
        }
        result
    }

    fn apply_prepared(
        &mut self,
        netlist: &Netlist,
        revision: u64,
        removed: Vec<String>,
        replaced: Vec<String>,
        added: Vec<&str>,
        events: &Listener<Svc>,
    ) -> Result<u64, DnmError> {
        // 2. New modules: control services, then the process.
        let mut started = Vec::new();
        for name in &added {
            match self.add_module(netlist, name) {
                Ok(()) => started.push(name.to_string()),
                Err(e) => {
                    for s in &started {
                        self.stop_module(s);
                    }
                    return Err(e);
                }
            }
        }
        // 3. Every module gets its plan and prepares it.
        for (name, slot) in &self.modules {
            let plan = module_plan(netlist, name, revision);
            if let Err(e) = post_plan(slot, &plan) {
                for s in &started {
                    self.stop_module(s);
                }
                return Err(e);
            }
        }
        if let Err(e) = self.await_prepared(revision, events) {
            for s in &started {
                self.stop_module(s);
            }
            return Err(e);
        }
        // 4. Commit: the active task carries over if the new netlist still defines it.
        let tasks = task_slots(netlist);
        let task = self
            .active
            .clone()
            .filter(|t| tasks.contains(t))
            .or_else(|| netlist.initial_task().map(str::to_string));
        let slot = task
            .as_ref()
            .and_then(|t| tasks.iter().position(|x| x == t))
            .map_or(NO_TASK, |s| s as u16);
        self.word.update_with_copy(task_word(revision, slot));
        self.revision = revision;
        self.tasks = tasks;
        self.active = task;
        self.netlist = Some(netlist.clone());
        // 5. Removals and replacements.
        for name in removed {
            self.stop_module(&name);
            self.modules.remove(&name);
        }
        for name in replaced {
            self.stop_module(&name);
            self.modules.remove(&name);
            self.add_module(netlist, &name)?;
            if let Some(slot) = self.modules.get(&name) {
                post_plan(slot, &module_plan(netlist, &name, revision))?;
            }
        }
        // 6. Routes to and from other DNMs, and the recording, follow the committed revision.
        if let Some(net) = self.net.as_mut() {
            net.commit(netlist, &self.node);
        }
        if let Some(rec) = self.recorder.as_mut() {
            rec.commit(netlist, &self.name, revision);
        }
        tracing::info!(dnm = %self.name, revision, task = ?self.active, "netlist applied");
        Ok(revision)
    }

    /// Switches the active task: one store of the task word. Everything the task needs was
    /// prepared when the netlist was applied.
    pub fn switch(&mut self, task: &str) -> Result<SwitchRecord, DnmError> {
        let start = Instant::now();
        let slot =
            self.tasks
                .iter()
                .position(|t| t == task)
                .ok_or_else(|| DnmError::UnknownTask {
                    task: task.into(),
                    known: self.tasks.join(", "),
                })?;
        self.word
            .update_with_copy(task_word(self.revision, slot as u16));
        let duration_ns = start.elapsed().as_nanos() as u64;
        let record = SwitchRecord {
            dnm: self.name.clone(),
            revision: self.revision,
            from: self.active.replace(task.to_string()),
            to: task.to_string(),
            duration_ns,
            at_ns: monotonic_ns(),
        };
        for slot in self.modules.values() {
            // Wake modules that wait for input so they re-read their sources now.
            let _ = slot.wake.notify();
        }
        if let Some(rec) = &self.recorder {
            rec.switch(&record);
        }
        self.switches.push(record.clone());
        if self.switches.len() > 64 {
            self.switches.remove(0);
        }
        tracing::info!(dnm = %self.name, task, duration_ns, "task switched");
        Ok(record)
    }

    fn ensure_port(
        &mut self,
        module: &str,
        port: &str,
        payload: &dnm_netlist::Payload,
    ) -> Result<(), DnmError> {
        let key = output_service(module, port);
        if self.ports.contains_key(&key) {
            return Ok(());
        }
        let data =
            port_service(&self.node, &key, payload).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let event = event_service(&self.node, &output_event(module, port))
            .map_err(|e| DnmError::Ipc(e.to_string()))?;
        self.ports.insert(key, PortServices { data, event });
        Ok(())
    }

    fn add_module(&mut self, netlist: &Netlist, name: &str) -> Result<(), DnmError> {
        let decl = netlist
            .module(name)
            .ok_or_else(|| DnmError::Ipc(format!("module {name} vanished")))?
            .clone();
        let entry = netlist
            .catalog
            .get(&decl.kind)
            .ok_or_else(|| DnmError::Ipc(format!("kind {} vanished", decl.kind)))?
            .clone();
        let plan_pub = plan_service_factory(&self.node, name)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .publisher_builder()
            .initial_max_slice_len(MAX_PLAN_BYTES)
            .create()
            .map_err(ipc("plan publisher"))?;
        let wake = event_service(&self.node, &wake_event(name))
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .notifier_builder()
            .create()
            .map_err(ipc("wake notifier"))?;
        let status_sub = status_service_factory(&self.node, name)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .subscriber_builder()
            .create()
            .map_err(ipc("status subscriber"))?;
        let mut slot = ModuleSlot {
            decl,
            spec: entry.spec,
            source: entry.source,
            plan_pub,
            wake,
            status_sub,
            child: None,
            state: ModuleRunState::Starting,
            restarts: 0,
            restart_at: None,
            last_exit: None,
            status: Status::default(),
            rate: (Instant::now(), 0, 0.0),
            cpu: CpuMeter::default(),
        };
        // The current plan is posted before the process starts, so it finds it in history.
        if self.netlist.is_some() {
            post_plan(&slot, &module_plan(netlist, name, self.revision))?;
        }
        self.spawn(&mut slot)?;
        self.modules.insert(name.to_string(), slot);
        Ok(())
    }

    fn spawn(&self, slot: &mut ModuleSlot) -> Result<(), DnmError> {
        let trigger = match (slot.spec.trigger, slot.decl.rate_hz) {
            (dnm_netlist::Trigger::Periodic { .. }, Some(rate_hz)) => {
                dnm_netlist::Trigger::Periodic { rate_hz }
            }
            (t, _) => t,
        };
        let launch = Launch {
            system: self.system.clone(),
            dnm: self.name.clone(),
            prefix: self.prefix.clone(),
            module: slot.decl.name.clone(),
            kind: slot.decl.kind.clone(),
            params: slot.decl.params.clone(),
            trigger,
        };
        let exec = match &slot.source {
            KindSource::BuiltIn => self.options.module_host.clone(),
            KindSource::Exec { path } => PathBuf::from(path),
        };
        let json = serde_json::to_string(&launch).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let mut command = std::process::Command::new(&exec);
        command.arg("run").arg(json);
        // A module must not outlive its DNM: if the DNM's thread dies (even by SIGKILL of the
        // whole process), the kernel sends the module SIGTERM.
        // SAFETY: prctl is async-signal-safe and touches only the child's own state.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut command, || {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = command.spawn().map_err(|e| DnmError::Spawn {
            module: slot.decl.name.clone(),
            exec: exec.display().to_string(),
            why: e.to_string(),
        })?;
        tracing::info!(dnm = %self.name, module = %slot.decl.name, pid = child.id(), "module started");
        slot.child = Some(child);
        slot.state = ModuleRunState::Starting;
        Ok(())
    }

    /// Asks a module to exit (SIGTERM), then kills it if it has not after a grace period.
    fn stop_module(&mut self, name: &str) {
        let Some(slot) = self.modules.get_mut(name) else {
            return;
        };
        slot.state = ModuleRunState::Stopped;
        let Some(mut child) = slot.child.take() else {
            return;
        };
        terminate(&mut child, Duration::from_secs(2));
        tracing::info!(dnm = %self.name, module = name, "module stopped");
    }

    fn read_statuses(&mut self) {
        for slot in self.modules.values_mut() {
            while let Ok(Some(s)) = slot.status_sub.receive() {
                // Heartbeats of a process we already replaced are ignored.
                if Some(s.pid) == slot.pid() {
                    slot.status = *s;
                    if slot.state == ModuleRunState::Starting
                        && ModuleState::from_u32(s.state) == ModuleState::Running
                    {
                        slot.state = ModuleRunState::Running;
                    }
                }
            }
        }
    }

    fn await_prepared(&mut self, revision: u64, events: &Listener<Svc>) -> Result<(), DnmError> {
        let deadline = Instant::now() + self.options.prepare_timeout;
        loop {
            self.read_statuses();
            self.supervise();
            let waiting: Vec<&str> = self
                .modules
                .iter()
                .filter(|(_, s)| s.child.is_some() && s.status.plan_revision < revision)
                .map(|(n, _)| n.as_str())
                .collect();
            for name in &waiting {
                // A module that subscribed after the plan was posted gets it (as history) only
                // when the publisher updates its connections; then it needs a wake-up.
                let slot = &self.modules[*name];
                let _ = slot.plan_pub.update_connections();
                let _ = slot.wake.notify();
            }
            if waiting.is_empty() {
                return Ok(());
            }
            let now = Instant::now();
            if now >= deadline {
                return Err(DnmError::PrepareTimeout {
                    revision,
                    timeout_ms: self.options.prepare_timeout.as_millis(),
                    modules: waiting.join(", "),
                });
            }
            // Blocks until a module posts a status (or 50 ms pass, to notice exits).
            let wait = (deadline - now).min(Duration::from_millis(50));
            events
                .timed_wait(|_| (), wait)
                .map_err(ipc("wait for modules"))?;
        }
    }

    /// Notices exited modules, restarts them per policy, cleans up after the dead.
    fn supervise(&mut self) {
        let mut any_died = false;
        for (name, slot) in self.modules.iter_mut() {
            let Some(child) = slot.child.as_mut() else {
                continue;
            };
            match child.try_wait() {
                Ok(Some(exit)) => {
                    any_died = true;
                    slot.child = None;
                    slot.last_exit = Some(exit.to_string());
                    let restart = match slot.decl.restart.mode {
                        RestartMode::Always => true,
                        RestartMode::OnFailure => !exit.success(),
                        RestartMode::Never => false,
                    } && slot.restarts < slot.decl.restart.max_restarts;
                    slot.state = if restart {
                        ModuleRunState::Failed
                    } else {
                        ModuleRunState::Stopped
                    };
                    if restart {
                        // Back off: 100 ms, doubling to at most 5 s.
                        let backoff = Duration::from_millis(100 << slot.restarts.min(6))
                            .min(Duration::from_secs(5));
                        slot.restart_at = Some(Instant::now() + backoff);
                    }
                    tracing::warn!(dnm = %self.name, module = %name, %exit, restart, "module exited");
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(module = %name, "cannot poll module process: {e}"),
            }
        }
        for slot in self.modules.values() {
            if slot.state == ModuleRunState::Starting && slot.child.is_some() {
                // A (re)started process finds its plan as history once the publisher updates
                // its connections; then it needs a wake-up to read it.
                let _ = slot.plan_pub.update_connections();
                let _ = slot.wake.notify();
            }
        }
        if any_died {
            let c = self.node.try_cleanup_dead_nodes();
            self.cleaned += c.cleanups;
        }
        let now = Instant::now();
        let due: Vec<String> = self
            .modules
            .iter()
            .filter(|(_, s)| s.child.is_none() && s.restart_at.is_some_and(|t| t <= now))
            .map(|(n, _)| n.clone())
            .collect();
        for name in due {
            let Some(mut slot) = self.modules.remove(&name) else {
                continue;
            };
            slot.restart_at = None;
            slot.restarts += 1;
            if let Err(e) = self.spawn(&mut slot) {
                tracing::error!(module = %name, "restart failed: {e}");
                slot.state = ModuleRunState::Stopped;
            }
            self.modules.insert(name, slot);
        }
    }

    fn meter(&mut self) {
        self.cpu.sample(std::process::id());
        for slot in self.modules.values_mut() {
            if let Some(pid) = slot.pid() {
                slot.cpu.sample(pid);
            }
            let (t, steps, _) = slot.rate;
            let dt = t.elapsed().as_secs_f64();
            if dt >= 1.0 {
                let rate = slot.status.steps.saturating_sub(steps) as f64 / dt;
                slot.rate = (Instant::now(), slot.status.steps, rate);
            }
        }
    }

    /// The DNM's view of itself and its modules.
    pub fn report(&self) -> DnmReport {
        let now = monotonic_ns();
        DnmReport {
            system: self.system.clone(),
            dnm: self.name.clone(),
            pid: std::process::id(),
            revision: self.revision,
            netlist_digest: self
                .netlist
                .as_ref()
                .map(|n| format!("{:016x}", n.digest()))
                .unwrap_or_default(),
            netlist_file: self.netlist.as_ref().map(|n| n.file.display().to_string()),
            active_task: self.active.clone(),
            tasks: self.tasks.clone(),
            cpu_percent: self.cpu.percent,
            memory: procfs::memory(std::process::id()),
            modules: self
                .modules
                .iter()
                .map(|(name, s)| ModuleReport {
                    name: name.clone(),
                    kind: s.decl.kind.clone(),
                    state: s.state,
                    pid: s.pid(),
                    restarts: s.restarts,
                    last_exit: s.last_exit.clone(),
                    plan_revision: s.status.plan_revision,
                    steps: s.status.steps,
                    sent: s.status.sent,
                    step_errors: s.status.step_errors,
                    rate_hz: s.rate.2,
                    last_step_age_ms: (s.status.last_step_ns > 0)
                        .then(|| now.saturating_sub(s.status.last_step_ns) / 1_000_000),
                    cpu_percent: s.cpu.percent,
                    memory: s.pid().and_then(procfs::memory),
                })
                .collect(),
            switches: self.switches.clone(),
            cleaned_dead_nodes: self.cleaned,
            peers: self
                .net
                .as_ref()
                .map(|n| n.peer_reports(self.netlist.as_ref()))
                .unwrap_or_default(),
            routes: self.net.as_ref().map(Net::report).unwrap_or_default(),
            recording: self.recorder.as_ref().map(crate::record::Recorder::report),
        }
    }

    /// The netlist text in force, if any.
    pub fn netlist(&self) -> Option<&Netlist> {
        self.netlist.as_ref()
    }

    /// Runs the DNM until SIGINT/SIGTERM or until `commands` disconnects: waits on module
    /// notifications and a supervision tick, never spins.
    pub fn run(
        &mut self,
        commands: &Receiver<Command>,
        events: &Listener<Svc>,
    ) -> Result<(), DnmError> {
        let waitset = WaitSetBuilder::new()
            .create::<Svc>()
            .map_err(ipc("waitset"))?;
        let _events_guard = waitset.attach_notification(events).map_err(ipc("attach"))?;
        let _tick_guard = waitset
            .attach_interval(self.options.tick)
            .map_err(ipc("attach"))?;
        loop {
            let result = waitset
                .wait_and_process_once(|_| CallbackProgression::Continue)
                .map_err(ipc("wait"))?;
            if matches!(
                result,
                WaitSetRunResult::Interrupt | WaitSetRunResult::TerminationRequest
            ) {
                // iceoryx2 hands a signal to one waiter: tell the other DNMs of this process.
                STOP.store(true, std::sync::atomic::Ordering::Relaxed);
                break;
            }
            if STOP.load(std::sync::atomic::Ordering::Relaxed) {
                break;
            }
            events.try_wait(|_| ()).map_err(ipc("events"))?;
            loop {
                match commands.try_recv() {
                    Ok(cmd) => self.handle(cmd, events),
                    Err(std::sync::mpsc::TryRecvError::Empty) => break,
                    Err(std::sync::mpsc::TryRecvError::Disconnected) => return Ok(()),
                }
            }
            self.read_statuses();
            self.supervise();
            self.serve_net(events);
            self.meter();
        }
        Ok(())
    }

    /// Answers what arrived over Zenoh and keeps module liveliness tokens in step.
    fn serve_net(&mut self, events: &Listener<Svc>) {
        let Some(net) = self.net.as_mut() else {
            return;
        };
        for inbound in net.take_inbound() {
            match inbound {
                Inbound::Peer { dnm, alive } => {
                    if let Some(net) = self.net.as_mut() {
                        net.set_peer(dnm, alive);
                    }
                }
                Inbound::Query(target, query) => self.answer(target, &query, events),
            }
        }
        let running: Vec<String> = self
            .modules
            .iter()
            .filter(|(_, s)| s.state == ModuleRunState::Running)
            .map(|(n, _)| n.clone())
            .collect();
        if let Some(net) = self.net.as_mut() {
            net.sync_module_tokens(running.iter().map(String::as_str));
        }
    }

    fn answer(&mut self, target: Target, query: &zenoh::query::Query, events: &Listener<Svc>) {
        use zenoh::Wait;
        use zenoh::bytes::Encoding;
        let reply_json = |key: String, body: &serde_json::Value| {
            let bytes = serde_json::to_vec(body).unwrap_or_default();
            if let Err(e) = query
                .reply(key, bytes)
                .encoding(Encoding::APPLICATION_JSON)
                .wait()
            {
                tracing::debug!("zenoh reply: {e}");
            }
        };
        match target {
            Target::Dnm => reply_json(
                crate::keys::dnm(&self.system, &self.name),
                &to_json(&self.report()),
            ),
            Target::Netlist => reply_json(
                crate::keys::netlist(&self.system, &self.name),
                &to_json(&self.netlist_state()),
            ),
            Target::Module => {
                let names: Vec<String> = self.modules.keys().cloned().collect();
                for name in names {
                    let key = crate::keys::module(&self.system, &self.name, &name);
                    let matches = zenoh::key_expr::KeyExpr::try_from(key.as_str())
                        .is_ok_and(|k| k.intersects(query.key_expr()));
                    if matches {
                        let state = self.module_state(&name);
                        reply_json(key, &state);
                    }
                }
            }
            Target::Port => {
                let Some(net) = self.net.as_mut() else {
                    return;
                };
                for (key, message, last) in net.last_values(query.key_expr()) {
                    let Some((header, bytes)) = last else {
                        continue;
                    };
                    if let Err(e) = query
                        .reply(key, bytes.clone())
                        .encoding(crate::keys::encoding(message))
                        .attachment(crate::keys::encode_header(header).to_vec())
                        .wait()
                    {
                        tracing::debug!("zenoh reply: {e}");
                    }
                }
            }
            Target::Cmd => {
                let response = self.command(query.payload().map(|p| p.to_bytes()), events);
                let key = crate::keys::cmd(&self.system, &self.name);
                let bytes = serde_json::to_vec(&response).unwrap_or_default();
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
            }
        }
    }

    /// The applied netlist, for peers and tools.
    pub fn netlist_state(&self) -> crate::net::NetlistState {
        crate::net::NetlistState {
            system: self.system.clone(),
            dnm: self.name.clone(),
            revision: self.revision,
            digest: self
                .netlist
                .as_ref()
                .map(|n| format!("{:016x}", n.digest()))
                .unwrap_or_default(),
            file: self.netlist.as_ref().map(|n| n.file.display().to_string()),
            active_task: self.active.clone(),
            text: self.netlist.as_ref().map(|n| n.text.clone()),
        }
    }

    /// One module's report plus the last value of each of its outputs.
    fn module_state(&mut self, name: &str) -> serde_json::Value {
        let report = self.report().modules.into_iter().find(|m| m.name == name);
        let ports: Vec<String> = self
            .modules
            .get(name)
            .map(|s| s.spec.outputs.iter().map(|p| p.name.clone()).collect())
            .unwrap_or_default();
        let mut outputs = serde_json::Map::new();
        if let Some(net) = self.net.as_mut() {
            for p in ports {
                let v = net.last_value_json(name, &p);
                outputs.insert(p, v);
            }
        }
        let mut v = serde_json::to_value(report).unwrap_or_default();
        if let Some(o) = v.as_object_mut() {
            o.insert("dnm".into(), self.name.clone().into());
            o.insert("outputs".into(), serde_json::Value::Object(outputs));
        }
        v
    }

    /// Runs a command that came over Zenoh; a retried id gets the first answer again.
    fn command(
        &mut self,
        payload: Option<std::borrow::Cow<'_, [u8]>>,
        events: &Listener<Svc>,
    ) -> crate::admin::Response {
        use crate::admin::{Request, Response};
        let cmd: ZenohCommand = match payload.as_deref().map(serde_json::from_slice) {
            Some(Ok(c)) => c,
            Some(Err(e)) => {
                return Response::error(format!(
                    "bad command: {e}; send JSON such as {{\"id\":\"42\",\"cmd\":\"switch\",\"task\":\"auto\"}}"
                ));
            }
            None => {
                return Response::error(
                    "empty command; send JSON such as {\"id\":\"42\",\"cmd\":\"switch\",\"task\":\"auto\"}",
                );
            }
        };
        if let Some(id) = &cmd.id {
            if let Some((_, r)) = self.answered.iter().find(|(i, _)| i == id) {
                return r.clone();
            }
        }
        let response = match cmd.request {
            Request::Status => Response {
                ok: true,
                dnms: vec![self.report()],
                ..Response::default()
            },
            Request::Netlist => Response {
                ok: true,
                revision: Some(self.revision),
                netlist: self.netlist.as_ref().map(|n| n.text.clone()),
                ..Response::default()
            },
            Request::Switch { task } => match self.switch(&task) {
                Ok(s) => Response {
                    ok: true,
                    revision: Some(s.revision),
                    switches: vec![s],
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{}`: {e}", self.name)),
            },
            Request::Apply { file, text } => {
                match crate::parse_netlist(std::path::Path::new(&file), &text) {
                    Err(e) => Response::error(format!("netlist refused, nothing changed:\n{e}")),
                    Ok(n) if n.system != self.system => Response::error(format!(
                        "netlist is for system `{}`, this is `{}`; nothing changed",
                        n.system, self.system
                    )),
                    Ok(n) => match self.apply(&n, events) {
                        Ok(revision) => Response {
                            ok: true,
                            revision: Some(revision),
                            ..Response::default()
                        },
                        Err(e) => Response::error(format!("DNM `{}`: {e}", self.name)),
                    },
                }
            }
        };
        if let Some(id) = cmd.id {
            self.answered.push_back((id, response.clone()));
            if self.answered.len() > 256 {
                self.answered.pop_front();
            }
        }
        response
    }

    fn handle(&mut self, cmd: Command, events: &Listener<Svc>) {
        match cmd {
            Command::Status(reply) => {
                let _ = reply.send(self.report());
            }
            Command::Switch(task, reply) => {
                let _ = reply.send(self.switch(&task).map_err(|e| e.to_string()));
            }
            Command::Apply(netlist, reply) => {
                let _ = reply.send(self.apply(&netlist, events).map_err(|e| e.to_string()));
            }
            Command::Netlist(reply) => {
                let _ = reply.send(self.netlist_state());
            }
        }
    }

    /// Stops every module (SIGTERM, then SIGKILL after a grace period).
    pub fn shutdown(&mut self) {
        let names: Vec<String> = self.modules.keys().cloned().collect();
        for slot in self.modules.values_mut() {
            if let Some(child) = &slot.child {
                // SAFETY: kill(2) with a pid we spawned and still own.
                unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
            }
        }
        for name in names {
            self.stop_module(&name);
        }
        // Finishes the recording: summary and footer.
        self.recorder.take();
        tracing::info!(dnm = %self.name, "stopped");
    }
}

impl Drop for Dnm {
    fn drop(&mut self) {
        if self.modules.values().any(|s| s.child.is_some()) {
            self.shutdown();
        }
    }
}

fn to_json<T: Serialize>(v: &T) -> serde_json::Value {
    serde_json::to_value(v).unwrap_or_default()
}

fn post_plan(slot: &ModuleSlot, plan: &Plan) -> Result<(), DnmError> {
    let bytes = serde_json::to_vec(plan).map_err(|e| DnmError::Ipc(e.to_string()))?;
    if bytes.len() > MAX_PLAN_BYTES {
        return Err(DnmError::Ipc(format!(
            "plan of `{}` is {} bytes, more than {MAX_PLAN_BYTES}",
            slot.decl.name,
            bytes.len()
        )));
    }
    let sample = slot
        .plan_pub
        .loan_slice_uninit(bytes.len())
        .map_err(ipc("loan plan"))?;
    sample
        .write_from_slice(&bytes)
        .send()
        .map_err(ipc("post plan"))?;
    slot.wake.notify().map_err(ipc("wake module"))?;
    Ok(())
}

/// SIGTERM, wait up to `grace`, then SIGKILL; always reaps.
pub(crate) fn terminate(child: &mut Child, grace: Duration) {
    // SAFETY: kill(2) with the pid of a child we have not reaped yet.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    let deadline = Instant::now() + grace;
    while Instant::now() < deadline {
        if let Ok(Some(_)) = child.try_wait() {
            return;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let _ = child.kill();
    let _ = child.wait();
}
