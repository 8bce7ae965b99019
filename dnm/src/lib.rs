//! The connection layer: a database node module (DNM) per computer or process group.
//!
//! A DNM hosts its modules as separate processes, each with its own shared memory for its
//! output ports (iceoryx2). It turns the netlist into references from inputs to outputs, and
//! prepares, when a netlist is applied, every subscription any defined task needs; switching
//! the active task is then a single store into a shared task word that every module reads once
//! per step. It supervises its modules (restarts, CPU, rates) and cleans up the shared memory of
//! processes that died.
//!
//! ```no_run
//! # fn main() -> anyhow::Result<()> {
//! use dnm::{Dnm, DnmOptions};
//! let netlist = dnm::load_netlist("configs/pipeline.toml".as_ref())?;
//! let mut node = Dnm::new(&netlist.system, "local", DnmOptions::standard()?)?;
//! let events = node.status_listener()?;
//! node.apply(&netlist, &events)?;
//! node.switch("b")?;
//! # Ok(()) }
//! ```

pub use dnm_router::ZenohOptions;

pub mod admin;
mod dnm;
pub mod keys;
pub mod net;
pub mod plan;
pub mod procfs;
pub mod record;
pub mod remote;
pub mod replay;
pub mod stats;
pub mod values;
mod worker;

pub use dnm::{
    Command, Dnm, DnmError, DnmOptions, DnmReport, ModuleReport, ModuleRunState, SwitchRecord,
};

use std::path::{Path, PathBuf};
use std::time::Duration;

use dnm_netlist::{KindSpec, Netlist, NetlistError};

impl DnmOptions {
    /// The module host next to the running executable (or `$DNM_MODULE_HOST`), 5 s to prepare
    /// a revision, a 100 ms supervision tick.
    pub fn standard() -> std::io::Result<Self> {
        Ok(Self {
            module_host: module_host_path()?,
            prepare_timeout: Duration::from_secs(5),
            tick: Duration::from_millis(100),
            record: None,
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

/// Asks a module executable for its kind (`EXEC describe`).
pub fn describe_exec(path: &Path) -> Result<KindSpec, String> {
    let out = std::process::Command::new(path)
        .arg("describe")
        .output()
        .map_err(|e| e.to_string())?;
    if !out.status.success() {
        return Err(format!("`describe` exited with {}", out.status));
    }
    serde_json::from_slice(&out.stdout).map_err(|e| format!("`describe` printed no kind: {e}"))
}

/// Links whose output and input run on different DNMs, with (from DNM, to DNM): the routes
/// Zenoh carries (see [`net`]).
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

/// Every built-in kind: the standard ones and Beetle-One's. `dnm-module-host` runs them.
pub fn registry() -> dnm_module::Registry {
    dnm_rover::register(dnm_modules::registry())
}

/// The built-in kinds as a netlist catalog.
pub fn catalog() -> dnm_netlist::Catalog {
    let mut c = dnm_netlist::Catalog::new();
    for spec in registry().specs() {
        c.insert(spec, dnm_netlist::KindSource::BuiltIn);
    }
    c
}

/// Loads and validates a netlist against the built-in kinds and the executables it declares.
pub fn load_netlist(path: &Path) -> Result<Netlist, NetlistError> {
    Netlist::load(path, &catalog(), &mut describe_exec)
}

/// Validates netlist text (e.g. sent by an operator) the same way.
pub fn parse_netlist(path: &Path, text: &str) -> Result<Netlist, NetlistError> {
    Netlist::parse(path, text, &catalog(), &mut describe_exec)
}

/// `text` (a netlist) with each module on the DNM `assignment` gives it and `new_dnms`
/// declared; `unpin` also drops `pinned` flags (for placements that moved pinned modules).
pub fn placed_text(
    text: &str,
    assignment: &std::collections::BTreeMap<String, String>,
    new_dnms: &[(String, Option<String>)],
    unpin: bool,
) -> Result<String, String> {
    let mut doc: toml::Table = text
        .parse()
        .map_err(|e| format!("parsing the netlist: {e}"))?;
    if !new_dnms.is_empty() {
        let dnms = doc
            .entry("dnm")
            .or_insert_with(|| toml::Value::Array(Vec::new()))
            .as_array_mut()
            .ok_or("`dnm` is not an array")?;
        for (name, parent) in new_dnms {
            let mut t = toml::Table::new();
            t.insert("name".into(), name.clone().into());
            if let Some(p) = parent {
                t.insert("parent".into(), p.clone().into());
            }
            dnms.push(t.into());
        }
    }
    let modules = doc
        .get_mut("module")
        .and_then(|m| m.as_array_mut())
        .ok_or("the netlist has no modules")?;
    for m in modules.iter_mut().filter_map(|m| m.as_table_mut()) {
        let name = m.get("name").and_then(|n| n.as_str()).unwrap_or_default();
        if let Some(d) = assignment.get(name) {
            m.insert("dnm".into(), d.clone().into());
        }
        if unpin {
            m.remove("pinned");
        }
    }
    toml::to_string(&doc).map_err(|e| e.to_string())
}
