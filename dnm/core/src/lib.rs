//! The connection layer's core: one database node module (DNM).
//!
//! A DNM hosts its modules as separate processes, each with its own shared memory for its
//! output ports (iceoryx2). It turns the netlist into references from inputs to outputs and,
//! when a netlist is applied, prepares every subscription any defined task needs; switching the
//! active task is then a single store into a shared task word that every module reads once per
//! step. It supervises its modules (exits, hangs, restarts, CPU, rates) and cleans up the
//! shared memory of processes that died.
//!
//! The core knows neither Zenoh nor MCAP nor any catalogue of module kinds: what reaches other
//! DNMs (the Zenoh bridge) or a disk (the recorder) plugs in as a [`Plugin`], called at each
//! step of an apply (prepare, abort, commit), at every switch, at every module event and for
//! every report. Commands reach the DNM's thread through a [`Commander`]; an apply never holds
//! up a switch.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let netlist: dnm_netlist::Netlist = unimplemented!();
//! use dnm_core::{Dnm, DnmOptions};
//! let mut node = Dnm::new("pipeline", "local", DnmOptions::standard()?)?;
//! node.apply(&netlist)?;          // prepares every task, commits revision 1
//! node.switch("b")?;              // one store into the task word
//! let commander = node.commander()?; // for other threads: status, switch, apply
//! node.run()?;                    // supervises until SIGTERM or the commanders are gone
//! # Ok(()) }
//! ```

mod apply;
mod node;
pub mod plan;
pub mod procfs;
mod supervise;
pub mod values;
pub mod worker;

pub use dnm_proto as proto;
pub use dnm_proto::{
    DnmReport, ModuleEvent, ModuleReport, ModuleRunState, NetlistState, SwitchRecord,
};
pub use node::{Commander, Dnm, request_stop};

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use dnm_netlist::Netlist;
use iceoryx2::prelude::*;

/// Failures of DNM operations. Each leaves the running system as it was.
#[derive(Debug, thiserror::Error)]
pub enum DnmError {
    #[error("shared memory: {0}")]
    Ipc(String),
    #[error(
        "DNM `{dnm}` of system `{system}` is already running on this machine (its task word exists); stop it first"
    )]
    AlreadyRunning { system: String, dnm: String },
    #[error("unknown task `{task}`; defined tasks: {known}")]
    UnknownTask { task: String, known: String },
    #[error("no netlist applied yet")]
    NoNetlist,
    #[error(
        "netlist does not declare DNM `{0}`, which this process hosts; keep it or stop this DNM first"
    )]
    DnmMissing(String),
    #[error(
        "modules did not prepare revision {revision} within {timeout_ms} ms: {modules}; the previous revision stays active"
    )]
    PrepareTimeout {
        revision: u64,
        timeout_ms: u128,
        modules: String,
    },
    #[error(
        "module `{module}` exited while preparing revision {revision} ({exit}); the previous revision stays active"
    )]
    PrepareExit {
        module: String,
        revision: u64,
        exit: String,
    },
    #[error("{plugin}: {why}; the previous revision stays active")]
    Plugin { plugin: &'static str, why: String },
    #[error("cannot start module `{module}` ({exec}): {why}")]
    Spawn {
        module: String,
        exec: String,
        why: String,
    },
    #[error("the DNM is busy: {0} commands are queued; try again")]
    Busy(usize),
    #[error("the DNM has stopped")]
    Stopped,
    #[error("{0}")]
    Refused(String),
}

/// How a DNM runs its modules.
#[derive(Debug, Clone)]
pub struct DnmOptions {
    /// Executable that runs built-in kinds (`dnm-module-host`).
    pub module_host: PathBuf,
    /// How long modules get to prepare a new revision.
    pub prepare_timeout: Duration,
    /// Supervision period: exits, hangs, restarts, CPU readings.
    pub tick: Duration,
    /// How long a module that is not periodic may go without a sign of life before it is
    /// reported hung (a module's `hung_after` overrides it).
    pub on_input_hung_after: Duration,
    /// How long a stopped module gets to exit after SIGTERM before SIGKILL.
    pub stop_grace: Duration,
}

impl DnmOptions {
    /// The module host next to the running executable (or `$DNM_MODULE_HOST`), 5 s to prepare
    /// a revision, a 100 ms supervision tick, 2 s without a sign of life for on-input modules.
    pub fn standard() -> std::io::Result<Self> {
        Ok(Self {
            module_host: module_host_path()?,
            prepare_timeout: Duration::from_secs(5),
            tick: Duration::from_millis(100),
            on_input_hung_after: Duration::from_secs(2),
            stop_grace: Duration::from_secs(2),
        })
    }
}

/// Where the standard module host executable is.
pub fn module_host_path() -> std::io::Result<PathBuf> {
    if let Some(p) = std::env::var_os("DNM_MODULE_HOST") {
        return Ok(PathBuf::from(p));
    }
    let exe = std::env::current_exe()?;
    let dir = exe.parent().unwrap_or(Path::new("."));
    // Test and bench executables live one level down, in `deps/`.
    for candidate in [dir.join("dnm-module-host"), dir.join("../dnm-module-host")] {
        if candidate.exists() {
            return Ok(candidate);
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::NotFound,
        format!(
            "dnm-module-host not found next to {}; build it with `cargo build --workspace` or set DNM_MODULE_HOST",
            exe.display()
        ),
    ))
}

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

/// Something a DNM carries along with its modules: the Zenoh bridge, the recorder. The DNM
/// calls it from its own thread; a plugin must return quickly (hand slow work to its own
/// threads) so switches and supervision are never delayed.
pub trait Plugin {
    /// Its name, in errors and logs.
    fn name(&self) -> &'static str;
    /// Before modules get the plans of `revision`: make what they will reference (for example
    /// mirrors of remote outputs). An error aborts the apply.
    fn prepare(
        &mut self,
        ctx: &Context<'_>,
        netlist: &Netlist,
        revision: u64,
    ) -> Result<(), String> {
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
    /// The DNM's newest state, after every supervision pass and command.
    fn published(&mut self, snapshot: &Arc<Snapshot>) {
        let _ = snapshot;
    }
}

/// The DNM's state at one moment, shared with plugins that answer tools from their own threads.
#[derive(Debug, Clone)]
pub struct Snapshot {
    pub report: DnmReport,
    pub netlist: NetlistState,
}

/// Identifies a command for exactly-once handling: the sending client and its id.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct CommandKey {
    pub client: String,
    pub id: String,
}

/// Where a command's answer goes: a function the DNM's thread calls once. It must not block
/// (send it on a channel, for example).
pub struct Reply<T>(Box<dyn FnOnce(T) + Send>);

impl<T> std::fmt::Debug for Reply<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Reply")
    }
}

impl<T: Send + 'static> Reply<T> {
    pub fn new(f: impl FnOnce(T) + Send + 'static) -> Self {
        Self(Box::new(f))
    }

    /// A reply that lands on a channel the caller waits on.
    pub fn channel() -> (Self, std::sync::mpsc::Receiver<T>) {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        (
            Self::new(move |v| {
                let _ = tx.send(v);
            }),
            rx,
        )
    }

    pub(crate) fn send(self, v: T) {
        (self.0)(v)
    }
}

/// What a DNM's thread takes from other threads.
#[derive(Debug)]
pub enum Command {
    Status(Reply<DnmReport>),
    Netlist(Reply<NetlistState>),
    Switch {
        task: String,
        key: Option<CommandKey>,
        reply: Reply<Result<SwitchRecord, String>>,
    },
    /// Apply a validated netlist. The answer comes when the revision is committed or refused;
    /// switches go on meanwhile.
    Apply {
        netlist: Box<Netlist>,
        key: Option<CommandKey>,
        reply: Reply<Result<u64, String>>,
    },
}

/// Links whose output and input run on different DNMs, with (from DNM, to DNM): the routes
/// between DNMs.
pub fn crossing_links(netlist: &Netlist) -> Vec<(dnm_netlist::Link, String, String)> {
    let dnm_of = |m: &str| netlist.module(m).map(|m| m.dnm.clone()).unwrap_or_default();
    netlist
        .all_links()
        .into_iter()
        .filter_map(|l| {
            let (a, b) = (dnm_of(&l.from.module), dnm_of(&l.to.module));
            (a != b).then(|| (l.clone(), a, b))
        })
        .collect()
}
