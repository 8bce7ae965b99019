//! Onboard sequences: a plan the rover carries out on its own, step by step, in the logical
//! layer's TOML like netlists (`configs/sequences/`). Checked against the netlist it runs on,
//! with located errors like a netlist's.
//!
//! ```toml
//! [sequence]
//! name = "explore"
//!
//! [[guard]]                                  # checked for as long as the sequence runs
//! abort_if = "battery.state.charge < 0.2"
//! task = "teleop"                            # switched to when it fires; the sequence aborts
//!
//! [[step]]
//! switch = "auto"
//!
//! [[step]]
//! wait_until = "autopilot.progress.reached >= 3 or odometry.odom.distance > 40"
//! timeout = "5m"
//! on_timeout = "safe"                        # abort (default), safe, or continue
//!
//! [[step]]
//! edit = { replace = "camera", params = ["fov_deg=40"] }
//!
//! [[step]]
//! wait = "10s"
//!
//! [[step]]
//! switch = "teleop"
//! ```
//!
//! A step is one of: `switch` to a task; `edit` a module (`add`, `replace` or `remove`, as
//! `dnm module` does); `apply` a netlist file (relative to the sequence); `wait` a duration;
//! `at` a rover time (ns since the Unix epoch); `wait_until` a condition on outputs, with a
//! `timeout` and what to do `on_timeout`; `end` (unconditionally) or `end_if` a condition. A
//! condition compares numeric (or boolean) fields of modules' outputs, `module.port.field`
//! (`field[i]` for an element of an array field), with `<`, `<=`, `>`, `>=`, `==`, `!=`, joined
//! by `and` and `or` (`and` binds tighter) and grouped with parentheses.

use std::ops::Range;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use toml::Spanned;

use crate::error::{NetlistError, Reporter};
use crate::{MessageType, Netlist, POD_ENCODING, parse_duration_ms};

/// A checked sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sequence {
    pub name: String,
    /// The file it was read from (errors and `apply` paths are relative to it).
    pub file: PathBuf,
    /// Checked for as long as the sequence runs.
    pub guards: Vec<Guard>,
    pub steps: Vec<Step>,
}

/// A sequence-wide limit: when `condition` holds, the rover switches to `task` and the
/// sequence aborts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Guard {
    pub condition: Condition,
    pub task: String,
}

/// One step of a sequence.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Step {
    Switch {
        task: String,
    },
    Edit {
        edit: SequenceEdit,
    },
    /// A netlist file, relative to the sequence's own.
    Apply {
        file: String,
    },
    Wait {
        ms: u64,
    },
    /// Until this rover time (wall clock, ns since the Unix epoch).
    At {
        unix_ns: u64,
    },
    WaitUntil {
        condition: Condition,
        timeout_ms: u64,
        on_timeout: OnTimeout,
    },
    /// The sequence finishes here (when `condition` holds, if there is one).
    End {
        condition: Option<Condition>,
    },
}

/// A module edit as a step: what `dnm module add|replace|remove` does.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SequenceEdit {
    Add {
        name: String,
        kind: String,
        dnm: Option<String>,
        params: Vec<String>,
        links: Vec<String>,
    },
    Replace {
        name: String,
        kind: Option<String>,
        params: Vec<String>,
    },
    Remove {
        name: String,
    },
}

/// What a `wait_until` does when its timeout passes first.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OnTimeout {
    /// The sequence stops where it is.
    Abort,
    /// The rover is made safe (the netlist's loss-of-signal task) and the sequence stops.
    Safe,
    /// The next step runs.
    Continue,
}

/// A condition on outputs.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Condition {
    Compare { field: FieldRef, op: Op, value: f64 },
    And(Box<Condition>, Box<Condition>),
    Or(Box<Condition>, Box<Condition>),
}

/// A comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Op {
    #[serde(rename = "<")]
    Lt,
    #[serde(rename = "<=")]
    Le,
    #[serde(rename = ">")]
    Gt,
    #[serde(rename = ">=")]
    Ge,
    #[serde(rename = "==")]
    Eq,
    #[serde(rename = "!=")]
    Ne,
}

impl Op {
    /// Whether `a op b`.
    pub fn holds(self, a: f64, b: f64) -> bool {
        match self {
            Op::Lt => a < b,
            Op::Le => a <= b,
            Op::Gt => a > b,
            Op::Ge => a >= b,
            Op::Eq => a == b,
            Op::Ne => a != b,
        }
    }
}

/// A field of a module's output: `module.port.field` or `module.port.field[index]`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct FieldRef {
    pub module: String,
    pub port: String,
    pub field: String,
    pub index: Option<usize>,
}

impl std::fmt::Display for FieldRef {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}.{}.{}", self.module, self.port, self.field)?;
        if let Some(i) = self.index {
            write!(f, "[{i}]")?;
        }
        Ok(())
    }
}

impl Condition {
    /// Levels of `and`/`or` (a comparison is 0).
    pub fn levels(&self) -> usize {
        match self {
            Condition::Compare { .. } => 0,
            Condition::And(a, b) | Condition::Or(a, b) => 1 + a.levels().max(b.levels()),
        }
    }

    /// Every field the condition reads.
    pub fn fields(&self) -> Vec<&FieldRef> {
        match self {
            Condition::Compare { field, .. } => vec![field],
            Condition::And(a, b) | Condition::Or(a, b) => {
                let mut v = a.fields();
                v.extend(b.fields());
                v
            }
        }
    }

    /// Its value, given the newest value of each field (`None`: not known yet, so a
    /// comparison on it does not hold).
    pub fn holds(&self, value_of: &dyn Fn(&FieldRef) -> Option<f64>) -> bool {
        match self {
            Condition::Compare { field, op, value } => {
                value_of(field).is_some_and(|v| op.holds(v, *value))
            }
            Condition::And(a, b) => a.holds(value_of) && b.holds(value_of),
            Condition::Or(a, b) => a.holds(value_of) || b.holds(value_of),
        }
    }
}

impl Sequence {
    /// Reads and checks a sequence file against `netlist`.
    pub fn load(path: &Path, netlist: &Netlist) -> Result<Self, NetlistError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| NetlistError::unreadable(path, &e, "sequence"))?;
        Self::parse(path, &text, netlist)
    }

    /// Checks sequence text against `netlist`: every task, module, port and field it names
    /// exists, every compared field is numeric (or boolean, compared with `true`/`false`), and
    /// no step follows an unconditional `end`. Steps are checked against `netlist` as it is:
    /// a module a step adds or removes is not seen by the steps after it. `file` names it in
    /// errors.
    pub fn parse(file: &Path, text: &str, netlist: &Netlist) -> Result<Self, NetlistError> {
        let mut r = Reporter::new(file, text);
        let raw: RawSequence = match toml::from_str(text) {
            Ok(raw) => raw,
            Err(e) => {
                let message = e.message().to_string();
                r.error(
                    e.span(),
                    "toml",
                    message,
                    Some("fix the TOML syntax or field name at this position".into()),
                );
                r.finish().map_err(as_sequence)?;
                unreachable!("finish reports the error above")
            }
        };
        let mut check = Check { r: &mut r, netlist };
        let name = raw.sequence.name.get_ref().clone();
        if name.trim().is_empty() {
            check.r.error(
                Some(raw.sequence.name.span()),
                "sequence.name",
                "a sequence needs a name",
                None,
            );
        }
        let guards = raw
            .guard
            .iter()
            .enumerate()
            .filter_map(|(i, g)| check.guard(i, g))
            .collect();
        let steps = check.steps(&raw.step);
        r.finish().map_err(as_sequence)?;
        Ok(Sequence {
            name,
            file: file.to_path_buf(),
            guards,
            steps,
        })
    }
}

fn as_sequence(e: NetlistError) -> NetlistError {
    NetlistError {
        document: "sequence",
        ..e
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSequence {
    sequence: RawHeader,
    #[serde(default)]
    guard: Vec<RawGuard>,
    #[serde(default)]
    step: Vec<Spanned<RawStep>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawHeader {
    name: Spanned<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawGuard {
    abort_if: Spanned<String>,
    task: Spanned<String>,
}

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawStep {
    switch: Option<Spanned<String>>,
    edit: Option<Spanned<RawEdit>>,
    apply: Option<Spanned<String>>,
    wait: Option<Spanned<String>>,
    at: Option<Spanned<u64>>,
    wait_until: Option<Spanned<String>>,
    timeout: Option<Spanned<String>>,
    on_timeout: Option<Spanned<String>>,
    end: Option<Spanned<bool>>,
    end_if: Option<Spanned<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawEdit {
    add: Option<String>,
    replace: Option<String>,
    remove: Option<String>,
    kind: Option<String>,
    dnm: Option<String>,
    #[serde(default)]
    params: Vec<String>,
    #[serde(default)]
    links: Vec<String>,
}

/// What a check goes through.
struct Check<'r, 'a> {
    r: &'r mut Reporter<'a>,
    netlist: &'r Netlist,
}

impl Check<'_, '_> {
    fn guard(&mut self, i: usize, g: &RawGuard) -> Option<Guard> {
        let field = format!("guard[{i}]");
        let condition = self.condition(&g.abort_if, &format!("{field}.abort_if"));
        let task = self.task(&g.task, &format!("{field}.task"));
        Some(Guard {
            condition: condition?,
            task: task?,
        })
    }

    fn steps(&mut self, raw: &[Spanned<RawStep>]) -> Vec<Step> {
        if raw.is_empty() {
            self.r.error(
                None,
                "step",
                "a sequence needs at least one step",
                Some("add a `[[step]]`, e.g. `switch = \"auto\"`".into()),
            );
        }
        let mut steps = Vec::new();
        let mut ended: Option<usize> = None;
        for (i, s) in raw.iter().enumerate() {
            let field = format!("step[{i}]");
            if let Some(at) = ended {
                self.r.error(
                    Some(s.span()),
                    field.clone(),
                    format!("never runs: the sequence ends unconditionally at step[{at}]"),
                    Some("remove the step, or make that end an `end_if`".into()),
                );
            }
            if let Some(step) = self.step(s, &field) {
                if matches!(step, Step::End { condition: None }) {
                    ended.get_or_insert(i);
                }
                steps.push(step);
            }
        }
        steps
    }

    fn step(&mut self, s: &Spanned<RawStep>, field: &str) -> Option<Step> {
        let raw = s.get_ref();
        let actions = [
            raw.switch.is_some(),
            raw.edit.is_some(),
            raw.apply.is_some(),
            raw.wait.is_some(),
            raw.at.is_some(),
            raw.wait_until.is_some(),
            raw.end.is_some(),
            raw.end_if.is_some(),
        ];
        let count = actions.iter().filter(|a| **a).count();
        if count != 1 {
            self.r.error(
                Some(s.span()),
                field,
                if count == 0 {
                    "a step does nothing"
                } else {
                    "a step does exactly one thing"
                },
                Some(
                    "give it one of `switch`, `edit`, `apply`, `wait`, `at`, `wait_until`, \
                     `end`, `end_if`"
                        .into(),
                ),
            );
            return None;
        }
        if raw.wait_until.is_none() && (raw.timeout.is_some() || raw.on_timeout.is_some()) {
            let key = if raw.timeout.is_some() {
                "timeout"
            } else {
                "on_timeout"
            };
            self.r.error(
                Some(s.span()),
                format!("{field}.{key}"),
                "only a `wait_until` step has a timeout",
                None,
            );
        }
        if let Some(t) = &raw.switch {
            return Some(Step::Switch {
                task: self.task(t, &format!("{field}.switch"))?,
            });
        }
        if let Some(e) = &raw.edit {
            return Some(Step::Edit {
                edit: self.edit(e, &format!("{field}.edit"))?,
            });
        }
        if let Some(f) = &raw.apply {
            return Some(Step::Apply {
                file: f.get_ref().clone(),
            });
        }
        if let Some(w) = &raw.wait {
            return Some(Step::Wait {
                ms: self.duration(w, &format!("{field}.wait"))?,
            });
        }
        if let Some(at) = &raw.at {
            return Some(Step::At {
                unix_ns: *at.get_ref(),
            });
        }
        if let Some(c) = &raw.wait_until {
            return self.wait_until(raw, c, field);
        }
        if let Some(end) = &raw.end {
            if !*end.get_ref() {
                self.r.error(
                    Some(end.span()),
                    format!("{field}.end"),
                    "`end = false` does nothing",
                    Some("remove the step, or write `end = true`".into()),
                );
                return None;
            }
            return Some(Step::End { condition: None });
        }
        let c = raw.end_if.as_ref()?;
        Some(Step::End {
            condition: Some(self.condition(c, &format!("{field}.end_if"))?),
        })
    }

    fn wait_until(&mut self, raw: &RawStep, c: &Spanned<String>, field: &str) -> Option<Step> {
        let condition = self.condition(c, &format!("{field}.wait_until"));
        let Some(t) = &raw.timeout else {
            self.r.error(
                Some(c.span()),
                format!("{field}.timeout"),
                "a `wait_until` needs a `timeout`",
                Some("add e.g. `timeout = \"2m\"`; nothing waits forever on board".into()),
            );
            return None;
        };
        let timeout_ms = self.duration(t, &format!("{field}.timeout"));
        let on_timeout = match raw.on_timeout.as_ref().map(|o| (o, o.get_ref().as_str())) {
            None | Some((_, "abort")) => Some(OnTimeout::Abort),
            Some((_, "safe")) => Some(OnTimeout::Safe),
            Some((_, "continue")) => Some(OnTimeout::Continue),
            Some((o, other)) => {
                self.r.error(
                    Some(o.span()),
                    format!("{field}.on_timeout"),
                    format!("unknown `on_timeout = \"{other}\"`"),
                    Some("use \"abort\", \"safe\" or \"continue\"".into()),
                );
                None
            }
        };
        Some(Step::WaitUntil {
            condition: condition?,
            timeout_ms: timeout_ms?,
            on_timeout: on_timeout?,
        })
    }

    fn task(&mut self, t: &Spanned<String>, field: &str) -> Option<String> {
        let name = t.get_ref();
        if self.netlist.tasks.contains_key(name) {
            return Some(name.clone());
        }
        let known: Vec<&str> = self.netlist.tasks.keys().map(String::as_str).collect();
        self.r.error(
            Some(t.span()),
            field,
            format!("unknown task `{name}`"),
            Some(format!("the netlist's tasks: {}", known.join(", "))),
        );
        None
    }

    fn duration(&mut self, d: &Spanned<String>, field: &str) -> Option<u64> {
        let ms = parse_duration_ms(d.get_ref());
        if ms.is_none() {
            self.r.error(
                Some(d.span()),
                field,
                format!("`{}` is not a duration", d.get_ref()),
                Some("write e.g. \"500ms\", \"10s\", \"2m\" or \"1h\"".into()),
            );
        }
        ms
    }

    fn edit(&mut self, e: &Spanned<RawEdit>, field: &str) -> Option<SequenceEdit> {
        let raw = e.get_ref();
        let named = [&raw.add, &raw.replace, &raw.remove]
            .iter()
            .filter(|x| x.is_some())
            .count();
        if named != 1 {
            self.r.error(
                Some(e.span()),
                field,
                "an edit names one module to `add`, `replace` or `remove`",
                None,
            );
            return None;
        }
        let unused = unused_keys(raw);
        if !unused.is_empty() {
            self.r.error(
                Some(e.span()),
                field,
                format!("this edit does not use {}", unused.join(", ")),
                Some(
                    "remove them: a replace takes `kind` and `params`, a remove only the name"
                        .into(),
                ),
            );
            return None;
        }
        let known_module = |check: &mut Self, name: &str| {
            if check.netlist.module(name).is_some() {
                return true;
            }
            check.r.error(
                Some(e.span()),
                field,
                format!("unknown module `{name}`"),
                Some(format!("the netlist's modules: {}", check.module_names())),
            );
            false
        };
        let known_kind = |check: &mut Self, kind: &str| {
            if check.netlist.catalog.get(kind).is_some() {
                return true;
            }
            check.r.error(
                Some(e.span()),
                field,
                format!("unknown kind `{kind}`"),
                None,
            );
            false
        };
        if let Some(name) = &raw.add {
            let Some(kind) = &raw.kind else {
                self.r.error(
                    Some(e.span()),
                    field,
                    format!("adding `{name}` needs its `kind`"),
                    None,
                );
                return None;
            };
            if self.netlist.module(name).is_some() {
                self.r.error(
                    Some(e.span()),
                    field,
                    format!("module `{name}` exists already"),
                    Some("replace it, or pick another name".into()),
                );
                return None;
            }
            return known_kind(self, kind).then(|| SequenceEdit::Add {
                name: name.clone(),
                kind: kind.clone(),
                dnm: raw.dnm.clone(),
                params: raw.params.clone(),
                links: raw.links.clone(),
            });
        }
        if let Some(name) = &raw.replace {
            let kind_ok = raw.kind.as_ref().is_none_or(|k| known_kind(self, k));
            return (known_module(self, name) && kind_ok).then(|| SequenceEdit::Replace {
                name: name.clone(),
                kind: raw.kind.clone(),
                params: raw.params.clone(),
            });
        }
        let name = raw.remove.as_ref()?;
        known_module(self, name).then(|| SequenceEdit::Remove { name: name.clone() })
    }

    fn module_names(&self) -> String {
        let names: Vec<&str> = self
            .netlist
            .modules
            .iter()
            .map(|m| m.name.as_str())
            .collect();
        names.join(", ")
    }

    /// A condition, parsed and checked against the netlist; errors point at its text.
    fn condition(&mut self, c: &Spanned<String>, field: &str) -> Option<Condition> {
        match parse_condition(c.get_ref()) {
            Err(e) => {
                let at = self.inner(c, e.at);
                self.r.error(
                    Some(at),
                    field,
                    e.message,
                    Some(
                        "write `module.port.field OP number`, joined by `and`/`or`, e.g. \
                         `odometry.odom.distance >= 5.0`"
                            .into(),
                    ),
                );
                None
            }
            Ok(parsed) => {
                let mut ok = true;
                for (cmp, at) in &parsed.comparisons {
                    let at = self.inner(c, *at);
                    ok &= self.comparison(cmp, at, field);
                }
                ok.then_some(parsed.condition)
            }
        }
    }

    /// The span of byte `at` of a condition's text: exact when the file spells the string as
    /// it reads (one quote, no escapes), else the string's start.
    fn inner(&self, c: &Spanned<String>, at: usize) -> Range<usize> {
        let span = c.span();
        let text = c.get_ref();
        let raw = self
            .r
            .text()
            .get(span.start + 1..span.end.saturating_sub(1));
        if raw == Some(text.as_str()) && at <= text.len() {
            return span.start + 1 + at..span.end;
        }
        span
    }

    /// Whether a comparison names an output field that exists and has the literal's type.
    fn comparison(&mut self, cmp: &Comparison, span: Range<usize>, field: &str) -> bool {
        let f = &cmp.field;
        let Some(spec) = self.netlist.kind_of(&f.module) else {
            self.r.error(
                Some(span),
                field,
                format!("unknown module `{}`", f.module),
                Some(format!("the netlist's modules: {}", self.module_names())),
            );
            return false;
        };
        let Some(port) = spec.outputs.iter().find(|p| p.name == f.port) else {
            let outs: Vec<&str> = spec.outputs.iter().map(|p| p.name.as_str()).collect();
            self.r.error(
                Some(span),
                field,
                format!("module `{}` has no output `{}`", f.module, f.port),
                Some(format!("its outputs: {}", outs.join(", "))),
            );
            return false;
        };
        let fields = match pod_fields(&port.message) {
            Some(fields) => fields,
            None => {
                self.r.error(
                    Some(span),
                    field,
                    format!(
                        "output `{}.{}` ({}) is not a fixed-size message: its fields cannot be compared",
                        f.module, f.port, port.message.schema_name
                    ),
                    None,
                );
                return false;
            }
        };
        let Some((ty, count)) = fields
            .iter()
            .find(|(_, name, _)| *name == f.field)
            .map(|(ty, _, n)| (*ty, *n))
        else {
            let names: Vec<&str> = fields.iter().map(|(_, n, _)| *n).collect();
            self.r.error(
                Some(span),
                field,
                format!(
                    "`{}.{}` ({}) has no field `{}`",
                    f.module, f.port, port.message.schema_name, f.field
                ),
                Some(format!("its fields: {}", names.join(", "))),
            );
            return false;
        };
        if let Some(p) = type_problem(f, ty, count, cmp) {
            self.r.error(Some(span), field, p, None);
            return false;
        }
        true
    }
}

/// What is wrong with comparing field `f` (of type `ty`, an array of `count` if it is one) as
/// `cmp` does, if anything.
fn type_problem(f: &FieldRef, ty: &str, count: Option<usize>, cmp: &Comparison) -> Option<String> {
    let shape = match (count, f.index) {
        (Some(n), None) => Some(format!(
            "`{f}` is an array of {n}: compare one element, e.g. `{f}[0]`"
        )),
        (None, Some(_)) => Some(format!("`{}` is not an array", f.field)),
        (Some(n), Some(i)) if i >= n => Some(format!("`{f}` is past the end: it has {n}")),
        _ => None,
    };
    if shape.is_some() {
        return shape;
    }
    let boolean = ty == "bool";
    if !boolean && !NUMERIC.contains(&ty) {
        return Some(format!(
            "`{f}` is a {ty}, not a number: it cannot be compared"
        ));
    }
    match &cmp.literal {
        Literal::Bool(_) if !boolean => Some(format!(
            "`{f}` is a number ({ty}): compare it with a number"
        )),
        Literal::Number(_) if boolean => Some(format!(
            "`{f}` is true or false: compare it with `true` or `false`"
        )),
        Literal::Text(t) => Some(format!(
            "`{t}` is text: `{f}` is {} and compares only with {}",
            if boolean { "true or false" } else { "a number" },
            if boolean {
                "`true` or `false`"
            } else {
                "a number"
            }
        )),
        _ if boolean && cmp.op != Op::Eq && cmp.op != Op::Ne => Some(format!(
            "`{f}` is true or false: compare it with `==` or `!=`"
        )),
        _ => None,
    }
}

/// Keys an edit gives that its kind of edit does not use: a replace takes `kind` and
/// `params`, a remove only the name.
fn unused_keys(raw: &RawEdit) -> Vec<&'static str> {
    let given = [
        ("kind", raw.kind.is_some()),
        ("dnm", raw.dnm.is_some()),
        ("params", !raw.params.is_empty()),
        ("links", !raw.links.is_empty()),
    ];
    let used: &[&str] = match (&raw.add, &raw.replace) {
        (Some(_), _) => &["kind", "dnm", "params", "links"],
        (None, Some(_)) => &["kind", "params"],
        (None, None) => &[],
    };
    given
        .into_iter()
        .filter(|(k, set)| *set && !used.contains(k))
        .map(|(k, _)| k)
        .collect()
}

/// The field types a comparison reads as numbers.
const NUMERIC: [&str; 12] = [
    "int8", "uint8", "byte", "char", "int16", "uint16", "int32", "uint32", "int64", "uint64",
    "float32", "float64",
];

/// A fixed-size message's fields: (type, name, array length). Constants (`int32 X = 5`) are
/// not fields.
fn pod_fields(message: &MessageType) -> Option<Vec<(&str, &str, Option<usize>)>> {
    if message.encoding != POD_ENCODING {
        return None;
    }
    let mut out = Vec::new();
    for line in message.schema.lines() {
        let line = line.split('#').next().unwrap_or("").trim();
        if line.is_empty() {
            continue;
        }
        if line.contains('=') {
            continue;
        }
        let mut parts = line.split_whitespace();
        let (ty, name) = (parts.next()?, parts.next()?);
        match ty.split_once('[') {
            Some((base, rest)) => {
                out.push((base, name, Some(rest.strip_suffix(']')?.parse().ok()?)));
            }
            None => out.push((ty, name, None)),
        }
    }
    Some(out)
}

/// A literal a field is compared with.
#[derive(Debug, Clone, PartialEq)]
enum Literal {
    Number(f64),
    Bool(bool),
    Text(String),
}

/// One comparison as written.
#[derive(Debug, Clone, PartialEq)]
struct Comparison {
    field: FieldRef,
    op: Op,
    literal: Literal,
}

/// A parsed condition and its comparisons, each with where it starts in the text.
#[derive(Debug)]
struct Parsed {
    condition: Condition,
    comparisons: Vec<(Comparison, usize)>,
}

/// Why a condition's text does not parse, and where.
#[derive(Debug, Clone, PartialEq)]
struct ConditionError {
    at: usize,
    message: String,
}

#[derive(Debug, Clone, PartialEq)]
enum Token {
    Word(String),
    Number(f64),
    Text(String),
    Op(Op),
    Open,
    Close,
}

/// The longest a condition may be (it comes from files and, uploaded, from the network).
const MAX_CONDITION: usize = 4096;
/// Nesting of parentheses, at most.
const MAX_DEPTH: usize = 32;
/// Levels of `and`/`or` a condition may have, parentheses and chains together (a chain of `n`
/// is `log2 n` levels): what is stored with a sequence stays well inside the 128 levels of
/// nesting its JSON may have.
const MAX_LEVELS: usize = 40;

fn tokens(text: &str) -> Result<Vec<(Token, usize)>, ConditionError> {
    let err = |at: usize, message: String| Err(ConditionError { at, message });
    if text.len() > MAX_CONDITION {
        return err(
            0,
            format!("the condition is longer than {MAX_CONDITION} bytes; split it into steps"),
        );
    }
    let b = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    while i < b.len() {
        let c = b[i] as char;
        let start = i;
        if c.is_whitespace() {
            i += 1;
            continue;
        }
        let two = text.get(i..i + 2).unwrap_or("");
        let op = match two {
            "<=" => Some((Op::Le, 2)),
            ">=" => Some((Op::Ge, 2)),
            "==" => Some((Op::Eq, 2)),
            "!=" => Some((Op::Ne, 2)),
            _ => match c {
                '<' => Some((Op::Lt, 1)),
                '>' => Some((Op::Gt, 1)),
                _ => None,
            },
        };
        if let Some((op, n)) = op {
            out.push((Token::Op(op), start));
            i += n;
        } else if c == '(' || c == ')' {
            out.push((if c == '(' { Token::Open } else { Token::Close }, start));
            i += 1;
        } else if c == '\'' || c == '"' {
            let Some(end) = text[i + 1..].find(c) else {
                return err(start, "text without its closing quote".into());
            };
            out.push((Token::Text(text[i + 1..i + 1 + end].to_string()), start));
            i += end + 2;
        } else if c.is_ascii_digit() || c == '-' || c == '+' || c == '.' {
            while i < b.len()
                && ((b[i] as char).is_ascii_alphanumeric() || matches!(b[i], b'.' | b'-' | b'+'))
            {
                i += 1;
            }
            match text[start..i].parse::<f64>() {
                Ok(v) if v.is_finite() => out.push((Token::Number(v), start)),
                _ => return err(start, format!("`{}` is not a number", &text[start..i])),
            }
        } else if c.is_ascii_alphabetic() || c == '_' {
            while i < b.len()
                && ((b[i] as char).is_ascii_alphanumeric()
                    || matches!(b[i], b'_' | b'-' | b'.' | b'[' | b']'))
            {
                i += 1;
            }
            out.push((Token::Word(text[start..i].to_string()), start));
        } else {
            let ch = text[i..].chars().next().unwrap_or(c);
            let hint = if ch == '=' {
                " (compare with `==`)"
            } else {
                ""
            };
            return err(start, format!("unexpected `{ch}`{hint}"));
        }
    }
    Ok(out)
}

/// Parses `a.b.c >= 1 and (d.e.f < 2 or g.h.i == true)`.
fn parse_condition(text: &str) -> Result<Parsed, ConditionError> {
    let toks = tokens(text)?;
    let mut p = Parser {
        toks: &toks,
        pos: 0,
        end: text.len(),
        comparisons: Vec::new(),
    };
    let condition = p.or(0)?;
    if let Some((_, at)) = p.toks.get(p.pos) {
        return Err(ConditionError {
            at: *at,
            message: "expected `and`, `or` or the end of the condition here".into(),
        });
    }
    Ok(Parsed {
        condition,
        comparisons: p.comparisons,
    })
}

/// `a op b op c …` as a tree of `join` as shallow as it can be (both operators are
/// associative): a long chain is a few levels, not one per term. Refused past [`MAX_LEVELS`].
fn balanced(
    mut terms: Vec<Condition>,
    join: &dyn Fn(Box<Condition>, Box<Condition>) -> Condition,
    at: usize,
) -> Result<Condition, ConditionError> {
    fn build(
        terms: &mut std::vec::Drain<'_, Condition>,
        n: usize,
        join: &dyn Fn(Box<Condition>, Box<Condition>) -> Condition,
    ) -> Option<Condition> {
        if n <= 1 {
            return terms.next();
        }
        let left = build(terms, n / 2, join)?;
        let right = build(terms, n - n / 2, join)?;
        Some(join(Box::new(left), Box::new(right)))
    }
    let n = terms.len();
    let tree = build(&mut terms.drain(..), n, join).ok_or(ConditionError {
        at,
        message: "expected a comparison here".into(),
    })?;
    if tree.levels() > MAX_LEVELS {
        return Err(ConditionError {
            at,
            message: format!(
                "the condition nests more than {MAX_LEVELS} levels of `and`, `or` and \
                 parentheses; split it into steps"
            ),
        });
    }
    Ok(tree)
}

struct Parser<'t> {
    toks: &'t [(Token, usize)],
    pos: usize,
    end: usize,
    comparisons: Vec<(Comparison, usize)>,
}

impl Parser<'_> {
    fn at(&self) -> usize {
        self.toks.get(self.pos).map_or(self.end, |(_, at)| *at)
    }

    fn keyword(&mut self, word: &str) -> bool {
        if matches!(self.toks.get(self.pos), Some((Token::Word(w), _)) if w == word) {
            self.pos += 1;
            return true;
        }
        false
    }

    fn or(&mut self, depth: usize) -> Result<Condition, ConditionError> {
        let at = self.at();
        let mut terms = vec![self.and(depth)?];
        while self.keyword("or") {
            terms.push(self.and(depth)?);
        }
        balanced(terms, &Condition::Or, at)
    }

    fn and(&mut self, depth: usize) -> Result<Condition, ConditionError> {
        let at = self.at();
        let mut terms = vec![self.primary(depth)?];
        while self.keyword("and") {
            terms.push(self.primary(depth)?);
        }
        balanced(terms, &Condition::And, at)
    }

    fn primary(&mut self, depth: usize) -> Result<Condition, ConditionError> {
        let at = self.at();
        let fail = |message: &str| ConditionError {
            at,
            message: message.into(),
        };
        match self.toks.get(self.pos) {
            Some((Token::Open, _)) => {
                if depth >= MAX_DEPTH {
                    return Err(fail("parentheses nested too deep"));
                }
                self.pos += 1;
                let inside = self.or(depth + 1)?;
                if !matches!(self.toks.get(self.pos), Some((Token::Close, _))) {
                    return Err(ConditionError {
                        at: self.at(),
                        message: "expected `)` here".into(),
                    });
                }
                self.pos += 1;
                Ok(inside)
            }
            Some((Token::Word(w), _)) if w != "and" && w != "or" => {
                let field = field_ref(w).ok_or_else(|| {
                    fail(&format!(
                        "`{w}` is not `module.port.field` (or `module.port.field[index]`)"
                    ))
                })?;
                self.pos += 1;
                let Some((Token::Op(op), _)) = self.toks.get(self.pos) else {
                    return Err(ConditionError {
                        at: self.at(),
                        message: "expected a comparison (`<`, `<=`, `>`, `>=`, `==`, `!=`) here"
                            .into(),
                    });
                };
                let op = *op;
                self.pos += 1;
                let literal = match self.toks.get(self.pos) {
                    Some((Token::Number(v), _)) => Literal::Number(*v),
                    Some((Token::Text(t), _)) => Literal::Text(t.clone()),
                    Some((Token::Word(w), _)) if w == "true" || w == "false" => {
                        Literal::Bool(w == "true")
                    }
                    _ => {
                        return Err(ConditionError {
                            at: self.at(),
                            message: "expected a number (or `true`/`false`) here".into(),
                        });
                    }
                };
                self.pos += 1;
                let value = match &literal {
                    Literal::Number(v) => *v,
                    Literal::Bool(b) => f64::from(u8::from(*b)),
                    Literal::Text(_) => f64::NAN,
                };
                self.comparisons.push((
                    Comparison {
                        field: field.clone(),
                        op,
                        literal,
                    },
                    at,
                ));
                Ok(Condition::Compare { field, op, value })
            }
            _ => Err(fail("expected `module.port.field` or `(` here")),
        }
    }
}

/// `module.port.field` or `module.port.field[index]`.
fn field_ref(word: &str) -> Option<FieldRef> {
    let mut parts = word.splitn(3, '.');
    let (module, port, rest) = (parts.next()?, parts.next()?, parts.next()?);
    let (field, index) = match rest.split_once('[') {
        Some((f, i)) => (f, Some(i.strip_suffix(']')?.parse().ok()?)),
        None => (rest, None),
    };
    let name_ok = |s: &str| {
        !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            && !s.starts_with(|c: char| c.is_ascii_digit())
    };
    (name_ok(module) && name_ok(port) && name_ok(field)).then(|| FieldRef {
        module: module.into(),
        port: port.into(),
        field: field.into(),
        index,
    })
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn and_binds_tighter_than_or_and_parentheses_group() {
        let p = parse_condition("a.b.c < 1 or d.e.f >= 2 and g.h.i[1] == 3").unwrap();
        let Condition::Or(_, right) = &p.condition else {
            panic!("{:?}", p.condition);
        };
        assert!(matches!(**right, Condition::And(..)));
        let p = parse_condition("(a.b.c < 1 or d.e.f >= 2) and g.h.i != -0.5").unwrap();
        assert!(matches!(p.condition, Condition::And(..)));
        assert_eq!(p.comparisons.len(), 3);
        assert_eq!(p.comparisons[2].0.field.index, None);
        assert_eq!(p.comparisons[2].1, 30);
    }

    #[test]
    fn a_long_chain_is_a_shallow_tree_that_a_store_reads_back() {
        // As long as a condition may be: about 300 comparisons joined by `or`.
        let mut text = String::new();
        let mut n = 0;
        while text.len() + 24 < MAX_CONDITION {
            if n > 0 {
                text.push_str(if n % 7 == 0 { " and " } else { " or " });
            }
            text.push_str(&format!("o.p.x == {n}"));
            n += 1;
        }
        let p = parse_condition(&text).unwrap();
        assert_eq!(p.comparisons.len(), n);
        assert!(p.condition.levels() <= 12, "{}", p.condition.levels());
        // The order of the terms is kept.
        let literals: Vec<_> = p.comparisons.iter().map(|c| c.0.literal.clone()).collect();
        assert_eq!(literals[..2], [Literal::Number(0.0), Literal::Number(1.0)]);
        // Stored as JSON with a sequence and read back (serde_json reads 128 levels at most).
        let json = serde_json::to_string(&p.condition).unwrap();
        let back: Condition = serde_json::from_str(&json).unwrap();
        assert_eq!(back, p.condition);
        // It holds as the chain says: x == 1 is in an `or` term of its own.
        let x = |v: f64| move |_: &FieldRef| Some(v);
        assert!(p.condition.holds(&x(1.0)));
        assert!(!p.condition.holds(&x(-1.0)));
        // Parentheses and chains together, past the levels allowed: refused, with the fix.
        let deep = format!(
            "{}o.p.x == 1{}",
            "(o.p.x == 1 or o.p.x == 2 or o.p.x == 3 or ".repeat(30),
            ")".repeat(30)
        );
        let e = parse_condition(&deep).unwrap_err();
        assert!(e.message.contains("split it into steps"), "{e:?}");
    }

    #[test]
    fn a_condition_holds_on_known_values_only() {
        let c = parse_condition("o.p.x >= 5 and o.p.y < 1")
            .unwrap()
            .condition;
        let values = |x: Option<f64>| {
            move |f: &FieldRef| match f.field.as_str() {
                "x" => x,
                _ => Some(0.0),
            }
        };
        assert!(c.holds(&values(Some(5.0))));
        assert!(!c.holds(&values(Some(4.9))));
        assert!(!c.holds(&values(None)));
        assert_eq!(c.fields().len(), 2);
    }

    #[test]
    fn names_may_hold_dashes_and_a_lone_equals_sign_is_explained() {
        let p = parse_condition("wheel_left-2.state.x > -1").unwrap();
        assert_eq!(p.comparisons[0].0.field.module, "wheel_left-2");
        let e = parse_condition("a.b.c = 1").unwrap_err();
        assert!(e.message.contains("`==`"), "{e:?}");
    }

    #[test]
    fn bad_conditions_say_where() {
        let e = parse_condition("a.b.c >").unwrap_err();
        assert_eq!(e.at, 7);
        assert!(e.message.contains("expected a number"), "{e:?}");
        let e = parse_condition("a.b >= 1").unwrap_err();
        assert_eq!(e.at, 0);
        let e = parse_condition("(a.b.c >= 1").unwrap_err();
        assert!(e.message.contains("`)`"), "{e:?}");
        let e = parse_condition("a.b.c >= 1 b.c.d").unwrap_err();
        assert_eq!(e.at, 11);
        let e = parse_condition(&"(".repeat(100)).unwrap_err();
        assert!(e.message.contains("too deep"), "{e:?}");
        assert!(parse_condition(&"x".repeat(5000)).is_err());
        assert!(parse_condition("a.b.c >= 1e999").is_err());
        assert!(parse_condition("a.b.c >= 'x").is_err());
    }
}
