//! The logical layer: netlist files that describe a system's DNMs, its modules and the tasks
//! that wire them, validated against the module kinds available.
//!
//! ```no_run
//! use dnm_netlist::{Catalog, Netlist};
//! let catalog = Catalog::new(); // normally the built-in kinds
//! let netlist = Netlist::load("configs/pipeline.toml", &catalog, &mut |_| Err("no executables".into()))?;
//! for task in netlist.tasks.values() {
//!     println!("{}: {} links", task.name, task.links.len());
//! }
//! # Ok::<(), dnm_netlist::NetlistError>(())
//! ```
//!
//! Errors name the file, line, column and field, and say what to do; every problem in the file
//! is reported at once. The validated [`Netlist`] carries a petgraph [`ModuleGraph`] that
//! placement and routing reuse.

mod door;
pub mod downlink;
mod error;
mod model;
pub mod sequence;
pub mod spec;
mod validate;
pub mod values;
pub mod wiring;

pub use door::{AcceptError, NetlistDoor, ParseNetlist};
pub use downlink::Decimator;
pub use error::{Describe, DescribeError, Diagnostic, NetlistError};
pub use model::{
    Backfill, Connection, DEFAULT_DNM, DnmDecl, DownlinkEntry, Link, LinkLoss, MAX_HUNG_AFTER_MS,
    MAX_NAME_LEN, MAX_RATE_HZ, MIN_HUNG_AFTER_MS, MIN_RATE_HZ, Module, ModuleGraph, ModuleNode,
    Netlist, PortRef, RestartMode, RestartPolicy, Task, parse_duration_ms,
};
pub use sequence::Sequence;
pub use spec::{
    Catalog, CatalogEntry, DNM_SUBSCRIBERS, KindSource, KindSpec, LARGE_PAYLOAD_BYTES, MAX_READERS,
    MIN_LARGE_SUBSCRIBERS, MIN_SUBSCRIBERS, MessageType, POD_ENCODING, ParamKind, ParamSpec,
    ParamValue, Payload, PortSpec, Standard, Trigger,
};
pub use validate::{BadName, valid_name};
pub use wiring::{WiredModule, Wiring};
