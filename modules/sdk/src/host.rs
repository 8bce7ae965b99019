//! Starting module processes: a host executable that runs any of a set of registered kinds.
//!
//! The DNM starts a module as `HOST run '<launch json>'`; `HOST describe` prints the kinds as
//! JSON so a netlist can declare an external executable with `[kind.NAME] exec = "..."`.

use std::process::ExitCode;

use dnm_netlist::KindSpec;

use crate::protocol::Launch;
use crate::runtime::author::{Module, ModuleError};
use crate::runtime::offline::make;
use crate::runtime::process::run;

/// A registered kind: its spec and how to run it.
#[derive(Debug, Clone, Copy)]
pub struct Registration {
    pub spec: fn() -> KindSpec,
    pub run: fn(&Launch) -> Result<(), ModuleError>,
    /// Builds the module in this process, to step it with [`crate::Offline`].
    pub make: fn(&mut crate::Setup<'_>) -> Result<Box<dyn crate::Stepper>, ModuleError>,
}

/// The kinds one executable can run.
#[derive(Debug, Default, Clone)]
pub struct Registry {
    kinds: Vec<Registration>,
}

impl Registry {
    pub fn new() -> Self {
        Self::default()
    }

    pub fn register<M: Module>(mut self) -> Self {
        self.kinds.push(Registration {
            spec: M::kind,
            run: run::<M>,
            make: make::<M>,
        });
        self
    }

    pub fn specs(&self) -> Vec<KindSpec> {
        let mut specs: Vec<KindSpec> = self.kinds.iter().map(|k| (k.spec)()).collect();
        specs.sort_by(|a, b| a.name.cmp(&b.name));
        specs
    }

    pub fn find(&self, kind: &str) -> Option<&Registration> {
        self.kinds.iter().find(|k| (k.spec)().name == kind)
    }
}

/// The `main` of a module executable.
///
/// ```no_run
/// # use dnm_module::{Registry, host_main};
/// fn main() -> std::process::ExitCode {
///     host_main(&Registry::new() /* .register::<MyModule>() */)
/// }
/// ```
pub fn host_main(registry: &Registry) -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("describe" | "--describe") => {
            let specs = registry.specs();
            // A single-kind executable describes itself as one object.
            let json = if specs.len() == 1 {
                serde_json::to_string_pretty(&specs[0])
            } else {
                serde_json::to_string_pretty(&specs)
            };
            match json {
                Ok(j) => {
                    println!("{j}");
                    ExitCode::SUCCESS
                }
                Err(e) => {
                    eprintln!("cannot describe kinds: {e}");
                    ExitCode::FAILURE
                }
            }
        }
        Some("run") if args.len() == 2 => {
            crate::init_logging();
            let launch: Launch = match serde_json::from_str(&args[1]) {
                Ok(l) => l,
                Err(e) => {
                    eprintln!("bad launch description: {e}");
                    return ExitCode::from(2);
                }
            };
            let Some(kind) = registry.find(&launch.kind) else {
                eprintln!("this executable has no kind `{}`", launch.kind);
                return ExitCode::from(2);
            };
            match (kind.run)(&launch) {
                Ok(()) => ExitCode::SUCCESS,
                Err(e) => {
                    tracing::error!(module = %launch.module, "module failed: {e}");
                    ExitCode::FAILURE
                }
            }
        }
        _ => {
            eprintln!(
                "usage: {} describe | run '<launch json>'\n(module processes are started by a DNM)",
                std::env::args().next().unwrap_or_default()
            );
            ExitCode::from(2)
        }
    }
}
