//! What `dnm monitor --session` hands the monitor process on its standard input: a recording
//! read back, in recorded time order, one frame at a time. A frame is a 4-byte little-endian
//! length, a JSON [`PlaybackFrame`] of that length, then, for a sample, its bytes.

use serde::{Deserialize, Serialize};

use crate::station::SequenceEvent;
use crate::{ModuleEvent, SwitchRecord};

/// One frame of a recording read back; `W` is the wiring tools see (`dnm_netlist::Wiring`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PlaybackFrame<W> {
    /// The wiring in force from this time on: a new revision, or a task switched to.
    Wiring { at_unix_ns: u64, wiring: W },
    /// A sample of an output port: its `bytes` bytes follow the frame.
    Sample {
        at_unix_ns: u64,
        dnm: String,
        module: String,
        port: String,
        bytes: u64,
    },
    /// A DNM's task switch, as recorded.
    Switch {
        at_unix_ns: u64,
        record: SwitchRecord,
    },
    /// A module event, as recorded.
    Event { at_unix_ns: u64, event: ModuleEvent },
    /// An onboard sequence's event, as recorded.
    Sequence {
        at_unix_ns: u64,
        event: SequenceEvent,
    },
}

/// The largest frame header a reader takes: a wiring of a few hundred modules fits.
pub const MAX_HEADER: usize = 16 << 20;
