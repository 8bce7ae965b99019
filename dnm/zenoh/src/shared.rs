//! What the bridge's threads and callbacks share, and the bounds of their queues.

use std::collections::BTreeMap;
use std::sync::atomic::{AtomicU64, AtomicUsize};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use dnm_core::Snapshot;
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

/// What the bridge's threads and callbacks share.
#[derive(Default)]
pub(crate) struct Shared {
    pub(crate) snapshot: Mutex<Option<Arc<Snapshot>>>,
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
    pub(crate) fn snapshot(&self) -> Option<Arc<Snapshot>> {
        self.snapshot.lock().ok().and_then(|s| s.clone())
    }
}
