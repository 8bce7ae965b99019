//! What can go wrong in a DNM's operations.

/// Failures of DNM operations. Each leaves the running system as it was.
#[derive(Debug, thiserror::Error)]
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
        "modules did not prepare revision {revision} within {timeout_ms} ms: {modules}; the previous revision stays active"
    )]
    PrepareTimeout {
        revision: u64,
        timeout_ms: u128,
        modules: String,
    },
    #[error(
        "module `{module}` exited while preparing revision {revision} ({exit}); the previous revision stays active"
    )]
    PrepareExit {
        module: String,
        revision: u64,
        exit: String,
    },
    #[error(
        "module `{module}` could not prepare revision {revision} (its log says why); the previous revision stays active"
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
}

/// Maps an iceoryx2 error to [`DnmError::Ipc`], naming what failed.
pub(crate) fn ipc<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> DnmError {
    move |e| DnmError::Ipc(format!("{what}: {e:?}"))
}
