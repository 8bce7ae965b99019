//! What a DNM carries along with its modules (the Zenoh bridge, the recorder), and what it shows
//! them.

use std::collections::BTreeSet;
use std::sync::Arc;

use dnm_netlist::Netlist;
use dnm_proto::{DnmReport, ModuleEvent, ModuleRunState, NetlistState, Safed, SwitchRecord};
use iceoryx2::prelude::*;

/// What a [`Plugin`] sees of its DNM.
#[derive(Debug)]
pub struct Context<'a> {
    pub system: &'a str,
    pub dnm: &'a str,
    /// The iceoryx2 file prefix of the DNM's shared-memory namespace.
    pub prefix: &'a str,
    /// The DNM's iceoryx2 node, to open port services in its namespace.
    pub node: &'a Node<ipc::Service>,
    /// Output services (`module/port`) of the modules running here before this apply.
    pub local_outputs: &'a BTreeSet<String>,
}

/// Why a plugin could not prepare a revision: its own error, whatever its type.
pub type PluginPrepareError = Box<dyn std::error::Error + Send + Sync>;

/// Something a DNM carries along with its modules: the Zenoh bridge, the recorder. The DNM
/// calls it from its own thread; a plugin must return quickly (hand slow work to its own
/// threads) so switches and supervision are never delayed.
pub trait Plugin {
    /// Its name, in errors and logs.
    fn name(&self) -> &'static str;
    /// Before modules get the plans of `revision`: make what they will reference (for example
    /// mirrors of remote outputs). An error aborts the apply; its message says why.
    fn prepare(
        &mut self,
        ctx: &Context<'_>,
        netlist: &Netlist,
        revision: u64,
    ) -> Result<(), PluginPrepareError> {
        let _ = (ctx, netlist, revision);
        Ok(())
    }
    /// The apply of `revision` failed: undo what [`Plugin::prepare`] made.
    fn abort(&mut self, ctx: &Context<'_>, revision: u64) {
        let _ = (ctx, revision);
    }
    /// `revision` is in force.
    fn commit(&mut self, ctx: &Context<'_>, netlist: &Netlist, revision: u64) {
        let _ = (ctx, netlist, revision);
    }
    /// The active task changed.
    fn switch(&mut self, record: &SwitchRecord) {
        let _ = record;
    }
    /// A module started, exited, hung, recovered, was restarted or given up on.
    fn module_event(&mut self, event: &ModuleEvent) {
        let _ = event;
    }
    /// Adds its part to a report of the DNM.
    fn report(&self, report: &mut DnmReport) {
        let _ = report;
    }
    /// The DNM's newest state: after every command that changes it, on the supervision tick
    /// when anything a reader acts on changed, when a tool asked for one
    /// ([`Command::Refresh`](crate::Command::Refresh)), and at least once every
    /// [`SNAPSHOT_EVERY`](crate::SNAPSHOT_EVERY).
    fn published(&mut self, snapshot: &Arc<Snapshot>) {
        let _ = snapshot;
    }
}

/// The DNM's state at one moment, shared with plugins that answer tools from their own threads.
#[derive(Debug, Clone)]
pub struct Snapshot {
    pub report: DnmReport,
    pub netlist: NetlistState,
    /// When it was taken.
    pub taken: std::time::Instant,
}

/// What the DNM's readers act on without asking for a fresh snapshot: a change of any of it
/// is published on the tick it is seen (or at once, by the command that made it).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Watched {
    pub(crate) revision: u64,
    pub(crate) last_attempt: u64,
    pub(crate) active: Option<String>,
    pub(crate) preparing: Option<u64>,
    pub(crate) holding: Option<u64>,
    pub(crate) scheduled_at: Option<u64>,
    pub(crate) stopping: usize,
    pub(crate) safed: Option<Safed>,
    /// Per module, in name order: state, process, restarts, hangs, the revision it follows.
    pub(crate) modules: Vec<(ModuleRunState, Option<u32>, u32, u32, u64)>,
    /// The newest switch and module event (both logs keep a bounded tail, so their lengths
    /// stop changing).
    pub(crate) last_switch_ns: Option<u64>,
    pub(crate) last_event_ns: Option<u64>,
}
