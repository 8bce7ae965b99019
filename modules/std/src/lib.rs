//! The standard module kinds, grouped by role: `sources` produce data, `tasks` transform it,
//! `sinks` consume it. [`registry`] lists them all; the `dnm-module-host` executable runs them.
//!
//! ```
//! let kinds = dnm_modules::registry().specs();
//! assert!(kinds.iter().any(|k| k.name == "relay"));
//! ```

use dnm_module::Registry;
use dnm_netlist::{Catalog, KindSource};

pub mod sinks;
pub mod sources;
pub mod tasks;

/// Every standard kind.
pub fn registry() -> Registry {
    Registry::new()
        .register::<sources::Ticker>()
        .register::<sources::BlobSource>()
        .register::<tasks::Relay>()
        .register::<tasks::Pair>()
        .register::<tasks::Merge>()
        .register::<sinks::Latency>()
}

/// The standard kinds as a netlist catalog.
pub fn catalog() -> Catalog {
    let mut c = Catalog::new();
    for spec in registry().specs() {
        c.insert(spec, KindSource::BuiltIn);
    }
    c
}
