//! Reading a netlist file into a validated [`Netlist`].

use std::collections::{BTreeMap, BTreeSet};
use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use petgraph::stable_graph::{NodeIndex, StableDiGraph};
use serde::{Deserialize, Serialize};
use toml::Spanned;

use crate::error::{NetlistError, Reporter, suggest};
use crate::spec::{Catalog, KindSource, KindSpec, ParamValue};

/// The DNM that hosts modules which name none, when the netlist declares no DNM at all.
pub const DEFAULT_DNM: &str = "local";

/// Longest name allowed for systems, DNMs, modules, ports and tasks. Names become
/// shared-memory service names and network keys, so they stay short and plain.
pub const MAX_NAME_LEN: usize = 48;

// ---------------------------------------------------------------------------------------------
// The file as written.

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawNetlist {
    system: Spanned<RawSystem>,
    #[serde(default)]
    dnm: Vec<Spanned<RawDnm>>,
    #[serde(default)]
    kind: BTreeMap<Spanned<String>, Spanned<RawKind>>,
    #[serde(default)]
    module: Vec<Spanned<RawModule>>,
    #[serde(default)]
    task: BTreeMap<Spanned<String>, Spanned<RawTask>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSystem {
    name: Spanned<String>,
    default_task: Option<Spanned<String>>,
    authority: Option<Spanned<String>>,
    on_link_loss: Option<Spanned<RawLinkLoss>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawLinkLoss {
    after: Spanned<String>,
    task: Spanned<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDnm {
    name: Spanned<String>,
    parent: Option<Spanned<String>>,
    link: Option<Spanned<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawKind {
    exec: Spanned<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawModule {
    name: Spanned<String>,
    kind: Spanned<String>,
    dnm: Option<Spanned<String>>,
    #[serde(default)]
    pinned: Option<Spanned<bool>>,
    rate_hz: Option<Spanned<f64>>,
    restart: Option<Spanned<RestartMode>>,
    max_restarts: Option<u32>,
    hung_after: Option<Spanned<String>>,
    #[serde(default)]
    params: BTreeMap<Spanned<String>, Spanned<toml::Value>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawTask {
    #[serde(default)]
    description: String,
    #[serde(default)]
    links: Vec<Spanned<String>>,
}

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
pub struct Dnm {
    pub name: String,
    pub parent: Option<String>,
    /// `link = "radio"`: reached over the radio link (the ground's DNMs). It follows the
    /// authority's decisions when it hears them and never holds up a transaction; the others
    /// are on the rover's own network and take every decision together.
    #[serde(default)]
    pub radio: bool,
}

/// What the rover does when no ground station has been heard for a while:
/// `on_link_loss = { after = "5s", task = "safe" }`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct LinkLoss {
    pub after_ms: u64,
    pub task: String,
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
    pub dnms: Vec<Dnm>,
    pub modules: Vec<Module>,
    pub tasks: BTreeMap<String, Task>,
    /// Every kind the netlist can use: the catalog it was validated against plus its own.
    pub catalog: Catalog,
    graph: ModuleGraph,
    nodes: BTreeMap<String, NodeIndex>,
}

impl Netlist {
    /// Reads and validates a netlist file.
    pub fn load(
        path: impl AsRef<Path>,
        catalog: &Catalog,
        describe: &mut dyn FnMut(&Path) -> Result<KindSpec, String>,
    ) -> Result<Self, NetlistError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| NetlistError {
            file: path.to_path_buf(),
            diagnostics: vec![crate::Diagnostic {
                field: "file".into(),
                message: format!("cannot read: {e}"),
                help: Some("check the path".into()),
                location: None,
            }],
        })?;
        Self::parse(path, &text, catalog, describe)
    }

    /// Validates netlist text. `file` names it in errors; relative `exec` paths of declared
    /// kinds resolve against its folder. `describe` asks an executable for its kind.
    pub fn parse(
        file: &Path,
        text: &str,
        catalog: &Catalog,
        describe: &mut dyn FnMut(&Path) -> Result<KindSpec, String>,
    ) -> Result<Self, NetlistError> {
        let mut r = Reporter::new(file, text);
        let raw: RawNetlist = match toml::from_str(text) {
            Ok(raw) => raw,
            Err(e) => {
                let message = e.message().to_string();
                let help = if message.contains("missing field `system`") {
                    Some("add a `[system]` table with `name = \"...\"`".to_string())
                } else {
                    Some("fix the TOML syntax or field name at this position".to_string())
                };
                r.error(e.span(), "toml", message, help);
                r.finish()?;
                unreachable!("finish reports the error above")
            }
        };
        let netlist = validate(file, text, raw, catalog, describe, &mut r);
        r.finish()?;
        Ok(netlist)
    }

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

    pub fn dnm(&self, name: &str) -> Option<&Dnm> {
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

fn valid_name(name: &str) -> Result<(), String> {
    if name.is_empty() {
        return Err("is empty".into());
    }
    if name.len() > MAX_NAME_LEN {
        return Err(format!("is longer than {MAX_NAME_LEN} characters"));
    }
    let mut chars = name.chars();
    let first_ok = chars.next().is_some_and(|c| c.is_ascii_alphabetic());
    if !first_ok
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        return Err("must start with a letter and use only letters, digits, `_` and `-`".into());
    }
    Ok(())
}

fn check_name(r: &mut Reporter<'_>, name: &Spanned<String>, field: &str) -> bool {
    match valid_name(name.get_ref()) {
        Ok(()) => true,
        Err(why) => {
            r.error(
                Some(name.span()),
                field,
                format!("name `{}` {why}", name.get_ref()),
                Some("rename it, e.g. `wheel_left`".into()),
            );
            false
        }
    }
}

fn span_of<T>(s: &Spanned<T>) -> Option<Range<usize>> {
    Some(s.span())
}

/// Parses `a.out -> b.in`.
fn parse_link(text: &str) -> Result<Link, String> {
    let (from, to) = text
        .split_once("->")
        .ok_or_else(|| "a link is written `module.output -> module.input`".to_string())?;
    let port = |s: &str, side: &str| -> Result<PortRef, String> {
        let s = s.trim();
        let (module, port) = s
            .split_once('.')
            .ok_or_else(|| format!("{side} `{s}` must be `module.port`"))?;
        if module.is_empty() || port.is_empty() || port.contains('.') {
            return Err(format!("{side} `{s}` must be `module.port`"));
        }
        Ok(PortRef {
            module: module.to_string(),
            port: port.to_string(),
        })
    };
    Ok(Link {
        from: port(from, "output")?,
        to: port(to, "input")?,
    })
}

fn validate(
    file: &Path,
    text: &str,
    raw: RawNetlist,
    catalog: &Catalog,
    describe: &mut dyn FnMut(&Path) -> Result<KindSpec, String>,
    r: &mut Reporter<'_>,
) -> Netlist {
    let system = raw.system.into_inner();
    check_name(r, &system.name, "system.name");

    // DNMs and their hierarchy.
    let mut dnms: Vec<Dnm> = Vec::new();
    for (i, d) in raw.dnm.iter().enumerate() {
        let d = d.get_ref();
        let field = format!("dnm[{i}].name");
        if !check_name(r, &d.name, &field) {
            continue;
        }
        if dnms.iter().any(|x| &x.name == d.name.get_ref()) {
            r.error(
                span_of(&d.name),
                field,
                format!("DNM `{}` is declared twice", d.name.get_ref()),
                Some("give every DNM a unique name".into()),
            );
            continue;
        }
        let radio = match &d.link {
            None => false,
            Some(l) if l.get_ref() == "radio" => true,
            Some(l) if l.get_ref() == "local" => false,
            Some(l) => {
                r.error(
                    span_of(l),
                    format!("dnm[{i}].link"),
                    format!("link `{}` is not known", l.get_ref()),
                    Some(
                        "use `link = \"radio\"` for a DNM across the radio, or leave it out".into(),
                    ),
                );
                false
            }
        };
        dnms.push(Dnm {
            name: d.name.get_ref().clone(),
            parent: d.parent.as_ref().map(|p| p.get_ref().clone()),
            radio,
        });
    }
    let dnm_names: Vec<String> = dnms.iter().map(|d| d.name.clone()).collect();
    for (i, d) in raw.dnm.iter().enumerate() {
        let Some(parent) = &d.get_ref().parent else {
            continue;
        };
        if !dnm_names.contains(parent.get_ref()) {
            r.error(
                span_of(parent),
                format!("dnm[{i}].parent"),
                format!("parent DNM `{}` is not declared", parent.get_ref()),
                Some(suggest(
                    parent.get_ref(),
                    dnm_names.iter().map(String::as_str),
                )),
            );
        }
    }
    for (i, d) in dnms.iter().enumerate() {
        // Walk up; a walk longer than the number of DNMs is a cycle.
        let mut cur = d.parent.clone();
        let mut steps = 0;
        while let Some(p) = cur {
            steps += 1;
            if p == d.name || steps > dnms.len() {
                r.error(
                    raw.dnm
                        .get(i)
                        .and_then(|x| x.get_ref().parent.as_ref().map(|p| p.span())),
                    format!("dnm[{i}].parent"),
                    format!("DNM `{}` is its own ancestor", d.name),
                    Some("DNMs form a tree: remove one `parent` of the cycle".into()),
                );
                break;
            }
            cur = dnms
                .iter()
                .find(|x| x.name == p)
                .and_then(|x| x.parent.clone());
        }
    }
    if dnms.is_empty() {
        dnms.push(Dnm {
            name: DEFAULT_DNM.to_string(),
            parent: None,
            radio: false,
        });
    }
    let default_dnm = dnms[0].name.clone();

    // Kinds: the given catalog plus executables declared in the file.
    let mut kinds = catalog.clone();
    let base = file.parent().unwrap_or(Path::new("."));
    for (name, k) in &raw.kind {
        let field = format!("kind.{}", name.get_ref());
        if !check_name(r, name, &field) {
            continue;
        }
        let exec = k.get_ref().exec.get_ref();
        let path = base.join(exec);
        match describe(&path) {
            Ok(spec) if &spec.name == name.get_ref() => kinds.insert(
                spec,
                KindSource::Exec {
                    path: path.to_string_lossy().into_owned(),
                },
            ),
            Ok(spec) => r.error(
                span_of(&k.get_ref().exec),
                format!("{field}.exec"),
                format!(
                    "`{exec}` describes kind `{}`, not `{}`",
                    spec.name,
                    name.get_ref()
                ),
                Some(format!("rename the table to `[kind.{}]`", spec.name)),
            ),
            Err(why) => r.error(
                span_of(&k.get_ref().exec),
                format!("{field}.exec"),
                format!("cannot describe `{}`: {why}", path.display()),
                Some(
                    "build the module executable and check the path (relative to this file)".into(),
                ),
            ),
        }
    }

    // Modules.
    let mut modules: Vec<Module> = Vec::new();
    for (i, m) in raw.module.iter().enumerate() {
        let m = m.get_ref();
        let field = format!("module[{i}]");
        if !check_name(r, &m.name, &format!("{field}.name")) {
            continue;
        }
        let name = m.name.get_ref().clone();
        if modules.iter().any(|x| x.name == name) {
            r.error(
                span_of(&m.name),
                format!("{field}.name"),
                format!("module `{name}` is declared twice"),
                Some("give every module a unique name".into()),
            );
            continue;
        }
        let Some(entry) = kinds.get(m.kind.get_ref()) else {
            r.error(
                span_of(&m.kind),
                format!("{field}.kind"),
                format!("module `{name}` has unknown kind `{}`", m.kind.get_ref()),
                Some(format!(
                    "{}; or declare it with `[kind.{}] exec = \"path/to/executable\"`",
                    suggest(m.kind.get_ref(), kinds.names()),
                    m.kind.get_ref()
                )),
            );
            continue;
        };
        let spec = &entry.spec;
        if let Some(dnm) = &m.dnm
            && !dnm_names.contains(dnm.get_ref())
        {
            r.error(
                span_of(dnm),
                format!("{field}.dnm"),
                format!(
                    "module `{name}` is pinned to DNM `{}`, which does not exist",
                    dnm.get_ref()
                ),
                Some(format!(
                    "declare it with `[[dnm]] name = \"{}\"` or pin to an existing DNM: {}",
                    dnm.get_ref(),
                    suggest(dnm.get_ref(), dnm_names.iter().map(String::as_str))
                )),
            );
        }
        if let Some(rate) = &m.rate_hz
            && !(rate.get_ref().is_finite() && (MIN_RATE_HZ..=MAX_RATE_HZ).contains(rate.get_ref()))
        {
            r.error(
                span_of(rate),
                format!("{field}.rate_hz"),
                format!(
                    "rate {} Hz is outside {MIN_RATE_HZ}..={MAX_RATE_HZ} Hz",
                    rate.get_ref()
                ),
                Some(format!(
                    "use a rate from {MIN_RATE_HZ} to {MAX_RATE_HZ}, e.g. `rate_hz = 20.0`"
                )),
            );
        }
        let hung_after_ms = match &m.hung_after {
            None => None,
            Some(h) => match parse_duration_ms(h.get_ref()) {
                Some(ms) if (MIN_HUNG_AFTER_MS..=MAX_HUNG_AFTER_MS).contains(&ms) => Some(ms),
                Some(ms) => {
                    r.error(
                        span_of(h),
                        format!("{field}.hung_after"),
                        format!(
                            "{ms} ms is outside {MIN_HUNG_AFTER_MS} ms..={} s",
                            MAX_HUNG_AFTER_MS / 1000
                        ),
                        Some("use e.g. `hung_after = \"2s\"`".into()),
                    );
                    None
                }
                None => {
                    r.error(
                        span_of(h),
                        format!("{field}.hung_after"),
                        format!("`{}` is not a duration", h.get_ref()),
                        Some("write a number and a unit: `500ms`, `2s`, `1.5s`, `1m`, `1h`".into()),
                    );
                    None
                }
            },
        };
        let mut params = BTreeMap::new();
        for (key, value) in &m.params {
            let pfield = format!("{field}.params.{}", key.get_ref());
            let Some(pspec) = spec.param(key.get_ref()) else {
                r.error(
                    span_of(key),
                    pfield,
                    format!("kind `{}` has no parameter `{}`", spec.name, key.get_ref()),
                    Some(suggest(
                        key.get_ref(),
                        spec.params.iter().map(|p| p.name.as_str()),
                    )),
                );
                continue;
            };
            let given = toml_to_param(value.get_ref());
            match given.and_then(|v| v.coerce(pspec.kind)) {
                Some(v) => {
                    params.insert(pspec.name.clone(), v);
                }
                None => r.error(
                    span_of(value),
                    pfield,
                    format!("parameter `{}` must be a {}", pspec.name, pspec.kind),
                    Some(match &pspec.default {
                        Some(d) => format!("for example `{} = {d}`", pspec.name),
                        None => format!("give a {} value", pspec.kind),
                    }),
                ),
            }
        }
        for pspec in &spec.params {
            if params.contains_key(&pspec.name) {
                continue;
            }
            match &pspec.default {
                Some(d) => {
                    params.insert(pspec.name.clone(), d.clone());
                }
                None => r.error(
                    span_of(&m.name),
                    format!("{field}.params.{}", pspec.name),
                    format!(
                        "module `{name}` needs parameter `{}` ({})",
                        pspec.name, pspec.kind
                    ),
                    Some(format!("add it under `[module.params]`: {}", pspec.doc)),
                ),
            }
        }
        let hard_pin = m.pinned.as_ref().is_some_and(|p| *p.get_ref());
        if hard_pin && m.dnm.is_none() {
            r.error(
                m.pinned.as_ref().and_then(span_of),
                format!("{field}.pinned"),
                format!("module `{name}` is pinned but names no DNM"),
                Some("add `dnm = \"...\"`, the computer whose hardware it drives".into()),
            );
        }
        let pinned = m.dnm.as_ref().map(|d| d.get_ref().clone());
        modules.push(Module {
            pinned: hard_pin,
            dnm: pinned.clone().unwrap_or_else(|| default_dnm.clone()),
            pinned_dnm: pinned,
            name,
            kind: spec.name.clone(),
            rate_hz: m.rate_hz.as_ref().map(|r| *r.get_ref()),
            restart: RestartPolicy {
                mode: m.restart.as_ref().map(|r| *r.get_ref()).unwrap_or_default(),
                max_restarts: m
                    .max_restarts
                    .unwrap_or(RestartPolicy::default().max_restarts),
            },
            hung_after_ms,
            params,
        });
    }

    // Tasks.
    let mut tasks = BTreeMap::new();
    // Readers of each output on each DNM, across tasks: a port's shared memory holds a slot for
    // each of them.
    let mut readers: BTreeMap<(PortRef, String), BTreeSet<String>> = BTreeMap::new();
    for (tname, t) in &raw.task {
        let tfield = format!("task.{}", tname.get_ref());
        check_name(r, tname, &tfield);
        let mut links: Vec<Link> = Vec::new();
        for (j, l) in t.get_ref().links.iter().enumerate() {
            let field = format!("{tfield}.links[{j}]");
            let link = match parse_link(l.get_ref()) {
                Ok(link) => link,
                Err(why) => {
                    r.error(
                        span_of(l),
                        field,
                        format!("cannot read link `{}`: {why}", l.get_ref()),
                        Some("write it as `\"source.output -> sink.input\"`".into()),
                    );
                    continue;
                }
            };
            if check_link(r, &link, l, &field, &modules, &kinds) {
                if let Some(prev) = links.iter().find(|x| x.to == link.to) {
                    let msg = if prev.from == link.from {
                        format!("link `{link}` is listed twice")
                    } else {
                        format!(
                            "input `{}` is fed by both `{}` and `{}` in task `{}`",
                            link.to,
                            prev.from,
                            link.from,
                            tname.get_ref()
                        )
                    };
                    r.error(
                        span_of(l),
                        field,
                        msg,
                        Some("an input reads from one output per task: keep one link, or put the other in its own task".into()),
                    );
                    continue;
                }
                check_readers(r, &link, l, &field, &modules, &kinds, &mut readers);
                links.push(link);
            }
        }
        tasks.insert(
            tname.get_ref().clone(),
            Task {
                name: tname.get_ref().clone(),
                description: t.get_ref().description.clone(),
                links,
            },
        );
    }
    if let Some(d) = &system.default_task
        && !tasks.contains_key(d.get_ref())
    {
        r.error(
            span_of(d),
            "system.default_task",
            format!("default task `{}` is not defined", d.get_ref()),
            Some(suggest(d.get_ref(), tasks.keys().map(String::as_str))),
        );
    }

    if let Some(a) = &system.authority {
        match dnms.iter().find(|d| &d.name == a.get_ref()) {
            None => r.error(
                span_of(a),
                "system.authority",
                format!("authority DNM `{}` is not declared", a.get_ref()),
                Some(suggest(a.get_ref(), dnms.iter().map(|d| d.name.as_str()))),
            ),
            Some(d) if d.radio => r.error(
                span_of(a),
                "system.authority",
                format!("authority DNM `{}` is across the radio link", a.get_ref()),
                Some("name a DNM of the rover: it must decide while the link is down".into()),
            ),
            Some(_) => {}
        }
    }
    let on_link_loss = system.on_link_loss.as_ref().and_then(|l| {
        let l = l.get_ref();
        let after_ms = match parse_duration_ms(l.after.get_ref()) {
            Some(ms) if (MIN_LINK_LOSS_MS..=MAX_LINK_LOSS_MS).contains(&ms) => Some(ms),
            _ => {
                r.error(
                    span_of(&l.after),
                    "system.on_link_loss.after",
                    format!(
                        "`{}` is not a duration from {} s to {} h",
                        l.after.get_ref(),
                        MIN_LINK_LOSS_MS / 1000,
                        MAX_LINK_LOSS_MS / 3_600_000
                    ),
                    Some("use e.g. `after = \"5s\"`".into()),
                );
                None
            }
        };
        if !tasks.contains_key(l.task.get_ref()) {
            r.error(
                span_of(&l.task),
                "system.on_link_loss.task",
                format!("task `{}` is not defined", l.task.get_ref()),
                Some(suggest(l.task.get_ref(), tasks.keys().map(String::as_str))),
            );
            return None;
        }
        Some(LinkLoss {
            after_ms: after_ms?,
            task: l.task.get_ref().clone(),
        })
    });

    // The module graph.
    let mut graph = ModuleGraph::default();
    let mut nodes = BTreeMap::new();
    for m in &modules {
        nodes.insert(
            m.name.clone(),
            graph.add_node(ModuleNode {
                module: m.name.clone(),
            }),
        );
    }
    if !r.has_errors() {
        let mut edges: BTreeMap<&Link, BTreeSet<String>> = BTreeMap::new();
        for t in tasks.values() {
            for l in &t.links {
                edges.entry(l).or_default().insert(t.name.clone());
            }
        }
        for (l, in_tasks) in edges {
            if let (Some(&a), Some(&b)) = (nodes.get(&l.from.module), nodes.get(&l.to.module)) {
                graph.add_edge(
                    a,
                    b,
                    Connection {
                        from_port: l.from.port.clone(),
                        to_port: l.to.port.clone(),
                        tasks: in_tasks,
                    },
                );
            }
        }
    }

    Netlist {
        file: file.to_path_buf(),
        text: text.to_string(),
        system: system.name.into_inner(),
        default_task: system.default_task.map(Spanned::into_inner),
        authority_dnm: system.authority.map(Spanned::into_inner),
        on_link_loss,
        dnms,
        modules,
        tasks,
        catalog: kinds,
        graph,
        nodes,
    }
}

/// Counts `link`'s reader against its output's limit on the reader's DNM; refuses the link
/// that first goes over it.
fn check_readers(
    r: &mut Reporter<'_>,
    link: &Link,
    at: &Spanned<String>,
    field: &str,
    modules: &[Module],
    kinds: &Catalog,
    readers: &mut BTreeMap<(PortRef, String), BTreeSet<String>>,
) {
    let (Some(to), Some(from)) = (
        modules.iter().find(|m| m.name == link.to.module),
        modules.iter().find(|m| m.name == link.from.module),
    ) else {
        return;
    };
    let Some(payload) = kinds
        .get(&from.kind)
        .and_then(|k| k.spec.output(&link.from.port))
        .map(|p| p.message.payload)
    else {
        return;
    };
    let set = readers
        .entry((link.from.clone(), to.dnm.clone()))
        .or_default();
    if !set.insert(to.name.clone()) {
        return;
    }
    let max = payload.max_readers();
    if set.len() == max + 1 {
        let size = if payload.is_large() {
            format!(
                " (samples of up to {} bytes: each reader reserves {} of them in shared memory)",
                payload.max_bytes(),
                crate::spec::SAMPLES_PER_SUBSCRIBER
            )
        } else {
            String::new()
        };
        r.error(
            span_of(at),
            field.to_string(),
            format!(
                "output `{}` would feed {} modules on DNM `{}`; it can feed at most {max}{size}",
                link.from,
                set.len(),
                to.dnm
            ),
            Some(
                "feed the others through a relay module (one reader that republishes), or \
                 place some readers on another DNM"
                    .into(),
            ),
        );
    }
}

fn check_link(
    r: &mut Reporter<'_>,
    link: &Link,
    at: &Spanned<String>,
    field: &str,
    modules: &[Module],
    kinds: &Catalog,
) -> bool {
    let names = || modules.iter().map(|m| m.name.as_str());
    let mut ok = true;
    let mut types = [None, None];
    for (side, port) in [(0, &link.from), (1, &link.to)] {
        let Some(m) = modules.iter().find(|m| m.name == port.module) else {
            r.error(
                span_of(at),
                field,
                format!("unknown module `{}` in link `{link}`", port.module),
                Some(suggest(&port.module, names())),
            );
            ok = false;
            continue;
        };
        let Some(kind) = kinds.get(&m.kind).map(|e| &e.spec) else {
            ok = false;
            continue;
        };
        let (found, list, what) = if side == 0 {
            (kind.output(&port.port), &kind.outputs, "output")
        } else {
            (kind.input(&port.port), &kind.inputs, "input")
        };
        match found {
            Some(p) => types[side] = Some(p.message.clone()),
            None => {
                let other = if side == 0 {
                    kind.input(&port.port)
                        .map(|_| "it is an input: links go output -> input")
                } else {
                    kind.output(&port.port)
                        .map(|_| "it is an output: links go output -> input")
                };
                r.error(
                    span_of(at),
                    field,
                    format!(
                        "module `{}` (kind `{}`) has no {what} port `{}`",
                        port.module, kind.name, port.port
                    ),
                    Some(other.map(str::to_string).unwrap_or_else(|| {
                        suggest(&port.port, list.iter().map(|p| p.name.as_str()))
                    })),
                );
                ok = false;
            }
        }
    }
    if let [Some(out), Some(inp)] = &types
        && !out.compatible_with(inp)
    {
        r.error(
            span_of(at),
            field,
            format!(
                "type mismatch in `{link}`: `{}` sends {out} but `{}` reads {inp}",
                link.from, link.to
            ),
            Some(
                "link an output of the input's type, or put a converting module between them"
                    .into(),
            ),
        );
        ok = false;
    }
    ok
}

fn toml_to_param(v: &toml::Value) -> Option<ParamValue> {
    Some(match v {
        toml::Value::String(s) => ParamValue::String(s.clone()),
        toml::Value::Integer(i) => ParamValue::Int(*i),
        toml::Value::Float(f) => ParamValue::Float(*f),
        toml::Value::Boolean(b) => ParamValue::Bool(*b),
        _ => return None,
    })
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

    #[test]
    fn parses_links() {
        let l = parse_link(" a.out ->b.in ").unwrap();
        assert_eq!(l.to_string(), "a.out -> b.in");
        assert!(parse_link("a.out b.in").is_err());
        assert!(parse_link("a -> b.in").is_err());
        assert!(parse_link("a.x.y -> b.in").is_err());
    }

    #[test]
    fn names_are_plain() {
        assert!(valid_name("wheel_left-2").is_ok());
        assert!(valid_name("2wheel").is_err());
        assert!(valid_name("a/b").is_err());
        assert!(valid_name("").is_err());
    }
}
