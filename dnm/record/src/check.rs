//! Determinism check (`dnm replay --check MODULE`): a module's code, built in this process
//! from the recorded netlist (its kind and parameters, optionally changed), is stepped on its
//! recorded inputs in time order, under the task in force at each instant; what it writes is
//! compared, message by message, with what it wrote on the rover. The first divergence is
//! reported with the fields that differ. Numbers are compared within a relative tolerance: a
//! sample from another DNM reaches the module with its send time converted through the wall
//! clock (off by up to a few microseconds), which a module deriving rates from send times
//! sees; `0` compares bit for bit.
//!
//! The module is stepped where it stepped on the rover: at each of its recorded outputs, on the
//! newest inputs sent before it (an input module that received several samples between two
//! steps saw only the newest). A step that wrote nothing left no trace, so a module whose steps
//! do not all write is checked at the steps that wrote.
//!
//! The check makes two passes over the recording (`Pass`), accumulating a `Tally`; the module
//! under check is a `Subject`, which it can build afresh and take through its past where what
//! it read is uncertain. `compare` then turns the tally into the report.

use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::path::Path;
use std::rc::Rc;
use std::sync::Arc;

use dnm_module::protocol::PortHeader;
use dnm_module::{ModuleError, Offline, Setup, Stepper};
use dnm_netlist::{KindSpec, MessageType, Netlist, ParamKind, ParamValue, PortSpec};
use serde::Serialize;

use crate::codec::{ReadError, Reading, reading_of};
use crate::replay::{Merge, Msg, OpenError, RecordingFilesError, inputs, recorded_netlist};

/// Builds a module of a kind (by name) from its setup: the module registry's `make`. The check
/// reports its error as [`CheckError::Build`].
pub type Make<'a> = dyn Fn(&str, &mut Setup<'_>) -> Result<Box<dyn Stepper>, MakeError> + 'a;

/// Why a module could not be built for the check.
#[derive(Debug, thiserror::Error)]
pub enum MakeError {
    #[error("this build cannot run kind `{0}` here")]
    UnknownKind(String),
    #[error(transparent)]
    Module(#[from] ModuleError),
}

/// Why a `--set` parameter change is refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParamError {
    #[error("kind `{kind}` has no parameter `{name}`; its parameters: {}", known.join(", "))]
    Unknown {
        kind: String,
        name: String,
        known: Vec<String>,
    },
    /// `text` is not a value of the parameter's type.
    #[error("`{name}` is {}: `{text}` is not one", what(*expected))]
    BadValue {
        name: String,
        expected: ParamKind,
        text: String,
    },
}

/// A value of `kind`, as [`ParamError::BadValue`] asks for it.
fn what(kind: ParamKind) -> &'static str {
    match kind {
        ParamKind::Float => "a number",
        ParamKind::Int => "an integer",
        ParamKind::Bool => "true or false",
        ParamKind::String => "a string",
    }
}

/// Why a determinism check did not run to its report.
#[derive(Debug, thiserror::Error)]
pub enum CheckError {
    #[error(transparent)]
    Files(#[from] RecordingFilesError),
    #[error("the recording holds no netlist")]
    NoNetlist,
    /// The recorded netlist does not parse or validate.
    #[error(transparent)]
    Netlist(dnm_netlist::NetlistError),
    #[error("the recorded netlist has no module `{module}`; its modules: {}", modules.join(", "))]
    UnknownModule {
        module: String,
        modules: Vec<String>,
    },
    #[error("no kind `{kind}` for `{module}`")]
    NoKind { kind: String, module: String },
    #[error(transparent)]
    Param(#[from] ParamError),
    /// The module could not be built (the registry's or the module's message).
    #[error("building `{module}`: {reason}")]
    Build { module: String, reason: String },
    #[error("`{module}` has no input linked in any task: nothing to feed it")]
    NoInputs { module: String },
    #[error(transparent)]
    Open(#[from] OpenError),
    /// A recorded message of the module's inputs or outputs could not be read back.
    #[error("{topic}: the message sent at {sent} ns: {source}")]
    Unreadable {
        topic: String,
        sent: u64,
        #[source]
        source: ReadError,
    },
    /// The module's code returned an error from a step.
    #[error("`{module}` failed to step at {at} ns: {source}")]
    Step {
        module: String,
        at: u64,
        #[source]
        source: ModuleError,
    },
    #[error(
        "the recording holds no outputs of `{module}` (was it recorded? `dnm recordings --json` lists the channels)"
    )]
    NotRecorded { module: String },
}

/// Where the replayed module first wrote something other than what was recorded.
#[derive(Debug, Clone, Serialize)]
pub struct Divergence {
    /// `module.port`.
    pub output: String,
    /// Which of that output's messages (0: the first).
    pub index: usize,
    /// When the recorded one was sent (Unix ns).
    pub recorded_unix_ns: Option<u64>,
    pub recorded: Option<serde_json::Value>,
    pub replayed: Option<serde_json::Value>,
    /// The fields that differ.
    pub fields: Vec<String>,
    /// The recording had lost inputs of the module before this message (see
    /// [`CheckReport::first_unrecorded_input`]): what the module read there is unknown, so the
    /// divergence may be the recording's rather than the module's.
    pub after_unrecorded_inputs: bool,
}

/// Where the recording first lost samples of one of the module's inputs.
#[derive(Debug, Clone, Serialize)]
pub struct UnrecordedInputs {
    /// The input's source port, `/<module>/<port>`.
    pub source: String,
    /// The first sequence number missing...
    pub from_seq: u64,
    /// ...and the last.
    pub to_seq: u64,
    /// They were sent after the recorded sample before them (Unix ns)...
    pub after_unix_ns: u64,
    /// ...and before the next.
    pub before_unix_ns: u64,
}

/// One output's messages, recorded and replayed, compared in order up to the first
/// divergence.
#[derive(Debug, Clone, Serialize)]
pub struct Compared {
    pub recorded: usize,
    pub replayed: usize,
    /// Bit for bit the same.
    pub identical: usize,
    /// Numbers within the tolerance.
    pub within_tolerance: usize,
}

/// What a determinism check found.
#[derive(Debug, Clone, Serialize)]
pub struct CheckReport {
    pub module: String,
    pub kind: String,
    /// Parameters it ran with (the recorded ones, with any changed).
    pub params: BTreeMap<String, ParamValue>,
    pub inputs_fed: u64,
    pub steps: u64,
    /// Outputs the recording missed (sequence numbers skipped): stepped for, not compared.
    pub unrecorded: u64,
    /// Samples of the module's inputs the recording missed (their sequence numbers skipped,
    /// while the module read that input): it read them on the rover, the check could not. A
    /// port with two publishers at once (a replay beside its module) can read as such a gap.
    pub unrecorded_inputs: u64,
    /// The first such gap to end (the recording's samples are read in time order, so a gap is
    /// found at the sample after it); [`Divergence::after_unrecorded_inputs`] counts from the
    /// earliest start of any gap.
    pub first_unrecorded_input: Option<UnrecordedInputs>,
    /// Relative tolerance numbers were compared with (0: bit for bit).
    pub tolerance: f64,
    /// Per output port.
    pub outputs: BTreeMap<String, Compared>,
    pub divergence: Option<Divergence>,
    /// No divergence, and something was compared.
    pub ok: bool,
}

/// A parameter value for `spec`'s parameter `name` from text (`--set name=value`).
pub fn param(spec: &KindSpec, name: &str, text: &str) -> Result<ParamValue, ParamError> {
    let p = spec
        .params
        .iter()
        .find(|p| p.name == name)
        .ok_or_else(|| ParamError::Unknown {
            kind: spec.name.clone(),
            name: name.to_string(),
            known: spec.params.iter().map(|p| p.name.clone()).collect(),
        })?;
    let bad = || ParamError::BadValue {
        name: name.to_string(),
        expected: p.kind,
        text: text.to_string(),
    };
    Ok(match p.kind {
        ParamKind::Float => ParamValue::Float(
            text.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(bad)?,
        ),
        ParamKind::Int => ParamValue::Int(text.parse().map_err(|_| bad())?),
        ParamKind::Bool => ParamValue::Bool(text.parse().map_err(|_| bad())?),
        ParamKind::String => ParamValue::String(text.to_string()),
    })
}

/// Checks `module` of the recording at `path` (a session folder or a file): see the module
/// documentation. `set` changes parameters (`name`, `value` as text); numbers that differ by
/// less than `tolerance` (relative) count as equal.
pub fn check(
    path: &Path,
    module: &str,
    set: &[(String, String)],
    tolerance: f64,
    parse: &crate::ParseNetlist,
    make: &Make<'_>,
) -> Result<CheckReport, CheckError> {
    let files = inputs(path)?;
    let text = recorded_netlist(&files).ok_or(CheckError::NoNetlist)?;
    let netlist = parse(Path::new("recorded.toml"), &text).map_err(CheckError::Netlist)?;
    let subject = Subject::of(&netlist, module, set, tolerance, make)?;
    let mut stepper = subject.build()?;
    if subject.feeds.is_empty() {
        return Err(CheckError::NoInputs {
            module: module.to_string(),
        });
    }
    // Two passes. The first finds the shortest time from an input's send to the module's next
    // output: a sample sent later than that before an output cannot have reached the module
    // for it (it was still on its way from another DNM). The second feeds and steps.
    let (_, summaries) = Merge::open(&files)?;
    let raw_ports = raw_ports(&summaries);
    let module_dnm = dnm_of(&summaries, module);
    let mut tally = Tally::default();
    for feeding in [false, true] {
        let (merge, _) = Merge::open(&files)?;
        Pass::new(
            &subject,
            feeding,
            module_dnm.as_deref(),
            raw_ports.clone(),
            &mut stepper,
            &mut tally,
        )
        .run(merge)?;
    }
    let (outputs, divergence) = compare(module, &subject.spec.outputs, tolerance, &tally);
    let compared: usize = outputs
        .values()
        .map(|c| c.identical + c.within_tolerance)
        .sum();
    if tally.recorded.is_empty() {
        return Err(CheckError::NotRecorded {
            module: module.to_string(),
        });
    }
    Ok(CheckReport {
        module: module.to_string(),
        kind: subject.kind.to_string(),
        params: subject.params,
        inputs_fed: tally.fed,
        steps: tally.steps,
        unrecorded: tally.unrecorded,
        unrecorded_inputs: tally.unrecorded_inputs,
        first_unrecorded_input: tally.first_unrecorded_input,
        tolerance,
        outputs,
        ok: divergence.is_none() && compared > 0,
        divergence,
    })
}

/// Ports whose own bytes the files' summaries list beside their standard message.
fn raw_ports(summaries: &[Option<mcap::Summary>]) -> BTreeSet<String> {
    summaries
        .iter()
        .flatten()
        .flat_map(|s| s.channels.values())
        .filter(|c| crate::is_raw(&c.topic))
        .map(|c| c.topic.trim_end_matches(crate::RAW_SUFFIX).to_string())
        .collect()
}

/// The DNM `module` ran on, from the files' channels (`/<dnm>/<module>/...`).
fn dnm_of(summaries: &[Option<mcap::Summary>], module: &str) -> Option<String> {
    summaries
        .iter()
        .flatten()
        .flat_map(|s| s.channels.values())
        .find_map(|c| {
            let mut parts = c.topic.trim_start_matches('/').split('/');
            let dnm = parts.next()?;
            (parts.next()? == module).then(|| dnm.to_string())
        })
}

/// Inputs kept for rebuilding the module: beyond this, the newest input is taken as read.
const MAX_HISTORY: usize = 64 << 20;
/// Inputs waiting for the module's next recorded step, at most.
const MAX_PENDING: usize = 4096;

/// A sample of one of the module's inputs.
#[derive(Debug, Clone, PartialEq)]
struct Sample {
    /// When it was sent (Unix ns).
    sent: u64,
    /// Which input of the module it is for.
    input: usize,
    seq: u64,
    bytes: Vec<u8>,
}

/// What a step wrote: output, header, bytes.
type Written = (usize, PortHeader, Vec<u8>);

/// The outputs `written` wrote, sorted.
fn ports_of(written: &[Written]) -> Vec<usize> {
    let mut ports: Vec<usize> = written.iter().map(|(o, _, _)| *o).collect();
    ports.sort_unstable();
    ports
}

/// A step of the module's past, to rebuild it.
#[derive(Clone)]
enum Act {
    Task(Option<String>),
    Input(Sample),
    Clear(usize),
    Step(u64),
}

/// The module's last step, to redo it if the next one shows it read an older input.
struct LastStep {
    /// `history` before its inputs.
    history_len: usize,
    inputs: Vec<Sample>,
    at: u64,
    port: usize,
    recorded: Vec<u8>,
    /// The outputs it wrote (sorted).
    wrote: Vec<usize>,
}

/// The module under check: its kind, parameters and links, and how to build it.
struct Subject<'a> {
    module: &'a str,
    kind: &'a str,
    spec: KindSpec,
    /// Parameters it runs with (the recorded ones, with any changed).
    params: BTreeMap<String, ParamValue>,
    make: &'a Make<'a>,
    netlist: &'a Netlist,
    /// Which recorded outputs (`/<module>/<port>`) feed which input, per task.
    feeds: HashMap<String, Vec<(String, usize)>>,
    tolerance: f64,
}

impl<'a> Subject<'a> {
    /// `module` of `netlist`, its parameters changed by `set`.
    fn of(
        netlist: &'a Netlist,
        module: &'a str,
        set: &[(String, String)],
        tolerance: f64,
        make: &'a Make<'a>,
    ) -> Result<Self, CheckError> {
        let decl = netlist
            .modules
            .iter()
            .find(|m| m.name == module)
            .ok_or_else(|| CheckError::UnknownModule {
                module: module.to_string(),
                modules: netlist.modules.iter().map(|m| m.name.clone()).collect(),
            })?;
        let spec = netlist
            .kind_of(module)
            .ok_or_else(|| CheckError::NoKind {
                kind: decl.kind.clone(),
                module: module.to_string(),
            })?
            .clone();
        let mut params = decl.params.clone();
        for (name, value) in set {
            params.insert(name.clone(), param(&spec, name, value)?);
        }
        let mut feeds: HashMap<String, Vec<(String, usize)>> = HashMap::new();
        for (task, t) in &netlist.tasks {
            for l in &t.links {
                if l.to.module != module {
                    continue;
                }
                if let Some(i) = spec.inputs.iter().position(|p| p.name == l.to.port) {
                    feeds
                        .entry(format!("/{}/{}", l.from.module, l.from.port))
                        .or_default()
                        .push((task.clone(), i));
                }
            }
        }
        Ok(Self {
            module,
            kind: &decl.kind,
            spec,
            params,
            make,
            netlist,
            feeds,
            tolerance,
        })
    }

    /// The module, built.
    fn build(&self) -> Result<Box<dyn Stepper>, CheckError> {
        (self.make)(
            self.kind,
            &mut Setup::new(self.module, &self.spec, &self.params),
        )
        .map_err(|e| CheckError::Build {
            module: self.module.to_string(),
            reason: e.to_string(),
        })
    }

    /// The module built afresh and taken through `history`.
    fn rebuild(&self, history: &[Act]) -> Result<(Box<dyn Stepper>, Offline), String> {
        let mut stepper = (self.make)(
            self.kind,
            &mut Setup::new(self.module, &self.spec, &self.params),
        )
        .map_err(|e| e.to_string())?;
        let mut offline = Offline::new(&self.spec, None);
        for act in history {
            match act {
                Act::Task(t) => offline.set_task(t.as_deref()),
                Act::Clear(i) => offline.clear_input(*i),
                Act::Input(s) => offline.set_input(s.input, s.sent, s.seq, s.bytes.clone()),
                Act::Step(at) => {
                    offline
                        .step(stepper.as_mut(), *at)
                        .map_err(|e| e.to_string())?;
                }
            }
        }
        Ok((stepper, offline))
    }

    /// Builds the module afresh, takes it through `history`, gives it `inputs` and steps it at
    /// `now`: what it writes.
    fn attempt<'s>(
        &self,
        history: &[Act],
        inputs: impl Iterator<Item = &'s Sample>,
        now: u64,
    ) -> Result<Vec<Written>, String> {
        let (mut stepper, mut offline) = self.rebuild(history)?;
        for s in inputs {
            offline.set_input(s.input, s.sent, s.seq, s.bytes.clone());
        }
        offline
            .step(stepper.as_mut(), now)
            .map_err(|e| e.to_string())
    }

    /// Whether `replayed`, written on output `port`, is `recorded`: bit for bit, or within the
    /// tolerance.
    fn same(&self, port: usize, replayed: &[u8], recorded: &[u8]) -> bool {
        let value = |x: &[u8]| dnm_netlist::values::decode(&self.spec.outputs[port].message, x);
        replayed == recorded
            || (self.tolerance > 0.0
                && differing(&value(replayed), &value(recorded), self.tolerance).is_empty())
    }

    /// Whether a step that wrote `written` wrote `recorded` on output `port`.
    fn matches(&self, written: &[Written], port: usize, recorded: &[u8]) -> bool {
        written
            .iter()
            .find(|(o, _, _)| *o == port)
            .is_some_and(|(_, _, b)| self.same(port, b, recorded))
    }

    /// The recorded output feeding input `input` under `task`.
    fn source(&self, task: Option<&str>, input: usize) -> Option<&str> {
        self.feeds
            .iter()
            .find(|(_, v)| {
                v.iter()
                    .any(|(vt, vi)| Some(vt.as_str()) == task && *vi == input)
            })
            .map(|(k, _)| k.as_str())
    }

    /// What channel `topic` is to the check (`raw`: a port's own bytes, kept beside its
    /// standard message), and its port's message type; `None`: nothing.
    fn role(
        &self,
        topic: &str,
        raw: bool,
        raw_ports: &BTreeSet<String>,
    ) -> Option<(MessageType, Role)> {
        let port_topic = if raw {
            topic.strip_suffix(crate::RAW_SUFFIX)?
        } else {
            if raw_ports.contains(topic) {
                return None; // its own bytes, beside it, are read instead
            }
            topic
        };
        let mut parts = port_topic.trim_start_matches('/').splitn(3, '/');
        let (_dnm, m, p) = (parts.next()?, parts.next()?, parts.next()?);
        if m == self.module {
            let i = self.spec.outputs.iter().position(|o| o.name == p)?;
            return Some((self.spec.outputs[i].message.clone(), Role::Output(i)));
        }
        let source = format!("/{m}/{p}");
        if !self.feeds.contains_key(&source) {
            return None;
        }
        let message = self
            .netlist
            .kind_of(m)?
            .outputs
            .iter()
            .find(|o| o.name == p)?
            .message
            .clone();
        Some((message, Role::Input(source)))
    }
}

/// A recorded output: sent (Unix ns), sequence number, bytes (None: the recording missed it).
type RecordedOutput = (u64, u64, Option<Vec<u8>>);

/// What the passes over the recording accumulate.
#[derive(Debug, Default)]
struct Tally {
    /// The shortest time from an input's send to the module's next output (the first pass's).
    min_lag: Option<u64>,
    /// Per output: what the module wrote on the rover...
    recorded: BTreeMap<usize, Vec<RecordedOutput>>,
    /// ...and here.
    replayed: BTreeMap<usize, Vec<Vec<u8>>>,
    unrecorded: u64,
    unrecorded_inputs: u64,
    first_unrecorded_input: Option<UnrecordedInputs>,
    /// The earliest time any gap of the inputs began (they are found in the order they end).
    unrecorded_since: Option<u64>,
    fed: u64,
    steps: u64,
}

impl Tally {
    /// Samples of input `source` the recording lost: those after sequence number `last`, sent
    /// at `last_sent`, up to `seq`, sent at `sent`.
    fn lost_inputs(&mut self, source: &str, last: u64, last_sent: u64, seq: u64, sent: u64) {
        self.unrecorded_inputs += seq - last - 1;
        self.unrecorded_since = Some(
            self.unrecorded_since
                .map_or(last_sent, |t| t.min(last_sent)),
        );
        self.first_unrecorded_input
            .get_or_insert_with(|| UnrecordedInputs {
                source: source.to_string(),
                from_seq: last + 1,
                to_seq: seq - 1,
                after_unix_ns: last_sent,
                before_unix_ns: sent,
            });
    }
}

/// A channel's port type, how it is read, and what it is to the check.
struct ChannelUse {
    message: MessageType,
    reading: Reading,
    role: Role,
}

/// What a channel is to the check.
#[derive(Debug, Clone)]
enum Role {
    /// Recorded output `/<module>/<port>` feeding the checked module.
    Input(String),
    /// The checked module's output (index).
    Output(usize),
}

/// The recording's channels, as the check reads them.
struct Channels {
    /// Ports whose own bytes are recorded beside their standard message.
    raw_ports: BTreeSet<String>,
    /// Per (topic, schema): the port's message type and how to read it (None: not ours).
    readings: HashMap<ChannelKey, Option<Rc<ChannelUse>>>,
}

/// A channel's topic and schema name.
type ChannelKey = (Arc<str>, Arc<str>);

impl Channels {
    /// What `m`'s channel is to the check, and how to read it.
    fn use_of(&mut self, m: &Msg, subject: &Subject<'_>) -> Option<Rc<ChannelUse>> {
        let topic = &*m.topic;
        let raw = crate::is_raw(topic);
        if raw {
            self.raw_ports
                .insert(topic.trim_end_matches(crate::RAW_SUFFIX).to_string());
        }
        let raw_ports = &self.raw_ports;
        self.readings
            .entry((m.topic.clone(), m.schema.clone()))
            .or_insert_with(|| {
                let (message, role) = subject.role(topic, raw, raw_ports)?;
                let reading = reading_of(&message, &m.schema, raw).ok()?;
                Some(Rc::new(ChannelUse {
                    message,
                    reading,
                    role,
                }))
            })
            .clone()
    }
}

/// The port bytes of `m`, a message of `channel`.
fn read_port(m: &Msg, channel: &ChannelUse) -> Result<Vec<u8>, CheckError> {
    channel
        .reading
        .read(&channel.message, &m.data)
        .map_err(|source| CheckError::Unreadable {
            topic: m.topic.to_string(),
            sent: m.time,
            source,
        })
}

/// One pass over the recording, in time order. The first (not `feeding`) only measures the
/// shortest lag from an input to the module's next output; the second feeds the module its
/// inputs and steps it at its recorded outputs.
struct Pass<'p, 'a> {
    subject: &'p Subject<'a>,
    feeding: bool,
    /// The first pass's shortest lag (0 in the first pass).
    lag: u64,
    /// The DNM the module ran on: its task switches are the module's.
    module_dnm: Option<&'p str>,
    task: Option<String>,
    stepper: &'p mut Box<dyn Stepper>,
    offline: Offline,
    channels: Channels,
    /// Inputs sent but not yet given to the module.
    pending: VecDeque<Sample>,
    last_input: Option<u64>,
    /// Last sequence number seen per input source, for the samples the recording lost.
    /// (sequence number, send time, whether the module read that input then).
    input_seq: HashMap<Arc<str>, (u64, u64, bool)>,
    /// What the module went through, to rebuild it where what it read is uncertain.
    history: Vec<Act>,
    history_bytes: usize,
    last_step: Option<LastStep>,
    /// Whether `history` is kept (not once it grew past [`MAX_HISTORY`]).
    keeping: bool,
    tally: &'p mut Tally,
}

impl<'p, 'a> Pass<'p, 'a> {
    fn new(
        subject: &'p Subject<'a>,
        feeding: bool,
        module_dnm: Option<&'p str>,
        raw_ports: BTreeSet<String>,
        stepper: &'p mut Box<dyn Stepper>,
        tally: &'p mut Tally,
    ) -> Self {
        let task = subject.netlist.default_task.clone();
        Self {
            subject,
            feeding,
            lag: tally.min_lag.unwrap_or(0),
            module_dnm,
            offline: Offline::new(&subject.spec, task.as_deref()),
            history: vec![Act::Task(task.clone())],
            task,
            stepper,
            channels: Channels {
                raw_ports,
                readings: HashMap::new(),
            },
            pending: VecDeque::new(),
            last_input: None,
            input_seq: HashMap::new(),
            history_bytes: 0,
            last_step: None,
            keeping: true,
            tally,
        }
    }

    fn run(mut self, mut merge: Merge) -> Result<(), CheckError> {
        while let Some(m) = merge.next() {
            if m.topic.ends_with("/_switches") {
                self.on_switch(&m);
                continue;
            }
            let Some(channel) = self.channels.use_of(&m, self.subject) else {
                continue;
            };
            match &channel.role {
                Role::Input(source) => self.on_input(&m, source, &channel)?,
                Role::Output(i) => self.on_output(&m, *i, &channel)?,
            }
        }
        Ok(())
    }

    /// Remembers `act` of the module's past, while it is kept.
    fn remember(&mut self, act: Act) {
        if self.keeping {
            self.history.push(act);
        }
    }

    /// A task switch of the module's DNM.
    fn on_switch(&mut self, m: &Msg) {
        let Some(dnm) = self.module_dnm else {
            return;
        };
        if *m.topic != format!("/{dnm}/_switches") {
            return;
        }
        let Ok(v) = serde_json::from_slice::<serde_json::Value>(&m.data) else {
            return;
        };
        let Some(to) = v["to"].as_str() else {
            return;
        };
        let old = self.task.replace(to.to_string());
        self.offline.set_task(self.task.as_deref());
        self.remember(Act::Task(self.task.clone()));
        // An input whose source the switch changed shows nothing from before it.
        for i in 0..self.subject.spec.inputs.len() {
            if self.subject.source(old.as_deref(), i)
                != self.subject.source(self.task.as_deref(), i)
            {
                self.offline.clear_input(i);
                self.remember(Act::Clear(i));
            }
        }
        self.last_step = None;
    }

    /// A sample of recorded output `source`, which feeds the module.
    fn on_input(&mut self, m: &Msg, source: &str, channel: &ChannelUse) -> Result<(), CheckError> {
        let Some(targets) = self.subject.feeds.get(source) else {
            return Ok(());
        };
        let task = self.task.as_deref();
        let seq = u64::from(m.seq);
        let read = targets.iter().any(|(t, _)| task == Some(t.as_str()));
        // A restarted source counts from 0 again: only a jump forward is a loss.
        // Samples lost while the module was not reading the input do not count.
        if let Some((last, last_sent, was_read)) =
            self.input_seq.insert(m.topic.clone(), (seq, m.time, read))
            && seq > last + 1
            && read
            && was_read
            && self.feeding
        {
            self.tally.lost_inputs(source, last, last_sent, seq, m.time);
        }
        for (t, i) in targets {
            if task != Some(t.as_str()) {
                continue;
            }
            self.last_input = Some(m.time);
            if self.feeding {
                let bytes = read_port(m, channel)?;
                self.pending.push_back(Sample {
                    sent: m.time,
                    input: *i,
                    seq,
                    bytes,
                });
                // A module that stopped stepping (not linked, idle) reads only the newest:
                // older inputs need not wait.
                if self.pending.len() > MAX_PENDING {
                    self.pending.pop_front();
                }
            }
        }
        Ok(())
    }

    /// A recorded message of the module's output `port`.
    fn on_output(&mut self, m: &Msg, port: usize, channel: &ChannelUse) -> Result<(), CheckError> {
        if !self.feeding {
            if let Some(t) = self.last_input {
                let gap = m.time.saturating_sub(t);
                self.tally.min_lag = Some(self.tally.min_lag.map_or(gap, |l| l.min(gap)));
            }
            return Ok(());
        }
        let bytes = read_port(m, channel)?;
        // A recorded step: unless an earlier step already wrote this output (a step that wrote
        // several), step on the inputs that had reached it. Outputs the recording missed (its
        // sequence numbers jump): the module stepped for them too, one pending input each.
        self.step_missed(m, port)?;
        let done = self.tally.recorded.get(&port).map_or(0, Vec::len);
        let made = self.tally.replayed.get(&port).map_or(0, Vec::len);
        if made <= done {
            self.step_recorded(m.time, port, &bytes)?;
        }
        self.tally
            .recorded
            .entry(port)
            .or_default()
            .push((m.time, u64::from(m.seq), Some(bytes)));
        Ok(())
    }

    /// Inputs pending that had reached the module at `now`.
    fn eligible(&self, now: u64) -> usize {
        self.pending
            .iter()
            .take_while(|s| s.sent.saturating_add(self.lag) <= now)
            .count()
    }

    /// Gives the module `s` (and remembers it, to rebuild the module).
    fn give(&mut self, s: Sample) {
        if self.keeping {
            self.history_bytes += s.bytes.len();
            self.history.push(Act::Input(s.clone()));
        }
        self.offline.set_input(s.input, s.sent, s.seq, s.bytes);
        self.tally.fed += 1;
    }

    /// Steps the module at `now`: what it wrote.
    fn step(&mut self, now: u64) -> Result<Vec<Written>, CheckError> {
        self.tally.steps += 1;
        self.remember(Act::Step(now));
        self.offline
            .step(self.stepper.as_mut(), now)
            .map_err(|source| CheckError::Step {
                module: self.subject.module.to_string(),
                at: now,
                source,
            })
    }

    /// Steps the module for the outputs on `port` the recording missed before `m`.
    fn step_missed(&mut self, m: &Msg, port: usize) -> Result<(), CheckError> {
        let missed = self
            .tally
            .recorded
            .get(&port)
            .and_then(|r| r.last())
            .map_or(0, |(_, seq, _)| u64::from(m.seq).saturating_sub(seq + 1))
            .min(1024);
        let mut ready = self.eligible(m.time) as u64;
        for j in 0..missed {
            // One input each, leaving at least one for the recorded step.
            if ready > missed - j
                && let Some(s) = self.pending.pop_front()
            {
                ready -= 1;
                self.give(s);
            }
            let written = self.step(m.time)?;
            for (o, _, b) in written {
                self.tally.replayed.entry(o).or_default().push(b);
            }
            self.tally
                .recorded
                .entry(port)
                .or_default()
                .push((m.time, u64::from(m.seq), None));
            // Its outputs are not the recorded step's: nothing to redo across.
            self.last_step = None;
            self.tally.unrecorded += 1;
        }
        Ok(())
    }

    /// How many of the inputs pending at `now` the step that wrote `recorded` on `port` read.
    fn choose_inputs(&self, now: u64, port: usize, recorded: &[u8]) -> usize {
        let eligible = self.eligible(now);
        // Several inputs arrived since its last step: it read the newest, or (a burst, e.g.
        // the samples queued while it started) an older one. The one that reproduces the
        // recorded output is the one it read; the module is rebuilt from the steps so far to
        // try each.
        if eligible > 1 && self.keeping {
            // The newest first: what a module that wakes on input reads.
            for c in (1..=eligible).rev() {
                let tried = self
                    .subject
                    .attempt(&self.history, self.pending.iter().take(c), now);
                if tried.is_ok_and(|w| self.subject.matches(&w, port, recorded)) {
                    return c;
                }
            }
        }
        eligible
    }

    /// The module's step at `now` that wrote `recorded` on `port`.
    fn step_recorded(&mut self, now: u64, port: usize, recorded: &[u8]) -> Result<(), CheckError> {
        let take = self.choose_inputs(now, port, recorded);
        let mut before = self.history.len();
        let mut given = Vec::new();
        for _ in 0..take {
            if let Some(s) = self.pending.pop_front() {
                self.give(s.clone());
                given.push(s);
            }
        }
        let mut written = self.step(now)?;
        // Not what it wrote: perhaps the step before read an older input than the newest (all
        // of them gave the same output then). Redo both steps, that one reading fewer, when
        // that reproduces both outputs.
        if !self.subject.matches(&written, port, recorded)
            && self.keeping
            && let Some(last) = &self.last_step
            && last.inputs.len() > 1
            && let Some(redo) = self.find_redo(last, &given, now, port, recorded)
            // The redone step must have written the same outputs, so that the entries it
            // replaces are its own.
            && ports_of(&redo.earlier) == last.wrote
            && let Some(redone) = self.apply_redo(redo, now)
        {
            (before, given, written) = redone;
        }
        self.last_step = self.keeping.then(|| LastStep {
            history_len: before,
            inputs: given,
            at: now,
            port,
            recorded: recorded.to_vec(),
            wrote: ports_of(&written),
        });
        if self.history_bytes > MAX_HISTORY && self.keeping {
            // Too much to keep: from here on the newest input is taken as read.
            self.keeping = false;
            self.history.clear();
            self.history.shrink_to_fit();
        }
        for (o, _, b) in written {
            self.tally.replayed.entry(o).or_default().push(b);
        }
        Ok(())
    }

    /// The last step redone reading fewer of its inputs, and this one (at `now`, which read
    /// `given`) then reading some of the rest, such that both write what was recorded.
    fn find_redo(
        &self,
        last: &LastStep,
        given: &[Sample],
        now: u64,
        port: usize,
        recorded: &[u8],
    ) -> Option<Redo> {
        let subject = self.subject;
        let base = &self.history[..last.history_len];
        for c in (1..last.inputs.len()).rev() {
            let Ok(earlier) = subject.attempt(base, last.inputs[..c].iter(), last.at) else {
                continue;
            };
            if !subject.matches(&earlier, last.port, &last.recorded) {
                continue;
            }
            let mut history: Vec<Act> = base.to_vec();
            for s in &last.inputs[..c] {
                history.push(Act::Input(s.clone()));
            }
            history.push(Act::Step(last.at));
            // This step then read some of the rest: the newest first.
            let rest: Vec<Sample> = last.inputs[c..].iter().chain(given).cloned().collect();
            for read in (1..=rest.len()).rev() {
                let Ok(written) = subject.attempt(&history, rest[..read].iter(), now) else {
                    continue;
                };
                if subject.matches(&written, port, recorded) {
                    return Some(Redo {
                        history,
                        earlier,
                        written,
                        rest,
                        read,
                    });
                }
            }
        }
        None
    }

    /// Takes the module through `redo` (this step at `now`): its history, inputs pending and
    /// outputs as redone. Returns this step's history length before its inputs, the inputs it
    /// read and what it wrote; `None` (nothing changed) if the module cannot be rebuilt so.
    fn apply_redo(&mut self, redo: Redo, now: u64) -> Option<(usize, Vec<Sample>, Vec<Written>)> {
        let Redo {
            mut history,
            earlier,
            written,
            mut rest,
            read,
        } = redo;
        let before = history.len();
        for s in &rest[..read] {
            history.push(Act::Input(s.clone()));
        }
        history.push(Act::Step(now));
        let (stepper, offline) = self.subject.rebuild(&history).ok()?;
        // What it had not read yet waits for its next steps.
        let unread = rest.split_off(read);
        self.tally.fed -= unread.len() as u64;
        for s in unread.into_iter().rev() {
            self.pending.push_front(s);
        }
        self.history = history;
        *self.stepper = stepper;
        self.offline = offline;
        // The earlier step's outputs, as redone.
        for (o, _, b) in earlier {
            if let Some(v) = self.tally.replayed.get_mut(&o)
                && let Some(x) = v.last_mut()
            {
                *x = b;
            }
        }
        Some((before, rest, written))
    }
}

/// The last step and the current one, redone (see [`Pass::find_redo`]).
struct Redo {
    /// The history up to and including the last step, redone.
    history: Vec<Act>,
    /// What the last step wrote, redone.
    earlier: Vec<Written>,
    /// What the current step wrote, redone.
    written: Vec<Written>,
    /// The last step's inputs it no longer reads, then the current step's.
    rest: Vec<Sample>,
    /// How many of `rest` the current step reads.
    read: usize,
}

/// Compares each output's recorded and replayed messages in order: per output (by name), the
/// counts; and the earliest divergence of any.
fn compare(
    module: &str,
    outputs: &[PortSpec],
    tolerance: f64,
    tally: &Tally,
) -> (BTreeMap<String, Compared>, Option<Divergence>) {
    let mut compared = BTreeMap::new();
    let mut divergence: Option<Divergence> = None;
    for (i, port) in outputs.iter().enumerate() {
        let rec = tally
            .recorded
            .get(&i)
            .map(Vec::as_slice)
            .unwrap_or_default();
        let rep = tally
            .replayed
            .get(&i)
            .map(Vec::as_slice)
            .unwrap_or_default();
        let value = |b: &[u8]| dnm_netlist::values::decode(&port.message, b);
        let mut identical = 0;
        let same = rec
            .iter()
            .zip(rep)
            .take_while(|((_, _, a), b)| {
                let Some(a) = a else {
                    return true; // not recorded: nothing to compare with
                };
                if a == *b {
                    identical += 1;
                    return true;
                }
                tolerance > 0.0 && differing(&value(a), &value(b), tolerance).is_empty()
            })
            .count();
        let missing = rec
            .iter()
            .take(same)
            .filter(|(_, _, a)| a.is_none())
            .count();
        compared.insert(
            port.name.clone(),
            Compared {
                recorded: rec.len(),
                replayed: rep.len(),
                identical,
                within_tolerance: same - identical - missing,
            },
        );
        // What it wrote after the recording stopped is not a divergence; less than recorded is.
        if same < rec.len() {
            let (r, p) = (rec.get(same), rep.get(same));
            let fields = match (r, p) {
                (Some((_, _, Some(a))), Some(b)) => differing(&value(a), &value(b), tolerance),
                _ => Vec::new(),
            };
            let d = Divergence {
                output: format!("{module}.{}", port.name),
                index: same,
                recorded_unix_ns: r.map(|(t, _, _)| *t),
                recorded: r.and_then(|(_, _, a)| a.as_deref().map(value)),
                replayed: p.map(|b| value(b)),
                fields,
                after_unrecorded_inputs: tally
                    .unrecorded_since
                    .is_some_and(|since| r.is_none_or(|(t, _, _)| since < *t)),
            };
            let earlier = match (&divergence, d.recorded_unix_ns) {
                (None, _) => true,
                (Some(prev), Some(t)) => prev.recorded_unix_ns.is_none_or(|p| t < p),
                (Some(_), None) => false,
            };
            if earlier {
                divergence = Some(d);
            }
        }
    }
    (compared, divergence)
}

/// The fields (dotted paths) where two decoded messages differ: numbers by more than
/// `tolerance` relative to the larger (integers exactly).
fn differing(a: &serde_json::Value, b: &serde_json::Value, tolerance: f64) -> Vec<String> {
    fn walk(
        path: &str,
        a: &serde_json::Value,
        b: &serde_json::Value,
        tol: f64,
        out: &mut Vec<String>,
    ) {
        use serde_json::Value::{Array, Number, Object};
        match (a, b) {
            (Number(x), Number(y)) if x.is_f64() || y.is_f64() => {
                let (x, y) = (
                    x.as_f64().unwrap_or(f64::NAN),
                    y.as_f64().unwrap_or(f64::NAN),
                );
                let close = x == y || (x - y).abs() <= tol * x.abs().max(y.abs());
                if !close {
                    out.push(path.to_string());
                }
            }
            (Object(x), Object(y)) => {
                for (k, v) in x {
                    let p = if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    };
                    match y.get(k) {
                        Some(w) => walk(&p, v, w, tol, out),
                        None => out.push(p),
                    }
                }
            }
            (Array(x), Array(y)) if x.len() == y.len() => {
                for (i, (v, w)) in x.iter().zip(y).enumerate() {
                    walk(&format!("{path}[{i}]"), v, w, tol, out);
                }
            }
            _ if a != b => out.push(if path.is_empty() {
                "(the message)".into()
            } else {
                path.to_string()
            }),
            _ => {}
        }
    }
    let mut out = Vec::new();
    walk("", a, b, tolerance, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use dnm_module::msg::{Message, Tick};
    use dnm_netlist::{ParamSpec, Trigger};
    use serde_json::json;

    fn sorted(mut v: Vec<String>) -> Vec<String> {
        v.sort();
        v
    }

    #[test]
    fn differing_names_the_fields_beyond_the_tolerance() {
        let a = json!({"x": 1.0, "y": 2.0, "n": 3, "v": [1.0, 2.0], "s": "a", "gone": 1});
        let b = json!({"x": 1.000_000_001, "y": 2.5, "n": 4, "v": [1.0, 2.1], "s": "a"});
        assert_eq!(sorted(differing(&a, &b, 1e-6)), ["gone", "n", "v[1]", "y"]);
        // Bit for bit: the small difference counts too.
        assert_eq!(
            sorted(differing(&a, &b, 0.0)),
            ["gone", "n", "v[1]", "x", "y"]
        );
        // Integers compare exactly whatever the tolerance.
        assert_eq!(
            differing(&json!({"n": 100}), &json!({"n": 101}), 0.5),
            ["n"]
        );
        assert!(differing(&a, &a, 0.0).is_empty());
        assert_eq!(
            differing(&json!([1.0]), &json!([1.0, 2.0]), 0.1),
            ["(the message)"]
        );
        assert_eq!(
            differing(&json!({"p": {"q": "a"}}), &json!({"p": {"q": "b"}}), 0.1),
            ["p.q"]
        );
    }

    fn spec() -> KindSpec {
        let p = |name: &str, kind| ParamSpec {
            name: name.into(),
            kind,
            default: None,
            doc: String::new(),
        };
        KindSpec {
            name: "odometry".into(),
            summary: String::new(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            params: vec![
                p("radius", ParamKind::Float),
                p("count", ParamKind::Int),
                p("on", ParamKind::Bool),
                p("frame", ParamKind::String),
            ],
            trigger: Trigger::OnInput,
        }
    }

    #[test]
    fn a_parameter_is_read_as_its_kind() {
        let s = spec();
        assert_eq!(param(&s, "radius", "0.16"), Ok(ParamValue::Float(0.16)));
        assert_eq!(param(&s, "count", "-3"), Ok(ParamValue::Int(-3)));
        assert_eq!(param(&s, "on", "true"), Ok(ParamValue::Bool(true)));
        assert_eq!(
            param(&s, "frame", "base link"),
            Ok(ParamValue::String("base link".into()))
        );
    }

    #[test]
    fn a_parameter_that_is_not_one_says_what_it_takes() {
        let s = spec();
        let e = param(&s, "wheel", "1").unwrap_err();
        assert!(matches!(&e, ParamError::Unknown { name, .. } if name == "wheel"));
        assert_eq!(
            e.to_string(),
            "kind `odometry` has no parameter `wheel`; its parameters: radius, count, on, frame"
        );
        for (name, text, what) in [
            ("radius", "fast", "a number"),
            ("radius", "inf", "a number"),
            ("radius", "NaN", "a number"),
            ("count", "1.5", "an integer"),
            ("on", "yes", "true or false"),
        ] {
            let e = param(&s, name, text).unwrap_err();
            assert_eq!(
                e.to_string(),
                format!("`{name}` is {what}: `{text}` is not one")
            );
        }
    }

    #[test]
    fn lost_inputs_are_counted_from_the_earliest_gap() {
        let mut t = Tally::default();
        t.lost_inputs("/enc/ticks", 10, 1_000, 14, 2_000);
        t.lost_inputs("/imu/data", 3, 500, 5, 2_500);
        assert_eq!(t.unrecorded_inputs, 3 + 1);
        assert_eq!(t.unrecorded_since, Some(500));
        let first = t.first_unrecorded_input.unwrap();
        assert_eq!(first.source, "/enc/ticks");
        assert_eq!((first.from_seq, first.to_seq), (11, 13));
        assert_eq!((first.after_unix_ns, first.before_unix_ns), (1_000, 2_000));
    }

    fn tick(seq: u64) -> Vec<u8> {
        bytemuck::bytes_of(&Tick { origin: 1, seq }).to_vec()
    }

    fn outputs(names: &[&str]) -> Vec<PortSpec> {
        names
            .iter()
            .map(|n| PortSpec {
                name: (*n).into(),
                message: Tick::message_type(),
            })
            .collect()
    }

    #[test]
    fn outputs_that_match_are_counted_and_not_a_divergence() {
        let mut t = Tally::default();
        t.recorded.insert(
            0,
            vec![
                (10, 0, Some(tick(0))),
                (20, 1, None),
                (30, 2, Some(tick(2))),
            ],
        );
        // More than recorded: what it wrote after the recording stopped.
        t.replayed
            .insert(0, vec![tick(0), tick(1), tick(2), tick(3)]);
        let (c, d) = compare("m", &outputs(&["out"]), 0.0, &t);
        assert!(d.is_none(), "{d:?}");
        let c = &c["out"];
        assert_eq!((c.recorded, c.replayed), (3, 4));
        assert_eq!((c.identical, c.within_tolerance), (2, 0));
    }

    #[test]
    fn the_earliest_divergence_is_reported_with_its_fields() {
        let mut t = Tally::default();
        t.recorded
            .insert(0, vec![(10, 0, Some(tick(0))), (40, 1, Some(tick(1)))]);
        t.replayed.insert(0, vec![tick(0), tick(7)]);
        t.recorded.insert(1, vec![(20, 0, Some(tick(0)))]);
        t.replayed.insert(1, vec![tick(5)]);
        t.unrecorded_since = Some(30);
        let (c, d) = compare("m", &outputs(&["a", "b"]), 0.0, &t);
        assert_eq!((c["a"].identical, c["b"].identical), (1, 0));
        let d = d.unwrap();
        assert_eq!((d.output.as_str(), d.index), ("m.b", 0));
        assert_eq!(d.recorded_unix_ns, Some(20));
        assert_eq!(d.fields, ["seq"]);
        assert_eq!(d.recorded.unwrap()["seq"], 0);
        assert_eq!(d.replayed.unwrap()["seq"], 5);
        // Inputs were lost only after it.
        assert!(!d.after_unrecorded_inputs);
    }

    #[test]
    fn fewer_outputs_than_recorded_is_a_divergence() {
        let mut t = Tally::default();
        t.recorded
            .insert(0, vec![(10, 0, Some(tick(0))), (40, 1, Some(tick(1)))]);
        t.replayed.insert(0, vec![tick(0)]);
        t.unrecorded_since = Some(30);
        let (_, d) = compare("m", &outputs(&["out"]), 0.0, &t);
        let d = d.unwrap();
        assert_eq!((d.index, d.recorded_unix_ns), (1, Some(40)));
        assert!(d.replayed.is_none() && d.fields.is_empty());
        assert!(d.after_unrecorded_inputs);
    }
}
