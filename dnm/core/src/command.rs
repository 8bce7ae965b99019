//! What other threads hand a DNM's thread, and where the answers go.

use dnm_netlist::Netlist;
use dnm_proto::{DnmReport, NetlistState, SwitchRecord};

use crate::DnmError;

/// Identifies a command for exactly-once handling: the sending client and its id.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct CommandKey {
    pub client: String,
    pub id: String,
}

/// Where a command's answer goes: a function the DNM's thread calls once. It must not block
/// (send it on a channel, for example).
pub struct Reply<T>(Box<dyn FnOnce(T) + Send>);

impl<T> std::fmt::Debug for Reply<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Reply")
    }
}

impl<T: Send + 'static> Reply<T> {
    pub fn new(f: impl FnOnce(T) + Send + 'static) -> Self {
        Self(Box::new(f))
    }

    /// A reply that lands on a channel the caller waits on.
    pub fn channel() -> (Self, std::sync::mpsc::Receiver<T>) {
        let (tx, rx) = std::sync::mpsc::sync_channel(1);
        (
            Self::new(move |v| {
                let _ = tx.send(v);
            }),
            rx,
        )
    }

    pub(crate) fn send(self, v: T) {
        (self.0)(v)
    }
}

/// What a DNM's thread takes from other threads.
#[derive(Debug)]
pub enum Command {
    Status(Reply<DnmReport>),
    /// Hand the plugins a fresh snapshot in this wake, once its module statuses are read
    /// (unless a command of the same wake made one): a tool asks for the live figures (steps,
    /// rates, CPU), which a snapshot otherwise carries at most
    /// [`SNAPSHOT_EVERY`](crate::SNAPSHOT_EVERY) old.
    Refresh,
    Netlist(Reply<NetlistState>),
    Switch {
        task: String,
        key: Option<CommandKey>,
        reply: Reply<Result<SwitchRecord, DnmError>>,
    },
    /// Apply a validated netlist. The answer comes when the revision is committed or refused;
    /// switches go on meanwhile.
    Apply {
        netlist: Box<Netlist>,
        key: Option<CommandKey>,
        reply: Reply<Result<u64, DnmError>>,
    },
    /// First phase of a transaction the system's authority runs across its DNMs: get ready to
    /// put `txn` in force and hold it until the decision. The answer comes once everything is
    /// prepared (for an apply: every module has opened the new revision's subscriptions).
    Prepare {
        txn: Txn,
        reply: Reply<Result<(), DnmError>>,
    },
    /// Second phase: commit the held transaction `id` at `at_unix_ns` (wall clock; at once if
    /// past) or drop it. The answer comes when it took effect (`None` when dropped). A retried
    /// decision is answered with its first result.
    Decide {
        decision: Decision,
        reply: Reply<Result<Option<SwitchRecord>, DnmError>>,
    },
    /// Takes over what the authority decided, outside any transaction: a DNM that missed a
    /// decision (it restarted, or was cut off) catches up with it. Applies `netlist` as
    /// `revision` in `task`, or only switches when the revision is already in force.
    Adopt {
        revision: u64,
        task: Option<String>,
        netlist: Box<Netlist>,
        reply: Reply<Result<u64, DnmError>>,
    },
    /// See [`SafeOrder`]. Answered once the safe task is in force here.
    Safe {
        order: SafeOrder,
        reply: Reply<Result<(), DnmError>>,
    },
}

/// Put the DNM's own modules on its safe task now: its authority's safing (`epoch`), or its
/// lease on the authority that ran out (`epoch` `None`). Whatever the DNM holds (a prepared
/// transaction, a decision waiting for its instant) is dropped first, so nothing decided
/// before the safing is put in force after it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SafeOrder {
    pub task: String,
    pub epoch: Option<u64>,
    pub reason: String,
}

/// What a transaction puts in force: `revision` with `task` active. With a netlist it is an
/// apply of that netlist as `revision`; without, a switch within the revision in force.
#[derive(Debug)]
pub struct Txn {
    pub id: u64,
    pub revision: u64,
    pub task: Option<String>,
    pub netlist: Option<Box<Netlist>>,
}

/// The authority's decision on transaction `id`, which put (or would have put) `revision` with
/// `task` in force.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Decision {
    pub id: u64,
    pub commit: bool,
    /// When every DNM puts it in force, wall-clock ns since the Unix epoch.
    pub at_unix_ns: u64,
    pub revision: u64,
    pub task: Option<String>,
}
