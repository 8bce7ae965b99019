//! The module SDK: what a module author writes, and the runtime of a module process.
//!
//! A module declares typed input and output ports and parameters ([`Kind`]), is built from its
//! parameters ([`Module::new`]), and steps periodically or when an input has new data
//! ([`Module::step`]). It reads inputs and writes outputs through [`Io`] without knowing what
//! they are connected to: the DNM decides that, and switches it by changing references.
//! Port payloads live in iceoryx2 shared memory and are loaned, written in place and sent
//! without copies; fixed-size [`msg::Message`]s and variable-size byte payloads are supported.
//!
//! ```
//! use dnm_module::{Input, Io, Kind, Module, ModuleError, Output, Setup, msg::Tick};
//! use dnm_netlist::KindSpec;
//!
//! struct Relay { input: Input<Tick>, output: Output<Tick> }
//!
//! impl Module for Relay {
//!     fn kind() -> KindSpec {
//!         Kind::new("relay", "forwards ticks").input::<Tick>("in").output::<Tick>("out").on_input().build()
//!     }
//!     fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
//!         Ok(Relay { input: setup.input("in")?, output: setup.output("out")? })
//!     }
//!     fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
//!         if let Some(tick) = io.read(&self.input) {
//!             io.write(&self.output, &tick)?;
//!         }
//!         Ok(())
//!     }
//! }
//! ```

mod host;
mod kind;
pub mod msg;
pub mod protocol;
mod runtime;

pub use host::{Registration, Registry, host_main};
pub use kind::Kind;
pub use runtime::abandoned::{AbandonedSweep, remove_abandoned_services};
pub use runtime::author::{BytesInput, BytesOutput, Input, Io, Module, ModuleError, Output, Setup};
pub use runtime::offline::{Offline, Stepper};
pub use runtime::process::{MakeModule, run_dynamic};
pub use runtime::services::{
    TaskWatch, event_service, event_service_for, plan_service_factory, port_service,
    port_service_for, recovering, status_service_factory,
};

/// Logs to stderr through `tracing`, filtered by `RUST_LOG` (default `info`); iceoryx2's own
/// log goes through the same subscriber at warning level.
pub fn init_logging() {
    init_logging_at("info");
}

/// [`init_logging`] with another default level (`RUST_LOG` still wins). Zenoh's chatter is kept
/// at warnings either way.
pub fn init_logging_at(level: &str) {
    use tracing_subscriber::EnvFilter;
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new(format!(
            "{level},zenoh=warn,zenoh_transport=warn,zenoh_link_tcp=warn,zenoh_link_udp=warn,zenoh_config=warn"
        ))
    });
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .try_init();
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Warn);
}
