//! DNMs on Zenoh: the [`Bridge`] a DNM carries as a plugin (routes between DNMs derived from
//! the netlist, queryables for tools, liveliness, commands), and the client side
//! ([`remote`]) that the `dnm` command and the ground station use to operate a system from any
//! machine on its Zenoh network.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let mut node: dnm_core::Dnm = unimplemented!();
//! # let session: zenoh::Session = unimplemented!();
//! # let door: dnm_netlist::NetlistDoor = unimplemented!();
//! let commander = node.commander()?;
//! let bridge = dnm_zenoh::Bridge::new(session, "beetle", "rover", node.prefix(), commander, door)?;
//! node.add_plugin(Box::new(bridge));
//! # Ok(()) }
//! ```

mod bridge;
mod command;
mod egress;
mod ingress;
pub mod lease;
mod query;
pub mod remote;
mod shared;
mod watch;
mod wire;

pub use bridge::{Bridge, BridgeStartError};
pub use shared::{COMMAND_QUEUE, QUERY_QUEUE};
pub use wire::encoding;

/// The newest netlist the running DNMs of `system` hold, if any answers within `timeout`.
/// A DNM that (re)starts into a running system continues from it.
pub fn newest_netlist(
    session: &zenoh::Session,
    system: &str,
    timeout: std::time::Duration,
) -> Option<dnm_proto::NetlistState> {
    bridge::newest_netlist_impl(session, system, timeout)
}
