//! The ground station: where operators command the rover from, across a radio link that loses
//! packets, delays them and drops out.
//!
//! Every command an operator gives gets the station's next sequence number and a unique id and
//! is stored durably (redb, fsync) before the operator is told it is queued. One thread sends
//! the commands the rover has not acknowledged, oldest first, in one query to the rover's
//! authority, again and again until it acknowledges them, across outages of any length and
//! restarts of the station; the same query is the station's ping when there is nothing to
//! send, and measures the link. The HTTP/JSON API ([`http`]) is what scripts, `dnm ground`
//! and the web interface use.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let session: zenoh::Session = unimplemented!();
//! use dnm_ground::{Station, StationOptions};
//! use dnm_proto::station::Order;
//! let station = Station::start(session, StationOptions::new("beetle", "ground-1", "ground-1.redb"))?;
//! let entry = station.submit(Order::Switch { task: "auto".into(), at_unix_ns: None, late_by_ms: None })?;
//! let done = station.wait(entry.seq, std::time::Duration::from_secs(60));
//! # Ok(()) }
//! ```

pub mod http;
pub mod view;
pub mod web;

pub use dnm_proto::clock::now_unix_ns;
use std::collections::{BTreeMap, VecDeque};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use redb::{Database, ReadableDatabase, ReadableTable, TableDefinition};
use serde::{Deserialize, Serialize};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};

use dnm_proto::keys;
use dnm_proto::station::{Downlink, Fate, Order, RoverState, Sent, SequenceStatus, Uplink};

const OUTBOX: TableDefinition<'_, u64, &[u8]> = TableDefinition::new("outbox");
const META: TableDefinition<'_, &str, u64> = TableDefinition::new("meta");

/// Answers the clock offset is estimated from.
const CLOCK_SAMPLES: usize = 16;
/// Events of each sequence the station keeps (the rover sends each once).
const SEQUENCE_EVENTS_KEPT: usize = 256;

/// Uplinks remembered for the loss estimate.
const LOSS_WINDOW: usize = 50;

#[derive(Debug, thiserror::Error)]
pub enum StationError {
    #[error("the station's outbox: {0}")]
    Store(String),
    #[error("{0}")]
    Invalid(String),
}

fn store<E: std::fmt::Display>(e: E) -> StationError {
    StationError::Store(e.to_string())
}

/// How a station works.
#[derive(Debug, Clone)]
pub struct StationOptions {
    pub system: String,
    /// The station's name, unique among the system's stations.
    pub name: String,
    /// The outbox database (created if missing).
    pub db: PathBuf,
    /// Between two uplinks when there is nothing to send.
    pub ping_every: Duration,
    /// How long an uplink waits for its answer at least (it grows with the measured round
    /// trip; beyond it, the uplink counts as lost).
    pub answer_timeout: Duration,
    /// Commands in one uplink, at most.
    pub batch: usize,
    /// Bytes of commands in one uplink, about (at least one command goes).
    pub batch_bytes: usize,
    /// Silence after which the link counts as down.
    pub down_after: Duration,
}

impl StationOptions {
    pub fn new(system: &str, name: &str, db: impl Into<PathBuf>) -> Self {
        Self {
            system: system.into(),
            name: name.into(),
            db: db.into(),
            ping_every: Duration::from_secs(1),
            answer_timeout: Duration::from_secs(5),
            batch: 32,
            batch_bytes: 8 * 1024,
            down_after: Duration::from_secs(3),
        }
    }
}

/// Where a command is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CommandState {
    /// Stored here, not sent yet.
    Queued,
    /// Sent, not acknowledged yet (sent again until it is).
    Sent,
    /// Stored by the rover; it runs after the station's earlier commands.
    Acknowledged,
    /// A time-tagged switch waiting on the rover for its time.
    Scheduled,
    /// In force on the rover (see the fate for revision and instant).
    Applied,
    /// Refused by the rover (see the fate for the reason); nothing changed.
    Refused,
    /// Cancelled before it ran.
    Cancelled,
}

impl CommandState {
    pub fn is_final(self) -> bool {
        matches!(self, Self::Applied | Self::Refused | Self::Cancelled)
    }
}

/// One command in the outbox.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Entry {
    pub seq: u64,
    pub id: String,
    pub order: Order,
    pub state: CommandState,
    /// What the rover said last.
    pub fate: Option<Fate>,
    pub queued_unix_ns: u64,
    pub sends: u32,
    pub acknowledged_unix_ns: Option<u64>,
    pub done_unix_ns: Option<u64>,
    /// The rover's safings this station had seen when the command was given (the newest's
    /// epoch): one given before the station saw the rover's newest safing is refused by the
    /// rover. `None`: the station had not heard the rover at all yet; it is sent with what the
    /// station knows when it first sends it.
    #[serde(default)]
    pub safings_seen: Option<u64>,
}

/// The radio link as the station sees it.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct LinkStatus {
    pub up: bool,
    /// Round-trip time of the last answered uplink, ms.
    pub rtt_ms: Option<f64>,
    /// Since the rover was last heard, ms.
    pub last_contact_ms: Option<u64>,
    /// Share of the last uplinks that got no answer, counted from the rover's first answer (before
    /// it, the rover was not up: that says nothing about the link).
    pub loss: f64,
    pub uplinks: u64,
    pub answered: u64,
    /// Commands not yet final.
    pub pending: usize,
    /// The rover as its authority last reported it.
    pub rover: Option<RoverState>,
    /// Why the rover refused the last uplink, if it did.
    pub error: Option<String>,
    /// The rover's clock minus this station's, estimated from the last answer (its rover time
    /// against the middle of the round trip), ms: relative time tags are turned into rover time
    /// with it.
    pub rover_clock_offset_ms: Option<f64>,
}

struct Inner {
    entries: BTreeMap<u64, Entry>,
    next_seq: u64,
    link: LinkStatus,
    contact: Option<Instant>,
    history: VecDeque<bool>,
    /// (round trip, clock offset ms) of the last answers.
    clock_samples: VecDeque<(Duration, f64)>,
}

struct Shared {
    options: StationOptions,
    /// The name the rover knows this outbox by: the station's name and the outbox's epoch.
    wire_name: String,
    session: zenoh::Session,
    db: Database,
    inner: Mutex<Inner>,
    changed: Condvar,
    wake: (Mutex<bool>, Condvar),
    /// Set while the regular lane waits for an answer.
    busy: AtomicBool,
    express: (Mutex<bool>, Condvar),
    timing: Mutex<Timing>,
    stop: AtomicBool,
}

/// A running ground station.
pub struct Station {
    shared: Arc<Shared>,
    threads: Vec<JoinHandle<()>>,
}

impl std::fmt::Debug for Station {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Station")
            .field("name", &self.shared.options.name)
            .finish_non_exhaustive()
    }
}

impl Station {
    /// Opens the outbox (commands stored by an earlier run are sent on) and starts the link.
    pub fn start(session: zenoh::Session, options: StationOptions) -> Result<Self, StationError> {
        if let Some(dir) = options.db.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(store)?;
        }
        let db = Database::create(&options.db)
            .map_err(|e| StationError::Store(format!("{}: {e}", options.db.display())))?;
        let mut entries = BTreeMap::new();
        let mut next_seq = 1;
        let epoch;
        {
            let tx = db.begin_write().map_err(store)?;
            tx.open_table(OUTBOX).map_err(store)?;
            tx.open_table(META).map_err(store)?;
            tx.commit().map_err(store)?;
            let rx = db.begin_read().map_err(store)?;
            let t = rx.open_table(OUTBOX).map_err(store)?;
            for row in t.iter().map_err(store)? {
                let (_, v) = row.map_err(store)?;
                let e: Entry = serde_json::from_slice(v.value()).map_err(store)?;
                next_seq = next_seq.max(e.seq + 1);
                entries.insert(e.seq, e);
            }
            let meta = rx.open_table(META).map_err(store)?;
            if let Some(v) = meta.get("next_seq").map_err(store)? {
                next_seq = next_seq.max(v.value());
            }
            epoch = meta.get("epoch").map_err(store)?.map(|v| v.value());
        }
        // The outbox's own numbering: a new outbox under an old name is another station to
        // the rover, so its numbers never meet those of the one it replaced.
        let epoch = match epoch {
            Some(e) => e,
            None => {
                let e = now_unix_ns() / 1_000_000;
                let tx = db.begin_write().map_err(store)?;
                tx.open_table(META)
                    .map_err(store)?
                    .insert("epoch", e)
                    .map_err(store)?;
                tx.commit().map_err(store)?;
                e
            }
        };
        let wire_name = format!("{}.{epoch:x}", options.name);
        tracing::info!(
            station = %options.name,
            commands = entries.len(),
            pending = entries.values().filter(|e| !e.state.is_final()).count(),
            "outbox open"
        );
        let shared = Arc::new(Shared {
            options,
            wire_name,
            session,
            db,
            inner: Mutex::new(Inner {
                entries,
                next_seq,
                link: LinkStatus::default(),
                contact: None,
                history: VecDeque::new(),
                clock_samples: VecDeque::new(),
            }),
            changed: Condvar::new(),
            wake: (Mutex::new(true), Condvar::new()),
            busy: AtomicBool::new(false),
            express: (Mutex::new(false), Condvar::new()),
            timing: Mutex::new(Timing::default()),
            stop: AtomicBool::new(false),
        });
        let mut threads = Vec::new();
        for (name, lane) in [
            ("ground-link", link_loop as fn(&Shared)),
            ("ground-express", express_loop),
        ] {
            let s = shared.clone();
            threads.push(
                std::thread::Builder::new()
                    .name(name.into())
                    .spawn(move || lane(&s))
                    .map_err(store)?,
            );
        }
        Ok(Self { shared, threads })
    }

    pub fn name(&self) -> &str {
        &self.shared.options.name
    }

    /// The station's Zenoh session (the web interface's view of the system uses it).
    pub fn session(&self) -> &zenoh::Session {
        &self.shared.session
    }

    pub fn system(&self) -> &str {
        &self.shared.options.system
    }

    /// Queues a command: stored durably, then sent. The entry comes back `queued`.
    pub fn submit(&self, order: Order) -> Result<Entry, StationError> {
        check(&order)?;
        let mut inner = self
            .shared
            .inner
            .lock()
            .map_err(|_| StationError::Store("lock poisoned".into()))?;
        let seq = inner.next_seq;
        let safings_seen = inner.link.rover.as_ref().map(safings_of);
        let entry = Entry {
            seq,
            id: format!("{}-{seq}-{:x}", self.shared.options.name, now_unix_ns()),
            order,
            state: CommandState::Queued,
            fate: None,
            queued_unix_ns: now_unix_ns(),
            sends: 0,
            acknowledged_unix_ns: None,
            done_unix_ns: None,
            safings_seen,
        };
        persist(&self.shared.db, &[&entry], Some(seq + 1))?;
        inner.next_seq = seq + 1;
        inner.entries.insert(seq, entry.clone());
        drop(inner);
        tracing::info!(seq, "command queued");
        wake(&self.shared);
        if self.shared.busy.load(Ordering::Relaxed)
            && let Ok(mut e) = self.shared.express.0.lock()
        {
            *e = true;
            self.shared.express.1.notify_all();
        }
        Ok(entry)
    }

    pub fn entry(&self, seq: u64) -> Option<Entry> {
        self.shared.inner.lock().ok()?.entries.get(&seq).cloned()
    }

    /// Commands from `since` on, oldest first; only the `last` of them if given (a page
    /// polling its outbox copies what it shows, not the mission's every command).
    pub fn entries(&self, since: u64, last: Option<usize>) -> Vec<Entry> {
        let Ok(i) = self.shared.inner.lock() else {
            return Vec::new();
        };
        let from = i
            .entries
            .range(since..)
            .rev()
            .take(last.unwrap_or(usize::MAX));
        let mut out: Vec<Entry> = from.map(|(_, e)| e.clone()).collect();
        out.reverse();
        out
    }

    pub fn link(&self) -> LinkStatus {
        let Ok(i) = self.shared.inner.lock() else {
            return LinkStatus::default();
        };
        let mut l = i.link.clone();
        l.last_contact_ms = i.contact.map(|c| c.elapsed().as_millis() as u64);
        l.up = i
            .contact
            .is_some_and(|c| c.elapsed() < self.shared.options.down_after);
        l.pending = i.entries.values().filter(|e| !e.state.is_final()).count();
        l
    }

    /// Waits until command `seq` is final (or `timeout` passes) and returns it.
    pub fn wait(&self, seq: u64, timeout: Duration) -> Option<Entry> {
        let deadline = Instant::now() + timeout;
        let mut inner = self.shared.inner.lock().ok()?;
        loop {
            let e = inner.entries.get(&seq)?.clone();
            let left = deadline.saturating_duration_since(Instant::now());
            if e.state.is_final() || left.is_zero() {
                return Some(e);
            }
            inner = self.shared.changed.wait_timeout(inner, left).ok()?.0;
        }
    }

    /// Stops the link thread; the outbox stays on disk.
    pub fn stop(mut self) {
        self.halt();
    }

    fn halt(&mut self) {
        self.shared.stop.store(true, Ordering::Relaxed);
        wake(&self.shared);
        self.shared.express.1.notify_all();
        for t in self.threads.drain(..) {
            let _ = t.join();
        }
    }
}

impl Drop for Station {
    fn drop(&mut self) {
        self.halt();
    }
}

/// Refuses what can never be sent.
fn check(order: &Order) -> Result<(), StationError> {
    match order {
        Order::Switch { task, .. } if task.is_empty() => {
            Err(StationError::Invalid("a switch needs a task".into()))
        }
        Order::Apply { text, .. } if text.len() > 1 << 20 => Err(StationError::Invalid(
            "netlist larger than 1 MiB; the radio link would carry it for minutes".into(),
        )),
        _ => Ok(()),
    }
}

fn wake(s: &Shared) {
    if let Ok(mut w) = s.wake.0.lock() {
        *w = true;
        s.wake.1.notify_all();
    }
}

fn persist(db: &Database, entries: &[&Entry], next_seq: Option<u64>) -> Result<(), StationError> {
    let tx = db.begin_write().map_err(store)?;
    {
        let mut t = tx.open_table(OUTBOX).map_err(store)?;
        for e in entries {
            let bytes = serde_json::to_vec(e).map_err(store)?;
            t.insert(e.seq, bytes.as_slice()).map_err(store)?;
        }
        if let Some(n) = next_seq {
            let mut meta = tx.open_table(META).map_err(store)?;
            meta.insert("next_seq", n).map_err(store)?;
        }
    }
    tx.commit().map_err(store)
}

/// Longest pause after uplinks that got no answer.
const MAX_BACKOFF: Duration = Duration::from_secs(4);
/// Longest wait for an answer.
const MAX_ANSWER_WAIT: Duration = Duration::from_secs(60);
/// An uplink that fails faster than this found no route to the rover.
const NO_ROUTE: Duration = Duration::from_millis(50);

/// What the uplinks learn of the link, shared by both lanes.
#[derive(Debug, Default)]
struct Timing {
    /// Smoothed round trip.
    srtt: Option<Duration>,
    /// Uplinks lost in a row: a link that does not answer is not flooded with more (each
    /// answer would queue behind the last on a slow radio).
    lost_in_row: u32,
}

/// The regular lane: sends what the rover has not acknowledged, pings when there is nothing,
/// backs off when the link does not answer.
fn link_loop(s: &Shared) {
    while !s.stop.load(Ordering::Relaxed) {
        s.busy.store(true, Ordering::Relaxed);
        let (answered, unreachable, has_commands) = uplink(s);
        s.busy.store(false, Ordering::Relaxed);
        let lost_in_row = s.timing.lock().map(|t| t.lost_in_row).unwrap_or(0);
        // With commands waiting, send again at once; after losses, back off (doubling);
        // otherwise ping.
        let pause = if unreachable {
            s.options.ping_every
        } else if !answered {
            (Duration::from_millis(250) * 2u32.saturating_pow(lost_in_row.min(6))).min(MAX_BACKOFF)
        } else if has_commands {
            Duration::from_millis(20)
        } else {
            s.options.ping_every
        };
        if let Ok(w) = s.wake.0.lock()
            && let Ok((mut w, _)) = s.wake.1.wait_timeout_while(w, pause, |w| !*w)
        {
            *w = false;
        }
    }
}

/// The express lane: a command given while the regular lane waits for an answer (a ping, or
/// a retry on a slow link) goes at once in an uplink of its own, instead of a round trip
/// later. Duplicates are harmless: the rover takes each command once.
fn express_loop(s: &Shared) {
    while !s.stop.load(Ordering::Relaxed) {
        let Ok(w) = s.express.0.lock() else {
            return;
        };
        let Ok(mut w) = s
            .express
            .1
            .wait_while(w, |w| !*w && !s.stop.load(Ordering::Relaxed))
        else {
            return;
        };
        *w = false;
        drop(w);
        if !s.stop.load(Ordering::Relaxed) {
            uplink(s);
        }
    }
}

/// One uplink: every command not acknowledged yet (oldest first, within the batch limits)
/// and the oldest whose fate is not known; then the answer taken in. Returns (answered, no
/// route to the rover at all, commands were pending).
fn uplink(s: &Shared) -> (bool, bool, bool) {
    let key = keys::authority_station(&s.options.system, &s.options.name);
    let (uplink, has_commands) = {
        let Ok(inner) = s.inner.lock() else {
            return (false, false, false);
        };
        let mut bytes = 0;
        let commands: Vec<Sent> = inner
            .entries
            .values()
            .filter(|e| matches!(e.state, CommandState::Queued | CommandState::Sent))
            .take(s.options.batch)
            .map(|e| Sent {
                seq: e.seq,
                id: e.id.clone(),
                order: e.order.clone(),
                safings_seen: e
                    .safings_seen
                    .unwrap_or_else(|| inner.link.rover.as_ref().map_or(0, safings_of)),
                given_unix_ns: Some(e.queued_unix_ns),
            })
            .take_while(|c| {
                let first = bytes == 0;
                bytes += serde_json::to_vec(c).map_or(0, |b| b.len());
                first || bytes <= s.options.batch_bytes
            })
            .collect();
        let pending_from = inner
            .entries
            .values()
            .find(|e| !e.state.is_final())
            .map_or(inner.next_seq, |e| e.seq);
        let waiting: Vec<u64> = inner
            .entries
            .values()
            .filter(|e| {
                matches!(
                    e.state,
                    CommandState::Acknowledged | CommandState::Scheduled
                )
            })
            .map(|e| e.seq)
            .take(64)
            .collect();
        let has = !commands.is_empty() || pending_from < inner.next_seq;
        let sequence_events = inner
            .link
            .rover
            .iter()
            .flat_map(|r| &r.sequences)
            .map(|q| (q.name.clone(), q.events_total))
            .collect();
        (
            Uplink {
                station: s.wire_name.clone(),
                commands,
                pending_from,
                waiting,
                sequence_events,
            },
            has,
        )
    };
    let sent_seqs: Vec<u64> = uplink.commands.iter().map(|c| c.seq).collect();
    mark_sent(s, &sent_seqs);
    let payload = serde_json::to_vec(&uplink).unwrap_or_default();
    let start = Instant::now();
    // Three round trips, and twice as long after each uplink lost in a row (as TCP's
    // retransmission timer): a link slower than the last guess is not asked again and
    // again before its answer can arrive.
    let timeout = s
        .timing
        .lock()
        .map(|t| {
            t.srtt
                .map_or(s.options.answer_timeout, |r| {
                    (r * 3).max(s.options.answer_timeout)
                })
                .saturating_mul(2u32.saturating_pow(t.lost_in_row.min(4)))
                .min(MAX_ANSWER_WAIT)
        })
        .unwrap_or(s.options.answer_timeout);
    let answer = s
        .session
        .get(&key)
        .payload(payload)
        // First on the link, and never dropped on the way: the routers of the radio wait
        // out a stalled link (configs/zenoh/*-router.json5) instead of closing it.
        .priority(Priority::InteractiveHigh)
        .congestion_control(CongestionControl::Block)
        .express(true)
        .timeout(timeout)
        .wait()
        .ok()
        .and_then(|rx| rx.recv().ok())
        .and_then(|r| r.result().ok().map(|s| s.payload().to_bytes().to_vec()))
        .and_then(|b| match serde_json::from_slice::<Downlink>(&b) {
            Ok(d) => Some(d),
            Err(e) => {
                tracing::error!("unreadable answer from the rover ({e}); is it another version?");
                None
            }
        });
    let rtt = start.elapsed();
    let answered = answer.is_some();
    tracing::debug!(
        commands = sent_seqs.len(),
        answered,
        ms = rtt.as_millis() as u64,
        timeout_ms = timeout.as_millis() as u64,
        "uplink"
    );
    // No route to the rover at all (the routers lost each other): it cost nothing on the
    // link, so it is not a reason to back off.
    let unreachable = !answered && rtt < NO_ROUTE;
    if let Some(d) = answer {
        take_downlink(s, d, rtt);
        if let Ok(mut t) = s.timing.lock() {
            t.srtt = Some(t.srtt.map_or(rtt, |r| (r * 7 + rtt) / 8));
            t.lost_in_row = 0;
        }
    } else if !unreachable && let Ok(mut t) = s.timing.lock() {
        t.lost_in_row = t.lost_in_row.saturating_add(1);
    }
    if let Ok(mut i) = s.inner.lock() {
        i.link.uplinks += 1;
        if answered || i.contact.is_some() {
            i.history.push_back(answered);
            if i.history.len() > LOSS_WINDOW {
                i.history.pop_front();
            }
            let lost = i.history.iter().filter(|a| !**a).count();
            i.link.loss = lost as f64 / i.history.len() as f64;
        }
    }
    (answered, unreachable, has_commands)
}

/// How far a command has come.
/// The epoch of the newest safing a rover state shows (0: none).
fn safings_of(r: &RoverState) -> u64 {
    r.last_safing.as_ref().map_or(0, |l| l.epoch)
}

fn rank(state: CommandState) -> u8 {
    match state {
        CommandState::Queued => 0,
        CommandState::Sent => 1,
        CommandState::Acknowledged => 2,
        CommandState::Scheduled => 3,
        CommandState::Applied | CommandState::Refused | CommandState::Cancelled => 4,
    }
}

fn mark_sent(s: &Shared, seqs: &[u64]) {
    let Ok(mut inner) = s.inner.lock() else {
        return;
    };
    let mut changed = Vec::new();
    for seq in seqs {
        if let Some(e) = inner.entries.get_mut(seq) {
            e.sends += 1;
            if e.state == CommandState::Queued {
                e.state = CommandState::Sent;
            }
            changed.push(e.clone());
        }
    }
    let refs: Vec<&Entry> = changed.iter().collect();
    if let Err(e) = persist(&s.db, &refs, None) {
        tracing::error!("outbox: {e}");
    }
}

fn take_downlink(s: &Shared, d: Downlink, rtt: Duration) {
    let Ok(mut inner) = s.inner.lock() else {
        return;
    };
    // As NTP does: the answer with the shortest round trip of the last few bounds the offset
    // best (the least room for the two ways to differ).
    let middle = now_unix_ns() as f64 - rtt.as_nanos() as f64 / 2.0;
    inner
        .clock_samples
        .push_back((rtt, (d.at_unix_ns as f64 - middle) / 1e6));
    if inner.clock_samples.len() > CLOCK_SAMPLES {
        inner.clock_samples.pop_front();
    }
    inner.link.rover_clock_offset_ms = inner
        .clock_samples
        .iter()
        .min_by_key(|(r, _)| *r)
        .map(|(_, o)| *o);
    inner.contact = Some(Instant::now());
    inner.link.answered += 1;
    inner.link.rtt_ms = Some(rtt.as_secs_f64() * 1e3);
    inner.link.error = d.error.clone();
    if let Some(e) = &d.error {
        tracing::warn!("the rover refused the uplink: {e}");
    }
    let old_events = inner.link.rover.as_ref().map_or(0, |r| r.events.len());
    if d.rover.events.len() != old_events {
        for e in &d.rover.events {
            tracing::info!(what = %e.what, "rover: {}", e.detail);
        }
    }
    // The sequences' events arrive once each: added to those the station holds.
    let mut rover = d.rover;
    if let Some(old) = inner.link.rover.take() {
        let mut held: BTreeMap<String, SequenceStatus> = old
            .sequences
            .into_iter()
            .map(|q| (q.name.clone(), q))
            .collect();
        rover.sequences = rover
            .sequences
            .into_iter()
            .map(|q| match held.remove(&q.name) {
                Some(mut h) => {
                    h.merge(q, SEQUENCE_EVENTS_KEPT);
                    h
                }
                None => q,
            })
            .collect();
    }
    inner.link.rover = Some(rover);
    let now = now_unix_ns();
    let mut changed: Vec<Entry> = Vec::new();
    for o in &d.outcomes {
        // The rover has not taken this station's commands from `expected` on (its store was
        // lost, or an uplink was): every one not final from there is sent again, in order.
        if let Fate::OutOfOrder { expected } = o.fate {
            for e in inner.entries.range_mut(expected..).map(|(_, e)| e) {
                if !e.state.is_final() && e.state != CommandState::Sent {
                    tracing::warn!(
                        seq = e.seq,
                        "the rover does not have this command: sending it again"
                    );
                    e.state = CommandState::Sent;
                    e.fate = Some(o.fate.clone());
                    changed.push(e.clone());
                }
            }
        }
    }
    for o in d.outcomes {
        if matches!(o.fate, Fate::OutOfOrder { .. }) {
            continue;
        }
        let Some(e) = inner.entries.get_mut(&o.seq) else {
            continue;
        };
        if e.id != o.id {
            tracing::error!(
                seq = o.seq,
                "the rover holds another command under this number"
            );
            continue;
        }
        let state = match &o.fate {
            Fate::Acknowledged => CommandState::Acknowledged,
            Fate::OutOfOrder { .. } => CommandState::Sent,
            Fate::Scheduled { .. } => CommandState::Scheduled,
            Fate::Applied { .. } | Fate::Done { .. } | Fate::Cancelled { .. } => {
                CommandState::Applied
            }
            Fate::CancelledBy { .. } => CommandState::Cancelled,
            Fate::Refused { .. } => CommandState::Refused,
        };
        if e.state == state && e.fate.as_ref() == Some(&o.fate) {
            continue;
        }
        // Answers to two uplinks may arrive in either order: a command never goes back.
        if rank(state) < rank(e.state) {
            continue;
        }
        if e.acknowledged_unix_ns.is_none() && state != CommandState::Sent {
            e.acknowledged_unix_ns = Some(now);
        }
        if state.is_final() {
            e.done_unix_ns = Some(now);
            tracing::info!(seq = o.seq, ?state, "command done");
        }
        e.state = state;
        e.fate = Some(o.fate);
        changed.push(e.clone());
    }
    let refs: Vec<&Entry> = changed.iter().collect();
    if let Err(e) = persist(&s.db, &refs, None) {
        tracing::error!("outbox: {e}");
    }
    drop(inner);
    s.changed.notify_all();
}
