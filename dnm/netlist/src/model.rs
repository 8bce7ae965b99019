//! The netlist model: a validated [`Netlist`], its DNMs, modules, tasks and links. Reading
//! and validating a file (`Netlist::load`, `Netlist::parse`) is in `validate.rs`.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::path::PathBuf;

use petgraph::stable_graph::{NodeIndex, StableDiGraph};
use serde::{Deserialize, Serialize};

use crate::spec::{Catalog, KindSpec, ParamValue};

/// The DNM that hosts modules which name none, when the netlist declares no DNM at all.
pub const DEFAULT_DNM: &str = "local";

/// Longest name allowed for systems, DNMs, modules, ports and tasks. Names become
/// shared-memory service names and network keys, so they stay short and plain.
pub const MAX_NAME_LEN: usize = 48;

// ---------------------------------------------------------------------------------------------
// The validated model.

/// What the DNM does when a module process exits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "kebab-case")]
pub enum RestartMode {
    /// Restart after any exit.
    Always,
    /// Restart after a crash or a non-zero exit.
    #[default]
    OnFailure,
    /// Leave it stopped and report it.
    Never,
}

/// Restart policy of one module.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RestartPolicy {
    pub mode: RestartMode,
    /// Restarts allowed before the module is left failed.
    pub max_restarts: u32,
}

impl Default for RestartPolicy {
    fn default() -> Self {
        Self {
            mode: RestartMode::OnFailure,
            max_restarts: 10,
        }
    }
}

/// A database node module: one per computer or process group.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct DnmDecl {
    pub name: String,
    pub parent: Option<String>,
    /// `link = "radio"`: reached over the radio link (the ground's DNMs). It follows the
    /// authority's decisions when it hears them and never holds up a transaction; the others
    /// are on the rover's own network and take every decision together.
    #[serde(default)]
    pub radio: bool,
}

/// What the rover does when no ground station has been heard for a while:
/// `on_link_loss = { after = "5s", task = "safe" }`, and what it does to an onboard sequence
/// running (`sequences = "run"`, the default, or `"stop"`).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LinkLoss {
    pub after_ms: u64,
    pub task: String,
    /// `sequences = "stop"`: loss of signal makes the rover safe even while a sequence runs,
    /// and stops it. By default a sequence running goes on through the silence (it is what the
    /// operators planned for it) and the rover is made safe only once it ends.
    #[serde(default)]
    pub stop_sequences: bool,
}

/// A module instance.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Module {
    pub name: String,
    pub kind: String,
    /// The DNM it is pinned to, if the netlist says so.
    pub pinned_dnm: Option<String>,
    /// The DNM it runs on: the pinned one, else the first declared DNM.
    pub dnm: String,
    /// `pinned = true`: it must stay on `dnm` (it drives that computer's hardware); placement
    /// moves only modules that are not.
    #[serde(default)]
    pub pinned: bool,
    /// Overrides the kind's periodic rate.
    pub rate_hz: Option<f64>,
    pub restart: RestartPolicy,
    /// `hung_after = "2s"`: how long it may go without stepping (or, while waiting for input,
    /// without a heartbeat) before its DNM reports it hung; by default derived from its rate.
    #[serde(default)]
    pub hung_after_ms: Option<u64>,
    /// Every declared parameter, defaults filled in.
    pub params: BTreeMap<String, ParamValue>,
}

/// An output port or input port of a module: `module.port`.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct PortRef {
    pub module: String,
    pub port: String,
}

impl fmt::Display for PortRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}.{}", self.module, self.port)
    }
}

/// A directed link from an output port to an input port.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
pub struct Link {
    pub from: PortRef,
    pub to: PortRef,
}

impl fmt::Display for Link {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} -> {}", self.from, self.to)
    }
}

/// A named set of links: one way of wiring the modules.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Task {
    pub name: String,
    pub description: String,
    pub links: Vec<Link>,
}

impl Task {
    /// The output feeding `input` in this task, if any.
    pub fn source_of(&self, input: &PortRef) -> Option<&PortRef> {
        self.links.iter().find(|l| &l.to == input).map(|l| &l.from)
    }
}

/// A module in the module graph.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ModuleNode {
    pub module: String,
}

/// An edge of the module graph: one output-to-input link and the tasks that use it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Connection {
    pub from_port: String,
    pub to_port: String,
    pub tasks: BTreeSet<String>,
}

/// The module graph: modules are nodes, every distinct link of any task is an edge.
pub type ModuleGraph = StableDiGraph<ModuleNode, Connection>;

/// A validated netlist.
#[derive(Debug, Clone)]
pub struct Netlist {
    pub file: PathBuf,
    /// The text it was read from, so it can be recorded and sent verbatim.
    pub text: String,
    pub system: String,
    pub default_task: Option<String>,
    /// The DNM that takes operators' commands and decides for all (`system.authority`; the
    /// root of the hierarchy when not named): see [`Netlist::authority`].
    pub authority_dnm: Option<String>,
    pub on_link_loss: Option<LinkLoss>,
    pub dnms: Vec<DnmDecl>,
    pub modules: Vec<Module>,
    pub tasks: BTreeMap<String, Task>,
    /// The downlink plan: the outputs the ground keeps a record of (`[[downlink]]`).
    pub downlink: Vec<DownlinkEntry>,
    /// Every kind the netlist can use: the catalog it was validated against plus its own.
    pub catalog: Catalog,
    pub(crate) graph: ModuleGraph,
    pub(crate) nodes: BTreeMap<String, NodeIndex>,
}

impl Netlist {
    /// The module graph (nodes: modules; edges: distinct links across all tasks).
    pub fn graph(&self) -> &ModuleGraph {
        &self.graph
    }

    /// The graph node of a module.
    pub fn node(&self, module: &str) -> Option<NodeIndex> {
        self.nodes.get(module).copied()
    }

    pub fn module(&self, name: &str) -> Option<&Module> {
        self.modules.iter().find(|m| m.name == name)
    }

    pub fn dnm(&self, name: &str) -> Option<&DnmDecl> {
        self.dnms.iter().find(|d| d.name == name)
    }

    /// The kind of a module.
    pub fn kind_of(&self, module: &str) -> Option<&KindSpec> {
        let m = self.module(module)?;
        self.catalog.get(&m.kind).map(|e| &e.spec)
    }

    /// Modules hosted by one DNM, in declaration order.
    pub fn modules_on<'a>(&'a self, dnm: &'a str) -> impl Iterator<Item = &'a Module> + 'a {
        self.modules.iter().filter(move |m| m.dnm == dnm)
    }

    /// The DNM that decides for all: `system.authority`, else the root of the hierarchy (the
    /// first DNM without a parent that is not across the radio).
    pub fn authority(&self) -> Option<&str> {
        self.authority_dnm.as_deref().or_else(|| {
            self.dnms
                .iter()
                .find(|d| d.parent.is_none() && !d.radio)
                .map(|d| d.name.as_str())
        })
    }

    /// The task that runs after the netlist is applied: `default_task`, else the first by name.
    pub fn initial_task(&self) -> Option<&str> {
        self.default_task
            .as_deref()
            .or_else(|| self.tasks.keys().next().map(String::as_str))
    }

    /// Modules on `dnm` that read output `module.port` in any task.
    pub fn reader_names(&self, module: &str, port: &str, dnm: &str) -> BTreeSet<&str> {
        self.tasks
            .values()
            .flat_map(|t| t.links.iter())
            .filter(|l| l.from.module == module && l.from.port == port)
            .filter(|l| self.module(&l.to.module).is_some_and(|m| m.dnm == dnm))
            .map(|l| l.to.module.as_str())
            .collect()
    }

    /// How many modules on `dnm` read output `module.port` in any task.
    pub fn readers(&self, module: &str, port: &str, dnm: &str) -> usize {
        self.reader_names(module, port, dnm).len()
    }

    /// Every distinct link of any task.
    pub fn all_links(&self) -> BTreeSet<&Link> {
        self.tasks.values().flat_map(|t| t.links.iter()).collect()
    }

    /// A stable digest of the netlist text, for telling revisions apart.
    pub fn digest(&self) -> u64 {
        // FNV-1a: stable across builds and platforms, unlike `DefaultHasher`.
        self.text.bytes().fold(0xcbf2_9ce4_8422_2325_u64, |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3)
        })
    }
}

/// Lowest `rate_hz` a module may run at.
pub const MIN_RATE_HZ: f64 = 0.01;
/// Highest `rate_hz` a module may run at.
pub const MAX_RATE_HZ: f64 = 10_000.0;
/// Shortest `on_link_loss.after`: below it, a few lost pings would look like a lost link.
pub const MIN_LINK_LOSS_MS: u64 = 1_000;
/// Longest `on_link_loss.after`.
pub const MAX_LINK_LOSS_MS: u64 = 24 * 3_600_000;

/// Shortest `hung_after`: below it, scheduling jitter and idle heartbeats (every 250 ms) would
/// read as a hang. A DNM also never uses less than two periods of a periodic module.
pub const MIN_HUNG_AFTER_MS: u64 = 500;
/// Longest `hung_after`.
pub const MAX_HUNG_AFTER_MS: u64 = 3_600_000;

/// `"500ms"`, `"2s"`, `"1.5s"`, `"1m"` in milliseconds.
pub fn parse_duration_ms(text: &str) -> Option<u64> {
    let t = text.trim();
    let (number, scale) = if let Some(n) = t.strip_suffix("ms") {
        (n, 1.0)
    } else if let Some(n) = t.strip_suffix('s') {
        (n, 1_000.0)
    } else if let Some(n) = t.strip_suffix('m') {
        (n, 60_000.0)
    } else if let Some(n) = t.strip_suffix('h') {
        (n, 3_600_000.0)
    } else {
        return None;
    };
    let v: f64 = number.trim().parse().ok()?;
    (v.is_finite() && v >= 0.0 && v * scale < 1e15).then(|| (v * scale).round() as u64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_durations() {
        assert_eq!(parse_duration_ms("250ms"), Some(250));
        assert_eq!(parse_duration_ms("1.5s"), Some(1500));
        assert_eq!(parse_duration_ms("2m"), Some(120_000));
        assert_eq!(parse_duration_ms("1h"), Some(3_600_000));
        assert_eq!(parse_duration_ms("5"), None);
        assert_eq!(parse_duration_ms("-1s"), None);
    }
}

/// In which order what the ground missed of an entry is sent again.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum Backfill {
    /// The newest first: the current state reaches the ground soonest.
    #[default]
    NewestFirst,
    /// The oldest first: the record fills in the order it happened.
    OldestFirst,
}

/// One entry of the downlink plan.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DownlinkEntry {
    pub output: PortRef,
    pub rate_hz: f64,
    /// 1 (sent again first) to [`crate::downlink::LOWEST_PRIORITY`].
    pub priority: u8,
    pub backfill: Backfill,
}

impl DownlinkEntry {
    /// The least time between two samples the ground keeps, ns.
    pub fn period_ns(&self) -> u64 {
        (1e9 / self.rate_hz) as u64
    }
}
