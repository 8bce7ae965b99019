//! The module process: opens the module's ports in its DNM's shared memory, follows the DNM's
//! plans, and runs the module's step on its trigger. Blocks on an iceoryx2 WaitSet; never spins.

use std::time::{Duration, Instant};

use dnm_netlist::{KindSpec, Payload, PortSpec, Trigger};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::sample_mut::SampleMut;
use iceoryx2::waitset::{WaitSet, WaitSetGuard, WaitSetRunResult};
use iceoryx2_bb_posix::signal::SignalHandler;

use super::author::{Io, Module, ModuleError, Ports, Setup, ipc};
use super::offline::Stepper;
use super::services::{
    Svc, TaskWatch, event_service, plan_service_factory, port_service, status_service_factory,
};
use crate::protocol::*;

type PortPublisher = Publisher<Svc, [u8], PortHeader>;
type PortSubscriber = Subscriber<Svc, [u8], PortHeader>;
type PortSample = Sample<Svc, [u8], PortHeader>;

/// Stands for "no step yet" where a task word is remembered.
const UNSET_WORD: u64 = u64::MAX;

/// A step posts the status when a step or a heartbeat last did more than this long ago, ns.
const STATUS_EVERY_NS: u64 = 100_000_000;

/// Runs module `M` in this process as described by `launch`, until the DNM stops it or a
/// termination signal arrives.
pub(crate) fn run<M: Module>(launch: &Launch) -> Result<(), ModuleError> {
    Process::open(launch, M::kind(), &mut |setup| Ok(Box::new(M::new(setup)?)))?.run()
}

/// Builds a module from its setup (see [`run_dynamic`]).
pub type MakeModule<'m> = dyn FnMut(&mut Setup<'_>) -> Result<Box<dyn Stepper>, ModuleError> + 'm;

/// Runs a module of kind `spec` in this process as described by `launch`, built by `make`
/// (for modules whose kind is known only at run time, such as those of another language),
/// until the DNM stops it or a termination signal arrives. A step that fails with
/// [`ModuleError::Fatal`] ends the process with its error, after posting it to the DNM (which
/// reports it in the module's exit event and applies its restart policy).
pub fn run_dynamic(
    launch: &Launch,
    spec: KindSpec,
    make: &mut MakeModule<'_>,
) -> Result<(), ModuleError> {
    Process::open(launch, spec, make)?.run()
}

/// How long a module that fails keeps its status publisher after posting why: the DNM reads
/// statuses on its supervision passes, and a sample of a publisher that is gone is gone.
const LINGER: Duration = Duration::from_millis(300);

/// Waits [`LINGER`] before a failing module ends, so its DNM reads the status that says why.
fn linger_for_the_dnm() {
    std::thread::sleep(LINGER);
}

/// Why the loop leaves a wait set, and what it does before the next.
enum Leave {
    /// The module stops (its status says so already).
    Stop,
    /// The DNM posted plans: open their sources.
    Prepare(Vec<Plan>),
    /// The DNM committed the plan at this index: retire the older plans and their sources.
    Retire(usize),
}

/// A module process: the module, its ports and its side of the conversation with the DNM.
struct Process<'a> {
    wakers: Wakers,
    serving: Serving<'a>,
    /// Declared last, so it outlives every port opened on it.
    node: Node<Svc>,
}

/// What wakes the loop besides its timers: the DNM's wake event, and the "new sample" event
/// of every open source (in the order of [`Inputs::conns`]). A wait set borrows these while it
/// exists, so they are kept apart from the state a wait changes.
struct Wakers {
    wake: Listener<Svc>,
    sources: Vec<Listener<Svc>>,
}

/// Everything of a module process a wait changes.
struct Serving<'a> {
    launch: &'a Launch,
    spec: KindSpec,
    /// The step period of a periodic module; an on-input module has none.
    period: Option<Duration>,
    inputs: Inputs,
    module: Box<dyn Stepper>,
    outputs: Vec<OutPort>,
    dnm: DnmLink,
    status: Status,
    /// When a step or a heartbeat last posted the status, CLOCK_MONOTONIC ns.
    last_status_ns: u64,
}

/// Our side of the conversation with the DNM (its wake event is among the [`Wakers`]).
struct DnmLink {
    task: TaskWatch,
    plans: Subscriber<Svc, [u8], ()>,
    status: Publisher<Svc, Status, ()>,
    notifier: Notifier<Svc>,
}

/// The module's inputs: the sources open, the routes of the prepared plans, and which source
/// feeds each input in the current step.
struct Inputs {
    conns: Vec<SourceConn>,
    plans: Vec<Routes>,
    /// Per input: the connection feeding it in this step.
    active: Vec<Option<usize>>,
    /// Per input: the generation of its source last returned by `read`.
    seen: Vec<Option<(usize, u64)>>,
    switches: Switches,
}

/// The task word of the previous step, each input's source under it, and the time from which
/// each input shows samples.
#[derive(Debug)]
struct Switches {
    last_word: u64,
    last_sources: Vec<Option<Source>>,
    /// Per input: samples sent before this time are not shown (the input was switched to its
    /// source then).
    fresh_after: Vec<u64>,
}

struct OutPort {
    /// Its declaration (name, message type, the most it sends).
    port: PortSpec,
    publisher: PortPublisher,
    notifier: Notifier<Svc>,
    seq: u64,
    /// A sample loaned in this step and not sent yet ([`Shm::loan`]).
    loaned: Option<SampleMut<Svc, [u8], PortHeader>>,
}

/// A subscription to one candidate source, with the newest sample taken from it.
struct SourceConn {
    source: Source,
    subscriber: PortSubscriber,
    latest: Option<PortSample>,
    /// Counts samples taken, so each input knows whether it has seen the latest.
    generation: u64,
}

/// The routes of one prepared plan: for each declared input (by index), source per task slot.
#[derive(Debug, Clone, PartialEq)]
struct Routes {
    revision: u64,
    tasks: Vec<String>,
    /// `[input][slot]` -> index into `conns`.
    by_input: Vec<Vec<Option<usize>>>,
}

/// A module process's ports as [`Io`] sees them during one step.
pub(crate) struct Shm<'a> {
    outputs: &'a mut [OutPort],
    conns: &'a [SourceConn],
    /// Per input: the connection feeding it in this step.
    active: &'a [Option<usize>],
    /// Per input: the generation of its source last returned by `read`.
    seen: &'a mut [Option<(usize, u64)>],
    /// Per input: samples sent before this time are not shown (the input was switched to its
    /// source then).
    fresh_after: &'a [u64],
    routes: Option<&'a Routes>,
    sent: &'a mut u64,
}

/// A wait set's attachments: the DNM's wake event, then the step timer of a periodic module,
/// or the heartbeat timer and the sources of an on-input module.
struct Waiter<'w, 'a> {
    waitset: &'w WaitSet<Svc>,
    // Dropped in the reverse order of attaching.
    sources: Vec<WaitSetGuard<'w, 'a, Svc>>,
    heartbeat: Option<WaitSetGuard<'w, 'static, Svc>>,
    tick: Option<WaitSetGuard<'w, 'static, Svc>>,
    wake: WaitSetGuard<'w, 'a, Svc>,
}

/// What woke one wait.
struct Wake {
    result: WaitSetRunResult,
    /// The step timer of a periodic module fired.
    ticked: bool,
    /// The heartbeat timer of an on-input module fired.
    beat: bool,
    /// Which events notified: the DNM's wake event, and the sources by their place in
    /// [`Wakers::sources`] (bit `i`; every source from the 64th on is bit 63).
    fired: Fired,
}

/// The wake events a wait reported.
#[derive(Default, Clone, Copy)]
struct Fired {
    control: bool,
    sources: u64,
}

impl Fired {
    /// Every event, fired or not.
    const ALL: Self = Self {
        control: true,
        sources: u64::MAX,
    };

    fn source(&mut self, i: usize) {
        self.sources |= 1 << i.min(63);
    }

    fn has_source(&self, i: usize) -> bool {
        self.sources & (1 << i.min(63)) != 0
    }

    /// The DNM or a source notified.
    fn any(&self) -> bool {
        self.control || self.sources != 0
    }
}

impl Wake {
    /// The first step of a periodic module, without a wait.
    fn first_step() -> Self {
        Self {
            result: WaitSetRunResult::AllEventsHandled,
            ticked: true,
            beat: false,
            fired: Fired::default(),
        }
    }
}

impl<'a> Process<'a> {
    /// Opens the module's side of its DNM's shared memory and builds the module.
    fn open(
        launch: &'a Launch,
        spec: KindSpec,
        make: &mut MakeModule<'_>,
    ) -> Result<Self, ModuleError> {
        // iceoryx2 turns SIGTERM and SIGINT into a termination request once its handler is
        // installed, which its first wait would do. Installed before any service is opened, a
        // module stopped while it creates one is never killed half-way through: it finishes
        // and exits at its first wait, or its open is interrupted and it exits with the error.
        if SignalHandler::termination_requested() {
            // One arrived as the handler was installed: raised again for the first wait.
            // SAFETY: raise(3) with iceoryx2's handler for SIGTERM installed.
            unsafe { libc::raise(libc::SIGTERM) };
        }
        let mut config =
            dnm_config(&launch.prefix).map_err(|e| ModuleError::Launch(e.to_string()))?;
        // What dead processes left is the DNM's to sweep (it has, before it starts this one):
        // a module starts without sweeping again, and leaves none of its own to race it.
        config.global.node.cleanup_dead_nodes_on_creation = false;
        config.global.node.cleanup_dead_nodes_on_destruction = false;
        let node_name: NodeName = launch
            .module
            .as_str()
            .try_into()
            .map_err(ipc("node name"))?;
        let node = NodeBuilder::new()
            .name(&node_name)
            .config(&config)
            .create::<Svc>()
            .map_err(ipc("node"))?;

        // Our side of the conversation with the DNM.
        let task = TaskWatch::on(&node)?;
        let plans = plan_service_factory(&node, &launch.module)?
            .subscriber_builder()
            .create()
            .map_err(ipc("plan subscriber"))?;
        let wake = event_service(&node, &wake_event(&launch.module))?
            .listener_builder()
            .create()
            .map_err(ipc("wake listener"))?;
        let status = status_service_factory(&node, &launch.module)?
            .publisher_builder()
            .create()
            .map_err(ipc("status publisher"))?;
        let notifier = event_service(&node, DNM_EVENT)?
            .notifier_builder()
            .create()
            .map_err(ipc("DNM notifier"))?;
        // Subscribed to its plans: the DNM hands them over as soon as it reads this.
        let hello = Status {
            pid: std::process::id(),
            state: ModuleState::Starting as u32,
            ..Status::default()
        };
        status.send_copy(hello).map_err(ipc("status"))?;
        notifier.notify().map_err(ipc("notify DNM"))?;
        let outputs = open_outputs(&node, &launch.module, &spec)?;

        let module = {
            let mut setup = Setup::new(&launch.module, &spec, &launch.params);
            match make(&mut setup) {
                Ok(m) => m,
                Err(e) => {
                    // The DNM reads why in this status when it sees the process exit.
                    let mut failed = Status {
                        pid: std::process::id(),
                        state: ModuleState::Starting as u32,
                        ..Status::default()
                    };
                    failed.set_error(&e.to_string());
                    let _ = status.send_copy(failed);
                    linger_for_the_dnm();
                    return Err(e);
                }
            }
        };
        let status_now = Status {
            pid: std::process::id(),
            state: ModuleState::Starting as u32,
            ..Status::default()
        };
        let period = step_period(&launch.trigger)?;
        let inputs = spec.inputs.len();
        Ok(Self {
            wakers: Wakers {
                wake,
                sources: Vec::new(),
            },
            serving: Serving {
                launch,
                spec,
                period,
                inputs: Inputs {
                    conns: Vec::new(),
                    plans: Vec::new(),
                    active: vec![None; inputs],
                    seen: vec![None; inputs],
                    switches: Switches::new(inputs),
                },
                module,
                outputs,
                dnm: DnmLink {
                    task,
                    plans,
                    status,
                    notifier,
                },
                status: status_now,
                last_status_ns: 0,
            },
            node,
        })
    }

    /// The process loop: serves the module under a wait set until its subscriptions must
    /// change, changes them, and starts over, until the module stops.
    fn run(mut self) -> Result<(), ModuleError> {
        loop {
            // Work that changes the set of subscriptions waits until the WaitSet is gone.
            match self.serve()? {
                Leave::Stop => return Ok(()),
                Leave::Retire(committed) => {
                    self.serving.inputs.plans.drain(..committed);
                    self.retire_unused();
                }
                Leave::Prepare(pending) => self.prepare(pending)?,
            }
        }
    }

    /// Waits and steps under one wait set until the module stops or its subscriptions must
    /// change.
    fn serve(&mut self) -> Result<Leave, ModuleError> {
        let waitset = WaitSetBuilder::new()
            .create::<Svc>()
            .map_err(ipc("waitset"))?;
        let waiter = Waiter::attach(&waitset, &self.wakers, self.serving.period)?;
        let serving = &mut self.serving;

        // Plans already posted (history) are handled before the first wait.
        let mut check_plans = true;
        // Once a heartbeat every event is drained, fired or not: when two notifiers race,
        // iceoryx2 can leave an event marked notified with its socket empty, after which it
        // sends nothing and the wait set never reports it; a drain resets it.
        let mut swept_at = Instant::now();
        loop {
            if check_plans {
                check_plans = false;
                if let Some(leave) = serving.receive_plans()? {
                    return Ok(leave);
                }
            }

            // A periodic module steps as soon as it has a plan, not a period later.
            let wake = if serving.first_step_due() {
                Wake::first_step()
            } else {
                waiter.wait()?
            };
            if wake.beat {
                serving.heartbeat()?;
            }
            if wake.result == WaitSetRunResult::TerminationRequest {
                serving.stop()?;
                return Ok(Leave::Stop);
            }
            // Any signal interrupts the wait (SIGCONT after a stop, for one). SIGINT and
            // SIGTERM are reported as a termination request by the next wait.
            if wake.result == WaitSetRunResult::Interrupt {
                continue;
            }
            let mut fired = wake.fired;
            if swept_at.elapsed() >= HEARTBEAT {
                swept_at = Instant::now();
                fired = Fired::ALL;
            }
            if fired.any() {
                check_plans = self.wakers.clear(fired)?;
            }

            // The reference swap: one read of the task word decides every input of this step.
            let word = serving.dnm.task.word();
            let (revision, _) = split_task_word(word);
            let routes = serving.inputs.plan_of(revision);
            if let Some(i) = routes
                && i > 0
            {
                // The DNM committed a newer revision: retire older plans and their sources.
                return Ok(Leave::Retire(i));
            }
            serving.inputs.select(word, routes, &serving.dnm.task)?;
            if serving.due(wake.ticked) {
                serving.step(word, routes)?;
            }
        }
    }

    /// Prepares the plans the DNM posted, then reports the newest revision prepared.
    fn prepare(&mut self, pending: Vec<Plan>) -> Result<(), ModuleError> {
        let serving = &mut self.serving;
        for plan in pending {
            let revision = plan.revision;
            // A plan this process cannot prepare is reported, not fatal: the DNM refuses
            // the revision and the module goes on serving the one in force.
            if let Err(e) = prepare(
                &self.node,
                &serving.spec,
                plan,
                &mut serving.inputs.conns,
                &mut self.wakers.sources,
                &mut serving.inputs.plans,
            ) {
                tracing::error!(module = %serving.launch.module, revision, "cannot prepare: {e}");
                // The revision in force itself: this process cannot serve it, so it ends and
                // its restart policy takes over.
                let (in_force, _) = split_task_word(serving.dnm.task.word());
                if revision == in_force {
                    return Err(e);
                }
                serving.status.prepare_failed = revision;
            }
        }
        // A plan that replaced a failed one may leave sources nothing uses.
        self.retire_unused();
        let serving = &mut self.serving;
        serving.status.plan_revision = serving.inputs.plans.last().map_or(0, |p| p.revision);
        serving.status.state = ModuleState::Running as u32;
        // A sign of life, so a module that hangs in its first step is found too.
        serving.status.heartbeat_ns = monotonic_ns();
        serving.publish_status()
    }

    /// Closes the subscriptions no remaining plan uses.
    fn retire_unused(&mut self) {
        let inputs = &mut self.serving.inputs;
        retire(
            &mut inputs.conns,
            &mut self.wakers.sources,
            &mut inputs.plans,
            &mut inputs.seen,
        );
    }
}

impl Serving<'_> {
    /// Takes the plans the DNM posted. `Some` when the wait set must go: the DNM stops the
    /// module, or there are plans to prepare.
    fn receive_plans(&mut self) -> Result<Option<Leave>, ModuleError> {
        let mut pending: Vec<Plan> = Vec::new();
        while let Some(sample) = self.dnm.plans.receive().map_err(ipc("plan receive"))? {
            let plan: Plan = serde_json::from_slice(sample.payload())
                .map_err(|e| ModuleError::Ipc(format!("bad plan from DNM: {e}")))?;
            if plan.stop {
                self.stop()?;
                return Ok(Some(Leave::Stop));
            }
            pending.push(plan);
        }
        Ok((!pending.is_empty()).then_some(Leave::Prepare(pending)))
    }

    /// On the heartbeat timer of a module waiting for input, which still tells its DNM it is
    /// alive: posts the status unless the last sign of life is under half a heartbeat old.
    fn heartbeat(&mut self) -> Result<(), ModuleError> {
        let now_ns = monotonic_ns();
        if now_ns.saturating_sub(self.status.heartbeat_ns) >= HEARTBEAT.as_nanos() as u64 / 2 {
            self.status.heartbeat_ns = now_ns;
            self.last_status_ns = now_ns;
            self.post_status()?;
        }
        Ok(())
    }

    /// Reports that the module stops.
    fn stop(&mut self) -> Result<(), ModuleError> {
        self.status.state = ModuleState::Stopping as u32;
        self.publish_status()
    }

    /// A periodic module with a plan that has not stepped yet.
    fn first_step_due(&self) -> bool {
        self.period.is_some() && self.status.steps == 0 && !self.inputs.plans.is_empty()
    }

    /// Whether the module steps after this wake-up: a periodic module when its timer fired, an
    /// on-input one when an input has something new.
    fn due(&self, ticked: bool) -> bool {
        match self.period {
            Some(_) => ticked,
            None => self.inputs.any_unread(),
        }
    }

    /// Steps the module under task word `word`, with plan `routes` (none if this process has
    /// no plan for the word yet), and posts the status if it has not lately.
    fn step(&mut self, word: u64, routes: Option<usize>) -> Result<(), ModuleError> {
        let now_ns = monotonic_ns();
        let inputs = &mut self.inputs;
        let mut io = Io {
            word,
            now_ns,
            ports: Ports::Shm(Shm {
                outputs: &mut self.outputs,
                conns: &inputs.conns,
                active: &inputs.active,
                seen: &mut inputs.seen,
                fresh_after: &inputs.switches.fresh_after,
                routes: routes.map(|i| &inputs.plans[i]),
                sent: &mut self.status.sent,
            }),
        };
        self.status.steps += 1;
        self.status.last_step_ns = now_ns;
        self.status.heartbeat_ns = now_ns;
        let stepped = self.module.step_io(&mut io);
        for out in self.outputs.iter_mut() {
            // A loan not sent in the step is given back.
            out.loaned = None;
        }
        if let Err(e) = stepped {
            self.status.step_errors += 1;
            self.status.set_error(&e.to_string());
            if let ModuleError::Fatal(_) = e {
                // The DNM reads why in the last status before it sees the process exit.
                self.publish_status()?;
                linger_for_the_dnm();
                return Err(e);
            }
            tracing::warn!(module = %self.launch.module, "step failed: {e}");
        }
        if now_ns.saturating_sub(self.last_status_ns) > STATUS_EVERY_NS {
            self.last_status_ns = now_ns;
            self.post_status()?;
        }
        Ok(())
    }

    /// Posts the status for the DNM's next supervision tick, without waking it: what a step
    /// or a heartbeat changes is not urgent.
    fn post_status(&self) -> Result<(), ModuleError> {
        self.dnm
            .status
            .send_copy(self.status)
            .map_err(ipc("status"))?;
        Ok(())
    }

    fn publish_status(&self) -> Result<(), ModuleError> {
        self.dnm.publish(&self.status)
    }
}

impl DnmLink {
    /// Posts `status` and tells the DNM.
    fn publish(&self, status: &Status) -> Result<(), ModuleError> {
        self.status.send_copy(*status).map_err(ipc("status"))?;
        self.notifier.notify().map_err(ipc("notify DNM"))?;
        Ok(())
    }
}

impl Wakers {
    /// Consumes the notifications of the events that woke a wait, and only theirs (one that
    /// came after the wait returned wakes the next one); true if the DNM's wake event was
    /// among them (it posted a plan, or stops the module). An event that did not fire costs no
    /// read of its socket, but once a heartbeat (see `serve`): most wake-ups are one source's.
    fn clear(&self, fired: Fired) -> Result<bool, ModuleError> {
        let mut control = false;
        if fired.control {
            self.wake
                .try_wait(|_| control = true)
                .map_err(ipc("wake"))?;
        }
        for (i, l) in self.sources.iter().enumerate() {
            if fired.has_source(i) {
                l.try_wait(|_| ()).map_err(ipc("listener"))?;
            }
        }
        Ok(control)
    }
}

impl<'w, 'a> Waiter<'w, 'a> {
    /// Attaches what a module with step period `period` (none: on input) waits for.
    fn attach(
        waitset: &'w WaitSet<Svc>,
        wakers: &'a Wakers,
        period: Option<Duration>,
    ) -> Result<Self, ModuleError> {
        let wake = waitset
            .attach_notification(&wakers.wake)
            .map_err(ipc("attach"))?;
        let tick = match period {
            Some(p) => Some(waitset.attach_interval(p).map_err(ipc("attach interval"))?),
            None => None,
        };
        // A module waiting for input still tells its DNM it is alive.
        let heartbeat = match period {
            Some(_) => None,
            None => Some(
                waitset
                    .attach_interval(HEARTBEAT)
                    .map_err(ipc("attach heartbeat"))?,
            ),
        };
        let mut sources = Vec::new();
        if period.is_none() {
            for l in &wakers.sources {
                sources.push(waitset.attach_notification(l).map_err(ipc("attach"))?);
            }
        }
        Ok(Self {
            waitset,
            sources,
            heartbeat,
            tick,
            wake,
        })
    }

    /// Blocks until a timer fires, something notifies, or a signal arrives.
    fn wait(&self) -> Result<Wake, ModuleError> {
        let mut ticked = false;
        let mut beat = false;
        let mut fired = Fired::default();
        let result = self
            .waitset
            .wait_and_process_once(|id| {
                if self.tick.as_ref().is_some_and(|g| id.has_event_from(g)) {
                    ticked = true;
                } else if self
                    .heartbeat
                    .as_ref()
                    .is_some_and(|g| id.has_event_from(g))
                {
                    beat = true;
                } else if id.has_event_from(&self.wake) {
                    fired.control = true;
                } else if let Some(i) = self.sources.iter().position(|g| id.has_event_from(g)) {
                    fired.source(i);
                }
                CallbackProgression::Continue
            })
            .map_err(ipc("wait"))?;
        Ok(Wake {
            result,
            ticked,
            beat,
            fired,
        })
    }
}

impl Inputs {
    /// The prepared plan of `revision`, by index.
    fn plan_of(&self, revision: u64) -> Option<usize> {
        self.plans.iter().position(|p| p.revision == revision)
    }

    /// Points every input at its source under task word `word` in plan `routes` (none if this
    /// process has no plan for the word yet), then takes what the active sources sent.
    fn select(
        &mut self,
        word: u64,
        routes: Option<usize>,
        task: &TaskWatch,
    ) -> Result<(), ModuleError> {
        let (_, slot) = split_task_word(word);
        let routes = routes.map(|i| &self.plans[i]);
        for (input, a) in self.active.iter_mut().enumerate() {
            *a = routes.and_then(|r| r.source(input, slot));
        }
        // Words this process has no plan for (it is still preparing) change nothing: the
        // first word it serves counts as its start, whenever it woke up.
        if routes.is_some() && self.switches.is_new(word) {
            // An input switched to another source shows only what that source sends
            // from the switch on: what it queued before (it may have gone quiet long
            // ago) is old. The DNM stamps each store of the word.
            let switched_at = task.switched_at();
            let sources = self
                .active
                .iter()
                .map(|a| a.map(|c| self.conns[c].source.clone()));
            self.switches.record(word, sources, switched_at);
        }
        for c in self.active.iter().flatten() {
            self.conns[*c].drain()?;
        }
        Ok(())
    }

    /// An on-input module steps when an input has a sample it has not read that was
    /// sent since the input's source became active.
    fn any_unread(&self) -> bool {
        self.active.iter().enumerate().any(|(input, c)| {
            c.is_some_and(|c| {
                let g = self.conns[c].generation;
                self.conns[c]
                    .latest
                    .as_ref()
                    .is_some_and(|s| sent_since(s, self.switches.fresh_after[input]))
                    && self.seen[input] != Some((c, g))
            })
        })
    }
}

impl Switches {
    fn new(inputs: usize) -> Self {
        Self {
            last_word: UNSET_WORD,
            last_sources: vec![None; inputs],
            fresh_after: vec![0; inputs],
        }
    }

    /// Whether `word` is not the task word of the previous step.
    fn is_new(&self, word: u64) -> bool {
        word != self.last_word
    }

    /// Records the step under `word` (stored at `switched_at`) with each input's `sources`:
    /// an input whose source changed since the previous step shows only samples sent since
    /// `switched_at`. The first step changes nothing.
    fn record(
        &mut self,
        word: u64,
        sources: impl Iterator<Item = Option<Source>>,
        switched_at: u64,
    ) {
        for (input, source) in sources.enumerate() {
            if self.last_word != UNSET_WORD && source != self.last_sources[input] {
                self.fresh_after[input] = switched_at;
            }
            self.last_sources[input] = source;
        }
        self.last_word = word;
    }
}

/// The step period of a module with `trigger`: none for an on-input module.
fn step_period(trigger: &Trigger) -> Result<Option<Duration>, ModuleError> {
    Ok(match *trigger {
        Trigger::Periodic { rate_hz } => Some(
            Duration::try_from_secs_f64(1.0 / rate_hz)
                .ok()
                .filter(|p| !p.is_zero())
                .ok_or_else(|| {
                    ModuleError::Launch(format!(
                        "rate_hz = {rate_hz} gives no usable period; use a rate between {} and {} Hz",
                        dnm_netlist::MIN_RATE_HZ,
                        dnm_netlist::MAX_RATE_HZ
                    ))
                })?,
        ),
        Trigger::OnInput => None,
    })
}

/// Opens a publisher and a "new sample" notifier for every output of `module` (kind `spec`).
fn open_outputs(
    node: &Node<Svc>,
    module: &str,
    spec: &KindSpec,
) -> Result<Vec<OutPort>, ModuleError> {
    let mut outputs = Vec::new();
    for port in &spec.outputs {
        let service = port_service(
            node,
            &output_service(module, &port.name),
            &port.message.payload,
        )?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(port.message.payload.max_bytes().max(1))
            .allocation_strategy(match port.message.payload {
                Payload::Fixed { .. } => AllocationStrategy::Static,
                Payload::Bytes { .. } => AllocationStrategy::PowerOfTwo,
            })
            .create()
            .map_err(ipc("publisher"))?;
        let notifier = event_service(node, &output_event(module, &port.name))?
            .notifier_builder()
            .create()
            .map_err(ipc("notifier"))?;
        outputs.push(OutPort {
            port: port.clone(),
            publisher,
            notifier,
            seq: 0,
            loaned: None,
        });
    }
    Ok(outputs)
}

/// Whether a sample was sent at or after `fresh_after_ns` (CLOCK_MONOTONIC).
fn sent_since(sample: &PortSample, fresh_after_ns: u64) -> bool {
    sample.user_header().stamp_ns >= fresh_after_ns
}

impl SourceConn {
    /// Takes everything queued, keeping only the newest sample.
    fn drain(&mut self) -> Result<bool, ModuleError> {
        let mut any = false;
        while let Some(sample) = self.subscriber.receive().map_err(ipc("receive"))? {
            self.latest = Some(sample);
            self.generation += 1;
            any = true;
        }
        Ok(any)
    }
}

impl Routes {
    fn source(&self, input: usize, slot: u16) -> Option<usize> {
        self.by_input
            .get(input)?
            .get(usize::from(slot))
            .copied()
            .flatten()
    }
}

impl Shm<'_> {
    /// The declaration of output `index`.
    pub(crate) fn output(&self, index: usize) -> Option<&PortSpec> {
        self.outputs.get(index).map(|o| &o.port)
    }

    /// The task of this step's word, by the plan serving it.
    pub(crate) fn task(&self, word: u64) -> Option<&str> {
        let (_, slot) = split_task_word(word);
        self.routes?
            .tasks
            .get(usize::from(slot))
            .map(String::as_str)
    }

    /// The newest sample on `input` (header and bytes), new or not.
    pub(crate) fn sample(&self, input: usize) -> Option<(PortHeader, &[u8])> {
        let conn = (*self.active.get(input)?)?;
        let after = self.fresh_after.get(input).copied().unwrap_or(0);
        self.conns[conn]
            .latest
            .as_ref()
            .filter(|s| sent_since(s, after))
            .map(|s| (*s.user_header(), s.payload()))
    }

    /// The newest sample on `input` if this input has not read it yet.
    pub(crate) fn take_new(&mut self, input: usize) -> Option<(PortHeader, &[u8])> {
        let conn = (*self.active.get(input)?)?;
        let c = &self.conns[conn];
        let mark = Some((conn, c.generation));
        if self.seen[input] == mark {
            return None;
        }
        let after = self.fresh_after.get(input).copied().unwrap_or(0);
        let sample = c.latest.as_ref().filter(|s| sent_since(s, after))?;
        self.seen[input] = mark;
        Some((*sample.user_header(), sample.payload()))
    }

    pub(crate) fn send(
        &mut self,
        index: usize,
        word: u64,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), ModuleError> {
        let out = &mut self.outputs[index];
        let sample = out.publisher.loan_slice_uninit(len).map_err(ipc("loan"))?;
        // Zero the uninitialised bytes only through the safe API: `write_from_fn` initialises
        // each byte once, then `fill` overwrites what it needs.
        let mut sample = sample.write_from_fn(|_| 0u8);
        fill(sample.payload_mut());
        self.stamp_and_send(index, word, sample)
    }

    /// A fixed-size value, copied once into shared memory (no zeroing first).
    pub(crate) fn send_slice(
        &mut self,
        index: usize,
        word: u64,
        data: &[u8],
    ) -> Result<(), ModuleError> {
        let sample = self.outputs[index]
            .publisher
            .loan_slice_uninit(data.len())
            .map_err(ipc("loan"))?;
        let sample = sample.write_from_slice(data);
        self.stamp_and_send(index, word, sample)
    }

    /// Loans `len` zeroed bytes of shared memory on output `index`, to be filled in place and
    /// sent by [`Shm::send_loaned`] in the same step (given back otherwise). A loan not sent
    /// yet on the same output is given back first.
    pub(crate) fn loan(&mut self, index: usize, len: usize) -> Result<&mut [u8], ModuleError> {
        let out = self
            .outputs
            .get_mut(index)
            .ok_or_else(|| ModuleError::Port {
                name: index.to_string(),
                problem: "no such output".into(),
            })?;
        out.loaned = None;
        let sample = out.publisher.loan_slice_uninit(len).map_err(ipc("loan"))?;
        let sample = out.loaned.insert(sample.write_from_fn(|_| 0u8));
        Ok(sample.payload_mut())
    }

    /// Sends the sample loaned on output `index`; an error if there is none.
    pub(crate) fn send_loaned(&mut self, index: usize, word: u64) -> Result<(), ModuleError> {
        let sample = self
            .outputs
            .get_mut(index)
            .and_then(|o| o.loaned.take())
            .ok_or_else(|| ModuleError::Port {
                name: index.to_string(),
                problem: "nothing loaned on this output in this step".into(),
            })?;
        self.stamp_and_send(index, word, sample)
    }

    fn stamp_and_send(
        &mut self,
        index: usize,
        word: u64,
        mut sample: SampleMut<Svc, [u8], PortHeader>,
    ) -> Result<(), ModuleError> {
        let out = &mut self.outputs[index];
        // Stamped last, so latency measures delivery, not how long the producer took to fill.
        *sample.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq: out.seq,
            task_word: word,
        };
        out.seq += 1;
        sample.send().map_err(ipc("send"))?;
        *self.sent += 1;
        out.notifier.notify().map_err(ipc("notify"))?;
        Ok(())
    }
}

/// Opens subscriptions for every source of `plan` not already open, and records its routes.
fn prepare(
    node: &Node<Svc>,
    spec: &KindSpec,
    plan: Plan,
    conns: &mut Vec<SourceConn>,
    listeners: &mut Vec<Listener<Svc>>,
    plans: &mut Vec<Routes>,
) -> Result<(), ModuleError> {
    let mut conn_of_source = Vec::with_capacity(plan.sources.len());
    for (source_idx, source) in plan.sources.iter().enumerate() {
        let payload = source_payload(spec, &plan, source_idx)?;
        let idx = match conns.iter().position(|c| &c.source == source) {
            Some(i) => i,
            None => {
                let (conn, listener) = open_source(node, source, &payload)?;
                conns.push(conn);
                listeners.push(listener);
                conns.len() - 1
            }
        };
        conn_of_source.push(idx);
    }
    let by_input = routes_by_input(spec, &plan, &conn_of_source);
    plans.retain(|p| p.revision < plan.revision);
    plans.push(Routes {
        revision: plan.revision,
        tasks: plan.tasks,
        by_input,
    });
    Ok(())
}

/// The payload of source `source_idx` of `plan`.
fn source_payload(spec: &KindSpec, plan: &Plan, source_idx: usize) -> Result<Payload, ModuleError> {
    // The source's layout is that of the inputs it feeds (the netlist checked they match).
    plan.inputs
        .iter()
        .find(|r| r.by_slot.contains(&Some(source_idx as u32)))
        .and_then(|r| spec.input(&r.port))
        .map(|p| p.message.payload)
        .ok_or_else(|| ModuleError::Ipc(format!("plan source {source_idx} feeds no input")))
}

/// Subscribes to `source` and listens to its "new sample" event.
fn open_source(
    node: &Node<Svc>,
    source: &Source,
    payload: &Payload,
) -> Result<(SourceConn, Listener<Svc>), ModuleError> {
    let (_, buffer) = port_limits(payload);
    let subscriber = port_service(node, &output_service(&source.module, &source.port), payload)?
        .subscriber_builder()
        .buffer_size(buffer)
        .create()
        .map_err(ipc("subscriber"))?;
    let listener = event_service(node, &output_event(&source.module, &source.port))?
        .listener_builder()
        .create()
        .map_err(ipc("listener"))?;
    let conn = SourceConn {
        source: source.clone(),
        subscriber,
        latest: None,
        generation: 0,
    };
    Ok((conn, listener))
}

/// For each input `spec` declares, the connection feeding it per task slot under `plan`, whose
/// sources are connections `conn_of_source`. An input the plan does not route has no slots.
fn routes_by_input(
    spec: &KindSpec,
    plan: &Plan,
    conn_of_source: &[usize],
) -> Vec<Vec<Option<usize>>> {
    spec.inputs
        .iter()
        .map(|port| {
            plan.inputs
                .iter()
                .find(|r| r.port == port.name)
                .map(|r| {
                    r.by_slot
                        .iter()
                        .map(|s| s.and_then(|s| conn_of_source.get(s as usize).copied()))
                        .collect()
                })
                .unwrap_or_default()
        })
        .collect()
}

/// Closes subscriptions no remaining plan uses, renumbering the routes that stay.
fn retire(
    conns: &mut Vec<SourceConn>,
    listeners: &mut Vec<Listener<Svc>>,
    plans: &mut [Routes],
    seen: &mut [Option<(usize, u64)>],
) {
    let used = used_conns(conns.len(), plans);
    if used.iter().all(|u| *u) {
        return;
    }
    let mut keep = used.iter();
    conns.retain(|_| *keep.next().unwrap_or(&false));
    let mut keep = used.iter();
    listeners.retain(|_| *keep.next().unwrap_or(&false));
    renumber(&renumbering(&used), plans, seen);
}

/// Which of `conns` connections some plan routes an input to.
fn used_conns(conns: usize, plans: &[Routes]) -> Vec<bool> {
    (0..conns)
        .map(|c| {
            plans
                .iter()
                .any(|p| p.by_input.iter().flatten().any(|s| *s == Some(c)))
        })
        .collect()
}

/// The new index of each connection once the unused ones are gone (none: it goes).
fn renumbering(used: &[bool]) -> Vec<Option<usize>> {
    let mut remap = vec![None; used.len()];
    let mut next = 0;
    for (i, u) in used.iter().enumerate() {
        if *u {
            remap[i] = Some(next);
            next += 1;
        }
    }
    remap
}

/// Points the routes and the inputs' read marks at the connections' new indices.
fn renumber(remap: &[Option<usize>], plans: &mut [Routes], seen: &mut [Option<(usize, u64)>]) {
    for p in plans.iter_mut() {
        for slots in &mut p.by_input {
            for s in slots.iter_mut() {
                *s = s.and_then(|c| remap[c]);
            }
        }
    }
    for s in seen.iter_mut() {
        *s = s.and_then(|(c, g)| remap[c].map(|c| (c, g)));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Kind;
    use crate::msg::Tick;

    #[test]
    fn a_wait_clears_only_the_sources_that_fired_and_past_64_all_of_the_rest() {
        let mut fired = Fired::default();
        fired.source(2);
        assert!(fired.has_source(2));
        assert!(!fired.has_source(0) && !fired.has_source(3) && !fired.control);
        // Sources from the 64th on share the last bit: one of them firing clears them all.
        fired.source(70);
        assert!(fired.has_source(63) && fired.has_source(64) && fired.has_source(200));
        assert!(!fired.has_source(62));
        assert!(Fired::ALL.control && (0..100).all(|i| Fired::ALL.has_source(i)));
    }

    fn source(module: &str) -> Source {
        Source {
            module: module.into(),
            port: "out".into(),
        }
    }

    fn routes(revision: u64, by_input: Vec<Vec<Option<usize>>>) -> Routes {
        Routes {
            revision,
            tasks: vec!["a".into(), "b".into()],
            by_input,
        }
    }

    #[test]
    fn a_periodic_module_steps_at_its_rate_and_an_on_input_one_has_no_period() {
        assert_eq!(
            step_period(&Trigger::Periodic { rate_hz: 50.0 }).unwrap(),
            Some(Duration::from_millis(20))
        );
        assert_eq!(step_period(&Trigger::OnInput).unwrap(), None);
        for rate_hz in [0.0, 1e12, f64::NAN, -1.0] {
            let err = step_period(&Trigger::Periodic { rate_hz }).unwrap_err();
            assert!(
                err.to_string()
                    .starts_with(&format!("launch description: rate_hz = {rate_hz} gives no")),
                "{err}"
            );
        }
    }

    #[test]
    fn routes_give_each_input_its_source_per_slot() {
        let r = routes(3, vec![vec![Some(0), None], vec![Some(1)]]);
        assert_eq!(r.source(0, 0), Some(0));
        assert_eq!(r.source(0, 1), None);
        assert_eq!(r.source(1, 0), Some(1));
        // Slots and inputs the plan does not know (NO_TASK among them) are unconnected.
        assert_eq!(r.source(1, 1), None);
        assert_eq!(r.source(0, NO_TASK), None);
        assert_eq!(r.source(2, 0), None);
    }

    #[test]
    fn only_an_input_whose_source_changed_hides_older_samples() {
        let mut s = Switches::new(2);
        assert!(s.is_new(task_word(1, 0)));
        // The first word served is the start: nothing is hidden.
        s.record(task_word(1, 0), [Some(source("a")), None].into_iter(), 100);
        assert_eq!(s.fresh_after, [0, 0]);
        assert!(!s.is_new(task_word(1, 0)));
        // Input 0 keeps its source, input 1 gets one.
        s.record(
            task_word(1, 1),
            [Some(source("a")), Some(source("b"))].into_iter(),
            200,
        );
        assert_eq!(s.fresh_after, [0, 200]);
        // Input 0 switches; input 1 keeps its source.
        s.record(
            task_word(2, 1),
            [Some(source("c")), Some(source("b"))].into_iter(),
            300,
        );
        assert_eq!(s.fresh_after, [300, 200]);
        assert_eq!(s.last_word, task_word(2, 1));
        assert_eq!(s.last_sources, [Some(source("c")), Some(source("b"))]);
    }

    fn two_input_kind() -> KindSpec {
        Kind::new("pair", "")
            .input::<Tick>("a")
            .input::<Tick>("b")
            .on_input()
            .build()
    }

    fn plan() -> Plan {
        Plan {
            revision: 4,
            tasks: vec!["x".into(), "y".into()],
            sources: vec![source("s0"), source("s1")],
            inputs: vec![InputRoute {
                port: "b".into(),
                by_slot: vec![Some(1), None, Some(0)],
            }],
            stop: false,
        }
    }

    #[test]
    fn a_plan_routes_inputs_to_the_connections_of_its_sources() {
        let spec = two_input_kind();
        // Source 0 is connection 5, source 1 connection 2.
        assert_eq!(
            routes_by_input(&spec, &plan(), &[5, 2]),
            [vec![], vec![Some(2), None, Some(5)]]
        );
        assert_eq!(
            source_payload(&spec, &plan(), 1).unwrap(),
            spec.inputs[1].message.payload
        );
        let mut unused = plan();
        unused.sources.push(source("s2"));
        assert_eq!(
            source_payload(&spec, &unused, 2).unwrap_err().to_string(),
            "shared memory: plan source 2 feeds no input"
        );
    }

    #[test]
    fn retiring_renumbers_the_connections_that_stay() {
        let mut plans = [
            routes(1, vec![vec![Some(0), Some(3)]]),
            routes(2, vec![vec![None, Some(3)]]),
        ];
        let used = used_conns(4, &plans);
        assert_eq!(used, [true, false, false, true]);
        let remap = renumbering(&used);
        assert_eq!(remap, [Some(0), None, None, Some(1)]);
        let mut seen = [Some((3, 7)), Some((1, 2)), None];
        renumber(&remap, &mut plans, &mut seen);
        assert_eq!(plans[0].by_input, [vec![Some(0), Some(1)]]);
        assert_eq!(plans[1].by_input, [vec![None, Some(1)]]);
        // A mark on a closed connection is forgotten.
        assert_eq!(seen, [Some((1, 7)), None, None]);
        assert!(
            used_conns(2, &[routes(1, vec![vec![Some(1), Some(0)]])])
                .iter()
                .all(|u| *u)
        );
    }
}
