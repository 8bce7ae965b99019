//! An apply in progress, applies waiting for it, and the remembered answers of commands.

use std::collections::BTreeMap;
use std::time::Instant;

use dnm_netlist::Netlist;
use dnm_proto::SwitchRecord;

use crate::command::{CommandKey, Reply};
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
    pub(crate) deadline: Instant,
    pub(crate) key: Option<CommandKey>,
    pub(crate) replies: Vec<Reply<Result<u64, String>>>,
    /// The authority's transaction this apply prepares: once prepared it is held (no deadline)
    /// until the decision.
    pub(crate) txn: Option<u64>,
    /// The task to put in force with the revision (else the active one carries over).
    pub(crate) task: Option<String>,
    /// Answered once every module has prepared.
    pub(crate) ready: Vec<Reply<Result<(), String>>>,
    /// Prepared and waiting for the authority's decision.
    pub(crate) held: bool,
}

/// The remembered answer of a command, by its key.
#[derive(Debug, Clone)]
pub(crate) enum Outcome {
    Switch(Result<SwitchRecord, String>),
    Apply(Result<u64, String>),
}

/// An apply waiting for the one in progress: the netlist, its command key, its reply.
pub(crate) type QueuedApply = (Netlist, Option<CommandKey>, Reply<Result<u64, String>>);
