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

use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use std::sync::Arc;

use dnm_module::protocol::PortHeader;
use dnm_module::{Offline, Setup, Stepper};
use dnm_netlist::{KindSpec, MessageType, ParamKind, ParamValue};
use serde::Serialize;

use crate::replay::{Merge, Reading, inputs, reading_of, recorded_netlist};

/// Builds a module of a kind (by name) from its setup: the module registry's `make`.
pub type Make<'a> = dyn Fn(&str, &mut Setup<'_>) -> Result<Box<dyn Stepper>, String> + 'a;

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
pub fn param(spec: &KindSpec, name: &str, text: &str) -> Result<ParamValue, String> {
    let p = spec.params.iter().find(|p| p.name == name).ok_or_else(|| {
        let names: Vec<&str> = spec.params.iter().map(|p| p.name.as_str()).collect();
        format!(
            "kind `{}` has no parameter `{name}`; its parameters: {}",
            spec.name,
            names.join(", ")
        )
    })?;
    let bad = |what: &str| format!("`{name}` is {what}: `{text}` is not one");
    Ok(match p.kind {
        ParamKind::Float => ParamValue::Float(
            text.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| bad("a number"))?,
        ),
        ParamKind::Int => ParamValue::Int(text.parse().map_err(|_| bad("an integer"))?),
        ParamKind::Bool => ParamValue::Bool(text.parse().map_err(|_| bad("true or false"))?),
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
    parse: &crate::ParseNetlist<'_>,
    make: &Make<'_>,
) -> Result<CheckReport, String> {
    let files = inputs(path)?;
    let text = recorded_netlist(&files).ok_or("the recording holds no netlist")?;
    let netlist = parse(Path::new("recorded.toml"), &text)?;
    let decl = netlist
        .modules
        .iter()
        .find(|m| m.name == module)
        .ok_or_else(|| {
            let names: Vec<&str> = netlist.modules.iter().map(|m| m.name.as_str()).collect();
            format!(
                "the recorded netlist has no module `{module}`; its modules: {}",
                names.join(", ")
            )
        })?;
    let spec = netlist
        .kind_of(module)
        .ok_or_else(|| format!("no kind `{}` for `{module}`", decl.kind))?
        .clone();
    let mut params = decl.params.clone();
    for (name, value) in set {
        params.insert(name.clone(), param(&spec, name, value)?);
    }
    let mut stepper = make(&decl.kind, &mut Setup::new(module, &spec, &params))
        .map_err(|e| format!("building `{module}`: {e}"))?;
    // Which recorded outputs feed which input, per task.
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
    if feeds.is_empty() {
        return Err(format!(
            "`{module}` has no input linked in any task: nothing to feed it"
        ));
    }
    // Two passes. The first finds the shortest time from an input's send to the module's next
    // output: a sample sent later than that before an output cannot have reached the module
    // for it (it was still on its way from another DNM). The second feeds and steps.
    let (_, summaries) = Merge::open(&files)?;
    let raw_ports: std::collections::BTreeSet<String> = summaries
        .iter()
        .flatten()
        .flat_map(|s| s.channels.values())
        .filter(|c| crate::is_raw(&c.topic))
        .map(|c| c.topic.trim_end_matches(crate::RAW_SUFFIX).to_string())
        .collect();
    let module_dnm: Option<String> = summaries
        .iter()
        .flatten()
        .flat_map(|s| s.channels.values())
        .find_map(|c| {
            let mut parts = c.topic.trim_start_matches('/').split('/');
            let dnm = parts.next()?;
            (parts.next()? == module).then(|| dnm.to_string())
        });
    let mut min_lag: Option<u64> = None;
    // Per output: (sent, sequence, bytes; None where the recording missed it).
    let mut recorded: BTreeMap<usize, Vec<RecordedOutput>> = BTreeMap::new();
    let mut unrecorded = 0u64;
    let mut unrecorded_inputs = 0u64;
    let mut first_unrecorded_input: Option<UnrecordedInputs> = None;
    // The earliest time any gap of the inputs began (they are found in the order they end).
    let mut unrecorded_since: Option<u64> = None;
    let mut replayed: BTreeMap<usize, Vec<Vec<u8>>> = BTreeMap::new();
    let (mut fed, mut steps) = (0u64, 0u64);
    for pass in 0..2 {
        let feeding = pass == 1;
        let lag = min_lag.unwrap_or(0);
        let mut task = netlist.default_task.clone();
        let mut offline = Offline::new(&spec, task.as_deref());
        let (mut merge, _) = Merge::open(&files)?;
        let mut raw_ports = raw_ports.clone();
        // Per (topic, schema): the port's message type and how to read it (None: not ours).
        let mut readings: HashMap<(Arc<str>, Arc<str>), Option<ChannelUse>> = HashMap::new();
        // Inputs sent but not yet given to the module: (sent, input, seq, bytes).
        let mut pending: std::collections::VecDeque<(u64, usize, u64, Vec<u8>)> =
            std::collections::VecDeque::new();
        let mut last_input: Option<u64> = None;
        // Last sequence number seen per input source, for the samples the recording lost.
        // (sequence number, send time, whether the module read that input then).
        let mut input_seq: HashMap<Arc<str>, (u64, u64, bool)> = HashMap::new();
        // What the module went through, to rebuild it where what it read is uncertain.
        let mut history: Vec<Act> = vec![Act::Task(task.clone())];
        let mut history_bytes = 0usize;
        let mut last_step: Option<LastStep> = None;
        let mut keeping = true;
        while let Some(m) = merge.next() {
            let topic = &*m.topic;
            if topic.ends_with("/_switches") {
                if module_dnm
                    .as_deref()
                    .is_some_and(|d| topic == format!("/{d}/_switches"))
                    && let Ok(v) = serde_json::from_slice::<serde_json::Value>(&m.data)
                    && let Some(to) = v["to"].as_str()
                {
                    let old = task.replace(to.to_string());
                    offline.set_task(task.as_deref());
                    if keeping {
                        history.push(Act::Task(task.clone()));
                    }
                    // An input whose source the switch changed shows nothing from before it.
                    for i in 0..spec.inputs.len() {
                        let source = |t: &Option<String>| {
                            feeds
                                .iter()
                                .find(|(_, v)| {
                                    v.iter().any(|(vt, vi)| Some(vt) == t.as_ref() && *vi == i)
                                })
                                .map(|(k, _)| k.clone())
                        };
                        if source(&old) != source(&task) {
                            offline.clear_input(i);
                            if keeping {
                                history.push(Act::Clear(i));
                            }
                        }
                    }
                    last_step = None;
                }
                continue;
            }
            let raw = crate::is_raw(topic);
            if raw {
                raw_ports.insert(topic.trim_end_matches(crate::RAW_SUFFIX).to_string());
            }
            let key = (m.topic.clone(), m.schema.clone());
            if !readings.contains_key(&key) {
                let r = role(topic, raw, &raw_ports, module, &spec, &feeds, &netlist).and_then(
                    |(message, role)| {
                        let reading = reading_of(&message, &m.schema, raw).ok()?;
                        Some((message, reading, role))
                    },
                );
                readings.insert(key.clone(), r);
            }
            let Some(Some((message, reading, role))) = readings.get(&key) else {
                continue;
            };
            match role {
                Role::Input(source) => {
                    let Some(targets) = feeds.get(source) else {
                        continue;
                    };
                    let seq = u64::from(m.seq);
                    let read = targets
                        .iter()
                        .any(|(t, _)| task.as_deref() == Some(t.as_str()));
                    // A restarted source counts from 0 again: only a jump forward is a loss.
                    // Samples lost while the module was not reading the input do not count.
                    if let Some((last, last_time, was_read)) =
                        input_seq.insert(m.topic.clone(), (seq, m.time, read))
                        && seq > last + 1
                        && read
                        && was_read
                        && feeding
                    {
                        unrecorded_inputs += seq - last - 1;
                        unrecorded_since =
                            Some(unrecorded_since.map_or(last_time, |t| t.min(last_time)));
                        first_unrecorded_input.get_or_insert_with(|| UnrecordedInputs {
                            source: source.clone(),
                            from_seq: last + 1,
                            to_seq: seq - 1,
                            after_unix_ns: last_time,
                            before_unix_ns: m.time,
                        });
                    }
                    for (t, i) in targets {
                        if task.as_deref() != Some(t.as_str()) {
                            continue;
                        }
                        last_input = Some(m.time);
                        if feeding {
                            let bytes = reading.read(message, &m.data).map_err(|e| {
                                format!("{topic}: the message sent at {} ns: {e}", m.time)
                            })?;
                            pending.push_back((m.time, *i, u64::from(m.seq), bytes));
                            // A module that stopped stepping (not linked, idle) reads only the
                            // newest: older inputs need not wait.
                            if pending.len() > MAX_PENDING {
                                pending.pop_front();
                            }
                        }
                    }
                }
                Role::Output(i) => {
                    if !feeding {
                        if let Some(t) = last_input {
                            let gap = m.time.saturating_sub(t);
                            min_lag = Some(min_lag.map_or(gap, |l| l.min(gap)));
                        }
                        continue;
                    }
                    let bytes = reading
                        .read(message, &m.data)
                        .map_err(|e| format!("{topic}: the message sent at {} ns: {e}", m.time))?;
                    // A recorded step: unless an earlier step already wrote this output (a
                    // step that wrote several), step on the inputs that had reached it.
                    // Outputs the recording missed (its sequence numbers jump): the module
                    // stepped for them too, one pending input each.
                    let missed = recorded
                        .get(i)
                        .and_then(|r| r.last())
                        .map_or(0, |(_, seq, _)| u64::from(m.seq).saturating_sub(seq + 1))
                        .min(1024);
                    let mut ready = pending
                        .iter()
                        .take_while(|(t, ..)| t.saturating_add(lag) <= m.time)
                        .count() as u64;
                    for j in 0..missed {
                        // One input each, leaving at least one for the recorded step.
                        if ready > missed - j
                            && let Some((t, input, seq, b)) = pending.pop_front()
                        {
                            ready -= 1;
                            if keeping {
                                history_bytes += b.len();
                                history.push(Act::Input(input, t, seq, b.clone()));
                            }
                            offline.set_input(input, t, seq, b);
                            fed += 1;
                        }
                        steps += 1;
                        if keeping {
                            history.push(Act::Step(m.time));
                        }
                        let written = offline.step(stepper.as_mut(), m.time).map_err(|e| {
                            format!("`{module}` failed to step at {} ns: {e}", m.time)
                        })?;
                        for (o, _, b) in written {
                            replayed.entry(o).or_default().push(b);
                        }
                        recorded
                            .entry(*i)
                            .or_default()
                            .push((m.time, u64::from(m.seq), None));
                        // Its outputs are not the recorded step's: nothing to redo across.
                        last_step = None;
                        unrecorded += 1;
                    }
                    let done = recorded.get(i).map_or(0, Vec::len);
                    let made = replayed.get(i).map_or(0, Vec::len);
                    if made <= done {
                        let eligible = pending
                            .iter()
                            .take_while(|(t, ..)| t.saturating_add(lag) <= m.time)
                            .count();
                        // Several inputs arrived since its last step: it read the newest, or
                        // (a burst, e.g. the samples queued while it started) an older one. The
                        // one that reproduces the recorded output is the one it read; the
                        // module is rebuilt from the steps so far to try each.
                        let mut take = eligible;
                        if eligible > 1 && keeping {
                            // The newest first: what a module that wakes on input reads.
                            for c in (1..=eligible).rev() {
                                let tried = attempt(
                                    &history,
                                    pending.iter().take(c),
                                    m.time,
                                    &decl.kind,
                                    &spec,
                                    &params,
                                    module,
                                    make,
                                );
                                let same = tried.ok().and_then(|w| {
                                    let b = w.into_iter().find(|(o, _, _)| o == i)?.2;
                                    let value = |x: &[u8]| {
                                        dnm_netlist::values::decode(&spec.outputs[*i].message, x)
                                    };
                                    Some(
                                        b == bytes
                                            || (tolerance > 0.0
                                                && differing(
                                                    &value(&b),
                                                    &value(&bytes),
                                                    tolerance,
                                                )
                                                .is_empty()),
                                    )
                                });
                                if same == Some(true) {
                                    take = c;
                                    break;
                                }
                            }
                        }
                        let mut before = history.len();
                        let mut given = Vec::new();
                        for _ in 0..take {
                            if let Some((t, input, seq, b)) = pending.pop_front() {
                                if keeping {
                                    history_bytes += b.len();
                                    history.push(Act::Input(input, t, seq, b.clone()));
                                }
                                offline.set_input(input, t, seq, b.clone());
                                given.push((t, input, seq, b));
                                fed += 1;
                            }
                        }
                        steps += 1;
                        if keeping {
                            history.push(Act::Step(m.time));
                        }
                        let written = offline.step(stepper.as_mut(), m.time).map_err(|e| {
                            format!("`{module}` failed to step at {} ns: {e}", m.time)
                        })?;
                        let matches = |w: &[(usize, PortHeader, Vec<u8>)],
                                       port: usize,
                                       want: &[u8]| {
                            w.iter()
                                .find(|(o, _, _)| *o == port)
                                .is_some_and(|(_, _, b)| {
                                    let value = |x: &[u8]| {
                                        dnm_netlist::values::decode(&spec.outputs[port].message, x)
                                    };
                                    b == want
                                        || (tolerance > 0.0
                                            && differing(&value(b), &value(want), tolerance)
                                                .is_empty())
                                })
                        };
                        let mut written = written;
                        // Not what it wrote: perhaps the step before read an older input than
                        // the newest (all of them gave the same output then). Redo both steps,
                        // that one reading fewer, when that reproduces both outputs.
                        if !matches(&written, *i, &bytes)
                            && keeping
                            && let Some(last) = &last_step
                            && last.inputs.len() > 1
                        {
                            let mut found = None;
                            'redo: for c in (1..last.inputs.len()).rev() {
                                let base = &history[..last.history_len];
                                let Ok(w1) = attempt(
                                    base,
                                    last.inputs[..c].iter(),
                                    last.at,
                                    &decl.kind,
                                    &spec,
                                    &params,
                                    module,
                                    make,
                                ) else {
                                    continue;
                                };
                                if !matches(&w1, last.port, &last.recorded) {
                                    continue;
                                }
                                let mut redone: Vec<Act> = base.to_vec();
                                for (t, input, seq, b) in &last.inputs[..c] {
                                    redone.push(Act::Input(*input, *t, *seq, b.clone()));
                                }
                                redone.push(Act::Step(last.at));
                                // This step then read some of the rest: the newest first.
                                let rest: Vec<_> =
                                    last.inputs[c..].iter().chain(&given).cloned().collect();
                                for d in (1..=rest.len()).rev() {
                                    let Ok(w2) = attempt(
                                        &redone,
                                        rest[..d].iter(),
                                        m.time,
                                        &decl.kind,
                                        &spec,
                                        &params,
                                        module,
                                        make,
                                    ) else {
                                        continue;
                                    };
                                    if matches(&w2, *i, &bytes) {
                                        found = Some((c, d, redone, rest, w1, w2));
                                        break 'redo;
                                    }
                                }
                            }
                            // The redone step must have written the same outputs, so that the
                            // entries it replaces are its own.
                            let found = found.filter(|(_, _, _, _, w1, _)| {
                                let mut ports: Vec<usize> = w1.iter().map(|(o, _, _)| *o).collect();
                                ports.sort_unstable();
                                ports == last.wrote
                            });
                            if let Some((_, d, mut redone, rest, w1, w2)) = found {
                                let redone_before = redone.len();
                                for (t, input, seq, b) in &rest[..d] {
                                    redone.push(Act::Input(*input, *t, *seq, b.clone()));
                                }
                                redone.push(Act::Step(m.time));
                                if let Ok((s2, o2)) =
                                    rebuild(&redone, &decl.kind, &spec, &params, module, make)
                                {
                                    // What it had not read yet waits for its next steps.
                                    for r in rest[d..].iter().rev() {
                                        pending.push_front(r.clone());
                                    }
                                    history = redone;
                                    stepper = s2;
                                    offline = o2;
                                    // The earlier step's outputs, as redone.
                                    for (o, _, b) in w1 {
                                        if let Some(v) = replayed.get_mut(&o)
                                            && let Some(x) = v.last_mut()
                                        {
                                            *x = b;
                                        }
                                    }
                                    written = w2;
                                    given = rest[..d].to_vec();
                                    before = redone_before;
                                    fed -= (rest.len() - d) as u64;
                                }
                            }
                        }
                        let mut wrote: Vec<usize> = written.iter().map(|(o, _, _)| *o).collect();
                        wrote.sort_unstable();
                        last_step = keeping.then(|| LastStep {
                            history_len: before,
                            inputs: given,
                            at: m.time,
                            port: *i,
                            recorded: bytes.clone(),
                            wrote,
                        });
                        if history_bytes > MAX_HISTORY && keeping {
                            // Too much to keep: from here on the newest input is taken as read.
                            keeping = false;
                            history.clear();
                            history.shrink_to_fit();
                        }
                        for (o, _, b) in written {
                            replayed.entry(o).or_default().push(b);
                        }
                    }
                    recorded
                        .entry(*i)
                        .or_default()
                        .push((m.time, u64::from(m.seq), Some(bytes)));
                }
            }
        }
    }
    let mut outputs = BTreeMap::new();
    let mut divergence: Option<Divergence> = None;
    for (i, port) in spec.outputs.iter().enumerate() {
        let rec = recorded.get(&i).map(Vec::as_slice).unwrap_or_default();
        let rep = replayed.get(&i).map(Vec::as_slice).unwrap_or_default();
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
        outputs.insert(
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
                after_unrecorded_inputs: unrecorded_since
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
    let compared: usize = outputs
        .values()
        .map(|c| c.identical + c.within_tolerance)
        .sum();
    if recorded.is_empty() {
        return Err(format!(
            "the recording holds no outputs of `{module}` (was it recorded? `dnm recordings --json` lists the channels)"
        ));
    }
    Ok(CheckReport {
        module: module.to_string(),
        kind: decl.kind.clone(),
        params,
        inputs_fed: fed,
        steps,
        unrecorded,
        unrecorded_inputs,
        first_unrecorded_input,
        tolerance,
        outputs,
        ok: divergence.is_none() && compared > 0,
        divergence,
    })
}

/// Inputs kept for rebuilding the module: beyond this, the newest input is taken as read.
const MAX_HISTORY: usize = 64 << 20;
/// Inputs waiting for the module's next recorded step, at most.
const MAX_PENDING: usize = 4096;

/// A step of the module's past, to rebuild it.
#[derive(Clone)]
enum Act {
    Task(Option<String>),
    Input(usize, u64, u64, Vec<u8>),
    Clear(usize),
    Step(u64),
}

/// The module's last step, to redo it if the next one shows it read an older input.
struct LastStep {
    /// `history` before its inputs.
    history_len: usize,
    inputs: Vec<(u64, usize, u64, Vec<u8>)>,
    at: u64,
    port: usize,
    recorded: Vec<u8>,
    /// The outputs it wrote (sorted).
    wrote: Vec<usize>,
}

/// The module built afresh and taken through `history`.
fn rebuild(
    history: &[Act],
    kind: &str,
    spec: &KindSpec,
    params: &BTreeMap<String, ParamValue>,
    module: &str,
    make: &Make<'_>,
) -> Result<(Box<dyn Stepper>, Offline), String> {
    let mut stepper = make(kind, &mut Setup::new(module, spec, params))?;
    let mut offline = Offline::new(spec, None);
    for act in history {
        match act {
            Act::Task(t) => offline.set_task(t.as_deref()),
            Act::Clear(i) => offline.clear_input(*i),
            Act::Input(i, t, seq, b) => offline.set_input(*i, *t, *seq, b.clone()),
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
#[allow(clippy::too_many_arguments)]
fn attempt<'a>(
    history: &[Act],
    inputs: impl Iterator<Item = &'a (u64, usize, u64, Vec<u8>)>,
    now: u64,
    kind: &str,
    spec: &KindSpec,
    params: &BTreeMap<String, ParamValue>,
    module: &str,
    make: &Make<'_>,
) -> Result<Vec<(usize, PortHeader, Vec<u8>)>, String> {
    let (mut stepper, mut offline) = rebuild(history, kind, spec, params, module, make)?;
    for (t, i, seq, b) in inputs {
        offline.set_input(*i, *t, *seq, b.clone());
    }
    offline
        .step(stepper.as_mut(), now)
        .map_err(|e| e.to_string())
}

/// A recorded output: sent (Unix ns), sequence number, bytes (None: the recording missed it).
type RecordedOutput = (u64, u64, Option<Vec<u8>>);

/// A channel's port type, how it is read, and what it is to the check.
type ChannelUse = (MessageType, Reading, Role);

/// What a channel is to the check.
#[derive(Debug, Clone)]
enum Role {
    /// Recorded output `/<module>/<port>` feeding the checked module.
    Input(String),
    /// The checked module's output (index).
    Output(usize),
}

fn role(
    topic: &str,
    raw: bool,
    raw_ports: &std::collections::BTreeSet<String>,
    module: &str,
    spec: &KindSpec,
    feeds: &HashMap<String, Vec<(String, usize)>>,
    netlist: &dnm_netlist::Netlist,
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
    if m == module {
        let i = spec.outputs.iter().position(|o| o.name == p)?;
        return Some((spec.outputs[i].message.clone(), Role::Output(i)));
    }
    let source = format!("/{m}/{p}");
    if !feeds.contains_key(&source) {
        return None;
    }
    let message = netlist
        .kind_of(m)?
        .outputs
        .iter()
        .find(|o| o.name == p)?
        .message
        .clone();
    Some((message, Role::Input(source)))
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
