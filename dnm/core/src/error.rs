//! What can go wrong in a DNM's operations.

/// Failures of DNM operations, as their replies carry them. Each leaves the running system as
/// it was.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DnmError {
    #[error("shared memory: {0}")]
    Ipc(String),
    #[error(
        "DNM `{dnm}` of system `{system}` is already running on this machine (its task word exists); stop it first"
    )]
    AlreadyRunning { system: String, dnm: String },
    #[error("unknown task `{task}`; defined tasks: {known}")]
    UnknownTask { task: String, known: String },
    #[error(
        "netlist does not declare DNM `{0}`, which this process hosts; keep it or stop this DNM first"
    )]
    DnmMissing(String),
    #[error(
        "modules did not prepare revision {revision} within {timeout_ms} ms: {modules}; {}", stays(*revision)
    )]
    PrepareTimeout {
        revision: u64,
        timeout_ms: u128,
        modules: String,
    },
    #[error(
        "module `{module}` exited while preparing revision {revision} ({exit}); {}", stays(*revision)
    )]
    PrepareExit {
        module: String,
        revision: u64,
        exit: String,
    },
    #[error(
        "module `{module}` could not prepare revision {revision} (its log says why); {}", stays(*revision)
    )]
    PrepareFailed { module: String, revision: u64 },
    #[error("{plugin}: {why}; the previous revision stays active")]
    Plugin { plugin: &'static str, why: String },
    #[error("cannot start module `{module}` ({exec}): {why}")]
    Spawn {
        module: String,
        exec: String,
        why: String,
    },
    #[error("the DNM is busy: {0} commands are queued; try again")]
    Busy(usize),
    #[error("the DNM has stopped")]
    Stopped,
    #[error("{0}")]
    Refused(String),
    #[error("command id `{id}` of `{client}` was already used for {used_for}")]
    IdReused {
        id: String,
        client: String,
        used_for: &'static str,
    },
    /// A transaction is held until its decision: nothing else is prepared or adopted meanwhile.
    #[error("DNM `{dnm}` holds transaction {txn}{until}")]
    Holding {
        dnm: String,
        txn: u64,
        until: &'static str,
    },
    #[error("DNM `{dnm}` has revision {in_force} in force, not {wanted}")]
    OtherRevision {
        dnm: String,
        in_force: u64,
        wanted: u64,
    },
    #[error("DNM `{dnm}` is applying a netlist; {retry}")]
    Applying { dnm: String, retry: &'static str },
    #[error("modules of DNM `{0}` are still stopping; send the transaction again")]
    StillStopping(String),
    #[error("transaction {0} dropped")]
    Dropped(u64),
    #[error(
        "DNM `{dnm}` does not hold transaction {txn} (it restarted or never prepared it); it needs revision {revision} adopted"
    )]
    NotHeld {
        dnm: String,
        txn: u64,
        revision: u64,
    },
    #[error("transaction {0} is no longer held here")]
    NoLongerHeld(u64),
    #[error("transaction {txn} given up: no decision within {limit_s} s")]
    GivenUp { txn: u64, limit_s: u64 },
    /// What the DNM held was dropped when it made itself safe.
    #[error("dropped: DNM `{dnm}` made itself safe ({reason})")]
    Safed { dnm: String, reason: String },
}

/// Maps an iceoryx2 error to [`DnmError::Ipc`], naming what failed.
pub(crate) fn ipc<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> DnmError {
    move |e| DnmError::Ipc(format!("{what}: {e:?}"))
}

/// What a failed prepare of `revision` leaves running.
fn stays(revision: u64) -> &'static str {
    if revision <= 1 {
        "nothing was running before it, and none of it runs"
    } else {
        "the previous revision stays active"
    }
}
