//! The sequencer: the outputs a running sequence names watched (every sample, through the
//! DNMs' watch keys), its guards and its step's condition evaluated on each new sample, its
//! waits and timeouts timed; what falls due is handed to the worker, which acts on it.

use std::collections::VecDeque;

use dnm_netlist::MessageType;
use dnm_netlist::sequence::{Condition, FieldRef, Step};
use dnm_proto::keys::{self, WatchRate};
use dnm_proto::station::SequenceState;
use serde_json::Value;

use crate::sequence::{Due, DueWhat, SequenceRun, describe_condition};
use crate::*;

/// What the sequencer watches for the current step of the sequence running (or paused).
#[derive(Debug, Clone)]
pub(crate) struct Armed {
    pub(crate) name: String,
    pub(crate) run: u64,
    pub(crate) step: usize,
    pub(crate) paused: bool,
    pub(crate) guards: Vec<Condition>,
    /// The step's condition (`wait_until`, `end_if`).
    pub(crate) condition: Option<Condition>,
    /// An `end_if`: decided on the first sample of its fields (ends, or goes on).
    pub(crate) end_if: bool,
    /// When the step began, rover time: its condition reads only samples sent since.
    pub(crate) since_unix_ns: u64,
    /// Rover time the step's wait or timeout ends, and what falls due then.
    pub(crate) deadline: Option<(u64, DueWhat)>,
    /// The outputs to watch: (dnm, module, port) and their message type.
    pub(crate) ports: Vec<((String, String, String), MessageType)>,
}

impl Armed {
    /// What the sequencer watches for `run` on `netlist` (`None`: nothing, or the sequence
    /// does not read against it).
    pub(crate) fn of(run: &SequenceRun, netlist: &Netlist) -> Option<Self> {
        let sequence = run.steps_of(netlist).ok()?;
        let step = sequence.steps.get(run.step);
        let paused = run.state == SequenceState::Paused;
        let (condition, deadline) = match step {
            Some(Step::Wait { ms }) => (None, Some((run.after_step_start(*ms), DueWhat::Elapsed))),
            Some(Step::At { unix_ns }) => (None, Some((*unix_ns, DueWhat::Elapsed))),
            Some(Step::WaitUntil {
                condition,
                timeout_ms,
                ..
            }) => (
                Some(condition.clone()),
                Some((run.after_step_start(*timeout_ms), DueWhat::TimedOut)),
            ),
            Some(Step::End { condition }) => (condition.clone(), None),
            _ => (None, None),
        };
        let end_if = matches!(step, Some(Step::End { condition: Some(_) }));
        let guards: Vec<Condition> = sequence
            .guards
            .iter()
            .map(|g| g.condition.clone())
            .collect();
        let mut ports = Vec::new();
        for f in guards.iter().chain(&condition).flat_map(Condition::fields) {
            let Some(m) = netlist.module(&f.module) else {
                continue;
            };
            let Some(out) = netlist
                .kind_of(&f.module)
                .and_then(|k| k.outputs.iter().find(|p| p.name == f.port))
            else {
                continue;
            };
            let key = (m.dnm.clone(), f.module.clone(), f.port.clone());
            if !ports.iter().any(|(k, _)| *k == key) {
                ports.push((key, out.message.clone()));
            }
        }
        Some(Self {
            name: run.name.clone(),
            run: run.run,
            step: run.step,
            paused,
            guards,
            condition,
            end_if,
            since_unix_ns: run.step_since_unix_ns,
            deadline: if paused { None } else { deadline },
            ports,
        })
    }

    fn same_step(&self, other: &Armed) -> bool {
        (&self.name, self.run, self.step) == (&other.name, other.run, other.step)
    }
}

/// The newest sample of an output.
#[derive(Debug, Clone)]
struct PortValue {
    value: Value,
    /// Its send time, rover time (ns since the Unix epoch).
    unix_ns: u64,
    seq: u64,
    received: Instant,
}

#[derive(Debug, Default)]
struct Watching {
    armed: Option<Armed>,
    /// When the current step was armed here: only samples received since count.
    since: Option<Instant>,
    /// Something fell due for it already.
    fired: bool,
    values: BTreeMap<(String, String), PortValue>,
}

/// The sequencer's state, shared by its thread, the Zenoh callbacks and the worker.
#[derive(Debug, Default)]
pub(crate) struct Sequencer {
    watching: Mutex<Watching>,
    dues: Mutex<VecDeque<Due>>,
    wake: (Mutex<bool>, Condvar),
}

impl Sequencer {
    /// Has the sequencer watch `armed` (the worker calls it after every change).
    pub(crate) fn arm(&self, armed: Option<Armed>) {
        let Ok(mut w) = self.watching.lock() else {
            return;
        };
        let (same, pause_changed) = match (&w.armed, &armed) {
            (Some(a), Some(b)) => (a.same_step(b), a.paused != b.paused),
            _ => (false, false),
        };
        if !same {
            w.fired = false;
            w.since = Some(Instant::now());
        } else if pause_changed {
            // Paused or resumed: what fell due meanwhile was dropped; it falls due again.
            w.fired = false;
        }
        w.armed = armed;
        drop(w);
        self.notify();
    }

    fn notify(&self) {
        if let Ok(mut b) = self.wake.0.lock() {
            *b = true;
            self.wake.1.notify_all();
        }
    }

    /// The oldest thing due, left in the queue until [`Sequencer::done`].
    pub(crate) fn peek(&self) -> Option<Due> {
        let dues = self.dues.lock().ok()?;
        // A guard goes first: it aborts the sequence whatever the step.
        dues.iter()
            .find(|d| matches!(d.what, DueWhat::Guard { .. }))
            .or_else(|| dues.front())
            .cloned()
    }

    /// `due` was dropped (its sequence was paused, say): the step falls due again.
    pub(crate) fn dropped(&self, due: &Due) {
        if let Ok(mut w) = self.watching.lock()
            && w.armed
                .as_ref()
                .is_some_and(|a| (&a.name, a.run, a.step) == (&due.name, due.run, due.step))
        {
            w.fired = false;
        }
        self.notify();
    }

    /// Takes `due` out of the queue: the worker acted on it.
    pub(crate) fn done(&self, due: &Due) {
        if let Ok(mut dues) = self.dues.lock()
            && let Some(i) = dues.iter().position(|d| d == due)
        {
            dues.remove(i);
        }
    }

    fn push(&self, s: &Shared, due: Due) {
        tracing::debug!(?due, "due");
        if let Ok(mut dues) = self.dues.lock() {
            dues.push_back(due);
        }
        s.wake();
    }

    /// A new sample of `module.port`: kept, and the conditions evaluated on it.
    fn sample(&self, s: &Shared, key: (String, String), v: PortValue) {
        let Ok(mut w) = self.watching.lock() else {
            return;
        };
        w.values.insert(key, v);
        if let Some(due) = evaluate(&mut w) {
            drop(w);
            self.push(s, due);
        }
    }

    /// The deadline of what is armed, if its time came: handed to the worker. Returns how
    /// long until it (or a second).
    fn tick(&self, s: &Shared) -> Duration {
        let Ok(mut w) = self.watching.lock() else {
            return Duration::from_secs(1);
        };
        let Some(armed) = w.armed.clone().filter(|_| !w.fired) else {
            return Duration::from_secs(1);
        };
        let Some((at, what)) = armed.deadline else {
            return Duration::from_secs(1);
        };
        let now = now_unix_ns();
        if now < at {
            return Duration::from_nanos(at - now).min(Duration::from_secs(1));
        }
        w.fired = true;
        drop(w);
        self.push(
            s,
            Due {
                name: armed.name,
                run: armed.run,
                step: armed.step,
                what,
            },
        );
        Duration::from_secs(1)
    }

    fn sleep(&self, d: Duration) {
        let Ok(b) = self.wake.0.lock() else {
            return;
        };
        if let Ok((mut b, _)) = self.wake.1.wait_timeout_while(b, d, |b| !*b) {
            *b = false;
        }
    }

    fn ports(&self) -> Vec<((String, String, String), MessageType)> {
        self.watching
            .lock()
            .ok()
            .and_then(|w| w.armed.as_ref().map(|a| a.ports.clone()))
            .unwrap_or_default()
    }
}

/// What falls due on the values `w` holds, if anything: a guard first, then the step's
/// condition (not while paused).
fn evaluate(w: &mut Watching) -> Option<Due> {
    if w.fired {
        return None;
    }
    let armed = w.armed.as_ref()?;
    let since = w.since?;
    let fresh = |f: &FieldRef| {
        w.values
            .get(&(f.module.clone(), f.port.clone()))
            .filter(|v| v.received >= since)
    };
    let value_of = |f: &FieldRef| fresh(f).and_then(|v| field_value(&v.value, f));
    // The step's condition reads only samples sent since the step began (a sample of the
    // module an edit replaced, or sent under the task a switch left, says nothing of it).
    let since_step = |f: &FieldRef| {
        w.values
            .get(&(f.module.clone(), f.port.clone()))
            .filter(|v| v.unix_ns >= armed.since_unix_ns)
    };
    let step_value = |f: &FieldRef| since_step(f).and_then(|v| field_value(&v.value, f));
    let said = |c: &Condition| {
        c.fields()
            .iter()
            .map(|f| match (fresh(f), value_of(f)) {
                (Some(v), Some(x)) => {
                    format!("{f} = {x} (sample {} sent at {} ns)", v.seq, v.unix_ns)
                }
                _ => format!("{f} unknown"),
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    // The newest sample a condition read: the one on which it came to hold.
    let newest = |c: &Condition| {
        c.fields()
            .iter()
            .filter_map(|f| fresh(f).map(|v| v.unix_ns))
            .max()
            .unwrap_or_else(now_unix_ns)
    };
    let due = |what| Due {
        name: armed.name.clone(),
        run: armed.run,
        step: armed.step,
        what,
    };
    if let Some((index, g)) = armed
        .guards
        .iter()
        .enumerate()
        .find(|(_, g)| g.holds(&value_of))
    {
        let d = due(DueWhat::Guard {
            index,
            detail: said(g),
            sample_unix_ns: newest(g),
        });
        w.fired = true;
        return Some(d);
    }
    let c = armed.condition.as_ref().filter(|_| !armed.paused)?;
    let holds = c.holds(&step_value);
    if armed.end_if && !holds {
        // Decided once every field has a sample: it does not hold, so the sequence goes on.
        if !c.fields().iter().all(|f| since_step(f).is_some()) {
            return None;
        }
        let d = due(DueWhat::Elapsed);
        w.fired = true;
        return Some(d);
    }
    if !holds {
        return None;
    }
    let d = due(DueWhat::Met {
        detail: format!("{} held: {}", describe_condition(c), said(c)),
        sample_unix_ns: newest(c),
    });
    w.fired = true;
    Some(d)
}

/// A field's number in a decoded sample (a boolean is 0 or 1).
pub(crate) fn field_value(sample: &Value, f: &FieldRef) -> Option<f64> {
    let v = sample.get(&f.field)?;
    let v = match f.index {
        Some(i) => v.get(i)?,
        None => v,
    };
    v.as_f64()
        .or_else(|| v.as_bool().map(|b| if b { 1.0 } else { 0.0 }))
}

/// Watches the outputs armed and times the steps until the authority stops.
pub(crate) fn sequencer_loop(s: &Arc<Shared>) {
    let mut subs: BTreeMap<(String, String, String), zenoh::pubsub::Subscriber<()>> =
        BTreeMap::new();
    while !s.stop.load(Ordering::Relaxed) {
        let ports = s.sequencer.ports();
        subs.retain(|k, _| ports.iter().any(|(p, _)| p == k));
        for (key, message) in ports {
            if subs.contains_key(&key) {
                continue;
            }
            let (dnm, module, port) = key.clone();
            let watch = keys::watch(&s.system, &dnm, &module, &port, WatchRate::Full);
            let shared = s.clone();
            let target = (module.clone(), port.clone());
            let declared = s
                .session
                .declare_subscriber(&watch)
                .callback(move |sample| {
                    let header = sample
                        .attachment()
                        .and_then(|a| keys::decode_header(&a.to_bytes()));
                    let value = dnm_netlist::values::decode(&message, &sample.payload().to_bytes());
                    let v = PortValue {
                        value,
                        unix_ns: header.map_or_else(now_unix_ns, |h| h.unix_ns),
                        seq: header.map_or(0, |h| h.seq),
                        received: Instant::now(),
                    };
                    shared.sequencer.sample(&shared, target.clone(), v);
                })
                .wait();
            match declared {
                Ok(sub) => {
                    tracing::debug!(key = %watch, "sequencer watches");
                    subs.insert(key, sub);
                }
                Err(e) => tracing::warn!(key = %watch, "the sequencer cannot watch: {e}"),
            }
        }
        let next = s.sequencer.tick(s);
        s.sequencer.sleep(next);
    }
}
