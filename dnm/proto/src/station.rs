//! What a ground station and the rover's authority say to each other over the radio link.
//!
//! The station sends an [`Uplink`] as a query on [`crate::keys::authority_station`] (its own name's key): the commands the
//! rover has not acknowledged yet, oldest first, each with the station's sequence number and a
//! unique id. The authority stores each durably before it acknowledges it, runs them exactly
//! once in the station's order, and answers with a [`Downlink`]: the fate of every command the
//! station asked about and the rover's state. An uplink without commands is a ping.

use serde::{Deserialize, Serialize};

/// An operator's command to the rover.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case")]
pub enum Order {
    /// Switch every DNM of the rover to `task`, at `at_unix_ns` (rover time) when given.
    Switch {
        task: String,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        at_unix_ns: Option<u64>,
        /// With `at_unix_ns`: how late after its time the switch may still run, ms (default
        /// [`DEFAULT_LATE_BY_MS`]); later, it is refused with the reason, never run.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        late_by_ms: Option<u64>,
    },
    /// Apply a netlist; `file` names it in errors.
    Apply { file: String, text: String },
    /// Add, replace or remove one module of the netlist in force when the command runs.
    Module { edit: ModuleEdit },
    /// Cancel this station's time-tagged command `seq` before it runs.
    Cancel { seq: u64 },
    /// Upload, start, pause, resume or cancel the onboard sequence `name`.
    Sequence {
        name: String,
        action: SequenceAction,
    },
}

/// What an [`Order::Sequence`] does to a sequence stored on the rover.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "do", rename_all = "snake_case")]
pub enum SequenceAction {
    /// Stores (or replaces, when it is not running) the sequence: its TOML `text`, checked
    /// against the netlist in force; `file` names it in errors. `netlists` are the files its
    /// `apply` steps name (as written in the sequence) and their text.
    Upload {
        file: String,
        text: String,
        #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
        netlists: std::collections::BTreeMap<String, String>,
    },
    /// Runs it from its first step (checked again against the netlist in force).
    Start,
    /// Holds it before its next step; waits and conditions stop counting.
    Pause,
    /// Goes on from where it was paused.
    Resume,
    /// Stops it where it is (the rover stays in its task).
    Cancel,
}

/// How late after its time a time-tagged switch may still run unless it says otherwise: a
/// switch meant for a moment is not run minutes after it (the authority was down, the command
/// crossed a long outage).
pub const DEFAULT_LATE_BY_MS: u64 = 60_000;

/// One module changed in the netlist in force.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "op", rename_all = "snake_case")]
pub enum ModuleEdit {
    /// A new module; `params` are `key=value` (a TOML value); `links` are
    /// `TASK:from.port -> to.port` (each takes over the input it feeds).
    Add {
        name: String,
        kind: String,
        #[serde(default)]
        dnm: Option<String>,
        #[serde(default)]
        params: Vec<String>,
        #[serde(default)]
        links: Vec<String>,
    },
    /// A module restarted as another kind or with other parameters: `params` (`key=value`)
    /// change those; the others keep their values unless `kind` names another kind, which
    /// starts from its own defaults.
    Replace {
        name: String,
        #[serde(default)]
        kind: Option<String>,
        #[serde(default)]
        params: Vec<String>,
    },
    /// A module and every link to or from it removed.
    Remove { name: String },
}

/// A command as a station sends it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Sent {
    /// The station's sequence number: 1, 2, ... in the order the operator gave the commands.
    pub seq: u64,
    /// Unique across stations and restarts.
    pub id: String,
    pub order: Order,
    /// How many times the station had seen the rover make itself safe when the operator gave
    /// this command ([`Safing::epoch`] of the newest it knew). A command given before the
    /// station saw the latest safing is refused: it was meant for a rover that was not safe.
    #[serde(default)]
    pub safings_seen: u64,
    /// When the operator gave it, station time (ns since the Unix epoch): a switch's lead
    /// counts from here as far as the rover can trust it (never later than from the start of
    /// its transaction, never closer to its decision than the rover's margin).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub given_unix_ns: Option<u64>,
}

/// What a station sends the authority.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Uplink {
    pub station: String,
    /// Commands not yet acknowledged, oldest first.
    #[serde(default)]
    pub commands: Vec<Sent>,
    /// The oldest of the station's commands whose final fate it does not know yet.
    #[serde(default)]
    pub pending_from: u64,
    /// Commands acknowledged earlier whose final fate the station still waits for (at most
    /// 64): the answer carries their fates.
    #[serde(default)]
    pub waiting: Vec<u64>,
    /// How many events of each sequence the station holds (their numbers, from 1): the answer
    /// carries the next ones (a few dozen at most), so a history crosses the radio once.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub sequence_events: std::collections::BTreeMap<String, u64>,
}

/// The fate of one command on the rover.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum Fate {
    /// Stored by the rover; it runs after the station's earlier commands.
    Acknowledged,
    /// Not taken: the station's command `expected` must come first (send from there).
    OutOfOrder { expected: u64 },
    /// A time-tagged switch that waits for its time.
    Scheduled { at_unix_ns: u64 },
    /// In force on every DNM of the rover from `at_unix_ns` (rover time).
    Applied {
        revision: u64,
        task: Option<String>,
        at_unix_ns: u64,
    },
    /// A cancel that took effect: command `target` will not run.
    Cancelled { target: u64 },
    /// A time-tagged switch cancelled by command `by`.
    CancelledBy { by: u64 },
    /// Not run; nothing changed on the rover.
    Refused { reason: String },
    /// Taken by the rover without changing what its DNMs run (a sequence stored, started,
    /// paused...): `detail` says what it did.
    Done { at_unix_ns: u64, detail: String },
}

impl Fate {
    /// Whether the command has reached its end (nothing more will happen to it).
    pub fn is_final(&self) -> bool {
        matches!(
            self,
            Fate::Applied { .. }
                | Fate::Done { .. }
                | Fate::Cancelled { .. }
                | Fate::CancelledBy { .. }
                | Fate::Refused { .. }
        )
    }
}

/// The fate of command `seq`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    pub seq: u64,
    pub id: String,
    #[serde(flatten)]
    pub fate: Fate,
}

/// Something the authority did on its own (a switch after losing the ground station).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RoverEvent {
    /// Rover time, ns since the Unix epoch.
    pub at_unix_ns: u64,
    /// `link_loss` (switched to the task the netlist names), `safed` (a DNM of the rover made
    /// itself safe, adopted), `link_back`.
    pub what: String,
    pub detail: String,
    pub revision: u64,
    pub task: Option<String>,
}

/// The rover making itself safe: its authority after losing every ground station, or a DNM of
/// the rover on its own after losing its authority (adopted by the authority when it is back).
/// Nothing taken before it runs: commands stored and not yet run and time tags waiting are
/// refused with it as the reason, and so is any command a station gave before it saw it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Safing {
    /// 1 for the rover's first safing, then one more each time.
    pub epoch: u64,
    /// Rover time, ns since the Unix epoch.
    pub at_unix_ns: u64,
    /// The task the rover went to (the netlist's `on_link_loss.task`).
    pub task: String,
    /// Why, in words.
    pub reason: String,
}

/// The authority's heartbeat, published a few times a second on
/// [`crate::keys::authority_beat`]: every DNM of the rover keeps a lease on it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Beat {
    /// The authority DNM.
    pub authority: String,
    /// The authority's wall clock when it sent the beat, ns since the Unix epoch: each DNM
    /// measures its clock's offset with it.
    pub at_unix_ns: u64,
    /// The decided revision and task.
    pub revision: u64,
    pub task: Option<String>,
    /// Since a ground station was last heard, ms (the authority's loss-of-signal clock).
    pub ground_silent_ms: u64,
    /// The safing in force (the rover is on its task and no command ran since), if any.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safing: Option<Safing>,
    /// The onboard sequence running, if one: loss of signal does not make the rover safe
    /// while it runs (the operators planned for the silence), so a DNM does not either.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sequence: Option<String>,
}

/// The rover as its authority sees it.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct RoverState {
    /// The authority DNM.
    pub authority: String,
    pub revision: u64,
    pub task: Option<String>,
    /// The last events, oldest first.
    #[serde(default)]
    pub events: Vec<RoverEvent>,
    /// Time-tagged commands waiting: (station, seq, at).
    #[serde(default)]
    pub scheduled: Vec<(String, u64, u64)>,
    /// The rover's newest safing, kept after the rover left it: a station stamps its commands
    /// with its epoch ([`Sent::safings_seen`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_safing: Option<Safing>,
    /// Whether the rover is still in that safing (no command has run since).
    #[serde(default)]
    pub safe: bool,
    /// The sequences stored on the rover, by name.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sequences: Vec<SequenceStatus>,
}

/// Where a sequence stored on the rover stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SequenceState {
    /// Stored, not started (or stored again since it last ran).
    Stored,
    Running,
    Paused,
    /// Went through its last step (or an `end`).
    Finished,
    /// Stopped before its end: cancelled, a guard fired, a timeout, a refused step, a safing.
    Aborted,
}

/// A sequence stored on the rover, as stations see it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceStatus {
    pub name: String,
    /// The file it was uploaded from.
    pub file: String,
    pub state: SequenceState,
    /// The step it is on (0-based; `steps` once it went through all of them).
    pub step: usize,
    pub steps: usize,
    /// The current step, in words (`wait_until autopilot.progress.reached >= 3`).
    #[serde(default)]
    pub doing: String,
    /// Why it waits, or why it stopped, in words.
    #[serde(default)]
    pub why: String,
    /// Rover time the current step began, ns since the Unix epoch.
    pub step_since_unix_ns: u64,
    /// Its history, oldest first: in an answer to a station, the events after those it holds.
    #[serde(default)]
    pub history: Vec<SequenceEvent>,
    /// The number of the newest event in `history` (events are numbered from 1 per sequence;
    /// all of them when `history` is empty).
    #[serde(default)]
    pub events_total: u64,
}

/// Events of one answer, per sequence, at most.
pub const EVENTS_PER_ANSWER: usize = 32;

impl SequenceStatus {
    /// Keeps in `history` only the events after the first `seen`, [`EVENTS_PER_ANSWER`] at most
    /// (`events_total` then numbers the last kept).
    pub fn after(&mut self, seen: u64) {
        // A station that holds more than the rover ever had saw a record that started over
        // since (a new store): it gets this one from its start.
        let seen = if seen > self.events_total { 0 } else { seen };
        let len = self.history.len() as u64;
        let first = self.events_total.saturating_sub(len).saturating_add(1);
        let skip = seen.saturating_add(1).saturating_sub(first).min(len) as usize;
        self.history.drain(..skip);
        self.history.truncate(EVENTS_PER_ANSWER);
        if !self.history.is_empty() {
            self.events_total = first - 1 + skip as u64 + self.history.len() as u64;
        }
    }

    /// Adds the events of `newer` (an answer about the same sequence) to this one's history,
    /// keeping the last `keep`.
    pub fn merge(&mut self, newer: SequenceStatus, keep: usize) {
        let mut history = std::mem::take(&mut self.history);
        let (held, total) = (self.events_total, newer.events_total);
        let first = total
            .saturating_sub(newer.history.len() as u64)
            .saturating_add(1);
        if total < held {
            // The rover's record of it started over (a new store): take it as it is.
            history.clear();
        }
        for (i, e) in newer.history.iter().cloned().enumerate() {
            let n = first.saturating_add(i as u64);
            if n > held || total < held {
                history.push(e);
            }
        }
        let over = history.len().saturating_sub(keep);
        history.drain(..over);
        *self = SequenceStatus {
            history,
            events_total: total.max(if total < held { 0 } else { held }),
            ..newer
        };
    }
}

/// Something that happened to a sequence on the rover.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SequenceEvent {
    /// Rover time, ns since the Unix epoch.
    pub at_unix_ns: u64,
    pub sequence: String,
    /// How many times the sequence was started (1 for its first run).
    pub run: u64,
    /// `stored`, `started`, `step_started`, `step_done`, `condition_met`, `timed_out`,
    /// `guard_fired`, `paused`, `resumed`, `finished`, `aborted`, `resumed_after_restart`.
    pub what: String,
    /// The step it concerns, if one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step: Option<usize>,
    pub detail: String,
    /// The send time of the sample on which a condition or guard held, rover time (ns since
    /// the Unix epoch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sample_unix_ns: Option<u64>,
    /// What a step's (or a guard's) transaction put in force, if it did.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub in_force: Option<InForce>,
}

/// A decision in force on every DNM of the rover.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InForce {
    pub revision: u64,
    pub task: Option<String>,
    /// The instant every DNM put it in force, rover time (ns since the Unix epoch).
    pub at_unix_ns: u64,
}

/// What the authority answers an [`Uplink`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Downlink {
    /// Rover time of the answer, ns since the Unix epoch.
    pub at_unix_ns: u64,
    pub outcomes: Vec<Outcome>,
    pub rover: RoverState,
    /// Set when the uplink could not be read; nothing was taken.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn status(total: u64, numbers: impl Iterator<Item = u64>) -> SequenceStatus {
        SequenceStatus {
            name: "s".into(),
            file: "s.toml".into(),
            state: SequenceState::Running,
            step: 0,
            steps: 1,
            doing: String::new(),
            why: String::new(),
            step_since_unix_ns: 0,
            history: numbers
                .map(|n| SequenceEvent {
                    at_unix_ns: n,
                    sequence: "s".into(),
                    run: 1,
                    what: "step_done".into(),
                    step: None,
                    detail: String::new(),
                    sample_unix_ns: None,
                    in_force: None,
                })
                .collect(),
            events_total: total,
        }
    }

    /// A station gets each event once, at most a few dozen an answer, and ends up holding
    /// them all in order; a rover whose record started over is taken as it is.
    #[test]
    fn sequence_events_cross_once_and_add_up_at_the_station() {
        // The rover keeps events 37..=100 (64 of them).
        let rover = status(100, 37..=100);
        let mut held = status(0, 1..1);
        for _ in 0..4 {
            let mut answer = rover.clone();
            answer.after(held.events_total);
            assert!(answer.history.len() <= EVENTS_PER_ANSWER);
            held.merge(answer, 256);
        }
        assert_eq!(held.events_total, 100);
        let got: Vec<u64> = held.history.iter().map(|e| e.at_unix_ns).collect();
        assert_eq!(got, (37..=100).collect::<Vec<_>>());
        // Up to date: nothing more crosses.
        let mut answer = rover.clone();
        answer.after(100);
        assert!(answer.history.is_empty());
        assert_eq!(answer.events_total, 100);
        // The rover's store was lost: its new record replaces the station's.
        let mut answer = status(3, 1..=3);
        answer.after(100);
        held.merge(answer, 256);
        assert_eq!(held.events_total, 3);
        assert_eq!(held.history.len(), 3);
    }

    /// A rover's answer numbering its events at the end of the counter is taken without harm.
    #[test]
    fn sequence_events_numbered_at_the_end_of_the_counter_are_taken() {
        let mut answer = status(u64::MAX, 1..1);
        answer.after(0);
        let mut held = status(0, 1..1);
        held.merge(answer, 256);
        let mut answer = status(0, 1..=5);
        answer.events_total = u64::MAX;
        answer.after(3);
        assert_eq!(answer.history.len(), 5);
        held.merge(answer, 256);
        // (The station held the counter's end already: nothing after it is new.)
        assert_eq!(held.events_total, u64::MAX);
    }

    /// Every fate survives the trip inside an outcome (its fields sit beside the outcome's).
    #[test]
    fn every_fate_reads_back_inside_an_outcome() {
        let fates = [
            Fate::Acknowledged,
            Fate::OutOfOrder { expected: 3 },
            Fate::Scheduled {
                at_unix_ns: u64::MAX,
            },
            Fate::Applied {
                revision: 4,
                task: Some("a".into()),
                at_unix_ns: 1_795_303_481_369_000_000,
            },
            Fate::Cancelled { target: 2 },
            Fate::CancelledBy { by: 9 },
            Fate::Refused {
                reason: "no".into(),
            },
            Fate::Done {
                at_unix_ns: 1,
                detail: "sequence `explore` stored".into(),
            },
        ];
        for fate in fates {
            let o = Outcome {
                seq: 7,
                id: "g-7".into(),
                fate,
            };
            let json = serde_json::to_string(&o).unwrap();
            let back: Outcome =
                serde_json::from_str(&json).unwrap_or_else(|e| panic!("{json}: {e}"));
            assert_eq!(back, o);
        }
    }
}
