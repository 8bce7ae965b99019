//! What the bridge's threads and callbacks share, and the bounds of their queues.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

use dnm_core::{Command, Commander, Snapshot};
use dnm_netlist::{MessageType, Wiring};
use iceoryx2::prelude::*;

use crate::lease::Lease;

pub(crate) type Svc = ipc::Service;
pub(crate) type TsSvc = ipc_threadsafe::Service;

/// Queries the query thread holds at most (queued or being answered).
pub const QUERY_QUEUE: usize = 256;
/// Commands the command thread holds at most (queued, at the DNM, or being answered).
pub const COMMAND_QUEUE: usize = 32;
/// Applies among them at most: applies take seconds, and must leave room for switches.
pub const APPLIES_IN_FLIGHT: usize = 4;

/// How old a snapshot may be when a tool asks for the DNM's report or a module's figures (the
/// default supervision tick: as fresh as when every tick made one).
const FRESH: Duration = Duration::from_millis(100);
/// How long a question waits for the DNM to hand over a fresh snapshot before it is answered
/// from the newest there is (the DNM may be putting a decision in force).
const FRESH_WAIT: Duration = Duration::from_millis(500);

/// What the bridge's threads and callbacks share.
#[derive(Default)]
pub(crate) struct Shared {
    pub(crate) snapshot: Mutex<Option<Arc<Snapshot>>>,
    /// Signalled with each new snapshot.
    pub(crate) fresh: Condvar,
    /// Since when a fresh snapshot is asked of the DNM and not yet handed over: no second
    /// request is queued (the DNM's command queue stays free for commands), and once the DNM
    /// has let one wait [`FRESH_WAIT`], questions are answered at once from the newest.
    pub(crate) refresh_asked: Mutex<Option<Instant>>,
    pub(crate) peers: Mutex<BTreeMap<String, (bool, Instant)>>,
    /// Peers that announced they stop in order (their leaving token), until they come back.
    pub(crate) leaving: Mutex<std::collections::BTreeSet<String>>,
    /// Local outputs and their types, for last-value readers (set at each commit).
    pub(crate) outputs: Mutex<Option<Vec<(String, MessageType)>>>,
    /// The wiring of the revision committed last.
    pub(crate) wiring: Mutex<Option<Wiring>>,
    /// The kinds that revision could use (built in and the executables it declares).
    pub(crate) kinds: Mutex<Option<Arc<dnm_netlist::Catalog>>>,
    pub(crate) queries_in_flight: AtomicUsize,
    pub(crate) commands_in_flight: AtomicUsize,
    pub(crate) applies_in_flight: Arc<AtomicUsize>,
    pub(crate) refused: AtomicU64,
    pub(crate) answered: AtomicU64,
    /// Set when the bridge is dropped: its threads end.
    pub(crate) stop: std::sync::atomic::AtomicBool,
    /// A `Look` is queued for the query thread and not yet taken: no second one is sent.
    pub(crate) look_pending: std::sync::atomic::AtomicBool,
    /// The system's authority, when it has one: switches and applies then come only from it
    /// (as transactions); a direct one would put this DNM on a task the others are not on.
    pub(crate) authority: std::sync::OnceLock<String>,
    /// The DNM's lease on that authority.
    pub(crate) lease: Mutex<Lease>,
}

impl Shared {
    /// The newest snapshot: what readers that act without asking need is never older than a
    /// tick (see `dnm_core`'s `publish`); the live figures may be up to a second old.
    pub(crate) fn snapshot(&self) -> Option<Arc<Snapshot>> {
        self.snapshot.lock().ok().and_then(|s| s.clone())
    }

    /// A snapshot at most [`FRESH`] old, for a tool asking for the live figures: the DNM is
    /// asked for one if the newest is older, and waited for up to [`FRESH_WAIT`]; past that
    /// (the DNM busy, its queue full) the newest there is.
    pub(crate) fn fresh_snapshot(&self, commander: &Commander) -> Option<Arc<Snapshot>> {
        let asked = Instant::now();
        let stale = |s: &Option<Arc<Snapshot>>| {
            s.as_ref()
                .is_none_or(|s| asked.saturating_duration_since(s.taken) > FRESH)
        };
        let current = self.snapshot();
        if !stale(&current) || self.stop.load(Ordering::Relaxed) {
            return current;
        }
        {
            let Ok(mut since) = self.refresh_asked.lock() else {
                return current;
            };
            match *since {
                // The DNM is busy (a decision coming into force): do not wait on it again.
                Some(at) if at.elapsed() >= FRESH_WAIT => return current,
                Some(_) => {}
                None => {
                    if commander.send(Command::Refresh).is_err() {
                        return current;
                    }
                    *since = Some(asked);
                }
            }
        }
        let Ok(guard) = self.snapshot.lock() else {
            return current;
        };
        let waited = self
            .fresh
            .wait_timeout_while(guard, FRESH_WAIT, |s| {
                stale(s) && !self.stop.load(Ordering::Relaxed)
            })
            .map(|(guard, _)| guard.clone());
        waited.ok().flatten().or(current)
    }

    /// The DNM handed over `snapshot`.
    pub(crate) fn set_snapshot(&self, snapshot: &Arc<Snapshot>) -> Option<Arc<Snapshot>> {
        let before = self
            .snapshot
            .lock()
            .ok()
            .and_then(|mut s| s.replace(snapshot.clone()));
        if let Ok(mut since) = self.refresh_asked.lock() {
            *since = None;
        }
        self.fresh.notify_all();
        before
    }
}
