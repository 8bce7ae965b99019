//! What the parts of a running system say to each other: the requests an operator's tool sends
//! a DNM, the replies, the reports a DNM gives of itself and its modules, and the Zenoh key
//! scheme ([`keys`]). Plain data with serde, so the `dnm` command, the ground station, the
//! Zenoh bridge and tests share one definition and none of them needs the DNM to read it.
//!
//! ```
//! use dnm_proto::{Request, RemoteCommand, keys};
//! let cmd = RemoteCommand::new("station-1", "42", Request::Switch { task: "auto".into() });
//! let json = serde_json::to_string(&cmd).unwrap();
//! assert_eq!(keys::cmd("beetle", "rover"), "beetle/dnm/rover/cmd");
//! assert!(json.contains(r#""cmd":"switch""#));
//! ```

pub mod clock;
pub mod keys;
pub mod playback;
pub mod station;

use serde::{Deserialize, Serialize};

/// Resident memory of a process, split so shared-memory segments are counted separately.
#[derive(Debug, Clone, Copy, Default, Serialize, Deserialize, PartialEq, Eq)]
pub struct Memory {
    /// Private anonymous memory (heap, stacks), KiB.
    pub anon_kib: u64,
    /// Mapped files (code, libraries), KiB.
    pub file_kib: u64,
    /// Shared memory (iceoryx2 segments), KiB.
    pub shmem_kib: u64,
}

impl Memory {
    /// Resident memory not counting shared-memory segments.
    pub fn private_kib(&self) -> u64 {
        self.anon_kib + self.file_kib
    }
}

/// Lifecycle of a hosted module, as its DNM sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ModuleRunState {
    Starting,
    Running,
    /// Alive but not stepping within its deadline (deadlock, endless loop, stopped); handled
    /// by its restart policy.
    Hung,
    /// Exited, crashed or killed; restarts per its policy.
    Failed,
    /// Stopped on purpose, or failed past its restart budget.
    Stopped,
}

/// What a DNM knows about one module.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleReport {
    pub name: String,
    pub kind: String,
    pub state: ModuleRunState,
    pub pid: Option<u32>,
    pub restarts: u32,
    /// Times it was found hung.
    #[serde(default)]
    pub hangs: u32,
    pub last_exit: Option<String>,
    pub plan_revision: u64,
    pub steps: u64,
    pub sent: u64,
    pub step_errors: u64,
    /// Steps per second over the last second.
    pub rate_hz: f64,
    /// Time since the module's last sign of life (a step or, while idle, a heartbeat), ms.
    pub last_step_age_ms: Option<u64>,
    /// How long it may go without a sign of life before it is reported hung, ms.
    #[serde(default)]
    pub hung_after_ms: u64,
    pub cpu_percent: f64,
    pub memory: Option<Memory>,
}

/// A task switch, as performed.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SwitchRecord {
    /// The DNM that switched.
    #[serde(default)]
    pub dnm: String,
    pub revision: u64,
    pub from: Option<String>,
    pub to: String,
    /// Time to perform the switch inside the DNM (lookup and the store), ns.
    pub duration_ns: u64,
    /// CLOCK_MONOTONIC time of the switch, ns.
    pub at_ns: u64,
}

/// Something that happened to a module: recorded, reported, and kept in the DNM's report.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ModuleEvent {
    pub dnm: String,
    pub module: String,
    /// `started`, `exited`, `hung`, `recovered`, `restarting`, `stopped`, `gave_up`.
    pub what: String,
    pub detail: String,
    /// CLOCK_MONOTONIC time, ns.
    pub at_ns: u64,
}

/// How another DNM of the system looks from here.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PeerReport {
    pub dnm: String,
    /// `alive`, `left` (stopped in order: it said so before its liveliness token went away),
    /// `lost` (its token went away unannounced) or `unseen`.
    pub state: String,
    /// How long it has been in that state, ms (absent while unseen).
    pub for_ms: Option<u64>,
}

/// Traffic of one route between DNMs.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RouteReport {
    pub key: String,
    pub messages: u64,
    pub bytes: u64,
    /// Samples that could not be forwarded (too large, shared memory full).
    pub dropped: u64,
}

/// A DNM's lease on its authority: when it last heard the authority's beat, and how far its
/// wall clock is from the authority's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LeaseReport {
    pub authority: String,
    /// Since the last beat, ms (`None`: never heard).
    pub heard_ms: Option<u64>,
    /// The authority's wall clock minus this DNM's, ms (the beat's one-way delay included,
    /// the smallest of the last few), `None` before the first beat.
    pub clock_offset_ms: Option<f64>,
    /// Beyond this offset the DNM refuses transactions (it would switch at the wrong moment).
    pub max_clock_offset_ms: u64,
}

/// A DNM's routes to and from other DNMs.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct NetReport {
    /// Outputs published for other DNMs.
    pub published: Vec<RouteReport>,
    /// Remote outputs mirrored into this DNM's shared memory.
    pub mirrored: Vec<RouteReport>,
    /// Queries refused because the DNM's query queue was full.
    #[serde(default)]
    pub queries_refused: u64,
    /// Queries answered.
    #[serde(default)]
    pub queries_answered: u64,
}

/// What a DNM's recorder has done.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct RecordReport {
    pub file: String,
    pub messages: u64,
    pub bytes: u64,
    /// Samples not recorded: queue full, overwritten before the reader got to them, or the
    /// writer stopped.
    pub dropped: u64,
    pub files: u64,
    /// Why the writer stopped, if it did (disk full, ...): nothing more is written.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// How regularly the DNM's supervision runs.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct SupervisionReport {
    /// The configured period, ms.
    pub period_ms: u64,
    /// Supervision passes so far.
    pub passes: u64,
    /// Longest time between two passes since the DNM started, ms.
    pub max_gap_ms: u64,
    /// Snapshots handed to the DNM's plugins so far (on changes, on request, and at least one
    /// a second).
    #[serde(default)]
    pub snapshots: u64,
}

/// A DNM on the task its netlist names for loss of signal because it was told to or by itself:
/// its authority's safing (`epoch`), or its own lease on the authority that ran out (`epoch`
/// `None` until the authority adopts it). Cleared by the next decision put in force.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Safed {
    /// The authority's safing it follows; `None`: made safe on its own.
    pub epoch: Option<u64>,
    /// Wall clock, ns since the Unix epoch.
    pub at_unix_ns: u64,
    pub task: String,
    pub reason: String,
}

/// The state of one DNM, for operators and tools.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DnmReport {
    pub system: String,
    pub dnm: String,
    pub pid: u32,
    /// The committed netlist revision.
    pub revision: u64,
    pub netlist_digest: String,
    pub netlist_file: Option<String>,
    pub active_task: Option<String>,
    pub tasks: Vec<String>,
    /// The revision being prepared, while an apply is in progress.
    #[serde(default)]
    pub preparing: Option<u64>,
    /// The newest revision number tried here (committed or not); the next must be newer.
    #[serde(default)]
    pub last_attempt: u64,
    /// The authority's transaction this DNM holds (prepared or scheduled), if any.
    #[serde(default)]
    pub holding: Option<u64>,
    /// When the scheduled decision takes effect, wall-clock ns since the Unix epoch.
    #[serde(default)]
    pub scheduled_at_unix_ns: Option<u64>,
    /// Module processes still stopping (removed, replaced, or of an apply undone).
    #[serde(default)]
    pub modules_stopping: u32,
    /// On its loss-of-signal task by the authority's safing or its own lease, if it is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safed: Option<Safed>,
    /// Its lease on the system's authority, where it follows one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lease: Option<LeaseReport>,
    pub cpu_percent: f64,
    pub memory: Option<Memory>,
    pub modules: Vec<ModuleReport>,
    pub switches: Vec<SwitchRecord>,
    /// The last module events (faults, restarts), oldest first.
    #[serde(default)]
    pub events: Vec<ModuleEvent>,
    /// Shared-memory leftovers of dead processes removed so far.
    pub cleaned_dead_nodes: u64,
    #[serde(default)]
    pub supervision: SupervisionReport,
    /// The other DNMs of the system, as seen over Zenoh (empty without Zenoh).
    #[serde(default)]
    pub peers: Vec<PeerReport>,
    /// Traffic of the routes to and from other DNMs.
    #[serde(default)]
    pub routes: NetReport,
    /// The recorder's progress, when recording.
    #[serde(default)]
    pub recording: Option<RecordReport>,
}

/// What a monitor shows of a DNM: `<system>/dnm/<dnm>?glance` answers it (a few KiB instead of
/// the whole report, asked every second across the radio). A whole [`DnmReport`] reads as one.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct DnmGlance {
    pub dnm: String,
    #[serde(default)]
    pub revision: u64,
    #[serde(default)]
    pub active_task: Option<String>,
    #[serde(default)]
    pub modules: Vec<ModuleGlance>,
    /// The last module events, oldest first.
    #[serde(default)]
    pub events: Vec<ModuleEvent>,
    /// The last switches, oldest first.
    #[serde(default)]
    pub switches: Vec<SwitchRecord>,
    #[serde(default)]
    pub peers: Vec<PeerReport>,
}

/// One module in a [`DnmGlance`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ModuleGlance {
    pub name: String,
    pub state: ModuleRunState,
    #[serde(default)]
    pub restarts: u32,
    #[serde(default)]
    pub rate_hz: f64,
    /// Times it was found hung.
    #[serde(default)]
    pub hangs: u32,
    #[serde(default)]
    pub cpu_percent: f64,
}

/// Events and switches a glance carries at most.
pub const GLANCE_HISTORY: usize = 16;

impl DnmGlance {
    pub fn of(r: &DnmReport) -> Self {
        let last = |n: usize| n.saturating_sub(GLANCE_HISTORY);
        Self {
            dnm: r.dnm.clone(),
            revision: r.revision,
            active_task: r.active_task.clone(),
            modules: r
                .modules
                .iter()
                .map(|m| ModuleGlance {
                    name: m.name.clone(),
                    state: m.state,
                    restarts: m.restarts,
                    rate_hz: m.rate_hz,
                    hangs: m.hangs,
                    cpu_percent: m.cpu_percent,
                })
                .collect(),
            events: r.events[last(r.events.len())..].to_vec(),
            switches: r.switches[last(r.switches.len())..].to_vec(),
            peers: r.peers.clone(),
        }
    }
}

/// What a DNM runs, in brief: `<system>/dnm/<dnm>?brief` answers it (a few hundred bytes
/// instead of the whole report, for checks across a slow link).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DnmBrief {
    pub dnm: String,
    pub pid: u32,
    pub revision: u64,
    pub netlist_digest: String,
    pub active_task: Option<String>,
    pub preparing: Option<u64>,
    pub last_attempt: u64,
    pub holding: Option<u64>,
    /// Modules not running (starting, failed, hung, stopped).
    pub modules_down: u32,
    /// Module processes still stopping (a new apply waits for them).
    #[serde(default)]
    pub modules_stopping: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub safed: Option<Safed>,
    /// The authority's wall clock minus this DNM's, ms.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub clock_offset_ms: Option<f64>,
}

impl DnmBrief {
    pub fn of(r: &DnmReport) -> Self {
        Self {
            dnm: r.dnm.clone(),
            pid: r.pid,
            revision: r.revision,
            netlist_digest: r.netlist_digest.clone(),
            active_task: r.active_task.clone(),
            preparing: r.preparing,
            last_attempt: r.last_attempt,
            holding: r.holding,
            modules_down: r
                .modules
                .iter()
                .filter(|m| m.state != ModuleRunState::Running)
                .count() as u32,
            modules_stopping: r.modules_stopping,
            safed: r.safed.clone(),
            clock_offset_ms: r.lease.as_ref().and_then(|l| l.clock_offset_ms),
        }
    }
}

/// The netlist a DNM has committed, as `<system>/dnm/<dnm>/netlist` answers it.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct NetlistState {
    pub system: String,
    pub dnm: String,
    pub revision: u64,
    pub digest: String,
    pub file: Option<String>,
    pub active_task: Option<String>,
    pub text: Option<String>,
}

/// A request to a running system.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case")]
pub enum Request {
    /// Every hosted DNM's report.
    Status,
    /// The netlist text in force.
    Netlist,
    /// Switch every hosted DNM to `task`.
    Switch { task: String },
    /// Validate and apply a new netlist; `file` names it in errors.
    Apply { file: String, text: String },
    /// First phase of the authority's transaction `txn`: prepare `revision` with `task` in
    /// force (an apply of netlist `text` when given, else a switch) and hold it until decided.
    Prepare {
        txn: u64,
        revision: u64,
        #[serde(default)]
        task: Option<String>,
        #[serde(default)]
        file: Option<String>,
        #[serde(default)]
        text: Option<String>,
    },
    /// Second phase: put transaction `txn` in force at `at_unix_ns` (wall clock), or drop it.
    Decide {
        txn: u64,
        commit: bool,
        at_unix_ns: u64,
        revision: u64,
        #[serde(default)]
        task: Option<String>,
    },
    /// Take over what the authority decided, outside a transaction (a DNM that missed it).
    Adopt {
        revision: u64,
        #[serde(default)]
        task: Option<String>,
        file: String,
        text: String,
    },
}

/// The answer to a [`Request`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Response {
    pub ok: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub revision: Option<u64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub switches: Vec<SwitchRecord>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dnms: Vec<DnmReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub netlist: Option<String>,
}

impl Response {
    pub fn error(msg: impl Into<String>) -> Self {
        Self {
            ok: false,
            error: Some(msg.into()),
            ..Self::default()
        }
    }
}

/// One answer from several DNMs or processes: all must agree to be ok.
pub fn merge(answers: Vec<Response>) -> Response {
    let mut out = Response {
        ok: true,
        ..Response::default()
    };
    let mut errors = Vec::new();
    for r in answers {
        if !r.ok {
            out.ok = false;
            errors.extend(r.error);
        }
        out.revision = out.revision.max(r.revision);
        out.switches.extend(r.switches);
        out.dnms.extend(r.dnms);
        if out.netlist.is_none() {
            out.netlist = r.netlist;
        }
    }
    if !errors.is_empty() {
        out.error = Some(errors.join("\n"));
    }
    out.dnms.sort_by(|a, b| a.dnm.cmp(&b.dnm));
    out
}

/// A command sent over Zenoh to `<system>/dnm/<dnm>/cmd`: a [`Request`], the sending client's
/// name and the command's id. A DNM applies each (client, id) once and answers a retry with the
/// first answer; two clients may use the same id without colliding.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RemoteCommand {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<String>,
    #[serde(flatten)]
    pub request: Request,
}

impl RemoteCommand {
    pub fn new(client: impl Into<String>, id: impl Into<String>, request: Request) -> Self {
        Self {
            client: Some(client.into()),
            id: Some(id.into()),
            request,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn commands_read_with_and_without_client() {
        let c: RemoteCommand =
            serde_json::from_str(r#"{"id":"1","cmd":"switch","task":"a"}"#).unwrap();
        assert_eq!(c.client, None);
        assert!(matches!(c.request, Request::Switch { ref task } if task == "a"));
        let back: RemoteCommand = serde_json::from_str(
            &serde_json::to_string(&RemoteCommand::new("g", "1", Request::Status)).unwrap(),
        )
        .unwrap();
        assert_eq!(back.client.as_deref(), Some("g"));
    }

    #[test]
    fn merge_fails_if_any_fails_and_sorts_dnms() {
        let m = merge(vec![
            Response {
                ok: true,
                revision: Some(2),
                ..Response::default()
            },
            Response::error("b refused"),
        ]);
        assert!(!m.ok);
        assert_eq!(m.revision, Some(2));
        assert_eq!(m.error.as_deref(), Some("b refused"));
    }
}
