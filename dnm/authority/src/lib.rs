//! The rover's authority: one DNM of the rover (the one the netlist names, else the root of
//! its hierarchy) takes the commands of ground stations and decides for every DNM.
//!
//! - **Exactly once, in order.** A station sends its commands with a sequence number; the
//!   authority stores each (redb, fsync) before acknowledging it, runs them in the station's
//!   order, stores each fate with the decision it led to in one transaction, and answers a
//!   re-sent command with that fate. A restarted authority re-runs nothing it finished.
//! - **Atomic across DNMs.** A switch or an apply is a two-phase transaction: every DNM of the
//!   rover prepares it and holds it; the authority stores its decision, then tells every DNM to
//!   put it in force at one instant (`switch_lead` ahead, wall clock). A DNM puts nothing in
//!   force on its own. A DNM that missed a decision (it restarted, or was cut off) is found by
//!   the reconciler, which sends the decision again or has the DNM adopt the decided revision.
//!   DNMs across the radio (`link = "radio"`) follow the decisions when they are reachable and
//!   never hold up a transaction.
//! - **Time-tagged switches** run at their rover time whether or not a station is in contact,
//!   and can be cancelled until then.
//! - **Safing** (`safing.rs`). With `on_link_loss` in the netlist, the authority makes the
//!   rover safe when no station has been heard for that long: it records a safing and
//!   announces it in its beat, which every DNM keeps a lease on; DNMs it cannot reach make
//!   themselves safe, and it adopts a safing a DNM made on its own. Nothing taken before a
//!   safing runs after it.
//! - **Arrival order.** Stations' commands run in the order they reached the rover.
//!
//! Clocks: the instants are wall-clock times, so the DNMs of the rover must share a
//! synchronised clock (NTP or PTP on the rover's network; one clock on one machine). The spread
//! of switch instants across DNMs is their clock offset plus the wake-up jitter of each
//! machine. Ground stations' clocks matter only for time tags, which are rover time.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let session: zenoh::Session = unimplemented!();
//! # let netlist: dnm_netlist::Netlist = unimplemented!();
//! # let door: dnm_netlist::NetlistDoor = unimplemented!();
//! let options = dnm_authority::AuthorityOptions::new("/var/lib/dnm/beetle-authority.redb");
//! let authority = dnm_authority::Authority::start(session, &netlist, door, options)?;
//! // ... until the DNMs stop:
//! authority.stop();
//! # Ok(()) }
//! ```

mod edit;
mod safing;
mod store;

pub(crate) use dnm_proto::clock::now_unix_ns;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_netlist::{AcceptError, Netlist, NetlistDoor};
use dnm_proto::station::{
    DEFAULT_LATE_BY_MS, Downlink, Fate, Order, RoverEvent, RoverState, Sent, Uplink,
};
use dnm_proto::{DnmBrief, RemoteCommand, Request, Response, keys};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::{ConsolidationMode, Query, QueryTarget};

pub use edit::{ModuleEditError, edit_netlist, param_value};
use store::{DecisionRecord, Finish, State, Store, Timer};

#[derive(Debug, thiserror::Error)]
pub enum AuthorityError {
    #[error("the authority's store: {0}")]
    Store(String),
    #[error("Zenoh: {0}")]
    Zenoh(String),
    #[error("{0}")]
    Netlist(String),
}

/// How the authority works.
#[derive(Debug, Clone)]
pub struct AuthorityOptions {
    /// Its database (created if missing).
    pub db: PathBuf,
    /// From the decision to the instant every DNM puts it in force: long enough for the
    /// decision to reach every DNM of the rover.
    pub switch_lead: Duration,
    /// How long the DNMs may take to prepare a transaction (start modules, subscribe).
    pub prepare_timeout: Duration,
    /// How often every DNM is checked against what was decided.
    pub reconcile_every: Duration,
}

impl AuthorityOptions {
    pub fn new(db: impl Into<PathBuf>) -> Self {
        Self {
            db: db.into(),
            switch_lead: Duration::from_millis(50),
            prepare_timeout: Duration::from_secs(10),
            reconcile_every: Duration::from_millis(500),
        }
    }
}

/// Longest lead of a decision, whatever was measured.
const MAX_LEAD: Duration = Duration::from_secs(1);

/// Uplinks waiting for the intake thread at most; more are dropped (the station sends again).
const UPLINK_QUEUE: usize = 64;
/// Commands in one uplink, at most (a station sends 32).
const MAX_UPLINK_COMMANDS: usize = 64;
/// Time-tagged switches waiting, at most; more are refused.
const MAX_TIMERS: usize = 256;
/// Events and time-tagged commands in an answer to a station, at most.
const STATE_EVENTS: usize = 16;

/// What the worker decides with: the durable state and the netlist in force.
pub(crate) struct Core {
    state: State,
    netlist: Netlist,
    digest: String,
}

/// What the lead of a decision must cover, as measured: a round trip to the slowest DNM and
/// a durable write (smoothed, the worst recent value weighing most).
#[derive(Debug, Default)]
struct Timing {
    round_trip: Duration,
    store: Duration,
    /// How long a transaction that runs at once keeps the worker, prepare to last ack.
    busy: Duration,
}

impl Timing {
    fn round_trip(&mut self, d: Duration) {
        self.round_trip = (self.round_trip * 7 / 8 + d / 8).max(d);
    }

    fn store(&mut self, d: Duration) {
        self.store = (self.store * 7 / 8 + d / 8).max(d);
    }

    fn busy(&mut self, d: Duration) {
        self.busy = (self.busy * 7 / 8 + d / 8).max(d).min(MAX_BUSY);
    }

    fn lead(&self, least: Duration) -> Duration {
        least.max((self.round_trip * 2 + self.store * 2).min(MAX_LEAD))
    }
}

/// The least and the most a transaction is expected to keep the worker when deciding whether
/// a command can run before a time tag falls due.
const MIN_BUSY: Duration = Duration::from_millis(500);
const MAX_BUSY: Duration = Duration::from_secs(5);

pub(crate) struct Shared {
    timing: Mutex<Timing>,
    system: String,
    name: String,
    session: zenoh::Session,
    store: Store,
    /// Where the netlists of stations' applies and module edits come in.
    door: NetlistDoor,
    options: AuthorityOptions,
    core: Mutex<Core>,
    /// What stations are told of the rover.
    rover: Mutex<RoverState>,
    /// When a station was last heard.
    contact: Mutex<Instant>,
    heard: AtomicBool,
    wake: (Mutex<bool>, Condvar),
    /// Wakes the beat thread (a safing is announced at once).
    beat: (Mutex<bool>, Condvar),
    /// When each DNM of the rover last answered the reconciler.
    dnms_heard: Mutex<BTreeMap<String, Instant>>,
    /// Time tags' instants on the monotonic clock.
    tag_clock: Mutex<BTreeMap<(String, u64), Instant>>,
    stop: AtomicBool,
}

impl Shared {
    fn wake(&self) {
        if let Ok(mut w) = self.wake.0.lock() {
            *w = true;
            self.wake.1.notify_all();
        }
    }

    fn sleep(&self, d: Duration) {
        let Ok(w) = self.wake.0.lock() else {
            return;
        };
        if let Ok((mut w, _)) = self.wake.1.wait_timeout_while(w, d, |w| !*w) {
            *w = false;
        }
    }
}

/// The running authority: its queryable for stations, its worker and its reconciler.
pub struct Authority {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
    _queryable: zenoh::query::Queryable<()>,
}

impl std::fmt::Debug for Authority {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Authority")
            .field("system", &self.shared.system)
            .field("dnm", &self.shared.name)
            .finish_non_exhaustive()
    }
}

impl Authority {
    /// Starts the authority of `netlist`'s system on `session`. Its state comes from the
    /// database; a new database starts from `netlist`, decided as the revision after any the
    /// running DNMs have used.
    pub fn start(
        session: zenoh::Session,
        netlist: &Netlist,
        door: NetlistDoor,
        options: AuthorityOptions,
    ) -> Result<Self, AuthorityError> {
        let name = netlist
            .authority()
            .ok_or_else(|| AuthorityError::Netlist("the netlist names no authority DNM".into()))?
            .to_string();
        let system = netlist.system.clone();
        let store = Store::open(&options.db)?;
        let state = match store.state()? {
            Some(s) => {
                if s.text != netlist.text {
                    tracing::warn!(
                        revision = s.revision,
                        "continuing from the decided revision {}; {} is not it (apply it to change)",
                        s.revision,
                        netlist.file.display()
                    );
                }
                s
            }
            None => {
                let found = reports(&session, &system, Duration::from_secs(1));
                let used = found
                    .iter()
                    .map(|r| r.last_attempt.max(r.revision))
                    .max()
                    .unwrap_or(0);
                let revision = used + 1;
                // A rover already running (this store was lost or replaced) goes on with what
                // it runs: the newest netlist in force on its DNMs, in its task.
                let (file, text, task) = match running(&session, &door) {
                    Some((n, task)) => {
                        tracing::warn!(
                            file = %n.file.display(),
                            task = ?task,
                            "a new store for a running rover: continuing with what it runs"
                        );
                        (n.file.display().to_string(), n.text.clone(), task)
                    }
                    None => (
                        netlist.file.display().to_string(),
                        netlist.text.clone(),
                        netlist.initial_task().map(str::to_string),
                    ),
                };
                let s = State {
                    revision,
                    task,
                    file,
                    text,
                    // Ids never seen before by any DNM, even if this database is new again:
                    // they start from the time it was created.
                    next_txn: (now_unix_ns() / 1_000_000_000) << 24,
                    burned: revision,
                    ..State::default()
                };
                store.save_state(&s)?;
                tracing::info!(revision, file = %netlist.file.display(), "authority decided its first revision");
                s
            }
        };
        let current = door.accept(&state.file, &state.text).map_err(|e| {
            AuthorityError::Netlist(format!("the decided netlist no longer validates: {e}"))
        })?;
        let digest = format!("{:016x}", current.digest());
        let contact = last_contact(&store);
        let shared = Arc::new(Shared {
            timing: Mutex::new(Timing::default()),
            system: system.clone(),
            name,
            session: session.clone(),
            store,
            door,
            options,
            core: Mutex::new(Core {
                state,
                netlist: current,
                digest,
            }),
            rover: Mutex::new(RoverState::default()),
            // A restarted authority counts the ground's silence from the last uplink it took,
            // not from its start: an authority that restarts does not put off loss of signal.
            contact: Mutex::new(contact),
            heard: AtomicBool::new(false),
            wake: (Mutex::new(false), Condvar::new()),
            beat: (Mutex::new(false), Condvar::new()),
            tag_clock: Mutex::new(BTreeMap::new()),
            dnms_heard: Mutex::new(BTreeMap::new()),
            stop: AtomicBool::new(false),
        });
        if let Ok(core) = shared.core.lock() {
            publish_rover(&shared, &core);
        }
        // Transactions a stopped authority left undecided are dropped by the reconciler; the
        // worker starts none while any DNM still holds one (it waits for them all in step), so
        // stations are heard from the first moment.
        let (tx, rx) = mpsc::sync_channel::<Query>(UPLINK_QUEUE);
        let queryable = session
            .declare_queryable(keys::authority_stations(&system))
            .callback(move |q| {
                if tx.try_send(q).is_err() {
                    tracing::warn!("uplink dropped: the authority is busy");
                }
            })
            .wait()
            .map_err(|e| AuthorityError::Zenoh(e.to_string()))?;
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|e| AuthorityError::Zenoh(format!("spawning {name}: {e}")))
        };
        let publisher = safing::beat_publisher(&session, &system)?;
        let threads = vec![
            spawn("authority-beat", {
                let s = shared.clone();
                Box::new(move || safing::beat_loop(&s, &publisher))
            })?,
            spawn("authority-intake", {
                let s = shared.clone();
                Box::new(move || intake_loop(&s, &rx))
            })?,
            spawn("authority-worker", {
                let s = shared.clone();
                Box::new(move || worker_loop(&s))
            })?,
            spawn("authority-reconcile", {
                let s = shared.clone();
                Box::new(move || reconcile_loop(&s, Side::Rover))
            })?,
            spawn("authority-reconcile-radio", {
                let s = shared.clone();
                Box::new(move || reconcile_loop(&s, Side::Radio))
            })?,
        ];
        tracing::info!(system = %system, dnm = %shared.name, "authority ready");
        Ok(Self {
            shared,
            threads,
            _queryable: queryable,
        })
    }

    /// Stops the authority's threads (a transaction in flight finishes first).
    pub fn stop(self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        self.shared.wake();
        safing::beat_now(&self.shared);
        for t in self.threads {
            let _ = t.join();
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Stations.

fn intake_loop(s: &Shared, rx: &mpsc::Receiver<Query>) {
    loop {
        let q = match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(q) => q,
            Err(mpsc::RecvTimeoutError::Timeout) if !s.stop.load(Ordering::Relaxed) => continue,
            Err(_) => return,
        };
        let answer = take_uplink(s, &q);
        let bytes = serde_json::to_vec(&answer).unwrap_or_default();
        if let Err(e) = q.reply(q.key_expr().clone(), bytes).wait() {
            tracing::debug!("answering a station: {e}");
        }
    }
}

fn take_uplink(s: &Shared, q: &Query) -> Downlink {
    let rover = || s.rover.lock().map(|r| r.clone()).unwrap_or_default();
    let refuse = |e: String| Downlink {
        at_unix_ns: now_unix_ns(),
        outcomes: Vec::new(),
        rover: rover(),
        error: Some(e),
    };
    let Some(payload) = q.payload() else {
        return refuse(
            "empty uplink; send JSON {\"station\":\"ground-1\",\"commands\":[...]}".into(),
        );
    };
    let up: Uplink = match serde_json::from_slice(&payload.to_bytes()) {
        Ok(u) => u,
        Err(e) => {
            return refuse(format!(
                "unreadable uplink ({e}); send JSON {{\"station\":\"ground-1\",\"commands\":[{{\"seq\":1,\"id\":\"…\",\"order\":{{\"cmd\":\"switch\",\"task\":\"auto\"}}}}]}}"
            ));
        }
    };
    if up.station.is_empty()
        || up.station.len() > 64
        || up.station.contains(['\0', '/', '*', '$', '?', '#'])
    {
        return refuse(format!(
            "station name `{}` is not usable: 1 to 64 characters, no `/`, `*`, `$`, `?`, `#`",
            up.station
        ));
    }
    // A station speaks only for itself: its name is the key's (which the access control binds
    // to its certificate), the outbox's epoch after a `.`.
    let keyed = keys::station_of(&s.system, q.key_expr().as_str()).unwrap_or_default();
    if up.station != keyed && !up.station.starts_with(&format!("{keyed}.")) {
        tracing::warn!(
            key = %q.key_expr(),
            station = %up.station,
            "uplink refused: a station speaks only for itself"
        );
        return refuse(format!(
            "uplink of station `{}` on the key of station `{keyed}`: a station sends on \
             {} only",
            up.station,
            keys::authority_station(&s.system, "<its own name>")
        ));
    }
    if up.commands.len() > MAX_UPLINK_COMMANDS {
        return refuse(format!(
            "{} commands in one uplink: send at most {MAX_UPLINK_COMMANDS} at a time",
            up.commands.len()
        ));
    }
    match s.store.admits(&up.station) {
        Ok(true) => {}
        Ok(false) => {
            return refuse(format!(
                "the rover keeps a record of at most {} stations; `{}` is not one of them",
                store::MAX_STATIONS,
                up.station
            ));
        }
        Err(e) => return refuse(format!("the rover could not read its store: {e}")),
    }
    if let Ok(mut c) = s.contact.lock() {
        *c = Instant::now();
    }
    if !s.heard.swap(true, Ordering::Relaxed) {
        s.wake();
    }
    match s
        .store
        .intake(&up.station, &up.commands, up.pending_from, &up.waiting)
    {
        Ok(outcomes) => {
            if outcomes.iter().any(|o| o.fate == Fate::Acknowledged) {
                s.wake();
            }
            Downlink {
                at_unix_ns: now_unix_ns(),
                outcomes,
                rover: rover(),
                error: None,
            }
        }
        Err(e) => {
            tracing::error!("taking commands of `{}`: {e}", up.station);
            refuse(format!("the rover could not store the commands: {e}"))
        }
    }
}

pub(crate) fn publish_rover(s: &Shared, core: &Core) {
    let scheduled = s
        .store
        .timers()
        .unwrap_or_default()
        .into_iter()
        .map(|t| (t.station, t.seq, t.at_unix_ns))
        .collect();
    let events = core
        .state
        .events
        .iter()
        .rev()
        .take(STATE_EVENTS)
        .rev()
        .cloned()
        .collect();
    if let Ok(mut r) = s.rover.lock() {
        *r = RoverState {
            authority: s.name.clone(),
            revision: core.state.revision,
            task: core.state.task.clone(),
            events,
            scheduled,
            last_safing: core.state.last_safing.clone(),
            safe: core.state.safe,
        };
    }
}

// ---------------------------------------------------------------------------------------------
// The worker: commands in order, time tags, loss of signal.

fn worker_loop(s: &Shared) {
    // The job waiting for the rover's DNMs to be in step, and since when.
    let mut gate: Option<(String, Instant)> = None;
    while !s.stop.load(Ordering::Relaxed) {
        match work_once(s, &mut gate) {
            Ok(true) => {}
            Ok(false) => s.sleep(Duration::from_millis(100)),
            Err(e) => {
                tracing::error!("authority: {e}");
                s.sleep(Duration::from_secs(1));
            }
        }
    }
}

/// What the worker does next.
enum Job {
    /// A station was heard again after the link was lost.
    LinkBack,
    LinkLoss {
        task: String,
        silent: Duration,
    },
    Timer(Timer),
    Command(String, Sent),
}

impl Job {
    fn key(&self) -> String {
        match self {
            Job::LinkBack => "link-back".into(),
            Job::LinkLoss { .. } => "link-loss".into(),
            Job::Timer(t) => format!("timer {} {}", t.station, t.seq),
            Job::Command(st, c) => format!("command {st} {}", c.seq),
        }
    }

    /// Whether it changes what the DNMs run (and so needs them all in step first).
    fn transacts(&self) -> bool {
        match self {
            Job::LinkBack => false,
            // Safing is no transaction: DNMs that cannot be reached make themselves safe.
            Job::LinkLoss { .. } => false,
            Job::Timer(_) => true,
            Job::Command(_, c) => !matches!(c.order, Order::Cancel { .. }),
        }
    }
}

fn next_job(s: &Shared, core: &Core) -> Result<Option<Job>, AuthorityError> {
    if s.heard.load(Ordering::Relaxed) && core.state.link_lost {
        return Ok(Some(Job::LinkBack));
    }
    if let Some(l) = &core.netlist.on_link_loss {
        let silent = s.contact.lock().map(|c| c.elapsed()).unwrap_or_default();
        if silent >= Duration::from_millis(l.after_ms) && !core.state.link_lost {
            return Ok(Some(Job::LinkLoss {
                task: l.task.clone(),
                silent,
            }));
        }
    }
    // Time-tagged switches whose time has come (prepared a little ahead).
    let margin = tag_margin(s);
    let now = now_unix_ns();
    let cancels = s.store.pending_cancels()?;
    let timers = s.store.timers()?;
    let due = tag_clock(s, &timers);
    let timer = timers
        .into_iter()
        // A cancel already taken for it runs first (the station's earlier commands with it).
        .filter(|t| !cancels.contains(&(t.station.clone(), t.seq)))
        .min_by_key(|t| t.at_unix_ns);
    // Due by the wall clock and by the monotonic one: a forward step of the wall clock does
    // not fire a tag early.
    let is_due = |t: &Timer, ahead: u64| {
        t.at_unix_ns <= now + ahead
            && due.get(&(t.station.clone(), t.seq)).is_none_or(|d| {
                d.saturating_duration_since(Instant::now()).as_nanos() as u64 <= ahead
            })
    };
    if let Some(t) = timer.as_ref().filter(|t| is_due(t, margin)) {
        return Ok(Some(Job::Timer(t.clone())));
    }
    let Some((station, sent)) = s.store.next_command()? else {
        return Ok(None);
    };
    // A command that would still hold the worker when a time tag is due to be prepared waits
    // for it: the tag is prepared early and runs at its time, the command right after.
    let busy = s
        .timing
        .lock()
        .map(|t| t.busy)
        .unwrap_or_default()
        .max(MIN_BUSY)
        .as_nanos() as u64;
    if !matches!(sent.order, Order::Cancel { .. })
        && let Some(t) = timer.filter(|t| is_due(t, margin + busy))
    {
        return Ok(Some(Job::Timer(t)));
    }
    Ok(Some(Job::Command(station, sent)))
}

/// Each time tag's instant on the monotonic clock, fixed when the authority first sees the tag
/// (from the wall clock then): a later step of the wall clock moves the wall-clock instant, not
/// this one, and a tag runs only once both have come. Tags no longer waiting are forgotten.
fn tag_clock(s: &Shared, timers: &[Timer]) -> BTreeMap<(String, u64), Instant> {
    let Ok(mut clock) = s.tag_clock.lock() else {
        return BTreeMap::new();
    };
    let now = now_unix_ns();
    clock.retain(|k, _| timers.iter().any(|t| (&t.station, t.seq) == (&k.0, k.1)));
    for t in timers {
        clock.entry((t.station.clone(), t.seq)).or_insert_with(|| {
            Instant::now() + Duration::from_nanos(t.at_unix_ns.saturating_sub(now))
        });
    }
    clock.clone()
}

/// Longest wait for the rover's DNMs to be in step before a transaction is tried anyway (and
/// refused with what the DNMs say).
const READY_WAIT: Duration = Duration::from_secs(30);

/// Does one piece of work if there is one; returns whether it did.
fn work_once(s: &Shared, gate: &mut Option<(String, Instant)>) -> Result<bool, AuthorityError> {
    let lock = || {
        s.core
            .lock()
            .map_err(|_| AuthorityError::Store("the authority's state lock is poisoned".into()))
    };
    let (job, snapshot) = {
        let core = lock()?;
        let Some(job) = next_job(s, &core)? else {
            *gate = None;
            return Ok(false);
        };
        let snapshot = job.transacts().then(|| Snapshot::of(&core));
        (job, snapshot)
    };
    if let Some(snap) = snapshot {
        // A DNM that restarted or missed a decision is brought in step by the reconciler
        // first: a transaction now would only be refused by it.
        let key = job.key();
        let since = match gate.as_ref() {
            Some((k, t)) if *k == key => *t,
            _ => Instant::now(),
        };
        *gate = Some((key, since));
        if since.elapsed() < READY_WAIT
            && let Some(why) = out_of_step(s, &snap)
        {
            tracing::debug!("waiting for the rover's DNMs: {why}");
            return Ok(false);
        }
    }
    *gate = None;
    let mut core = lock()?;
    let core = &mut *core;
    match job {
        Job::LinkBack => {
            core.state.link_lost = false;
            let e = RoverEvent {
                at_unix_ns: now_unix_ns(),
                what: "link_back".into(),
                detail: "a ground station was heard again; the rover stays in its task".into(),
                revision: core.state.revision,
                task: core.state.task.clone(),
            };
            tracing::info!("ground station heard again");
            core.state.event(e);
            s.store.save_state(&core.state)?;
        }
        Job::LinkLoss { task, silent } => {
            let reason = format!(
                "no ground station heard for {:.1} s: switching to `{task}`",
                silent.as_secs_f64()
            );
            s.heard.store(false, Ordering::Relaxed);
            core.state.link_lost = true;
            safing::make_safe(s, core, task, "link_loss", reason)?;
        }
        Job::Timer(t) if let Some(reason) = timer_refusal(core, &t) => {
            tracing::warn!(station = %t.station, seq = t.seq, "time-tagged switch refused: {reason}");
            s.store.finish(Finish {
                fates: vec![(&t.station, t.seq, &t.id, Fate::Refused { reason })],
                timer_remove: Some((&t.station, t.seq)),
                ..Finish::default()
            })?;
        }
        Job::Timer(t) => {
            let cmd = (t.station.clone(), t.seq, t.id.clone());
            transact(
                s,
                core,
                None,
                Some(t.task.clone()),
                Some(t.at_unix_ns),
                Some(cmd),
                Some((t.station.clone(), t.seq)),
            );
        }
        Job::Command(station, sent) => run_command(s, core, &station, sent)?,
    }
    publish_rover(s, core);
    Ok(true)
}

/// What the DNMs are checked against, copied out of the lock.
struct Snapshot {
    revision: u64,
    task: Option<String>,
    digest: String,
    next_txn: u64,
    file: String,
    text: String,
    decisions: Vec<DecisionRecord>,
    participants: Vec<String>,
    radio: Vec<String>,
}

impl Snapshot {
    fn of(core: &Core) -> Self {
        let (radio, participants): (Vec<_>, Vec<_>) =
            core.netlist.dnms.iter().partition(|d| d.radio);
        Self {
            revision: core.state.revision,
            task: core.state.task.clone(),
            digest: core.digest.clone(),
            next_txn: core.state.next_txn,
            file: core.state.file.clone(),
            text: core.state.text.clone(),
            decisions: core.state.decisions.clone(),
            participants: participants.into_iter().map(|d| d.name.clone()).collect(),
            radio: radio.into_iter().map(|d| d.name.clone()).collect(),
        }
    }

    fn in_step(&self, r: &DnmBrief) -> bool {
        r.holding.is_none()
            && r.preparing.is_none()
            && r.revision == self.revision
            && r.active_task == self.task
            && r.netlist_digest == self.digest
    }
}

/// Why the rover's DNMs are not all in step with what was decided, if they are not.
fn out_of_step(s: &Shared, snap: &Snapshot) -> Option<String> {
    let found = reports_of(s, &snap.participants, Duration::from_secs(1));
    for (d, r) in snap.participants.iter().zip(found) {
        match r {
            None => return Some(format!("DNM `{d}` does not answer")),
            Some(r) if !snap.in_step(&r) => {
                return Some(format!(
                    "DNM `{d}` is on revision {} task {:?}, holding {:?}",
                    r.revision, r.active_task, r.holding
                ));
            }
            // An apply undone (or a module replaced) a moment ago: its processes are still
            // going, and a new apply would be refused until they are gone.
            Some(r) if r.modules_stopping > 0 => {
                return Some(format!(
                    "DNM `{d}` still stops {} module processes",
                    r.modules_stopping
                ));
            }
            Some(_) => {}
        }
    }
    None
}

fn refuse(s: &Shared, station: &str, sent: &Sent, reason: String) -> Result<(), AuthorityError> {
    tracing::warn!(station, seq = sent.seq, "command refused: {reason}");
    s.store.finish(Finish {
        fates: vec![(station, sent.seq, &sent.id, Fate::Refused { reason })],
        done: Some((station, sent.seq)),
        ..Finish::default()
    })
}

fn run_command(
    s: &Shared,
    core: &mut Core,
    station: &str,
    sent: Sent,
) -> Result<(), AuthorityError> {
    let cmd = Some((station.to_string(), sent.seq, sent.id.clone()));
    if let Some(reason) = safing::stale(core, sent.safings_seen) {
        return refuse(s, station, &sent, reason);
    }
    match &sent.order {
        Order::Switch {
            task,
            at_unix_ns,
            late_by_ms,
        } => {
            let late_by = late_by_ms.unwrap_or(DEFAULT_LATE_BY_MS);
            if let Some(at) = *at_unix_ns
                && let Some(why) = too_late(at, late_by)
            {
                return refuse(s, station, &sent, why);
            }
            if !core.netlist.tasks.contains_key(task) {
                let known: Vec<&str> = core.netlist.tasks.keys().map(String::as_str).collect();
                return refuse(
                    s,
                    station,
                    &sent,
                    format!("unknown task `{task}`; the tasks are {}", known.join(", ")),
                );
            }
            let lead = tag_margin(s);
            if at_unix_ns.is_some_and(|at| at > now_unix_ns() + lead)
                && s.store.timers()?.len() >= MAX_TIMERS
            {
                return refuse(
                    s,
                    station,
                    &sent,
                    format!("{MAX_TIMERS} time-tagged switches wait already: cancel some first"),
                );
            }
            if let Some(at) = at_unix_ns.filter(|at| *at > now_unix_ns() + lead) {
                tracing::info!(
                    station,
                    seq = sent.seq,
                    task,
                    at,
                    "time-tagged switch scheduled"
                );
                return s.store.finish(Finish {
                    fates: vec![(
                        station,
                        sent.seq,
                        &sent.id,
                        Fate::Scheduled { at_unix_ns: at },
                    )],
                    done: Some((station, sent.seq)),
                    timer_add: Some(Timer {
                        station: station.to_string(),
                        seq: sent.seq,
                        id: sent.id.clone(),
                        task: task.clone(),
                        at_unix_ns: at,
                        safings_seen: sent.safings_seen,
                        late_by_ms: late_by,
                    }),
                    ..Finish::default()
                });
            }
            transact(s, core, None, Some(task.clone()), *at_unix_ns, cmd, None);
            Ok(())
        }
        Order::Apply { file, text } => match s.door.accept(file, text) {
            Err(e) => refuse(s, station, &sent, e.to_string()),
            Ok(n) => {
                transact(s, core, Some(n), None, None, cmd, None);
                Ok(())
            }
        },
        Order::Module { edit } => {
            let edited = edit_netlist(&core.state.text, edit)
                .map_err(|e| e.to_string())
                .and_then(|(text, what)| {
                    let file = format!("<{} netlist in force, {what}>", s.system);
                    s.door.accept(&file, &text).map_err(|e| match e {
                        AcceptError::Invalid(e) => {
                            format!("{what}: the netlist would not validate:\n{e}")
                        }
                        other => format!("{what}: {other}"),
                    })
                });
            match edited {
                Err(e) => refuse(s, station, &sent, e),
                Ok(n) => {
                    transact(s, core, Some(n), None, None, cmd, None);
                    Ok(())
                }
            }
        }
        Order::Cancel { seq } => {
            if let Some(t) = s.store.timer(station, *seq)? {
                tracing::info!(station, seq, "time-tagged switch cancelled");
                return s.store.finish(Finish {
                    fates: vec![
                        (station, *seq, &t.id, Fate::CancelledBy { by: sent.seq }),
                        (
                            station,
                            sent.seq,
                            &sent.id,
                            Fate::Cancelled { target: *seq },
                        ),
                    ],
                    done: Some((station, sent.seq)),
                    timer_remove: Some((station, *seq)),
                    ..Finish::default()
                });
            }
            let why = match s.store.fate(station, *seq)? {
                None if *seq >= sent.seq => format!("command {seq} comes after this cancel"),
                None => format!("command {seq} is not a time-tagged switch waiting for its time"),
                Some(Fate::Applied {
                    revision,
                    at_unix_ns,
                    ..
                }) => format!(
                    "command {seq} already ran (revision {revision}, at {at_unix_ns} ns rover time)"
                ),
                Some(f) => format!("command {seq} is not waiting: {}", describe(&f)),
            };
            refuse(s, station, &sent, format!("nothing to cancel: {why}"))
        }
    }
}

/// Why a time-tagged switch whose time has come may not run, if it may not.
fn timer_refusal(core: &Core, t: &Timer) -> Option<String> {
    if !core.netlist.tasks.contains_key(&t.task) {
        return Some(format!(
            "task `{}` is no longer defined (a netlist applied since removed it)",
            t.task
        ));
    }
    safing::stale(core, t.safings_seen).or_else(|| too_late(t.at_unix_ns, t.late_by_ms))
}

/// Why a time-tagged switch for `at` may no longer run, if it may not: it is more than
/// `late_by_ms` past its time.
fn too_late(at: u64, late_by_ms: u64) -> Option<String> {
    let late = now_unix_ns().saturating_sub(at);
    (late > late_by_ms.saturating_mul(1_000_000)).then(|| {
        format!(
            "not run: its time passed {:.1} s ago and it may run at most {:.1} s late (the \
             rover was out of reach or its authority down); send it again with a new time, or \
             a longer validity (`--late-by`)",
            late as f64 / 1e9,
            late_by_ms as f64 / 1e3
        )
    })
}

fn describe(f: &Fate) -> String {
    match f {
        Fate::Refused { reason } => format!("it was refused ({reason})"),
        Fate::CancelledBy { by } => format!("it was cancelled by command {by}"),
        Fate::Cancelled { .. } => "it is a cancel".into(),
        other => format!("{other:?}"),
    }
}

/// Runs one transaction on every DNM of the rover: prepare everywhere, decide (stored with
/// the command's fate in one write), then put in force at one instant everywhere.
#[allow(clippy::too_many_arguments)]
fn transact(
    s: &Shared,
    core: &mut Core,
    netlist: Option<Netlist>,
    task: Option<String>,
    at: Option<u64>,
    cmd: Option<(String, u64, String)>,
    timer_remove: Option<(String, u64)>,
) -> Fate {
    let origin = Origin { cmd, timer_remove };
    let finish = |core: &Core, fate: &Fate| origin.record(s, core, fate);
    let target = netlist.as_ref().unwrap_or(&core.netlist);
    let participants: Vec<String> = target
        .dnms
        .iter()
        .filter(|d| !d.radio)
        .map(|d| d.name.clone())
        .collect();
    let task = task_after(core, target, task);
    let (file, text) = match &netlist {
        Some(n) => (Some(n.file.display().to_string()), Some(n.text.clone())),
        None => (None, None),
    };
    // Numbers first, durably: a restarted authority never hands them out again.
    let (id, revision) = next_numbers(core, netlist.is_some());
    if let Err(e) = s.store.save_state(&core.state) {
        return Fate::Refused {
            reason: format!("the rover could not store the transaction: {e}"),
        };
    }
    let started = Instant::now();
    let prepare = Request::Prepare {
        txn: id,
        revision,
        task: task.clone(),
        file,
        text,
    };
    let votes = ask_all(s, &participants, &prepare, id, s.options.prepare_timeout);
    if netlist.is_none() {
        // A switch prepares at once: its prepare is one round trip to the slowest DNM.
        s.timing
            .lock()
            .map(|mut t| t.round_trip(started.elapsed()))
            .ok();
    }
    let refusals = refusals(&votes);
    if !refusals.is_empty() {
        let decision = DecisionRecord {
            txn: id,
            commit: false,
            at_unix_ns: now_unix_ns(),
            revision,
            task: task.clone(),
        };
        core.state.decided(decision.clone());
        let fate = Fate::Refused {
            reason: format!("nothing changed: {}", refusals.join("; ")),
        };
        let _ = finish(core, &fate);
        let _ = ask_all(
            s,
            &participants,
            &decide(&decision),
            id,
            Duration::from_secs(2),
        );
        tracing::warn!(txn = id, "transaction dropped: {}", refusals.join("; "));
        return fate;
    }
    // The instant leaves time to store the decision and for it to reach every DNM (both as
    // measured lately), so every DNM holds it before the instant and they switch together.
    let lead = s
        .timing
        .lock()
        .map(|t| t.lead(s.options.switch_lead))
        .unwrap_or(s.options.switch_lead);
    let at_unix_ns = (now_unix_ns() + lead.as_nanos() as u64).max(at.unwrap_or(0));
    let decision = DecisionRecord {
        txn: id,
        commit: true,
        at_unix_ns,
        revision,
        task: task.clone(),
    };
    let before = (
        core.state.clone(),
        core.netlist.clone(),
        core.digest.clone(),
    );
    let removal = netlist
        .as_ref()
        .map(|n| removal(&core.netlist, n, revision, task.clone()));
    core.state.decided(decision.clone());
    if let Some(n) = netlist {
        core.state.file = n.file.display().to_string();
        core.state.text = n.text.clone();
        core.digest = format!("{:016x}", n.digest());
        core.netlist = n;
    }
    let fate = Fate::Applied {
        revision,
        task: task.clone(),
        at_unix_ns,
    };
    let storing = Instant::now();
    let stored = finish(core, &fate);
    s.timing.lock().map(|mut t| t.store(storing.elapsed())).ok();
    if stored.is_ok() {
        // The beat says what is decided before any DNM puts it in force: a DNM must not
        // hear the safing this decision ends after it left it.
        publish_rover(s, core);
        safing::beat_now(s);
    }
    if let Err(e) = stored {
        // Not decided after all: drop it everywhere.
        (core.state, core.netlist, core.digest) = before;
        let abort = DecisionRecord {
            commit: false,
            ..decision
        };
        let _ = ask_all(
            s,
            &participants,
            &decide(&abort),
            id,
            Duration::from_secs(2),
        );
        return Fate::Refused {
            reason: format!("the rover could not store the decision: {e}"),
        };
    }
    let missing = put_in_force(s, &participants, &decision);
    if let Some((removed, request)) = removal.filter(|(r, _)| !r.is_empty()) {
        log_answers(ask_all(s, &removed, &request, id, Duration::from_secs(2)));
    }
    if at.is_none() {
        s.timing.lock().map(|mut t| t.busy(started.elapsed())).ok();
    }
    tracing::info!(
        txn = id,
        revision,
        task = ?task,
        ms = started.elapsed().as_millis() as u64,
        missing = ?missing,
        "decided"
    );
    fate
}

/// The command (or time tag) a transaction runs for: its fate is stored with the decision.
struct Origin {
    /// (station, seq, id).
    cmd: Option<(String, u64, String)>,
    /// The time tag it takes out, if it is one.
    timer_remove: Option<(String, u64)>,
}

impl Origin {
    /// Stores `fate` with the state and its newest decision, in one write.
    fn record(&self, s: &Shared, core: &Core, fate: &Fate) -> Result<(), AuthorityError> {
        let fates = self
            .cmd
            .iter()
            .map(|(st, seq, id)| (st.as_str(), *seq, id.as_str(), fate.clone()))
            .collect();
        let r = s.store.finish(Finish {
            fates,
            done: self.cmd.as_ref().map(|(st, seq, _)| (st.as_str(), *seq)),
            timer_add: None,
            timer_remove: self
                .timer_remove
                .as_ref()
                .map(|(st, seq)| (st.as_str(), *seq)),
            timers_remove: Vec::new(),
            state: Some(&core.state),
            decision: core.state.decisions.last(),
        });
        if let Err(e) = &r {
            tracing::error!("storing a decision: {e}");
        }
        r
    }
}

/// The task in force after a transaction on `target`: the one named, else the active one if
/// it is still defined, else the netlist's initial task.
fn task_after(core: &Core, target: &Netlist, task: Option<String>) -> Option<String> {
    task.filter(|t| target.tasks.contains_key(t))
        .or_else(|| {
            core.state
                .task
                .clone()
                .filter(|t| target.tasks.contains_key(t))
        })
        .or_else(|| target.initial_task().map(str::to_string))
}

/// The next transaction id and the revision it puts in force (a new one for an apply, never
/// used before; the one in force for a switch).
fn next_numbers(core: &mut Core, apply: bool) -> (u64, u64) {
    let id = core.state.next_txn;
    core.state.next_txn += 1;
    let revision = if apply {
        core.state.burned = core.state.burned.max(core.state.revision) + 1;
        core.state.burned
    } else {
        core.state.revision
    };
    (id, revision)
}

/// Why the DNMs refused a prepare, one line each (empty: every DNM is ready).
fn refusals(votes: &[(String, Result<Response, String>)]) -> Vec<String> {
    votes
        .iter()
        .filter_map(|(d, r)| match r {
            Ok(r) if r.ok => None,
            Ok(r) => Some(
                r.error
                    .clone()
                    .unwrap_or_else(|| format!("DNM `{d}` refused")),
            ),
            Err(e) => Some(format!("DNM `{d}`: {e}")),
        })
        .collect()
}

/// The DNMs an apply of `to` removes from `from`, and what they are told once the decision is
/// in force (so they stop their modules).
fn removal(
    from: &Netlist,
    to: &Netlist,
    revision: u64,
    task: Option<String>,
) -> (Vec<String>, Request) {
    let removed = from
        .dnms
        .iter()
        .filter(|d| to.dnm(&d.name).is_none())
        .map(|d| d.name.clone())
        .collect();
    let request = Request::Adopt {
        revision,
        task,
        file: to.file.display().to_string(),
        text: to.text.clone(),
    };
    (removed, request)
}

/// Sends the stored decision until every DNM acknowledges it (after the instant), three times
/// at most; returns those that did not (the reconciler catches them: the decision is stored).
fn put_in_force(s: &Shared, participants: &[String], decision: &DecisionRecord) -> Vec<String> {
    let request = decide(decision);
    let mut missing = participants.to_vec();
    for _ in 0..3 {
        let wait = Duration::from_nanos(decision.at_unix_ns.saturating_sub(now_unix_ns()))
            + Duration::from_secs(2);
        let acks = ask_all(s, &missing, &request, decision.txn, wait);
        missing = acks
            .into_iter()
            .filter(|(_, r)| !r.as_ref().is_ok_and(|r| r.ok))
            .map(|(d, _)| d)
            .collect();
        if missing.is_empty() {
            break;
        }
    }
    missing
}

fn decide(d: &DecisionRecord) -> Request {
    Request::Decide {
        txn: d.txn,
        commit: d.commit,
        at_unix_ns: d.at_unix_ns,
        revision: d.revision,
        task: d.task.clone(),
    }
}

/// How long before its time a time-tagged switch is started: time to prepare it and a lead
/// as long as the one the decision will get (as measured lately), twice over, so it is put in
/// force at its tag.
fn tag_margin(s: &Shared) -> u64 {
    let lead = s
        .timing
        .lock()
        .map(|t| t.lead(s.options.switch_lead))
        .unwrap_or(s.options.switch_lead);
    (lead * 4).as_nanos() as u64
}

/// Sends `req` to each DNM at once and collects their answers.
fn ask_all(
    s: &Shared,
    dnms: &[String],
    req: &Request,
    txn: u64,
    timeout: Duration,
) -> Vec<(String, Result<Response, String>)> {
    let phase = match req {
        Request::Prepare { .. } => "prepare",
        Request::Decide { commit: true, .. } => "commit",
        Request::Decide { .. } => "abort",
        _ => "adopt",
    };
    let cmd = RemoteCommand::new(
        format!("authority-{}", s.name),
        format!("{phase}-{txn}"),
        req.clone(),
    );
    let payload = serde_json::to_vec(&cmd).unwrap_or_default();
    let pending: Vec<_> = dnms
        .iter()
        .map(|d| {
            let r = s
                .session
                .get(keys::cmd(&s.system, d))
                .payload(payload.clone())
                .target(QueryTarget::BestMatching)
                .consolidation(ConsolidationMode::None)
                .priority(Priority::InteractiveHigh)
                .congestion_control(CongestionControl::Block)
                .express(true)
                .timeout(timeout)
                .wait();
            (d.clone(), r)
        })
        .collect();
    pending
        .into_iter()
        .map(|(d, r)| {
            let answer = match r {
                Err(e) => Err(e.to_string()),
                Ok(rx) => match rx.recv() {
                    Err(_) => Err(format!("no answer within {} ms", timeout.as_millis())),
                    Ok(reply) => {
                        let bytes = match reply.result() {
                            Ok(sample) => sample.payload().to_bytes().to_vec(),
                            Err(e) => e.payload().to_bytes().to_vec(),
                        };
                        serde_json::from_slice::<Response>(&bytes)
                            .map_err(|e| format!("unreadable answer: {e}"))
                    }
                },
            };
            (d, answer)
        })
        .collect()
}

/// What the DNMs named run, asked all at once (`None`: no answer in time).
fn reports_of(s: &Shared, dnms: &[String], timeout: Duration) -> Vec<Option<DnmBrief>> {
    let pending: Vec<_> = dnms
        .iter()
        .map(|d| {
            s.session
                .get(format!("{}?brief", keys::dnm(&s.system, d)))
                .priority(Priority::InteractiveHigh)
                .express(true)
                .timeout(timeout)
                .wait()
                .ok()
        })
        .collect();
    pending
        .into_iter()
        .map(|rx| {
            let reply = rx?.recv().ok()?;
            let sample = reply.result().ok()?;
            serde_json::from_slice(&sample.payload().to_bytes()).ok()
        })
        .collect()
}

/// The moment of the last uplink the store took, on this process's monotonic clock (now if
/// none, or if it is in the future).
fn last_contact(store: &Store) -> Instant {
    let now = Instant::now();
    store
        .last_contact_unix_ns()
        .ok()
        .flatten()
        .and_then(|at| {
            let ago = Duration::from_nanos(now_unix_ns().checked_sub(at)?);
            now.checked_sub(ago)
        })
        .unwrap_or(now)
}

/// The newest netlist in force on the reachable DNMs (that still validates here) and its task.
fn running(session: &zenoh::Session, door: &NetlistDoor) -> Option<(Netlist, Option<String>)> {
    let system = door.system();
    let replies = session
        .get(dnm_proto::keys::netlist(system, "*"))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(1))
        .wait()
        .ok()?;
    let mut newest: Option<dnm_proto::NetlistState> = None;
    while let Ok(r) = replies.recv() {
        if let Ok(sample) = r.result()
            && let Ok(n) =
                serde_json::from_slice::<dnm_proto::NetlistState>(&sample.payload().to_bytes())
            && n.text.is_some()
            && newest.as_ref().is_none_or(|x| n.revision > x.revision)
        {
            newest = Some(n);
        }
    }
    let n = newest?;
    let file = n.file.unwrap_or_else(|| "netlist.toml".into());
    let netlist = door.accept(&file, n.text.as_deref()?).ok()?;
    let task = n.active_task.filter(|t| netlist.tasks.contains_key(t));
    Some((netlist, task))
}

/// What every reachable DNM runs.
fn reports(session: &zenoh::Session, system: &str, timeout: Duration) -> Vec<DnmBrief> {
    let Ok(replies) = session
        .get(format!("{}?brief", keys::all_dnms(system)))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .wait()
    else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(sample) = r.result()
            && let Ok(d) = serde_json::from_slice::<DnmBrief>(&sample.payload().to_bytes())
        {
            out.push(d);
        }
    }
    out
}

// ---------------------------------------------------------------------------------------------
// The reconciler: DNMs that missed a decision catch up.

/// The DNMs one reconciler looks after: those on the rover answer at once, those across the
/// radio may take many seconds (a stalled link, a session being re-established), and waiting
/// for them must never delay a restarted rover DNM's catching up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Side {
    Rover,
    Radio,
}

impl Side {
    /// How long a pass waits for the DNMs' reports.
    fn report_timeout(self, s: &Shared) -> Duration {
        match self {
            Side::Rover => Duration::from_millis(1500),
            Side::Radio => s.options.prepare_timeout,
        }
    }
}

fn reconcile_loop(s: &Shared, side: Side) {
    while !s.stop.load(Ordering::Relaxed) {
        reconcile(s, side);
        let deadline = Instant::now() + s.options.reconcile_every;
        while Instant::now() < deadline && !s.stop.load(Ordering::Relaxed) {
            std::thread::sleep(Duration::from_millis(50).min(s.options.reconcile_every));
        }
    }
}

/// One pass: every DNM that holds a transaction gets its decision (or the order to drop it),
/// every DNM out of step adopts what was decided. Nothing waits under the state lock.
fn reconcile(s: &Shared, side: Side) {
    let (names, before) = match s.core.lock() {
        Ok(core) => (
            core.netlist
                .dnms
                .iter()
                .filter(|d| d.radio == (side == Side::Radio))
                .map(|d| d.name.clone())
                .collect::<Vec<_>>(),
            core.state.next_txn,
        ),
        Err(_) => return,
    };
    if names.is_empty() {
        return;
    }
    let found = reports_of(s, &names, side.report_timeout(s));
    // A DNM of the rover that made itself safe since the last decision, or that has not
    // answered for the loss-of-signal time: the whole rover is made safe before anything else
    // (and before any DNM is made to adopt the task it left). DNMs across the radio follow.
    if side == Side::Rover
        && (safing::adopt_dnm_safing(s, &found) || safing::safe_on_silent_dnm(s, &names, &found))
    {
        return;
    }
    // Taken after the reports: a report is never newer than the decisions it is judged by.
    let snap = match s.core.lock() {
        Ok(core) => Snapshot::of(&core),
        Err(_) => return,
    };
    // A transaction ran meanwhile: rover DNMs' reports may show it half done. Look again
    // later. (DNMs across the radio take no part in transactions; they adopt the newest
    // decision, which the snapshot, taken after their reports, holds.)
    if side == Side::Rover && snap.next_txn != before {
        return;
    }
    for r in found.into_iter().flatten() {
        if let Some(id) = r.holding {
            let known = snap
                .decisions
                .iter()
                .find(|d| d.txn == id)
                .cloned()
                .or_else(|| s.store.decision(id).ok().flatten());
            let d = match known {
                Some(d) => d,
                // Handed out after the snapshot: the worker is running it.
                None if id >= snap.next_txn => continue,
                // Never decided (the authority stopped before it could): dropped.
                None => DecisionRecord {
                    txn: id,
                    commit: false,
                    at_unix_ns: now_unix_ns(),
                    revision: r.revision,
                    task: r.active_task.clone(),
                },
            };
            tracing::info!(dnm = %r.dnm, txn = id, commit = d.commit, "sending a missed decision");
            log_answers(ask_all(
                s,
                std::slice::from_ref(&r.dnm),
                &decide(&d),
                id,
                Duration::from_secs(2),
            ));
            continue;
        }
        if r.preparing.is_some() || snap.in_step(&r) {
            continue;
        }
        // Decided again since the snapshot: these reports are old; look again next pass.
        if side == Side::Rover
            && s.core
                .lock()
                .map_or(true, |c| c.state.next_txn != snap.next_txn)
        {
            return;
        }
        // A DNM that already used the decided revision's number for something else (it was
        // out of reach when a new store chose it) could never adopt it: the decided state
        // gets a number no DNM has used, and every DNM adopts that.
        let used = r.last_attempt.max(r.revision);
        if used >= snap.revision && (r.revision != snap.revision || r.netlist_digest != snap.digest)
        {
            renumber(s, used);
            return;
        }
        // A rover DNM behind is only ever one that restarted (the others hold what they
        // prepared until decided); a radio DNM follows whenever it is reachable.
        tracing::info!(
            dnm = %r.dnm,
            from = r.revision,
            to = snap.revision,
            task = ?snap.task,
            radio = snap.radio.contains(&r.dnm),
            "DNM adopts the decided revision"
        );
        let adopt = Request::Adopt {
            revision: snap.revision,
            task: snap.task.clone(),
            file: snap.file.clone(),
            text: snap.text.clone(),
        };
        log_answers(ask_all(
            s,
            std::slice::from_ref(&r.dnm),
            &adopt,
            snap.revision,
            s.options.prepare_timeout,
        ));
    }
}

/// Gives the decided state a revision number above `used`.
fn renumber(s: &Shared, used: u64) {
    let Ok(mut core) = s.core.lock() else {
        return;
    };
    if core.state.revision > used {
        return;
    }
    let from = core.state.revision;
    core.state.burned = core.state.burned.max(used) + 1;
    core.state.revision = core.state.burned;
    if let Err(e) = s.store.save_state(&core.state) {
        tracing::error!("renumbering the decided revision: {e}");
        return;
    }
    tracing::warn!(
        from,
        to = core.state.revision,
        "a DNM had used the decided revision's number: decided again as a new revision"
    );
    publish_rover(s, &core);
}

fn log_answers(answers: Vec<(String, Result<Response, String>)>) {
    for (d, r) in answers {
        match r {
            Ok(r) if r.ok => {}
            Ok(r) => tracing::warn!(dnm = %d, "{}", r.error.unwrap_or_default()),
            Err(e) => tracing::warn!(dnm = %d, "{e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// A time tag runs at most its validity late, and says why it does not.
    #[test]
    fn a_time_tag_past_its_validity_is_refused_with_the_reason() {
        let now = now_unix_ns();
        assert_eq!(too_late(now + 1_000_000_000, 0), None);
        assert_eq!(too_late(now - 1_000_000_000, 60_000), None);
        let why = too_late(now - 90_000_000_000, 60_000).unwrap();
        assert!(why.contains("passed 90.0 s ago"), "{why}");
        assert!(why.contains("at most 60.0 s late"), "{why}");
        // Absurd values neither wrap nor panic.
        assert!(too_late(0, u64::MAX).is_none());
        assert!(too_late(0, 0).is_some());
    }
}
