//! Onboard sequences, the logical layer's task scheduler: a plan a station uploads, stored on
//! the rover and carried out by the authority whether or not a station is in contact.
//!
//! The rules (README, "Sequences"):
//! - **Commands.** Upload, start, pause, resume and cancel are station commands: exactly once,
//!   in order, through any outage. An upload is checked against the netlist in force (located
//!   errors, nothing stored when it fails); a start checks it again. One sequence runs (or is
//!   paused) at a time.
//! - **Steps.** A switch, an edit or an apply is a transaction like an operator's command;
//!   the step's progress is stored in the same write as the decision it led to. A refused
//!   step aborts the sequence. Waits and timeouts count in rover time from the step's start,
//!   less the time paused; an `at` step waits for its rover time. Conditions are evaluated on
//!   every new sample of the outputs they name (`sequencer.rs`).
//! - **Guards** are checked for as long as the sequence runs or is paused: one that holds
//!   switches the rover to its task and aborts the sequence.
//! - **Loss of signal** does not stop a running sequence: it is what the operators planned for
//!   the silence. The rover is made safe when the sequence ends if no station has been heard
//!   by then. With `on_link_loss.sequences = "stop"` in the netlist, loss of signal makes the
//!   rover safe at once and aborts the sequence. A paused sequence defers nothing.
//! - **Safing** for any fault (a DNM lost, a DNM safe on its own, loss of signal that stops
//!   sequences, a timeout's `on_timeout = "safe"`) aborts it.
//! - **A restarted authority resumes** a running sequence at the step it was on. A step whose
//!   decision was stored is never run again (its progress was stored with the decision); a
//!   step that was not decided changed nothing on any DNM (they drop undecided transactions)
//!   and runs, once. Waits go on counting from the step's start, so the time the authority was
//!   down counts. An authority down for longer than the loss-of-signal time finds the rover
//!   safe by its DNMs' lease, adopts that safing, and so aborts the sequence.

use std::path::Path;

use dnm_netlist::sequence::{Condition, OnTimeout, SequenceEdit, Step};
use dnm_netlist::{NetlistError, Sequence};
use dnm_proto::station::{
    InForce, ModuleEdit, SequenceAction, SequenceEvent, SequenceState, SequenceStatus,
};
use serde::{Deserialize, Serialize};

use crate::*;

/// Sequences stored on the rover, at most.
pub(crate) const MAX_SEQUENCES: usize = 16;
/// Bytes of one sequence file, at most.
const MAX_SEQUENCE_BYTES: usize = 256 * 1024;
/// Events kept in each sequence's history.
const HISTORY_KEPT: usize = 64;

/// A sequence stored on the rover and where it stands (durable: the store's `sequences`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct SequenceRun {
    pub(crate) name: String,
    pub(crate) file: String,
    pub(crate) text: String,
    /// The netlists its `apply` steps name, by the name the step gives.
    #[serde(default)]
    pub(crate) netlists: BTreeMap<String, String>,
    pub(crate) state: SequenceState,
    /// How many times it was started.
    pub(crate) run: u64,
    pub(crate) step: usize,
    pub(crate) step_since_unix_ns: u64,
    /// Time paused since the current step began, ns: waits and timeouts do not count it.
    #[serde(default)]
    pub(crate) paused_ns: u64,
    #[serde(default)]
    pub(crate) paused_at_unix_ns: Option<u64>,
    #[serde(default)]
    pub(crate) why: String,
    #[serde(default)]
    pub(crate) history: Vec<SequenceEvent>,
    /// Events it ever had (its history keeps the last ones).
    #[serde(default)]
    pub(crate) events_total: u64,
    /// Its steps as they read against the netlist in force when it was started: a run goes by
    /// them, whatever its own edits and applies change (each step is checked again when it
    /// runs: a switch to a task no longer defined is refused).
    #[serde(default)]
    pub(crate) started: Option<Sequence>,
}

impl SequenceRun {
    /// Reads its text against `netlist`.
    pub(crate) fn parse(&self, netlist: &Netlist) -> Result<Sequence, NetlistError> {
        Sequence::parse(Path::new(&self.file), &self.text, netlist)
    }

    /// The steps a run goes by: as read when it was started (else against `netlist`).
    pub(crate) fn steps_of(&self, netlist: &Netlist) -> Result<Sequence, NetlistError> {
        match &self.started {
            Some(q) => Ok(q.clone()),
            None => self.parse(netlist),
        }
    }

    pub(crate) fn active(&self) -> bool {
        matches!(self.state, SequenceState::Running | SequenceState::Paused)
    }

    pub(crate) fn event(&mut self, what: &str, step: Option<usize>, detail: String) {
        self.event_in_force(what, step, detail, None);
    }

    /// An event of a condition that held on the sample sent at `sample_unix_ns`.
    pub(crate) fn event_at_sample(
        &mut self,
        what: &str,
        step: Option<usize>,
        detail: String,
        sample_unix_ns: u64,
    ) {
        self.event_in_force(what, step, detail, None);
        if let Some(e) = self.history.last_mut() {
            e.sample_unix_ns = Some(sample_unix_ns);
        }
    }

    /// An event of a transaction that put `in_force` in force.
    pub(crate) fn event_in_force(
        &mut self,
        what: &str,
        step: Option<usize>,
        detail: String,
        in_force: Option<InForce>,
    ) {
        tracing::info!(sequence = %self.name, run = self.run, step, "{what}: {detail}");
        self.history.push(SequenceEvent {
            at_unix_ns: now_unix_ns(),
            sequence: self.name.clone(),
            run: self.run,
            what: what.into(),
            step,
            detail,
            sample_unix_ns: None,
            in_force,
        });
        self.events_total += 1;
        if self.history.len() > HISTORY_KEPT {
            self.history.remove(0);
        }
    }

    /// Its events after the first `seen` it ever had (those its history still keeps).
    pub(crate) fn events_after(&self, seen: u64) -> &[SequenceEvent] {
        let new = self
            .events_total
            .saturating_sub(seen)
            .min(self.history.len() as u64);
        &self.history[self.history.len() - new as usize..]
    }

    /// The rover time `ms` after the current step began, not counting time paused.
    pub(crate) fn after_step_start(&self, ms: u64) -> u64 {
        self.step_since_unix_ns
            .saturating_add(self.paused_ns)
            .saturating_add(ms.saturating_mul(1_000_000))
    }

    /// Goes on to the next step (of `steps`), begun at `at`; finished after the last.
    pub(crate) fn advance(&mut self, steps: usize, at: u64) {
        self.step += 1;
        self.step_since_unix_ns = at;
        self.paused_ns = 0;
        self.why.clear();
        if self.step >= steps {
            self.state = SequenceState::Finished;
            self.event("finished", None, "went through its last step".into());
        }
    }

    /// Stops it before its end.
    pub(crate) fn abort(&mut self, why: String) {
        self.abort_in_force(why, None);
    }

    /// Stops it before its end, with what its last transaction put in force.
    pub(crate) fn abort_in_force(&mut self, why: String, in_force: Option<InForce>) {
        self.state = SequenceState::Aborted;
        self.paused_at_unix_ns = None;
        self.event_in_force("aborted", Some(self.step), why.clone(), in_force);
        self.why = why;
    }

    /// As stations see it.
    pub(crate) fn status(&self, netlist: &Netlist) -> SequenceStatus {
        let parsed = self.steps_of(netlist).ok();
        let steps = parsed.as_ref().map_or(self.step, |q| q.steps.len());
        let doing = parsed
            .as_ref()
            .and_then(|q| q.steps.get(self.step))
            .map(describe_step)
            .unwrap_or_default();
        let why = match (
            self.state,
            parsed.as_ref().and_then(|q| q.steps.get(self.step)),
        ) {
            (SequenceState::Running, Some(step)) if self.why.is_empty() => waiting_for(self, step),
            _ => self.why.clone(),
        };
        SequenceStatus {
            name: self.name.clone(),
            file: self.file.clone(),
            state: self.state,
            step: self.step,
            steps,
            doing,
            why,
            step_since_unix_ns: self.step_since_unix_ns,
            history: self.history.clone(),
            events_total: self.events_total,
        }
    }
}

/// Why a running sequence is on `step`, in words.
fn waiting_for(run: &SequenceRun, step: &Step) -> String {
    let secs = |at: u64| at.saturating_sub(now_unix_ns()) as f64 / 1e9;
    match step {
        Step::Wait { ms } => format!("waits {:.1} s more", secs(run.after_step_start(*ms))),
        Step::At { unix_ns } => format!("waits {:.1} s for its rover time", secs(*unix_ns)),
        Step::WaitUntil {
            condition,
            timeout_ms,
            ..
        } => format!(
            "waits until {} ({:.1} s left before its timeout)",
            describe_condition(condition),
            secs(run.after_step_start(*timeout_ms))
        ),
        Step::End { condition: Some(c) } => format!("ends when {}", describe_condition(c)),
        _ => "runs its step".into(),
    }
}

/// A step in words, as a sequence file spells it.
pub(crate) fn describe_step(step: &Step) -> String {
    match step {
        Step::Switch { task } => format!("switch to `{task}`"),
        Step::Edit { edit } => match edit {
            SequenceEdit::Add { name, kind, .. } => format!("add module `{name}` ({kind})"),
            SequenceEdit::Replace { name, params, .. } => {
                format!("replace module `{name}` {}", params.join(" "))
            }
            SequenceEdit::Remove { name } => format!("remove module `{name}`"),
        },
        Step::Apply { file } => format!("apply {file}"),
        Step::Wait { ms } => format!("wait {:.1} s", *ms as f64 / 1e3),
        Step::At { unix_ns } => format!("wait until rover time {unix_ns} ns"),
        Step::WaitUntil { condition, .. } => {
            format!("wait until {}", describe_condition(condition))
        }
        Step::End { condition: None } => "end".into(),
        Step::End { condition: Some(c) } => format!("end if {}", describe_condition(c)),
    }
}

/// A condition in words, as a sequence file spells it.
pub(crate) fn describe_condition(c: &Condition) -> String {
    match c {
        Condition::Compare { field, op, value } => {
            let op = serde_json::to_value(op)
                .ok()
                .and_then(|v| v.as_str().map(str::to_string))
                .unwrap_or_default();
            format!("{field} {op} {value}")
        }
        Condition::And(a, b) => {
            format!("({} and {})", describe_condition(a), describe_condition(b))
        }
        Condition::Or(a, b) => format!("({} or {})", describe_condition(a), describe_condition(b)),
    }
}

/// The sequence running or paused, if one.
pub(crate) fn active(core: &Core) -> Option<&SequenceRun> {
    core.sequences.values().find(|r| r.active())
}

/// The sequence running (not paused), if one.
pub(crate) fn running(core: &Core) -> Option<&SequenceRun> {
    core.sequences
        .values()
        .find(|r| r.state == SequenceState::Running)
}

/// Runs a station's order on a sequence: stored with its fate in one write.
pub(crate) fn order(
    s: &Shared,
    core: &mut Core,
    station: &str,
    sent: &Sent,
    name: &str,
    action: &SequenceAction,
) -> Result<(), AuthorityError> {
    let by = format!("station `{station}` (command {})", sent.seq);
    let result = match action {
        SequenceAction::Upload {
            file,
            text,
            netlists,
        } => upload(core, &s.door, name, (file, text), netlists, &by),
        SequenceAction::Start => start(core, name, &by),
        SequenceAction::Pause => pause(core, name, &by),
        SequenceAction::Resume => resume(core, name, &by),
        SequenceAction::Cancel => cancel(core, name, &by),
    };
    let detail = match result {
        Err(reason) => return refuse(s, station, sent, reason),
        Ok(detail) => detail,
    };
    let run = core.sequences.get(name);
    s.store.finish(Finish {
        fates: vec![(
            station,
            sent.seq,
            &sent.id,
            Fate::Done {
                at_unix_ns: now_unix_ns(),
                detail,
            },
        )],
        done: Some((station, sent.seq)),
        sequence: run,
        ..Finish::default()
    })
}

fn stored<'a>(core: &'a mut Core, name: &str) -> Result<&'a mut SequenceRun, String> {
    let names: Vec<String> = core.sequences.keys().cloned().collect();
    core.sequences.get_mut(name).ok_or_else(|| {
        if names.is_empty() {
            format!("no sequence `{name}` is stored on the rover (none is): upload it first")
        } else {
            format!(
                "no sequence `{name}` is stored on the rover; the stored ones: {}",
                names.join(", ")
            )
        }
    })
}

fn upload(
    core: &mut Core,
    door: &NetlistDoor,
    name: &str,
    (file, text): (&str, &str),
    netlists: &BTreeMap<String, String>,
    by: &str,
) -> Result<String, String> {
    if text.len() > MAX_SEQUENCE_BYTES {
        return Err(format!(
            "{file}: {} bytes; a sequence may have at most {MAX_SEQUENCE_BYTES}",
            text.len()
        ));
    }
    let sequence = Sequence::parse(Path::new(file), text, &core.netlist)
        .map_err(|e| format!("the sequence does not check against the netlist in force:\n{e}"))?;
    if sequence.name != name {
        return Err(format!(
            "{file} is the sequence `{}`, not `{name}`: upload it under its own name",
            sequence.name
        ));
    }
    for step in &sequence.steps {
        let Step::Apply { file: f } = step else {
            continue;
        };
        let Some(netlist) = netlists.get(f) else {
            return Err(format!(
                "{file}: a step applies `{f}`, which the upload does not carry (the station \
                 reads it beside the sequence file)"
            ));
        };
        // Checked now, as it would be when its step runs: a bad one changes nothing.
        if let Err(e) = door.accept(f, netlist) {
            return Err(format!(
                "{file}: a step applies `{f}`, which does not check:\n{e}"
            ));
        }
    }
    if let Some(r) = core.sequences.get(name).filter(|r| r.active()) {
        return Err(format!(
            "sequence `{name}` is {} (step {}): cancel it before uploading it again",
            state_word(r.state),
            r.step + 1
        ));
    }
    if !core.sequences.contains_key(name) && core.sequences.len() >= MAX_SEQUENCES {
        return Err(format!(
            "the rover stores at most {MAX_SEQUENCES} sequences; upload this one under the name \
             of one it no longer needs"
        ));
    }
    let mut run = SequenceRun {
        name: name.to_string(),
        file: file.to_string(),
        text: text.to_string(),
        netlists: netlists.clone(),
        state: SequenceState::Stored,
        run: core.sequences.get(name).map_or(0, |r| r.run),
        step: 0,
        step_since_unix_ns: now_unix_ns(),
        paused_ns: 0,
        paused_at_unix_ns: None,
        why: String::new(),
        history: core
            .sequences
            .get(name)
            .map(|r| r.history.clone())
            .unwrap_or_default(),
        events_total: core.sequences.get(name).map_or(0, |r| r.events_total),
        started: None,
    };
    let detail = format!(
        "sequence `{name}` stored: {} steps, {} guards (from {file}, by {by})",
        sequence.steps.len(),
        sequence.guards.len()
    );
    run.event("stored", None, detail.clone());
    core.sequences.insert(name.to_string(), run);
    Ok(detail)
}

fn state_word(state: SequenceState) -> &'static str {
    match state {
        SequenceState::Stored => "stored",
        SequenceState::Running => "running",
        SequenceState::Paused => "paused",
        SequenceState::Finished => "finished",
        SequenceState::Aborted => "aborted",
    }
}

fn start(core: &mut Core, name: &str, by: &str) -> Result<String, String> {
    if let Some(other) = active(core) {
        return Err(format!(
            "sequence `{}` is {}: one sequence runs at a time (cancel it, or wait for its end)",
            other.name,
            state_word(other.state)
        ));
    }
    let netlist = core.netlist.clone();
    let run = stored(core, name)?;
    let sequence = run.parse(&netlist).map_err(|e| {
        format!("sequence `{name}` no longer checks against the netlist in force:\n{e}")
    })?;
    run.started = Some(sequence.clone());
    run.state = SequenceState::Running;
    run.run += 1;
    run.step = 0;
    run.step_since_unix_ns = now_unix_ns();
    run.paused_ns = 0;
    run.paused_at_unix_ns = None;
    run.why.clear();
    let detail = format!(
        "sequence `{name}` started (run {}, {} steps), by {by}",
        run.run,
        sequence.steps.len()
    );
    run.event("started", Some(0), detail.clone());
    Ok(detail)
}

fn pause(core: &mut Core, name: &str, by: &str) -> Result<String, String> {
    let run = stored(core, name)?;
    if run.state != SequenceState::Running {
        return Err(format!(
            "sequence `{name}` is {}, not running: nothing to pause",
            state_word(run.state)
        ));
    }
    run.state = SequenceState::Paused;
    run.paused_at_unix_ns = Some(now_unix_ns());
    let detail = format!("sequence `{name}` paused at step {}, by {by}", run.step + 1);
    run.event("paused", Some(run.step), detail.clone());
    run.why = detail.clone();
    Ok(detail)
}

fn resume(core: &mut Core, name: &str, by: &str) -> Result<String, String> {
    let run = stored(core, name)?;
    if run.state != SequenceState::Paused {
        return Err(format!(
            "sequence `{name}` is {}, not paused: nothing to resume",
            state_word(run.state)
        ));
    }
    let now = now_unix_ns();
    let paused = now.saturating_sub(run.paused_at_unix_ns.take().unwrap_or(now));
    run.paused_ns = run.paused_ns.saturating_add(paused);
    run.state = SequenceState::Running;
    run.why.clear();
    let detail = format!(
        "sequence `{name}` resumed at step {} after {:.1} s paused, by {by}",
        run.step + 1,
        paused as f64 / 1e9
    );
    run.event("resumed", Some(run.step), detail.clone());
    Ok(detail)
}

fn cancel(core: &mut Core, name: &str, by: &str) -> Result<String, String> {
    let run = stored(core, name)?;
    if !run.active() {
        return Err(format!(
            "sequence `{name}` is {}: nothing to cancel",
            state_word(run.state)
        ));
    }
    let detail = format!(
        "sequence `{name}` cancelled at step {}, by {by}; the rover stays in its task",
        run.step + 1
    );
    run.abort(detail.clone());
    Ok(detail)
}

/// What a running sequence's step needs from the worker, if anything (a transaction or its
/// end): `(name, run, step)`.
pub(crate) fn next_step(core: &Core) -> Option<(String, u64, usize)> {
    let run = running(core)?;
    let step = match run.steps_of(&core.netlist) {
        // The netlist changed under it: the worker aborts it, saying why.
        Err(_) => return Some((run.name.clone(), run.run, run.step)),
        Ok(q) => q.steps.get(run.step).cloned(),
    };
    match step {
        Some(Step::Switch { .. } | Step::Edit { .. } | Step::Apply { .. })
        | Some(Step::End { condition: None })
        | None => Some((run.name.clone(), run.run, run.step)),
        Some(_) => None,
    }
}

/// Where a transaction of a sequence came from: its fate moves the sequence on.
#[derive(Debug, Clone)]
pub(crate) enum StepOrigin {
    /// Step `step` of run `run` of sequence `name`.
    Step {
        name: String,
        run: u64,
        step: usize,
        steps: usize,
    },
    /// A guard fired: the sequence is aborted whatever the switch's fate.
    Guard {
        name: String,
        run: u64,
        detail: String,
    },
}

impl StepOrigin {
    pub(crate) fn name(&self) -> &str {
        match self {
            StepOrigin::Step { name, .. } | StepOrigin::Guard { name, .. } => name,
        }
    }

    /// Moves the sequence on by the transaction's fate (before the fate is stored: both go in
    /// one write).
    pub(crate) fn advance(&self, core: &mut Core, fate: &Fate) {
        match self {
            StepOrigin::Step {
                name,
                run,
                step,
                steps,
            } => {
                let Some(r) = core.sequences.get_mut(name).filter(|r| r.run == *run) else {
                    return;
                };
                match fate {
                    Fate::Applied {
                        revision,
                        task,
                        at_unix_ns,
                    } => {
                        r.event_in_force(
                            "step_done",
                            Some(*step),
                            format!(
                                "in force at {at_unix_ns} ns rover time (revision {revision}, \
                                 task {})",
                                task.as_deref().unwrap_or("-")
                            ),
                            Some(InForce {
                                revision: *revision,
                                task: task.clone(),
                                at_unix_ns: *at_unix_ns,
                            }),
                        );
                        r.advance(*steps, (*at_unix_ns).max(now_unix_ns()));
                    }
                    Fate::Refused { reason } => {
                        r.abort(format!("step {} refused: {reason}", step + 1));
                    }
                    _ => {}
                }
            }
            StepOrigin::Guard { name, run, detail } => {
                let Some(r) = core.sequences.get_mut(name).filter(|r| r.run == *run) else {
                    return;
                };
                let (outcome, in_force) = match fate {
                    Fate::Applied {
                        revision,
                        task,
                        at_unix_ns,
                    } => (
                        format!(
                            "switched to `{}`, in force at {at_unix_ns} ns rover time",
                            task.as_deref().unwrap_or("-")
                        ),
                        Some(InForce {
                            revision: *revision,
                            task: task.clone(),
                            at_unix_ns: *at_unix_ns,
                        }),
                    ),
                    Fate::Refused { reason } => (format!("its switch was refused: {reason}"), None),
                    other => (format!("{other:?}"), None),
                };
                r.abort_in_force(format!("{detail}; {outcome}"), in_force);
            }
        }
    }
}

/// Runs step `step` of a running sequence (a transaction, or its end); the sequence moves on
/// with the transaction's fate, stored with it.
pub(crate) fn run_step(
    s: &Shared,
    core: &mut Core,
    (name, run, step): (String, u64, usize),
) -> Result<(), AuthorityError> {
    let Some(r) = core
        .sequences
        .get(&name)
        .filter(|r| r.run == run && r.step == step && r.state == SequenceState::Running)
    else {
        return Ok(());
    };
    let parsed = r.steps_of(&core.netlist);
    let netlists = r.netlists.clone();
    let sequence = match parsed {
        Ok(q) => q,
        Err(e) => {
            return save_aborted(
                s,
                core,
                &name,
                format!("no longer checks against the netlist in force:\n{e}"),
            );
        }
    };
    let steps = sequence.steps.len();
    let origin = Origin {
        cmd: None,
        timer_remove: None,
        step: Some(StepOrigin::Step {
            name: name.clone(),
            run,
            step,
            steps,
        }),
        given_unix_ns: None,
    };
    if let Some(r) = core.sequences.get_mut(&name) {
        r.event(
            "step_started",
            Some(step),
            sequence
                .steps
                .get(step)
                .map(describe_step)
                .unwrap_or_default(),
        );
    }
    match sequence.steps.get(step) {
        None | Some(Step::End { condition: None }) => {
            if let Some(r) = core.sequences.get_mut(&name) {
                r.state = SequenceState::Finished;
                r.step = steps;
                r.event("finished", Some(step), "reached its end".into());
            }
            save(s, core, &name)
        }
        Some(Step::Switch { task }) => {
            if !core.netlist.tasks.contains_key(task) {
                return save_aborted(
                    s,
                    core,
                    &name,
                    format!(
                        "step {}: task `{task}` is not in the netlist in force",
                        step + 1
                    ),
                );
            }
            transact(s, core, None, Some(task.clone()), None, origin);
            Ok(())
        }
        Some(Step::Edit { edit }) => {
            let edit = module_edit(edit);
            let edited = edit_netlist(&core.state.text, &edit)
                .map_err(|e| e.to_string())
                .and_then(|(text, what)| {
                    let file = format!("<{} netlist in force, {what}>", s.system);
                    s.door.accept(&file, &text).map_err(|e| e.to_string())
                });
            match edited {
                Err(e) => save_aborted(s, core, &name, format!("step {}: {e}", step + 1)),
                Ok(n) => {
                    transact(s, core, Some(n), None, None, origin);
                    Ok(())
                }
            }
        }
        Some(Step::Apply { file }) => {
            let accepted = match netlists.get(file) {
                None => Err(format!("`{file}` was not uploaded with the sequence")),
                Some(text) => s.door.accept(file, text).map_err(|e| e.to_string()),
            };
            match accepted {
                Err(e) => save_aborted(s, core, &name, format!("step {}: {e}", step + 1)),
                Ok(n) => {
                    transact(s, core, Some(n), None, None, origin);
                    Ok(())
                }
            }
        }
        // Waits are the sequencer's.
        Some(_) => save(s, core, &name),
    }
}

fn module_edit(edit: &SequenceEdit) -> ModuleEdit {
    match edit.clone() {
        SequenceEdit::Add {
            name,
            kind,
            dnm,
            params,
            links,
        } => ModuleEdit::Add {
            name,
            kind,
            dnm,
            params,
            links,
        },
        SequenceEdit::Replace { name, kind, params } => ModuleEdit::Replace { name, kind, params },
        SequenceEdit::Remove { name } => ModuleEdit::Remove { name },
    }
}

fn save(s: &Shared, core: &Core, name: &str) -> Result<(), AuthorityError> {
    match core.sequences.get(name) {
        Some(r) => s.store.save_sequence(r),
        None => Ok(()),
    }
}

fn save_aborted(
    s: &Shared,
    core: &mut Core,
    name: &str,
    why: String,
) -> Result<(), AuthorityError> {
    tracing::warn!(sequence = name, "sequence aborted: {why}");
    if let Some(r) = core.sequences.get_mut(name) {
        r.abort(why);
    }
    save(s, core, name)
}

/// Aborts the sequence running or paused, if one, because the rover was made safe; returns
/// it (to be stored with the safing).
pub(crate) fn abort_for_safing(core: &mut Core, reason: &str) -> Option<SequenceRun> {
    let r = core.sequences.values_mut().find(|r| r.active())?;
    r.abort(format!("the rover was made safe: {reason}"));
    Some(r.clone())
}

/// What fell due for a sequence, found by the sequencer.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Due {
    pub(crate) name: String,
    pub(crate) run: u64,
    pub(crate) step: usize,
    pub(crate) what: DueWhat,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) enum DueWhat {
    /// A `wait` or `at` step's time came.
    Elapsed,
    /// A `wait_until` or `end_if` condition held: on which sample, in words.
    Met { detail: String, sample_unix_ns: u64 },
    /// A `wait_until`'s timeout passed first.
    TimedOut,
    /// Guard `index` held: on which sample, in words.
    Guard {
        index: usize,
        detail: String,
        sample_unix_ns: u64,
    },
}

impl Due {
    /// Whether it leads to a transaction (and so needs the DNMs in step first).
    pub(crate) fn transacts(&self) -> bool {
        matches!(self.what, DueWhat::Guard { .. })
    }
}

/// Acts on what fell due, if it is still the sequence's current step.
pub(crate) fn apply_due(s: &Shared, core: &mut Core, due: Due) -> Result<(), AuthorityError> {
    let guard = matches!(due.what, DueWhat::Guard { .. });
    let Some(r) = core.sequences.get(&due.name).filter(|r| {
        r.run == due.run
            && (r.state == SequenceState::Running || guard && r.state == SequenceState::Paused)
            && (guard || r.step == due.step)
    }) else {
        tracing::debug!(?due, "no longer due");
        s.sequencer.dropped(&due);
        return Ok(());
    };
    let sequence = match r.steps_of(&core.netlist) {
        Ok(q) => q,
        Err(e) => {
            return save_aborted(
                s,
                core,
                &due.name,
                format!("no longer checks against the netlist in force:\n{e}"),
            );
        }
    };
    let steps = sequence.steps.len();
    let step = sequence.steps.get(due.step).cloned();
    let name = due.name.clone();
    match due.what {
        DueWhat::Guard {
            index,
            detail,
            sample_unix_ns,
        } => {
            let Some(g) = sequence.guards.get(index) else {
                return Ok(());
            };
            let detail = format!(
                "guard `{}` fired ({detail})",
                describe_condition(&g.condition)
            );
            if let Some(r) = core.sequences.get_mut(&name) {
                r.event_at_sample("guard_fired", Some(r.step), detail.clone(), sample_unix_ns);
            }
            let origin = Origin {
                cmd: None,
                timer_remove: None,
                step: Some(StepOrigin::Guard {
                    name: name.clone(),
                    run: due.run,
                    detail,
                }),
                given_unix_ns: None,
            };
            let task = g.task.clone();
            if let Fate::Refused { reason } =
                transact(s, core, None, Some(task.clone()), None, origin)
            {
                // The guard's task is put in force all the same, as a safing: a DNM that cannot
                // take a transaction takes the beat's safing.
                safing::make_safe(
                    s,
                    core,
                    task.clone(),
                    "guard",
                    format!(
                        "sequence `{name}`: a guard fired and its switch to `{task}` was refused \
                         ({reason}): the rover is made safe on it"
                    ),
                )?;
            }
            Ok(())
        }
        DueWhat::Elapsed => {
            if let Some(r) = core.sequences.get_mut(&name) {
                let ended = step.as_ref().map(describe_step).unwrap_or_default();
                r.event("step_done", Some(due.step), ended);
                r.advance(steps, now_unix_ns());
            }
            save(s, core, &name)
        }
        DueWhat::Met {
            detail,
            sample_unix_ns,
        } => {
            if let Some(r) = core.sequences.get_mut(&name) {
                r.event_at_sample(
                    "condition_met",
                    Some(due.step),
                    detail.clone(),
                    sample_unix_ns,
                );
                if matches!(step, Some(Step::End { .. })) {
                    r.state = SequenceState::Finished;
                    r.step = steps;
                    r.event("finished", Some(due.step), format!("ended: {detail}"));
                } else {
                    r.advance(steps, now_unix_ns());
                }
            }
            save(s, core, &name)
        }
        DueWhat::TimedOut => timed_out(s, core, &name, (due.step, steps), step),
    }
}

/// A `wait_until`'s timeout passed first: the sequence goes on, stops, or the rover is made
/// safe, as the step says.
fn timed_out(
    s: &Shared,
    core: &mut Core,
    name: &str,
    (at, steps): (usize, usize),
    step: Option<Step>,
) -> Result<(), AuthorityError> {
    let Some(Step::WaitUntil {
        condition,
        timeout_ms,
        on_timeout,
    }) = step
    else {
        return Ok(());
    };
    let what = format!(
        "step {}: `{}` did not hold within {:.1} s",
        at + 1,
        describe_condition(&condition),
        timeout_ms as f64 / 1e3
    );
    match on_timeout {
        OnTimeout::Continue => {
            if let Some(r) = core.sequences.get_mut(name) {
                r.event("timed_out", Some(at), format!("{what}; going on"));
                r.advance(steps, now_unix_ns());
            }
            save(s, core, name)
        }
        OnTimeout::Abort => save_aborted(s, core, name, format!("{what}: aborted")),
        OnTimeout::Safe => match core.netlist.on_link_loss.clone() {
            Some(rule) => {
                if let Some(r) = core.sequences.get_mut(name) {
                    r.event("timed_out", Some(at), what.clone());
                }
                safing::make_safe(
                    s,
                    core,
                    rule.task.clone(),
                    "sequence_timeout",
                    format!("sequence `{name}`: {what}: switching to `{}`", rule.task),
                )
                .map(|_| ())
            }
            None => save_aborted(
                s,
                core,
                name,
                format!(
                    "{what}: the netlist names no safe task (`on_link_loss`), so the rover \
                     stays in its task"
                ),
            ),
        },
    }
}

/// On start: a sequence that was running when the authority stopped goes on at its step (the
/// rule above); says so in its history.
pub(crate) fn resume_after_restart(store: &Store, sequences: &mut BTreeMap<String, SequenceRun>) {
    for r in sequences.values_mut().filter(|r| r.active()) {
        let detail = format!(
            "the authority restarted: going on at step {} (steps decided before are not run \
             again)",
            r.step + 1
        );
        r.event("resumed_after_restart", Some(r.step), detail);
        if let Err(e) = store.save_sequence(r) {
            tracing::error!(sequence = %r.name, "storing its history: {e}");
        }
    }
}

/// Hands every sequence event not yet told (`told`: how many of each sequence's were) to
/// `tell`.
pub(crate) fn tell_new_events(
    core: &Core,
    told: &mut BTreeMap<String, u64>,
    tell: &mut dyn FnMut(&SequenceEvent),
) {
    for r in core.sequences.values() {
        let seen = told.entry(r.name.clone()).or_insert(0);
        for e in r.events_after(*seen) {
            tell(e);
        }
        *seen = r.events_total;
    }
}

/// Every stored sequence as stations see it.
pub(crate) fn statuses(core: &Core) -> Vec<SequenceStatus> {
    core.sequences
        .values()
        .map(|r| r.status(&core.netlist))
        .collect()
}

/// Whether loss of signal waits for the sequence running to end (and which it is).
pub(crate) fn defers_link_loss(core: &Core) -> Option<String> {
    let stops = core
        .netlist
        .on_link_loss
        .as_ref()
        .is_some_and(|l| l.stop_sequences);
    running(core).filter(|_| !stops).map(|r| r.name.clone())
}
