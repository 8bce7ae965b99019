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
mod intake;
mod reconcile;
mod safing;
mod sequence;
mod sequencer;
mod store;
mod transaction;
mod worker;

pub(crate) use dnm_proto::clock::now_unix_ns;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, mpsc};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_netlist::{AcceptError, Netlist, NetlistDoor};
use dnm_proto::station::{
    DEFAULT_LATE_BY_MS, Downlink, Fate, Order, RoverEvent, RoverState, Sent, SequenceEvent, Uplink,
};
use dnm_proto::{DnmBrief, RemoteCommand, Request, Response, keys};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};
use zenoh::query::{ConsolidationMode, Query, QueryTarget};

pub use edit::{ModuleEditError, edit_netlist, param_value};
use intake::*;
use reconcile::*;
use store::{DecisionRecord, Finish, State, Store, Timer};
use transaction::*;
use worker::*;

/// Why the authority could not start or go on. Nothing it decided is lost: its store keeps it.
#[derive(Debug, thiserror::Error)]
pub enum AuthorityError {
    /// The store (redb) failed.
    #[error("the authority's store: {0}")]
    Store(#[source] redb::Error),
    #[error("the authority's store at {path}: {source}")]
    StoreOpen {
        path: PathBuf,
        #[source]
        source: redb::Error,
    },
    #[error("the authority's store: creating its folder {path}: {source}")]
    StoreFolder {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A record in the store does not read back (written by another version, or damaged).
    #[error("the authority's store holds a record that does not read back: {0}")]
    Record(#[source] serde_json::Error),
    /// The store's tables disagree with each other.
    #[error("the authority's store: {0}")]
    Inconsistent(String),
    #[error("the authority's state lock is poisoned")]
    Poisoned,
    #[error("Zenoh: {0}")]
    Zenoh(#[source] zenoh::Error),
    #[error("spawning {name}: {source}")]
    Thread {
        name: String,
        #[source]
        source: std::io::Error,
    },
    #[error("the netlist names no authority DNM")]
    NoAuthority,
    #[error("the decided netlist no longer validates: {}", .0.in_transaction())]
    DecidedNetlist(#[source] AcceptError),
}

/// Where the authority hands each event of its sequences as it happens (besides publishing it
/// on [`keys::authority_sequences`]): its DNM's recorder, say.
#[derive(Clone)]
pub struct SequenceLog(pub Arc<dyn Fn(&SequenceEvent) + Send + Sync>);

impl std::fmt::Debug for SequenceLog {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SequenceLog")
    }
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
    /// Also told every sequence event.
    pub sequence_log: Option<SequenceLog>,
}

impl AuthorityOptions {
    pub fn new(db: impl Into<PathBuf>) -> Self {
        Self {
            db: db.into(),
            switch_lead: Duration::from_millis(50),
            prepare_timeout: Duration::from_secs(10),
            reconcile_every: Duration::from_millis(500),
            sequence_log: None,
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
    /// The onboard sequences stored, by name.
    sequences: BTreeMap<String, sequence::SequenceRun>,
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
        least.max(self.margin())
    }

    /// What must fit between a decision and its instant: its store and its way to every DNM,
    /// twice over.
    fn margin(&self) -> Duration {
        (self.round_trip * 2 + self.store * 2).min(MAX_LEAD)
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
    /// Woken when the authority stops (`stop` set): the reconcilers wait on it between passes.
    halt: (Mutex<()>, Condvar),
    /// When each DNM of the rover last answered the reconciler.
    dnms_heard: Mutex<safing::DnmsHeard>,
    /// Time tags' instants on the monotonic clock.
    tag_clock: Mutex<BTreeMap<(String, u64), Instant>>,
    /// The sequence running whose end loss of signal waits for (the beat says it).
    deferring: Mutex<Option<String>>,
    sequencer: sequencer::Sequencer,
    /// How many events of each sequence were told (published and logged).
    told: Mutex<BTreeMap<String, u64>>,
    sequence_events: zenoh::pubsub::Publisher<'static>,
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

    /// Waits `d`, or less if the authority stops meanwhile.
    fn pause(&self, d: Duration) {
        let Ok(h) = self.halt.0.lock() else {
            return;
        };
        let _ = self
            .halt
            .1
            .wait_timeout_while(h, d, |_| !self.stop.load(Ordering::Relaxed));
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
            .ok_or(AuthorityError::NoAuthority)?
            .to_string();
        let system = netlist.system.clone();
        let store = Store::open(&options.db)?;
        let state = decided_state(&store, &session, netlist, &door)?;
        let current = door
            .accept(&state.file, &state.text)
            .map_err(AuthorityError::DecidedNetlist)?;
        let digest = format!("{:016x}", current.digest());
        let contact = last_contact(&store);
        let mut sequences = store.sequences()?;
        // What was told before a restart is not told again.
        let told = sequences
            .iter()
            .map(|(n, r)| (n.clone(), r.events_total))
            .collect();
        sequence::resume_after_restart(&store, &mut sequences);
        let sequence_events = session
            .declare_publisher(keys::authority_sequences(&system))
            // Never holds up the worker: the history is in the rover's state for stations.
            .congestion_control(CongestionControl::Drop)
            .wait()
            .map_err(AuthorityError::Zenoh)?;
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
                sequences,
            }),
            rover: Mutex::new(RoverState::default()),
            // A restarted authority counts the ground's silence from the last uplink it took,
            // not from its start: an authority that restarts does not put off loss of signal.
            contact: Mutex::new(contact),
            heard: AtomicBool::new(false),
            wake: (Mutex::new(false), Condvar::new()),
            beat: (Mutex::new(false), Condvar::new()),
            halt: (Mutex::new(()), Condvar::new()),
            tag_clock: Mutex::new(BTreeMap::new()),
            dnms_heard: Mutex::new(safing::DnmsHeard::default()),
            deferring: Mutex::new(None),
            sequencer: sequencer::Sequencer::default(),
            told: Mutex::new(told),
            sequence_events,
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
                    // Flow control, not a fault: the station sends it again, and a station
                    // that hears nothing shows the link's state itself.
                    tracing::debug!("uplink dropped: the authority is busy");
                }
            })
            .wait()
            .map_err(AuthorityError::Zenoh)?;
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|source| AuthorityError::Thread {
                    name: name.to_string(),
                    source,
                })
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
            spawn("authority-sequencer", {
                let s = shared.clone();
                Box::new(move || sequencer::sequencer_loop(&s))
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
        // Under the lock: a reconciler that has just seen `stop` unset is waiting before this.
        if let Ok(_h) = self.shared.halt.0.lock() {
            self.shared.halt.1.notify_all();
        }
        safing::beat_now(&self.shared);
        for t in self.threads {
            let _ = t.join();
        }
    }
}

/// The state the authority goes on from: its store's, or, with a new store, the netlist's (or
/// what a rover already running runs), decided as the revision after any its DNMs have used.
fn decided_state(
    store: &Store,
    session: &zenoh::Session,
    netlist: &Netlist,
    door: &NetlistDoor,
) -> Result<State, AuthorityError> {
    let system = &netlist.system;
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
            let found = reports(session, system, Duration::from_secs(1));
            let used = found
                .iter()
                .map(|r| r.last_attempt.max(r.revision))
                .max()
                .unwrap_or(0);
            // (A DNM claiming the last revision there is gets it shared, and is never followed
            // past it: see `reconcile::renumber`.)
            let revision = used.saturating_add(1);
            // A rover already running (this store was lost or replaced) goes on with what
            // it runs: the newest netlist in force on its DNMs, in its task.
            let (file, text, task) = match running(session, door) {
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
    Ok(state)
}

/// The moment the ground's silence counts from, on this process's monotonic clock: the last
/// uplink the store took (now if it is in the future). A store that never took one belongs to a
/// rover starting up for the first time: its silence counts from [`safing::START_GRACE`] after
/// now, so the rover waits that long for its first contact before loss of signal makes it safe.
fn last_contact(store: &Store) -> Instant {
    let now = Instant::now();
    match store.last_contact_unix_ns().ok().flatten() {
        Some(at) => now_unix_ns()
            .checked_sub(at)
            .and_then(|ago| now.checked_sub(Duration::from_nanos(ago)))
            .unwrap_or(now),
        None => now + safing::START_GRACE,
    }
}
