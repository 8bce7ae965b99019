//! What other threads hand a DNM's thread, and where the answers go.

use dnm_netlist::Netlist;
use dnm_proto::{DnmReport, NetlistState, SwitchRecord};

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
    Netlist(Reply<NetlistState>),
    Switch {
        task: String,
        key: Option<CommandKey>,
        reply: Reply<Result<SwitchRecord, String>>,
    },
    /// Apply a validated netlist. The answer comes when the revision is committed or refused;
    /// switches go on meanwhile.
    Apply {
        netlist: Box<Netlist>,
        key: Option<CommandKey>,
        reply: Reply<Result<u64, String>>,
    },
}
