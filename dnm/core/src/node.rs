//! One DNM: its shared-memory namespace and task word, its modules, its commands and its loop.

use std::collections::{BTreeMap, VecDeque};
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_module::event_service;
use dnm_module::protocol::*;
use dnm_netlist::Netlist;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::writer::{EntryHandleMut, Writer};
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::blackboard::PortFactory as BlackboardFactory;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::waitset::WaitSetRunResult;

use dnm_proto::{
    DnmReport, Memory, ModuleEvent, ModuleReport, NetlistState, SupervisionReport, SwitchRecord,
};

use crate::command::{Command, CommandKey, Reply};
use crate::error::{DnmError, ipc};
use crate::exits::Exits;
use crate::janitor::Janitor;
use crate::options::DnmOptions;
use crate::pending::{Decided, HeldSwitch, NEAR, Outcome, PendingApply, QueuedApply, Scheduled};
use crate::plugin::{Plugin, Watched};
use crate::procfs::CpuMeter;
use crate::slot::{ModuleSlot, PortServices, Stopping, Svc};

type TsSvc = ipc_threadsafe::Service;

/// Commands queued for a DNM's thread at most; more are refused as busy.
pub(crate) const COMMAND_QUEUE: usize = 64;
/// Command answers remembered for retries.
const ANSWERED: usize = 1024;
/// Shortest time between two checks of the modules' processes.
const SUPERVISE_EVERY: Duration = Duration::from_millis(10);
/// How often the DNM reads its own and its modules' memory from `/proc`.
pub(crate) const MEMORY_EVERY: Duration = Duration::from_secs(5);

/// Set when this process was asked to terminate; every DNM loop of the process stops.
static STOP: AtomicBool = AtomicBool::new(false);

/// DNM loops running in this process.
static LOOPS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Asks every DNM loop of this process to stop (as SIGTERM does).
pub fn request_stop() {
    STOP.store(true, Ordering::Relaxed);
}

/// Forgets an earlier [`request_stop`] once no DNM loop of this process runs any more, so a
/// process can start DNMs again (a library user, a test). Returns whether it did.
pub fn clear_stop_if_idle() -> bool {
    if LOOPS.load(Ordering::Acquire) == 0 {
        STOP.store(false, Ordering::Relaxed);
        true
    } else {
        false
    }
}

/// Counts a running DNM loop while it lives.
struct LoopGuard;

impl LoopGuard {
    fn enter() -> Self {
        LOOPS.fetch_add(1, Ordering::AcqRel);
        LoopGuard
    }
}

impl Drop for LoopGuard {
    fn drop(&mut self) {
        LOOPS.fetch_sub(1, Ordering::AcqRel);
    }
}

/// Hands commands to a DNM's thread from any other thread and wakes it. Cheap to clone.
#[derive(Clone)]
pub struct Commander {
    dnm: String,
    tx: SyncSender<Command>,
    waker: Arc<Mutex<Notifier<TsSvc>>>,
    _node: Arc<Node<TsSvc>>,
}

impl std::fmt::Debug for Commander {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Commander")
            .field("dnm", &self.dnm)
            .finish_non_exhaustive()
    }
}

impl Commander {
    /// The DNM it commands.
    pub fn dnm(&self) -> &str {
        &self.dnm
    }

    /// Queues a command; refused at once when the DNM's queue is full or the DNM has stopped.
    pub fn send(&self, command: Command) -> Result<(), DnmError> {
        match self.tx.try_send(command) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) => return Err(DnmError::Busy(COMMAND_QUEUE)),
            Err(TrySendError::Disconnected(_)) => return Err(DnmError::Stopped),
        }
        if let Ok(n) = self.waker.lock() {
            let _ = n.notify();
        }
        Ok(())
    }
}

/// A database node module.
pub struct Dnm {
    pub(crate) system: String,
    pub(crate) name: String,
    pub(crate) prefix: String,
    pub(crate) options: DnmOptions,
    pub(crate) node: Node<Svc>,
    _board: BlackboardFactory<Svc, u64>,
    _writer: Writer<Svc, u64>,
    word: EntryHandleMut<Svc, u64, u64>,
    switched_at: EntryHandleMut<Svc, u64, u64>,
    /// Set once the DNM is shutting down: no apply starts any more.
    pub(crate) stopping_all: bool,
    _dnm_event: EventFactory<Svc>,
    events: Rc<Listener<Svc>>,
    pub(crate) ports: BTreeMap<String, PortServices>,
    pub(crate) modules: BTreeMap<String, ModuleSlot>,
    pub(crate) netlist: Option<Netlist>,
    /// The committed netlist's digest (hex), computed once at its commit.
    pub(crate) netlist_digest: String,
    /// The committed revision.
    pub(crate) revision: u64,
    /// The newest revision number handed out (committed or not).
    pub(crate) last_attempt: u64,
    pub(crate) tasks: Vec<String>,
    pub(crate) active: Option<String>,
    pub(crate) switches: VecDeque<SwitchRecord>,
    pub(crate) cpu: CpuMeter,
    pub(crate) memory: Option<Memory>,
    pub(crate) proc_read: Instant,
    pub(crate) memory_read: Instant,
    pub(crate) cleaned: u64,
    pub(crate) janitor: Janitor,
    /// Watches the module processes: an exit wakes the loop at once.
    pub(crate) exits: Option<Exits>,
    /// Set by the exit watch and the janitor: supervise at the next wake, not on the tick.
    prompt: Arc<AtomicBool>,
    pub(crate) plugins: Vec<Box<dyn Plugin>>,
    answered: VecDeque<(CommandKey, Outcome)>,
    pub(crate) apply: Option<PendingApply>,
    pub(crate) queued_applies: VecDeque<QueuedApply>,
    pub(crate) stopping: Vec<Stopping>,
    pub(crate) events_log: VecDeque<ModuleEvent>,
    pub(crate) held_switch: Option<HeldSwitch>,
    pub(crate) scheduled: Option<Scheduled>,
    pub(crate) decided: Decided,
    /// On the safe task by the authority's safing or its own lease, until the next decision.
    pub(crate) safed: Option<dnm_proto::Safed>,
    /// A transaction's prepare waiting for module processes to stop.
    pub(crate) deferred_prepare: Option<(crate::command::Txn, Reply<Result<(), DnmError>>)>,
    /// At real-time priority until a decision is in force.
    pub(crate) hurried: bool,
    pub(crate) warned_realtime: bool,
    commands: Receiver<Command>,
    command_tx: Option<SyncSender<Command>>,
    pub(crate) supervision: SupervisionReport,
    /// When the last snapshot was handed to plugins, and what it watched.
    pub(crate) published: Option<(Instant, Watched)>,
    /// A tool asked for a fresh snapshot ([`Command::Refresh`]).
    pub(crate) refresh: bool,
    last_pass: Option<Instant>,
    last_supervise: Instant,
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
        let config = dnm_config(&prefix).map_err(|e| DnmError::Ipc(e.to_string()))?;
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
        // A DNM killed while it created the board left it half-created: removed, then created.
        let board = dnm_module::recovering(
            &config,
            |_| false,
            || {
                node.service_builder(&board_name)
                    .blackboard_creator::<u64>()
                    .max_readers(MAX_MODULES)
                    .max_nodes(MAX_MODULES)
                    .add::<u64>(TASK_WORD_KEY, task_word(0, NO_TASK))
                    .add::<u64>(SWITCHED_AT_KEY, 0)
                    .create()
            },
        )
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
        let word = writer
            .entry::<u64>(&TASK_WORD_KEY)
            .map_err(ipc("task entry"))?;
        let switched_at = writer
            .entry::<u64>(&SWITCHED_AT_KEY)
            .map_err(ipc("switch time entry"))?;
        let dnm_event =
            event_service(&node, DNM_EVENT).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let events = dnm_event
            .listener_builder()
            .create()
            .map_err(ipc("status listener"))?;
        let (command_tx, commands) = std::sync::mpsc::sync_channel(COMMAND_QUEUE);
        let prompt = Arc::new(AtomicBool::new(false));
        Ok(Self {
            system: system.into(),
            name: name.into(),
            prefix,
            options,
            node,
            _board: board,
            _writer: writer,
            word,
            switched_at,
            stopping_all: false,
            _dnm_event: dnm_event,
            events: Rc::new(events),
            ports: BTreeMap::new(),
            modules: BTreeMap::new(),
            netlist: None,
            netlist_digest: String::new(),
            revision: 0,
            last_attempt: 0,
            tasks: Vec::new(),
            active: None,
            switches: VecDeque::new(),
            cpu: CpuMeter::default(),
            memory: None,
            // Read at the first pass.
            proc_read: Instant::now()
                .checked_sub(Duration::from_secs(2))
                .unwrap_or_else(Instant::now),
            memory_read: Instant::now()
                .checked_sub(MEMORY_EVERY)
                .unwrap_or_else(Instant::now),
            cleaned,
            janitor: Janitor::start(name, config.clone(), prompt.clone()),
            exits: Exits::start(name, config.clone(), prompt.clone()),
            prompt,
            plugins: Vec::new(),
            answered: VecDeque::new(),
            apply: None,
            queued_applies: VecDeque::new(),
            stopping: Vec::new(),
            events_log: VecDeque::new(),
            held_switch: None,
            scheduled: None,
            decided: Decided::new(),
            safed: None,
            deferred_prepare: None,
            hurried: false,
            warned_realtime: false,
            commands,
            command_tx: Some(command_tx),
            supervision: SupervisionReport::default(),
            published: None,
            refresh: false,
            last_pass: None,
            last_supervise: Instant::now(),
        })
    }

    /// Adds a plugin (the Zenoh bridge, the recorder). Add plugins before the first apply.
    pub fn add_plugin(&mut self, plugin: Box<dyn Plugin>) {
        self.plugins.push(plugin);
    }

    /// A handle for other threads to command this DNM. Take every commander you need before
    /// [`Dnm::run`]: the loop ends when all of them are dropped.
    pub fn commander(&self) -> Result<Commander, DnmError> {
        let tx = self.command_tx.clone().ok_or(DnmError::Stopped)?;
        let config = dnm_config(&self.prefix).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let node = NodeBuilder::new()
            .config(&config)
            .create::<TsSvc>()
            .map_err(ipc("commander node"))?;
        let notifier = event_service(&node, DNM_EVENT)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .notifier_builder()
            .create()
            .map_err(ipc("commander notifier"))?;
        Ok(Commander {
            dnm: self.name.clone(),
            tx,
            waker: Arc::new(Mutex::new(notifier)),
            _node: Arc::new(node),
        })
    }

    /// Continues a running system: the next apply yields `revision + 1` and starts in `task`
    /// (if its netlist defines it) instead of the netlist's initial task.
    pub fn continue_from(&mut self, revision: u64, task: Option<&str>) {
        self.revision = self.revision.max(revision);
        self.last_attempt = self.last_attempt.max(revision);
        if self.netlist.is_none() {
            self.active = task.map(str::to_string);
        }
    }

    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn system(&self) -> &str {
        &self.system
    }

    /// The iceoryx2 file prefix of this DNM's namespace.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// The committed revision.
    pub fn revision(&self) -> u64 {
        self.revision
    }

    /// Applies a netlist and waits for the outcome: starts added modules, prepares every
    /// reference of every task in all modules, then commits the new revision with one store.
    /// Modules it drops are stopped and changed ones replaced after the commit. On error the
    /// DNM is exactly as it was.
    pub fn apply(&mut self, netlist: &Netlist) -> Result<u64, DnmError> {
        let (reply, rx) = Reply::channel();
        self.begin_apply(netlist.clone(), None, reply);
        loop {
            if let Ok(r) = rx.try_recv() {
                return r;
            }
            // Blocks until a module posts a status (or 50 ms pass, to notice exits).
            self.events
                .timed_wait(|_| (), Duration::from_millis(50))
                .map_err(ipc("wait for modules"))?;
            self.read_statuses();
            self.progress_apply();
            self.supervise();
        }
    }

    /// Switches the active task: one store of the task word. Everything the task needs was
    /// prepared when the netlist was applied. Never waits for an apply in progress.
    pub fn switch(&mut self, task: &str) -> Result<SwitchRecord, DnmError> {
        // The time of the switch, for its record and for inputs to tell older samples from
        // newer: read before the switch itself, which is the lookup and the two stores.
        let at_ns = monotonic_ns();
        let start = Instant::now();
        let slot =
            self.tasks
                .iter()
                .position(|t| t == task)
                .ok_or_else(|| DnmError::UnknownTask {
                    task: task.into(),
                    known: self.tasks.join(", "),
                })?;
        self.store_word(task_word(self.revision, slot as u16), at_ns);
        let duration_ns = start.elapsed().as_nanos() as u64;
        let record = SwitchRecord {
            dnm: self.name.clone(),
            revision: self.revision,
            from: self.active.replace(task.to_string()),
            to: task.to_string(),
            duration_ns,
            at_ns,
        };
        for slot in self.modules.values() {
            // Wake modules that wait for input so they re-read their sources now.
            let _ = slot.wake.notify();
        }
        for p in &mut self.plugins {
            p.switch(&record);
        }
        self.switches.push_back(record.clone());
        if self.switches.len() > 64 {
            self.switches.pop_front();
        }
        tracing::info!(dnm = %self.name, task, duration_ns, "task switched");
        Ok(record)
    }

    /// Stores the task word, stamped with `at_ns` (CLOCK_MONOTONIC, taken just before): the
    /// time first, so a module that sees the new word reads a time no older than it.
    pub(crate) fn store_word(&mut self, word: u64, at_ns: u64) {
        self.switched_at.update_with_copy(at_ns);
        self.word.update_with_copy(word);
    }

    /// The DNM's view of itself and its modules.
    pub fn report(&self) -> DnmReport {
        let now = monotonic_ns();
        let mut report = DnmReport {
            system: self.system.clone(),
            dnm: self.name.clone(),
            pid: std::process::id(),
            revision: self.revision,
            netlist_digest: self.netlist_digest.clone(),
            netlist_file: self.netlist.as_ref().map(|n| n.file.display().to_string()),
            active_task: self.active.clone(),
            tasks: self.tasks.clone(),
            preparing: self.apply.as_ref().map(|a| a.revision),
            last_attempt: self.last_attempt,
            holding: self.holding(),
            scheduled_at_unix_ns: self.scheduled_at(),
            modules_stopping: self.stopping.len() as u32,
            safed: self.safed.clone(),
            lease: None,
            cpu_percent: self.cpu.percent,
            memory: self.memory,
            modules: self
                .modules
                .iter()
                .map(|(name, s)| {
                    let alive_ns = s.status.heartbeat_ns.max(s.status.last_step_ns);
                    ModuleReport {
                        name: name.clone(),
                        kind: s.decl.kind.clone(),
                        state: s.state,
                        pid: s.pid(),
                        restarts: s.restarts,
                        hangs: s.hangs,
                        last_exit: s.last_exit.clone(),
                        plan_revision: s.status.plan_revision,
                        steps: s.status.steps,
                        sent: s.status.sent,
                        step_errors: s.status.step_errors,
                        rate_hz: s.rate.2,
                        last_step_age_ms: (alive_ns > 0)
                            .then(|| now.saturating_sub(alive_ns) / 1_000_000),
                        hung_after_ms: s.hung_after.as_millis() as u64,
                        cpu_percent: s.cpu.percent,
                        memory: s.memory,
                    }
                })
                .collect(),
            switches: self.switches.iter().cloned().collect(),
            events: self.events_log.iter().cloned().collect(),
            cleaned_dead_nodes: self.cleaned + self.janitor.cleaned(),
            supervision: self.supervision.clone(),
            peers: Vec::new(),
            routes: Default::default(),
            recording: None,
        };
        for p in &self.plugins {
            p.report(&mut report);
        }
        report
    }

    /// The netlist in force.
    pub fn netlist(&self) -> Option<&Netlist> {
        self.netlist.as_ref()
    }

    /// The committed netlist, for peers and tools.
    pub fn netlist_state(&self) -> NetlistState {
        NetlistState {
            system: self.system.clone(),
            dnm: self.name.clone(),
            revision: self.revision,
            digest: self.netlist_digest.clone(),
            file: self.netlist.as_ref().map(|n| n.file.display().to_string()),
            active_task: self.active.clone(),
            text: self.netlist.as_ref().map(|n| n.text.clone()),
        }
    }

    /// Runs the DNM until SIGINT/SIGTERM, [`request_stop`], or until every [`Commander`] is
    /// dropped: waits on module notifications, commands and a supervision tick; never spins.
    pub fn run(&mut self) -> Result<(), DnmError> {
        // From now on the loop ends when the last commander goes.
        self.command_tx = None;
        let _running = LoopGuard::enter();
        let events = self.events.clone();
        let waitset = WaitSetBuilder::new()
            .create::<Svc>()
            .map_err(ipc("waitset"))?;
        let _events_guard = waitset
            .attach_notification(&*events)
            .map_err(ipc("attach"))?;
        let _tick_guard = waitset
            .attach_interval(self.options.tick)
            .map_err(ipc("attach"))?;
        self.supervision.period_ms = self.options.tick.as_millis() as u64;
        self.pass();
        loop {
            let result = match self.next_wake() {
                Some(t) => {
                    waitset.wait_and_process_once_with_timeout(|_| CallbackProgression::Continue, t)
                }
                None => waitset.wait_and_process_once(|_| CallbackProgression::Continue),
            }
            .map_err(ipc("wait"))?;
            if result == WaitSetRunResult::TerminationRequest {
                // iceoryx2 hands a signal to one waiter: tell the other DNMs of this process.
                request_stop();
                break;
            }
            // Any signal interrupts the wait; SIGINT and SIGTERM come back as a termination
            // request from the next wait.
            if result == WaitSetRunResult::Interrupt {
                continue;
            }
            if STOP.load(Ordering::Relaxed) {
                break;
            }
            events.try_wait(|_| ()).map_err(ipc("events"))?;
            self.run_due();
            if self.until_due().is_some_and(|d| d < NEAR) {
                // A decided instant is near: nothing else may hold up the store, so commands
                // and supervision wait until it is done.
                self.hurry();
                continue;
            }
            loop {
                match self.commands.try_recv() {
                    Ok(cmd) => self.handle(cmd),
                    Err(std::sync::mpsc::TryRecvError::Empty) => break,
                    Err(std::sync::mpsc::TryRecvError::Disconnected) => return Ok(()),
                }
            }
            self.give_up_stale_hold();
            self.retry_deferred_prepare();
            if self.quiet() {
                // No statuses are read while a switch is held: a snapshot asked for is made
                // from the last ones rather than waiting for the hold to end.
                if self.refresh {
                    self.publish();
                }
                continue;
            }
            self.read_statuses();
            self.progress_apply();
            // Exits are noticed within a few milliseconds (the janitor thread removes their shared
            // memory), not on every module heartbeat; readings and snapshots follow the tick.
            // An exit, a finished sweep or a start that is due asks for it at once.
            let prompted = self.prompt.swap(false, Ordering::AcqRel)
                || self.until_start() == Some(Duration::ZERO);
            if prompted || self.last_supervise.elapsed() >= SUPERVISE_EVERY {
                self.last_supervise = Instant::now();
                self.supervise();
            }
            let due = self
                .last_pass
                .is_none_or(|t| t.elapsed() + Duration::from_millis(1) >= self.options.tick);
            if due {
                self.pass();
            }
            // Asked for by a tool: made once this wake's statuses are read.
            if self.refresh {
                self.publish();
            }
        }
        Ok(())
    }

    /// How long the loop may wait: until a decided instant is near, or a module's start is due
    /// (not while the instant's quiet keeps supervision waiting: the instant comes first).
    fn next_wake(&self) -> Option<Duration> {
        let start = if self.quiet() {
            None
        } else {
            self.until_start()
        };
        match (self.until_due(), start) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The periodic part of supervision: CPU and memory readings, and a snapshot for plugins
    /// when one is due (exits, hangs and restarts are checked on every wake).
    fn pass(&mut self) {
        let now = Instant::now();
        if let Some(last) = self.last_pass {
            let gap = now.duration_since(last).as_millis() as u64;
            self.supervision.max_gap_ms = self.supervision.max_gap_ms.max(gap);
        }
        self.last_pass = Some(now);
        self.supervision.passes += 1;
        self.meter();
        self.publish_if_due();
    }

    pub(crate) fn answered(&self, key: &CommandKey) -> Option<Outcome> {
        self.answered
            .iter()
            .find(|(k, _)| k == key)
            .map(|(_, o)| o.clone())
    }

    pub(crate) fn remember(&mut self, key: CommandKey, outcome: Outcome) {
        self.answered.push_back((key, outcome));
        if self.answered.len() > ANSWERED {
            self.answered.pop_front();
        }
    }

    /// Answers every command still queued: reports as usual, switches and applies refused.
    pub(crate) fn refuse_queued_commands(&mut self) {
        while let Ok(cmd) = self.commands.try_recv() {
            match cmd {
                Command::Status(reply) => reply.send(self.report()),
                Command::Netlist(reply) => reply.send(self.netlist_state()),
                Command::Refresh => {}
                Command::Switch { reply, .. } => reply.send(Err(DnmError::Stopped)),
                Command::Apply { reply, .. } => reply.send(Err(DnmError::Stopped)),
                Command::Prepare { reply, .. } => reply.send(Err(DnmError::Stopped)),
                Command::Decide { reply, .. } => reply.send(Err(DnmError::Stopped)),
                Command::Adopt { reply, .. } => reply.send(Err(DnmError::Stopped)),
                Command::Safe { reply, .. } => reply.send(Err(DnmError::Stopped)),
            }
        }
    }

    fn handle(&mut self, cmd: Command) {
        match cmd {
            Command::Status(reply) => reply.send(self.report()),
            Command::Netlist(reply) => reply.send(self.netlist_state()),
            Command::Refresh => self.refresh = true,
            Command::Switch { task, key, reply } => {
                if let Some(k) = &key {
                    match self.answered(k) {
                        Some(Outcome::Switch(r)) => return reply.send(r),
                        Some(Outcome::Apply(_)) => {
                            return reply.send(Err(DnmError::IdReused {
                                id: k.id.clone(),
                                client: k.client.clone(),
                                used_for: "an apply",
                            }));
                        }
                        None => {}
                    }
                }
                let r = self.switch(&task);
                if let Some(k) = key {
                    self.remember(k, Outcome::Switch(r.clone()));
                }
                // Tools asking right after the answer see the state it reports.
                self.publish();
                reply.send(r);
            }
            Command::Apply {
                netlist,
                key,
                reply,
            } => {
                if let Some(k) = &key {
                    match self.answered(k) {
                        Some(Outcome::Apply(r)) => return reply.send(r),
                        Some(Outcome::Switch(_)) => {
                            return reply.send(Err(DnmError::IdReused {
                                id: k.id.clone(),
                                client: k.client.clone(),
                                used_for: "a switch",
                            }));
                        }
                        None => {}
                    }
                }
                self.begin_apply(*netlist, key, reply);
            }
            Command::Prepare { txn, reply } => self.prepare_txn(txn, reply),
            Command::Decide { decision, reply } => self.decide_txn(decision, reply),
            Command::Adopt {
                revision,
                task,
                netlist,
                reply,
            } => self.adopt(revision, task, *netlist, reply),
            Command::Safe { order, reply } => self.make_safe(order, reply),
        }
    }
}

impl Drop for Dnm {
    fn drop(&mut self) {
        if self.modules.values().any(|s| s.child.is_some())
            || !self.stopping.is_empty()
            || self.apply.is_some()
        {
            self.shutdown();
        }
    }
}
