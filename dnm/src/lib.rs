//! The `dnm` command's library: runs a machine's DNMs ([`admin::Host`]: each DNM on its own
//! thread, with its Zenoh bridge, its recorder and the machine's admin socket), reads netlists
//! against the built-in kinds, and the Beetle-One demo. The layers it puts together live in
//! their own crates: [`dnm_core`] (the DNM), [`dnm_zenoh`] (DNMs on Zenoh), [`dnm_record`]
//! (MCAP), [`dnm_proto`] (what they say to each other).
//!
//! ```no_run
//! # fn main() -> anyhow::Result<()> {
//! let netlist = dnm::load_netlist("configs/pipeline.toml".as_ref())?;
//! let options = dnm::HostOptions::standard()?;
//! let host = dnm::admin::Host::start(netlist, &["main".into()], options, zenoh::Config::default())?;
//! let status = dnm::admin::request("pipeline", &dnm::proto::Request::Status)?;
//! host.stop();
//! # Ok(()) }
//! ```

pub use dnm_core::{
    Command, Commander, Dnm, DnmError, DnmOptions, DnmReport, ModuleReport, ModuleRunState,
    SwitchRecord, crossing_links,
};
pub use dnm_proto as proto;
pub use dnm_proto::keys;
pub use dnm_record::{record, replay, stats};
pub use dnm_router::ZenohOptions;
pub use dnm_zenoh::remote;

pub mod admin;

use std::path::Path;

use dnm_netlist::{KindSpec, Netlist, NetlistError};

/// How a host runs its DNMs: the DNMs' own options and what they record.
#[derive(Debug, Clone)]
pub struct HostOptions {
    pub dnm: DnmOptions,
    /// Record every output port to MCAP; `None`: no recording.
    pub record: Option<record::RecordOptions>,
    /// Where durable state lives (the authority's database).
    pub state_dir: std::path::PathBuf,
}

/// Where durable state goes by default: `$DNM_STATE_DIR`, else `$XDG_STATE_HOME/dnm`, else
/// `~/.local/state/dnm`, else a folder under the temporary directory.
pub fn default_state_dir() -> std::path::PathBuf {
    if let Some(d) = std::env::var_os("DNM_STATE_DIR") {
        return d.into();
    }
    if let Some(d) = std::env::var_os("XDG_STATE_HOME") {
        return std::path::PathBuf::from(d).join("dnm");
    }
    if let Some(h) = std::env::var_os("HOME") {
        return std::path::PathBuf::from(h).join(".local/state/dnm");
    }
    std::env::temp_dir().join("dnm-state")
}

/// Whether a system is commanded through its authority: it names one, or it has DNMs across
/// a radio link. Its DNMs then start empty and take what the authority decided.
pub fn commanded_by_authority(netlist: &Netlist) -> bool {
    netlist.authority_dnm.is_some() || netlist.dnms.iter().any(|d| d.radio)
}

impl HostOptions {
    /// [`DnmOptions::standard`], no recording.
    pub fn standard() -> std::io::Result<Self> {
        Ok(Self {
            dnm: DnmOptions::standard()?,
            record: None,
            state_dir: default_state_dir(),
        })
    }
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

/// Every built-in kind: the standard ones and Beetle-One's. `dnm-module-host` runs them.
pub fn registry() -> dnm_module::Registry {
    dnm_module_host::registry()
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

/// [`parse_netlist`] with the error as text, as the Zenoh bridge and the recordings take it.
pub fn parse_netlist_text(path: &Path, text: &str) -> Result<Netlist, String> {
    parse_netlist(path, text).map_err(|e| e.to_string())
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
