//! What a DNM and its module processes say to each other through shared memory.
//!
//! Every DNM has its own iceoryx2 namespace (a file prefix), so DNMs on one machine never see
//! each other's services. Inside it:
//!
//! | service                 | pattern    | written by | carries                                   |
//! |-------------------------|------------|------------|-------------------------------------------|
//! | `<module>/<port>`       | pub/sub    | module     | the output port's samples (zero-copy)     |
//! | `<module>/<port>/ev`    | event      | module     | "new sample" after every send             |
//! | `_dnm/task`             | blackboard | DNM        | the (revision, task slot) word, its time  |
//! | `_dnm/plan/<module>`    | pub/sub    | DNM        | the module's [`Plan`]s (JSON, history 2)  |
//! | `_dnm/wake/<module>`    | event      | DNM        | "a new plan is posted" / "stop"           |
//! | `_dnm/status/<module>`  | pub/sub    | module     | [`Status`] heartbeats and plan acks       |
//! | `_dnm/ev`               | event      | modules    | "a status was posted"                     |
//!
//! A task switch is one store into `_dnm/task`. Modules read that word once per step and pick
//! every input's source from their plan with it, so a step never mixes two tasks.

use iceoryx2::prelude::*;
use serde::{Deserialize, Serialize};

use dnm_netlist::{ParamValue, Trigger};
use std::collections::BTreeMap;

/// Header in front of every port sample.
#[repr(C)]
#[derive(Debug, Clone, Copy, Default, ZeroCopySend)]
#[type_name("dnm::PortHeader")]
pub struct PortHeader {
    /// CLOCK_MONOTONIC time the producer sent it, in nanoseconds.
    pub stamp_ns: u64,
    /// Per-port sequence number, from 0.
    pub seq: u64,
    /// The task word the producer ran under.
    pub task_word: u64,
}

/// Largest plan message, in bytes.
pub const MAX_PLAN_BYTES: usize = 64 * 1024;
/// Subscribers an output port admits at least. The DNM creates each port's service for its
/// readers in the netlist plus spares ([`dnm_netlist::Payload::subscribers_for`]).
pub const MAX_PORT_SUBSCRIBERS: usize = dnm_netlist::MIN_SUBSCRIBERS;
/// The same for a large (over 64 KiB) byte port: each subscriber reserves whole samples.
pub const MAX_LARGE_PORT_SUBSCRIBERS: usize = dnm_netlist::MIN_LARGE_SUBSCRIBERS;
/// Payloads above this many bytes use the large-port limits.
pub use dnm_netlist::LARGE_PAYLOAD_BYTES;
/// Publishers one output port admits: the module, a replacement starting while the old one is
/// cleaned up, and a replay.
pub const MAX_PORT_PUBLISHERS: usize = 3;
/// Samples a subscriber keeps when it falls behind (then the oldest are overwritten).
pub const PORT_BUFFER: usize = 4;
/// Samples a subscriber of a large port keeps.
pub const LARGE_PORT_BUFFER: usize = 2;

/// Samples a recorder's subscriber may hold: it drains the port periodically instead of
/// waking on every sample, so it needs a deeper buffer than a module (which keeps only the
/// latest). Consumers still use [`port_limits`]'s buffer.
pub fn recorder_buffer(payload: &dnm_netlist::Payload) -> usize {
    match payload.max_bytes() {
        b if b <= 1024 => 32,
        b if b <= LARGE_PAYLOAD_BYTES => 8,
        // A 500 Hz camera sends 5 frames per 10 ms drain.
        _ => 8,
    }
}

/// (max subscribers, subscriber buffer) of a port with this payload. Shared memory per
/// publisher is about `subscribers * (buffer + borrowed) + 3` samples of the largest size.
pub fn port_limits(payload: &dnm_netlist::Payload) -> (usize, usize) {
    if payload.max_bytes() > LARGE_PAYLOAD_BYTES {
        (MAX_LARGE_PORT_SUBSCRIBERS, LARGE_PORT_BUFFER)
    } else {
        (MAX_PORT_SUBSCRIBERS, PORT_BUFFER)
    }
}
/// Samples a reader may hold at once (the latest value plus one being swapped in).
pub const PORT_BORROWED: usize = 2;
/// Connections of publishers gone (a module restarted or replaced) whose samples a subscriber
/// has not read yet that it keeps, beside its live ones. iceoryx2's default, 128, gives every
/// subscriber a table of 131 connections of 3.6 KB, written through at its creation: about
/// 470 KB per subscriber, 20 MB of Beetle-One's DNM process without recording. 16 is five
/// replacements of every publisher a port admits; past it the oldest gone publisher's unread
/// samples are dropped (iceoryx2 warns), never one a reader holds (it keeps at least
/// [`PORT_BORROWED`] for those).
pub const EXPIRED_CONNECTIONS: usize = 16;
/// Modules one DNM hosts at most.
pub const MAX_MODULES: usize = 256;

/// The active-task word: netlist revision in the high bits, task slot in the low 16.
pub fn task_word(revision: u64, slot: u16) -> u64 {
    (revision << 16) | u64::from(slot)
}

/// Splits a task word into (revision, slot).
pub fn split_task_word(word: u64) -> (u64, u16) {
    (word >> 16, (word & 0xffff) as u16)
}

/// Task slot meaning "no task active": every input is unconnected.
pub const NO_TASK: u16 = u16::MAX;

pub fn output_service(module: &str, port: &str) -> String {
    format!("{module}/{port}")
}

pub fn output_event(module: &str, port: &str) -> String {
    format!("{module}/{port}/ev")
}

pub const TASK_SERVICE: &str = "_dnm/task";
/// Key of the task word in the [`TASK_SERVICE`] blackboard.
pub const TASK_WORD_KEY: u64 = 0;
/// Key of the time (CLOCK_MONOTONIC ns) the task word was last stored: an input switched to
/// another source shows only samples sent since.
pub const SWITCHED_AT_KEY: u64 = 1;
pub const DNM_EVENT: &str = "_dnm/ev";

pub fn plan_service(module: &str) -> String {
    format!("_dnm/plan/{module}")
}

pub fn wake_event(module: &str) -> String {
    format!("_dnm/wake/{module}")
}

pub fn status_service(module: &str) -> String {
    format!("_dnm/status/{module}")
}

/// Why [`dnm_config`] failed.
#[derive(Debug, thiserror::Error)]
pub enum DnmConfigError {
    /// The prefix is not a valid iceoryx2 file name.
    #[error("bad shared-memory prefix `{prefix}`: {source:?}")]
    Prefix {
        prefix: String,
        #[source]
        source: SemanticStringError,
    },
}

/// The message, for callers that report errors as strings.
impl From<DnmConfigError> for String {
    fn from(e: DnmConfigError) -> Self {
        e.to_string()
    }
}

/// The iceoryx2 configuration of one DNM's namespace.
///
/// Its nodes are listed in a folder of their own (`nodes/<prefix>` under iceoryx2's root): a
/// sweep for dead processes, which every restart waits for, then reads this namespace's few
/// entries, not every node any system on the machine ever left behind.
pub fn dnm_config(prefix: &str) -> Result<Config, DnmConfigError> {
    let bad = |source| DnmConfigError::Prefix {
        prefix: prefix.to_string(),
        source,
    };
    let mut config = Config::default();
    config.global.prefix = FileName::new(prefix.as_bytes()).map_err(bad)?;
    config
        .defaults
        .publish_subscribe
        .subscriber_expired_connection_buffer = EXPIRED_CONNECTIONS;
    let mut nodes = config.global.node.directory;
    nodes
        .add_path_entry(&Path::new(prefix.as_bytes()).map_err(bad)?)
        .map_err(bad)?;
    config.global.node.directory = nodes;
    Ok(config)
}

/// The shared-memory prefix of a DNM: short, unique per (system, DNM), and a valid file name.
pub fn dnm_prefix(system: &str, dnm: &str) -> String {
    format!("dnm_{system}_{dnm}_")
}

/// Everything a module process needs to start, passed as JSON on its command line.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Launch {
    pub system: String,
    pub dnm: String,
    /// iceoryx2 file prefix of the DNM's namespace.
    pub prefix: String,
    pub module: String,
    pub kind: String,
    pub params: BTreeMap<String, ParamValue>,
    pub trigger: Trigger,
}

/// One candidate source of a module's inputs: an output port of some module.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Source {
    pub module: String,
    pub port: String,
}

/// How one input port is wired in each task slot.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct InputRoute {
    pub port: String,
    /// For every task slot, the index into [`Plan::sources`] feeding this input, or none.
    pub by_slot: Vec<Option<u32>>,
}

/// The references a module needs for one netlist revision: every source any task may connect
/// to it, and which source each input reads in each task.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Plan {
    pub revision: u64,
    /// Task names by slot.
    pub tasks: Vec<String>,
    pub sources: Vec<Source>,
    pub inputs: Vec<InputRoute>,
    /// Set when the DNM wants the module to exit cleanly.
    #[serde(default)]
    pub stop: bool,
}

/// Module lifecycle as reported in [`Status`].
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum ModuleState {
    Starting = 0,
    Running = 1,
    Stopping = 2,
    Failed = 3,
}

impl ModuleState {
    pub fn from_u32(v: u32) -> Self {
        match v {
            1 => ModuleState::Running,
            2 => ModuleState::Stopping,
            3 => ModuleState::Failed,
            _ => ModuleState::Starting,
        }
    }
}

/// A module's heartbeat, published on `_dnm/status/<module>`.
#[repr(C)]
#[derive(Debug, Clone, Copy, ZeroCopySend)]
#[type_name("dnm::Status")]
pub struct Status {
    pub pid: u32,
    /// A [`ModuleState`].
    pub state: u32,
    /// The newest plan revision the module has fully prepared (subscribers open).
    pub plan_revision: u64,
    /// Steps run so far.
    pub steps: u64,
    /// Samples sent on all outputs so far.
    pub sent: u64,
    /// CLOCK_MONOTONIC time of the last step, ns.
    pub last_step_ns: u64,
    /// Failed steps (the step returned an error).
    pub step_errors: u64,
    /// CLOCK_MONOTONIC time of the last heartbeat, ns: a module waiting for input posts one
    /// every [`HEARTBEAT`], so its DNM tells an idle module from a hung one.
    pub heartbeat_ns: u64,
    /// The newest plan revision this process could not prepare (0: none); the DNM refuses
    /// that revision.
    pub prepare_failed: u64,
    /// Bytes of [`Status::error`] in use.
    pub error_len: u32,
    /// The last error of a step, UTF-8, cut to fit (for a module of another language, its
    /// traceback): the DNM puts it in the module's events when the process exits.
    pub error: [u8; STATUS_ERROR_BYTES],
}

/// Bytes of a step's error a status carries.
pub const STATUS_ERROR_BYTES: usize = 1020;

impl Default for Status {
    fn default() -> Self {
        Self {
            pid: 0,
            state: 0,
            plan_revision: 0,
            steps: 0,
            sent: 0,
            last_step_ns: 0,
            step_errors: 0,
            heartbeat_ns: 0,
            prepare_failed: 0,
            error_len: 0,
            error: [0; STATUS_ERROR_BYTES],
        }
    }
}

impl Status {
    /// Keeps `text` as the last error, its end kept when it is too long (where a traceback
    /// says what failed), cut on a character boundary.
    pub fn set_error(&mut self, text: &str) {
        let mut start = text.len().saturating_sub(STATUS_ERROR_BYTES);
        while !text.is_char_boundary(start) {
            start += 1;
        }
        let bytes = &text.as_bytes()[start..];
        self.error[..bytes.len()].copy_from_slice(bytes);
        self.error_len = bytes.len() as u32;
    }

    /// The last error of a step, if one.
    pub fn error(&self) -> Option<String> {
        let len = (self.error_len as usize).min(STATUS_ERROR_BYTES);
        (len > 0).then(|| String::from_utf8_lossy(&self.error[..len]).into_owned())
    }
}

/// How often a module posts its status at least, stepping or idle.
pub const HEARTBEAT: std::time::Duration = std::time::Duration::from_millis(250);

/// Plans a module finds as history when it (re)starts: the committed one and the one being
/// prepared.
pub const PLAN_HISTORY: usize = 2;

/// CLOCK_MONOTONIC now, in nanoseconds: comparable across processes on one machine.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec and CLOCK_MONOTONIC is always supported.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    (ts.tv_sec as u64) * 1_000_000_000 + ts.tv_nsec as u64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_dnm_prefix_makes_a_config_and_a_bad_one_says_why() {
        let config = dnm_config(&dnm_prefix("sys", "main")).unwrap();
        assert_eq!(config.global.prefix.as_bytes(), b"dnm_sys_main_");
        let err = dnm_config("a/b").unwrap_err();
        assert!(matches!(&err, DnmConfigError::Prefix { prefix, .. } if prefix == "a/b"));
        assert!(std::error::Error::source(&err).is_some());
        let message = err.to_string();
        assert!(
            message.starts_with("bad shared-memory prefix `a/b`: "),
            "{message}"
        );
        assert_eq!(String::from(err), message);
    }

    #[test]
    fn a_task_word_splits_into_revision_and_slot() {
        assert_eq!(split_task_word(task_word(7, 3)), (7, 3));
        assert_eq!(split_task_word(task_word(1, NO_TASK)), (1, NO_TASK));
    }
}
