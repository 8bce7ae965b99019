//! Checking a netlist as written against the module kinds available, section by section, into
//! a [`Netlist`]. Every problem is reported, in the order of the sections: system name, DNMs,
//! kinds, modules, tasks and their links, default task, authority, link loss.

use std::collections::{BTreeMap, BTreeSet};
use std::ops::Range;
use std::path::Path;

use petgraph::stable_graph::NodeIndex;
use serde::Deserialize;
use toml::Spanned;

use crate::error::{NetlistError, Reporter, suggest};
use crate::model::{
    Connection, DEFAULT_DNM, DnmDecl, Link, LinkLoss, MAX_HUNG_AFTER_MS, MAX_LINK_LOSS_MS,
    MAX_NAME_LEN, MAX_RATE_HZ, MIN_HUNG_AFTER_MS, MIN_LINK_LOSS_MS, MIN_RATE_HZ, Module,
    ModuleGraph, ModuleNode, Netlist, PortRef, RestartMode, RestartPolicy, Task, parse_duration_ms,
};

impl Netlist {
    /// Reads and validates a netlist file.
    pub fn load(
        path: impl AsRef<Path>,
        catalog: &Catalog,
        describe: &mut crate::error::Describe<'_>,
    ) -> Result<Self, NetlistError> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path)
            .map_err(|e| NetlistError::unreadable(path, &e, "netlist"))?;
        Self::parse(path, &text, catalog, describe)
    }

    /// Validates netlist text. `file` names it in errors; relative `exec` paths of declared
    /// kinds resolve against its folder. `describe` asks an executable for its kind.
    pub fn parse(
        file: &Path,
        text: &str,
        catalog: &Catalog,
        describe: &mut crate::error::Describe<'_>,
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
}
use crate::spec::{Catalog, KindSource, KindSpec, ParamValue};

// ---------------------------------------------------------------------------------------------
// The file as written.

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct RawNetlist {
    system: Spanned<RawSystem>,
    #[serde(default)]
    dnm: Vec<Spanned<RawDnm>>,
    #[serde(default)]
    kind: BTreeMap<Spanned<String>, Spanned<RawKind>>,
    #[serde(default)]
    module: Vec<Spanned<RawModule>>,
    #[serde(default)]
    task: BTreeMap<Spanned<String>, Spanned<RawTask>>,
    #[serde(default)]
    downlink: Vec<Spanned<crate::downlink::RawDownlink>>,
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
    sequences: Option<Spanned<String>>,
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
// Validation.

/// Validates `raw`, read from `text` in `file`, reporting every problem to `r`. The netlist
/// returned is complete only when `r` has no errors.
pub(crate) fn validate(
    file: &Path,
    text: &str,
    raw: RawNetlist,
    catalog: &Catalog,
    describe: &mut crate::error::Describe<'_>,
    r: &mut Reporter<'_>,
) -> Netlist {
    let system = raw.system.into_inner();
    check_name(r, &system.name, "system.name");
    let mut v = Validation {
        r,
        dnm_names: Vec::new(),
        dnms: Vec::new(),
        kinds: catalog.clone(),
        modules: Vec::new(),
        tasks: BTreeMap::new(),
    };
    v.dnms(&raw.dnm);
    v.kinds(file, &raw.kind, describe);
    v.modules(&raw.module);
    v.tasks(&raw.task);
    v.default_task(&system);
    v.authority(&system);
    let on_link_loss = v.on_link_loss(&system);
    let downlink = crate::downlink::validate(v.r, &raw.downlink, &v.modules, &v.kinds);
    let (graph, nodes) = v.module_graph();

    Netlist {
        file: file.to_path_buf(),
        text: text.to_string(),
        system: system.name.into_inner(),
        default_task: system.default_task.map(Spanned::into_inner),
        authority_dnm: system.authority.map(Spanned::into_inner),
        on_link_loss,
        dnms: v.dnms,
        modules: v.modules,
        tasks: v.tasks,
        downlink,
        catalog: v.kinds,
        graph,
        nodes,
    }
}

/// What has been validated so far, and where problems go. Each section reads the ones before
/// it: modules need the DNMs and kinds, tasks need the modules.
#[derive(Debug)]
struct Validation<'v, 'r> {
    r: &'v mut Reporter<'r>,
    /// Names of the DNMs the file declares, in order (without the default DNM).
    dnm_names: Vec<String>,
    /// The declared DNMs, or the default one when the file declares none.
    dnms: Vec<DnmDecl>,
    /// Kinds: the given catalog plus executables declared in the file.
    kinds: Catalog,
    modules: Vec<Module>,
    tasks: BTreeMap<String, Task>,
}

impl Validation<'_, '_> {
    /// DNMs and their hierarchy.
    fn dnms(&mut self, raw: &[Spanned<RawDnm>]) {
        for (i, d) in raw.iter().enumerate() {
            self.declare_dnm(i, d.get_ref());
        }
        self.dnm_names = self.dnms.iter().map(|d| d.name.clone()).collect();
        self.dnm_parents(raw);
        self.dnm_cycles(raw);
        if self.dnms.is_empty() {
            self.dnms.push(DnmDecl {
                name: DEFAULT_DNM.to_string(),
                parent: None,
                radio: false,
            });
        }
    }

    /// One `[[dnm]]`: a valid, unique name and a known link.
    fn declare_dnm(&mut self, i: usize, d: &RawDnm) {
        let field = format!("dnm[{i}].name");
        if !check_name(self.r, &d.name, &field) {
            return;
        }
        if self.dnms.iter().any(|x| &x.name == d.name.get_ref()) {
            self.r.error(
                span_of(&d.name),
                field,
                format!("DNM `{}` is declared twice", d.name.get_ref()),
                Some("give every DNM a unique name".into()),
            );
            return;
        }
        let radio = match &d.link {
            None => false,
            Some(l) => match is_radio(l.get_ref()) {
                Some(radio) => radio,
                None => {
                    self.r.error(
                        span_of(l),
                        format!("dnm[{i}].link"),
                        format!("link `{}` is not known", l.get_ref()),
                        Some(
                            "use `link = \"radio\"` for a DNM across the radio, or leave it out"
                                .into(),
                        ),
                    );
                    false
                }
            },
        };
        self.dnms.push(DnmDecl {
            name: d.name.get_ref().clone(),
            parent: d.parent.as_ref().map(|p| p.get_ref().clone()),
            radio,
        });
    }

    /// Every `parent` is a declared DNM.
    fn dnm_parents(&mut self, raw: &[Spanned<RawDnm>]) {
        for (i, d) in raw.iter().enumerate() {
            let Some(parent) = &d.get_ref().parent else {
                continue;
            };
            if !self.dnm_names.contains(parent.get_ref()) {
                self.r.error(
                    span_of(parent),
                    format!("dnm[{i}].parent"),
                    format!("parent DNM `{}` is not declared", parent.get_ref()),
                    Some(suggest(
                        parent.get_ref(),
                        self.dnm_names.iter().map(String::as_str),
                    )),
                );
            }
        }
    }

    /// No DNM is its own ancestor.
    fn dnm_cycles(&mut self, raw: &[Spanned<RawDnm>]) {
        for (i, d) in self.dnms.iter().enumerate() {
            if in_cycle(&self.dnms, d) {
                self.r.error(
                    raw.get(i)
                        .and_then(|x| x.get_ref().parent.as_ref().map(|p| p.span())),
                    format!("dnm[{i}].parent"),
                    format!("DNM `{}` is its own ancestor", d.name),
                    Some("DNMs form a tree: remove one `parent` of the cycle".into()),
                );
            }
        }
    }

    /// Kinds: the given catalog plus executables declared in the file.
    fn kinds(
        &mut self,
        file: &Path,
        raw: &BTreeMap<Spanned<String>, Spanned<RawKind>>,
        describe: &mut crate::error::Describe<'_>,
    ) {
        // A netlist named without a folder lies in the current one: its executables are
        // `./name`, never looked up on the PATH.
        let base = file
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        for (name, k) in raw {
            let field = format!("kind.{}", name.get_ref());
            if !check_name(self.r, name, &field) {
                continue;
            }
            let exec = k.get_ref().exec.get_ref();
            let path = base.join(exec);
            match describe(&path) {
                Ok(spec) if &spec.name == name.get_ref() => self.kinds.insert(
                    spec,
                    KindSource::Exec {
                        path: path.to_string_lossy().into_owned(),
                    },
                ),
                Ok(spec) => self.r.error(
                    span_of(&k.get_ref().exec),
                    format!("{field}.exec"),
                    format!(
                        "`{exec}` describes kind `{}`, not `{}`",
                        spec.name,
                        name.get_ref()
                    ),
                    Some(format!("rename the table to `[kind.{}]`", spec.name)),
                ),
                Err(why) => self.r.error(
                    span_of(&k.get_ref().exec),
                    format!("{field}.exec"),
                    format!("cannot describe `{}`: {why}", path.display()),
                    Some(format!(
                        "`{} describe` must print the kind: build the module executable (a \
                         Python one: its `#!` Python must have the `dnm` package) and check \
                         the path (relative to this file)",
                        path.display()
                    )),
                ),
            }
        }
    }

    /// Modules, in file order.
    fn modules(&mut self, raw: &[Spanned<RawModule>]) {
        for (i, m) in raw.iter().enumerate() {
            if let Some(module) = self.module(&format!("module[{i}]"), m.get_ref()) {
                self.modules.push(module);
            }
        }
    }

    /// One `[[module]]` at `field`: a valid, unique name and a known kind, then its DNM,
    /// settings and parameters. `None` when it cannot be checked further.
    fn module(&mut self, field: &str, m: &RawModule) -> Option<Module> {
        if !check_name(self.r, &m.name, &format!("{field}.name")) {
            return None;
        }
        let name = m.name.get_ref().clone();
        if self.modules.iter().any(|x| x.name == name) {
            self.r.error(
                span_of(&m.name),
                format!("{field}.name"),
                format!("module `{name}` is declared twice"),
                Some("give every module a unique name".into()),
            );
            return None;
        }
        let Some(entry) = self.kinds.get(m.kind.get_ref()) else {
            self.r.error(
                span_of(&m.kind),
                format!("{field}.kind"),
                format!("module `{name}` has unknown kind `{}`", m.kind.get_ref()),
                Some(format!(
                    "{}; or declare it with `[kind.{}] exec = \"path/to/executable\"`",
                    suggest(m.kind.get_ref(), self.kinds.names()),
                    m.kind.get_ref()
                )),
            );
            return None;
        };
        let spec = &entry.spec;
        check_module_dnm(self.r, field, &name, m, &self.dnm_names);
        check_rate(self.r, field, m);
        let hung_after_ms = hung_after(self.r, field, m);
        let mut params = given_params(self.r, field, m, spec);
        default_params(self.r, field, &name, m, spec, &mut params);
        let hard_pin = m.pinned.as_ref().is_some_and(|p| *p.get_ref());
        if hard_pin && m.dnm.is_none() {
            self.r.error(
                m.pinned.as_ref().and_then(span_of),
                format!("{field}.pinned"),
                format!("module `{name}` is pinned but names no DNM"),
                Some("add `dnm = \"...\"`, the computer whose hardware it drives".into()),
            );
        }
        let pinned = m.dnm.as_ref().map(|d| d.get_ref().clone());
        Some(Module {
            pinned: hard_pin,
            // Unpinned modules run on the first DNM.
            dnm: pinned.clone().unwrap_or_else(|| self.dnms[0].name.clone()),
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
        })
    }

    /// Tasks and their links.
    fn tasks(&mut self, raw: &BTreeMap<Spanned<String>, Spanned<RawTask>>) {
        // Readers of each output on each DNM, across tasks: a port's shared memory holds a slot
        // for each of them.
        let mut readers: BTreeMap<(PortRef, String), BTreeSet<String>> = BTreeMap::new();
        for (tname, t) in raw {
            let tfield = format!("task.{}", tname.get_ref());
            check_name(self.r, tname, &tfield);
            let mut links: Vec<Link> = Vec::new();
            for (j, l) in t.get_ref().links.iter().enumerate() {
                let field = format!("{tfield}.links[{j}]");
                if let Some(link) = self.task_link(tname.get_ref(), l, &field, &links, &mut readers)
                {
                    links.push(link);
                }
            }
            self.tasks.insert(
                tname.get_ref().clone(),
                Task {
                    name: tname.get_ref().clone(),
                    description: t.get_ref().description.clone(),
                    links,
                },
            );
        }
    }

    /// One link `l` of `task` at `field`, given the task's valid links before it: readable,
    /// between existing ports of one type, the only link into its input, and within the reader
    /// limit of its output. `None` when it is not valid.
    fn task_link(
        &mut self,
        task: &str,
        l: &Spanned<String>,
        field: &str,
        links: &[Link],
        readers: &mut BTreeMap<(PortRef, String), BTreeSet<String>>,
    ) -> Option<Link> {
        let link = match parse_link(l.get_ref()) {
            Ok(link) => link,
            Err(why) => {
                self.r.error(
                    span_of(l),
                    field,
                    format!("cannot read link `{}`: {why}", l.get_ref()),
                    Some("write it as `\"source.output -> sink.input\"`".into()),
                );
                return None;
            }
        };
        if !check_link(self.r, &link, l, field, &self.modules, &self.kinds) {
            return None;
        }
        if let Some(prev) = links.iter().find(|x| x.to == link.to) {
            let msg = if prev.from == link.from {
                format!("link `{link}` is listed twice")
            } else {
                format!(
                    "input `{}` is fed by both `{}` and `{}` in task `{task}`",
                    link.to, prev.from, link.from,
                )
            };
            self.r.error(
                span_of(l),
                field,
                msg,
                Some("an input reads from one output per task: keep one link, or put the other in its own task".into()),
            );
            return None;
        }
        check_readers(self.r, &link, l, field, &self.modules, &self.kinds, readers);
        Some(link)
    }

    /// `system.default_task` names a task.
    fn default_task(&mut self, system: &RawSystem) {
        if let Some(d) = &system.default_task
            && !self.tasks.contains_key(d.get_ref())
        {
            self.r.error(
                span_of(d),
                "system.default_task",
                format!("default task `{}` is not defined", d.get_ref()),
                Some(suggest(d.get_ref(), self.tasks.keys().map(String::as_str))),
            );
        }
    }

    /// `system.authority` names a DNM of the rover.
    fn authority(&mut self, system: &RawSystem) {
        if let Some(a) = &system.authority {
            match self.dnms.iter().find(|d| &d.name == a.get_ref()) {
                None => self.r.error(
                    span_of(a),
                    "system.authority",
                    format!("authority DNM `{}` is not declared", a.get_ref()),
                    Some(suggest(
                        a.get_ref(),
                        self.dnms.iter().map(|d| d.name.as_str()),
                    )),
                ),
                Some(d) if d.radio => self.r.error(
                    span_of(a),
                    "system.authority",
                    format!("authority DNM `{}` is across the radio link", a.get_ref()),
                    Some("name a DNM of the rover: it must decide while the link is down".into()),
                ),
                Some(_) => {}
            }
        }
    }

    /// `system.on_link_loss`: a duration in range and a task.
    fn on_link_loss(&mut self, system: &RawSystem) -> Option<LinkLoss> {
        let l = system.on_link_loss.as_ref()?.get_ref();
        let after_ms = match parse_duration_ms(l.after.get_ref()) {
            Some(ms) if (MIN_LINK_LOSS_MS..=MAX_LINK_LOSS_MS).contains(&ms) => Some(ms),
            _ => {
                self.r.error(
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
        if !self.tasks.contains_key(l.task.get_ref()) {
            self.r.error(
                span_of(&l.task),
                "system.on_link_loss.task",
                format!("task `{}` is not defined", l.task.get_ref()),
                Some(suggest(
                    l.task.get_ref(),
                    self.tasks.keys().map(String::as_str),
                )),
            );
            return None;
        }
        let stop_sequences = match l.sequences.as_ref().map(|s| (s, s.get_ref().as_str())) {
            None | Some((_, "run")) => false,
            Some((_, "stop")) => true,
            Some((s, other)) => {
                self.r.error(
                    span_of(s),
                    "system.on_link_loss.sequences",
                    format!("`{other}` is not what loss of signal can do to a sequence"),
                    Some(
                        "use `sequences = \"run\"` (the default: a running sequence goes on) or \
                         `\"stop\"` (the rover is made safe and the sequence stops)"
                            .into(),
                    ),
                );
                return None;
            }
        };
        Some(LinkLoss {
            after_ms: after_ms?,
            task: l.task.get_ref().clone(),
            stop_sequences,
        })
    }

    /// The module graph: a node per module, and, when nothing is wrong, an edge per distinct
    /// link of any task.
    fn module_graph(&self) -> (ModuleGraph, BTreeMap<String, NodeIndex>) {
        let mut graph = ModuleGraph::default();
        let mut nodes = BTreeMap::new();
        for m in &self.modules {
            nodes.insert(
                m.name.clone(),
                graph.add_node(ModuleNode {
                    module: m.name.clone(),
                }),
            );
        }
        if !self.r.has_errors() {
            let mut edges: BTreeMap<&Link, BTreeSet<String>> = BTreeMap::new();
            for t in self.tasks.values() {
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
        (graph, nodes)
    }
}

// ---------------------------------------------------------------------------------------------
// Checks of single fields.

/// Why a name is refused (see [`valid_name`]).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum BadName {
    #[error("is empty")]
    Empty,
    #[error("is longer than {MAX_NAME_LEN} characters")]
    TooLong,
    #[error("must start with a letter and use only letters, digits, `_` and `-`")]
    Characters,
}

/// Whether `name` may name a DNM, a module, a kind, a port or a parameter: why not if not.
pub fn valid_name(name: &str) -> Result<(), BadName> {
    if name.is_empty() {
        return Err(BadName::Empty);
    }
    if name.len() > MAX_NAME_LEN {
        return Err(BadName::TooLong);
    }
    let first_ok = name.chars().next().is_some_and(|c| c.is_ascii_alphabetic());
    if !first_ok
        || !name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    {
        return Err(BadName::Characters);
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

/// A DNM's `link`: `Some(true)` for `"radio"`, `Some(false)` for `"local"`, `None` if unknown.
fn is_radio(link: &str) -> Option<bool> {
    match link {
        "radio" => Some(true),
        "local" => Some(false),
        _ => None,
    }
}

/// Whether walking up from `d` through the parents comes back to `d`. A walk longer than the
/// number of DNMs is a cycle.
fn in_cycle(dnms: &[DnmDecl], d: &DnmDecl) -> bool {
    let mut cur = d.parent.clone();
    let mut steps = 0;
    while let Some(p) = cur {
        steps += 1;
        if p == d.name || steps > dnms.len() {
            return true;
        }
        cur = dnms
            .iter()
            .find(|x| x.name == p)
            .and_then(|x| x.parent.clone());
    }
    false
}

/// The DNM a module is pinned to, if it names one, is declared.
fn check_module_dnm(
    r: &mut Reporter<'_>,
    field: &str,
    name: &str,
    m: &RawModule,
    dnm_names: &[String],
) {
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
}

/// A module's `rate_hz`, if given, is within [`MIN_RATE_HZ`]..=[`MAX_RATE_HZ`].
fn check_rate(r: &mut Reporter<'_>, field: &str, m: &RawModule) {
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
}

/// A module's `hung_after` in milliseconds: `None` when not given or not valid.
fn hung_after(r: &mut Reporter<'_>, field: &str, m: &RawModule) -> Option<u64> {
    let h = m.hung_after.as_ref()?;
    match parse_duration_ms(h.get_ref()) {
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
    }
}

/// The parameters a module gives, each one its kind declares, of the declared type.
fn given_params(
    r: &mut Reporter<'_>,
    field: &str,
    m: &RawModule,
    spec: &KindSpec,
) -> BTreeMap<String, ParamValue> {
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
    params
}

/// Fills in the defaults of the parameters module `name` does not give; those without a
/// default are missing.
fn default_params(
    r: &mut Reporter<'_>,
    field: &str,
    name: &str,
    m: &RawModule,
    spec: &KindSpec,
    params: &mut BTreeMap<String, ParamValue>,
) {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_links() {
        let l = parse_link(" a.out ->b.in ").unwrap();
        assert_eq!(l.to_string(), "a.out -> b.in");
        assert!(parse_link("a.out b.in").is_err());
        assert!(parse_link("a -> b.in").is_err());
        assert!(parse_link("a.x.y -> b.in").is_err());
    }

    fn dnm(name: &str, parent: Option<&str>) -> DnmDecl {
        DnmDecl {
            name: name.into(),
            parent: parent.map(str::to_string),
            radio: false,
        }
    }

    /// A `[[module]]` table as written, and the diagnostics `check` reports on it.
    fn module_diagnostics(
        text: &str,
        check: impl FnOnce(&mut Reporter<'_>, &RawModule),
    ) -> Vec<crate::Diagnostic> {
        let m: RawModule = toml::from_str(text).unwrap();
        let mut r = Reporter::new(Path::new("n.toml"), text);
        check(&mut r, &m);
        r.finish().err().map_or_else(Vec::new, |e| e.diagnostics)
    }

    fn drive() -> KindSpec {
        KindSpec {
            name: "drive".into(),
            summary: String::new(),
            inputs: vec![],
            outputs: vec![],
            params: vec![
                crate::ParamSpec {
                    name: "track_m".into(),
                    kind: crate::ParamKind::Float,
                    default: Some(ParamValue::Float(0.5)),
                    doc: String::new(),
                },
                crate::ParamSpec {
                    name: "board".into(),
                    kind: crate::ParamKind::String,
                    default: None,
                    doc: "serial device".into(),
                },
            ],
            trigger: crate::Trigger::OnInput,
        }
    }

    #[test]
    fn dnm_links_are_radio_or_local() {
        assert_eq!(is_radio("radio"), Some(true));
        assert_eq!(is_radio("local"), Some(false));
        assert_eq!(is_radio("wifi"), None);
    }

    #[test]
    fn cycles_are_found_from_every_dnm_in_or_below_them() {
        let tree = [dnm("rover", None), dnm("arm", Some("rover"))];
        assert!(!tree.iter().any(|d| in_cycle(&tree, d)));
        // A parent that is not declared ends the walk.
        let dangling = [dnm("arm", Some("zz"))];
        assert!(!in_cycle(&dangling, &dangling[0]));
        assert!(in_cycle(&[dnm("a", Some("a"))], &dnm("a", Some("a"))));
        let ring = [
            dnm("a", Some("b")),
            dnm("b", Some("a")),
            dnm("c", Some("a")),
        ];
        assert!(ring.iter().all(|d| in_cycle(&ring, d)));
    }

    #[test]
    fn hung_after_is_a_duration_in_range() {
        let mut got = None;
        let d = module_diagnostics("name = \"m\"\nkind = \"k\"\nhung_after = \"2s\"", |r, m| {
            got = hung_after(r, "module[0]", m);
        });
        assert_eq!((got, d.len()), (Some(2000), 0));
        let d = module_diagnostics(
            "name = \"m\"\nkind = \"k\"\nhung_after = \"10ms\"",
            |r, m| {
                assert_eq!(hung_after(r, "module[0]", m), None);
            },
        );
        assert_eq!(d[0].field, "module[0].hung_after");
        assert_eq!(d[0].message, "10 ms is outside 500 ms..=3600 s");
        assert_eq!(d[0].location, Some((3, 14)));
        let d = module_diagnostics(
            "name = \"m\"\nkind = \"k\"\nhung_after = \"soon\"",
            |r, m| {
                assert_eq!(hung_after(r, "module[0]", m), None);
            },
        );
        assert_eq!(d[0].message, "`soon` is not a duration");
        let d = module_diagnostics("name = \"m\"\nkind = \"k\"", |r, m| {
            assert_eq!(hung_after(r, "module[0]", m), None);
        });
        assert!(d.is_empty());
    }

    #[test]
    fn rates_are_finite_and_in_range() {
        let rate = |text: &str| {
            module_diagnostics(&format!("name = \"m\"\nkind = \"k\"\n{text}"), |r, m| {
                check_rate(r, "module[0]", m);
            })
        };
        assert!(rate("").is_empty());
        assert!(rate("rate_hz = 20.0").is_empty());
        assert_eq!(
            rate("rate_hz = 0.0")[0].message,
            "rate 0 Hz is outside 0.01..=10000 Hz"
        );
        assert_eq!(rate("rate_hz = nan")[0].field, "module[0].rate_hz");
    }

    #[test]
    fn params_are_checked_then_defaults_filled_in() {
        let spec = drive();
        let mut params = BTreeMap::new();
        let text = "name = \"d\"\nkind = \"drive\"\n[params]\ntrack_m = 1\nwheels = 4\n";
        let d = module_diagnostics(text, |r, m| {
            params = given_params(r, "module[0]", m, &spec);
            default_params(r, "module[0]", "d", m, &spec, &mut params);
        });
        // An integer is taken for a float.
        assert_eq!(params.get("track_m"), Some(&ParamValue::Float(1.0)));
        assert_eq!(params.len(), 1);
        let found: Vec<(&str, &str)> = d
            .iter()
            .map(|d| (d.field.as_str(), d.message.as_str()))
            .collect();
        assert_eq!(
            found,
            [
                (
                    "module[0].params.wheels",
                    "kind `drive` has no parameter `wheels`"
                ),
                (
                    "module[0].params.board",
                    "module `d` needs parameter `board` (string)"
                ),
            ]
        );
        let text = "name = \"d\"\nkind = \"drive\"\n[params]\nboard = \"/dev/ttyS0\"\n";
        let d = module_diagnostics(text, |r, m| {
            params = given_params(r, "module[0]", m, &spec);
            default_params(r, "module[0]", "d", m, &spec, &mut params);
        });
        assert!(d.is_empty());
        assert_eq!(params.get("track_m"), Some(&ParamValue::Float(0.5)));
    }

    #[test]
    fn names_are_plain() {
        assert!(valid_name("wheel_left-2").is_ok());
        assert!(valid_name("2wheel").is_err());
        assert!(valid_name("a/b").is_err());
        assert!(valid_name("").is_err());
    }
}
