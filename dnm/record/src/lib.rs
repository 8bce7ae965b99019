//! Recordings: every output port of a DNM written to MCAP by the [`record::Recorder`] (a DNM
//! plugin, off the modules' path), recordings replayed into a running system ([`replay`]), and
//! their statistics ([`stats`]).
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let mut node: dnm_core::Dnm = unimplemented!();
//! use dnm_record::record::{RecordOptions, Recorder};
//! let options = RecordOptions::timestamped("recordings".as_ref());
//! node.add_plugin(Box::new(Recorder::start(node.name(), node.prefix(), options)?));
//! # Ok(()) }
//! ```

pub mod record;
pub mod replay;
pub mod stats;

/// Parses and validates a netlist stored in a recording (`file` names it in errors).
pub type ParseNetlist<'a> =
    dyn Fn(&std::path::Path, &str) -> Result<dnm_netlist::Netlist, String> + 'a;
