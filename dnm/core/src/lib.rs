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

pub mod answer;
mod apply;
mod command;
mod error;
mod exits;
pub mod group;
mod janitor;
mod node;
mod options;
mod pending;
pub mod plan;
mod plugin;
pub mod procfs;
mod publish;
mod safe;
mod slot;
mod supervise;
mod txn;
pub mod worker;

pub use command::{Command, CommandKey, Decision, Reply, SafeOrder, Txn};
pub use dnm_proto as proto;
pub use dnm_proto::{
    DnmReport, ModuleEvent, ModuleReport, ModuleRunState, NetlistState, SwitchRecord,
};
pub use error::DnmError;
pub use node::{Commander, Dnm, clear_stop_if_idle, request_stop};
pub use options::{DnmOptions, module_host_path};
pub use plugin::{Context, Plugin, PluginPrepareError, Snapshot};
pub use publish::SNAPSHOT_EVERY;

use dnm_netlist::Netlist;

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
