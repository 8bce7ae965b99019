//! An apply in progress, applies waiting for it, transactions held and scheduled, and the
//! remembered answers of commands.

use crate::DnmError;
use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use dnm_netlist::Netlist;
use dnm_proto::SwitchRecord;

use crate::command::{CommandKey, Decision, Reply};
use crate::slot::ModuleSlot;

/// An apply in progress.
pub(crate) struct PendingApply {
    pub(crate) netlist: Netlist,
    pub(crate) revision: u64,
    pub(crate) removed: Vec<String>,
    pub(crate) replaced: Vec<String>,
    /// New modules, started but not part of the DNM until the commit.
    pub(crate) staged: BTreeMap<String, ModuleSlot>,
    /// Port services this apply created (released if it fails).
    pub(crate) new_ports: Vec<String>,
    /// Plugins that prepared (aborted in reverse if the apply fails).
    pub(crate) prepared_plugins: usize,
    /// How long modules get to prepare (the DNM's timeout and a share per process started).
    pub(crate) prepare_for: std::time::Duration,
    pub(crate) deadline: Instant,
    pub(crate) key: Option<CommandKey>,
    pub(crate) replies: Vec<Reply<Result<u64, DnmError>>>,
    /// The authority's transaction this apply prepares: once prepared it is held (no deadline)
    /// until the decision.
    pub(crate) txn: Option<u64>,
    /// The task to put in force with the revision (else the active one carries over).
    pub(crate) task: Option<String>,
    /// Answered once every module has prepared.
    pub(crate) ready: Vec<Reply<Result<(), DnmError>>>,
    /// Prepared and waiting for the authority's decision.
    pub(crate) held: bool,
}

/// The remembered answer of a command, by its key.
#[derive(Debug, Clone)]
pub(crate) enum Outcome {
    Switch(Result<SwitchRecord, DnmError>),
    Apply(Result<u64, DnmError>),
}

/// An apply waiting for the one in progress: the netlist, its command key, its reply.
pub(crate) type QueuedApply = (Netlist, Option<CommandKey>, Reply<Result<u64, DnmError>>);

/// A prepared switch waiting for its decision.
#[derive(Debug)]
pub(crate) struct HeldSwitch {
    pub(crate) id: u64,
    pub(crate) task: String,
    pub(crate) since: Instant,
}

/// A committed decision waiting for its instant.
pub(crate) struct Scheduled {
    pub(crate) decision: Decision,
    pub(crate) due: Instant,
    pub(crate) replies: Vec<Reply<DecideResult>>,
}

pub(crate) type DecideResult = Result<Option<SwitchRecord>, DnmError>;

/// Decisions remembered for retries.
pub(crate) const DECIDED: usize = 256;

/// How long a prepared switch keeps the loop quiet while it waits for the decision.
pub(crate) const QUIET_HOLD: Duration = Duration::from_secs(1);

/// From this long before a decided instant the loop leaves supervision and starting processes
/// until the decision is in force (before, a DNM waiting for an instant supervises as usual).
pub(crate) const QUIET_BEFORE: Duration = Duration::from_millis(200);

/// From this long before a decided instant the DNM's loop does nothing but wait for it.
pub(crate) const NEAR: Duration = Duration::from_millis(25);

/// The loop sleeps out the last this much before a decided instant instead of waiting on its
/// wait set, so the store lands within the timer's slack of the instant on every DNM.
pub(crate) const FINE_WAIT: Duration = Duration::from_millis(2);

/// Decisions remembered, by transaction id.
pub(crate) type Decided = VecDeque<(u64, DecideResult)>;
