//! What the rover and the ground say to each other about the downlink: a channel's
//! announcement, and a request for a stretch of the rover's recording and its answer.

use dnm_record::tap::ChannelDesc;
use serde::{Deserialize, Serialize};

/// A downlinked channel, published once (and kept in its publisher's cache for late
/// joiners) on `<system>/downlink_channels/<topic>`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Announce {
    /// The DNM whose recorder writes it.
    pub dnm: String,
    pub desc: ChannelDesc,
    /// Its plan: one message every `period_ns` at most (none: every message, as switches
    /// and events), what the ground misses of it sent again by `priority` (1 first), newest
    /// or oldest first.
    pub period_ns: Option<u64>,
    pub priority: u8,
    pub newest_first: bool,
}

/// A request to a DNM's recording (`<system>/downlink_history/<dnm>`): the plan's messages of
/// `topic` sent from `from_ns` to `to_ns` (Unix ns, both included), decimated to one every
/// `period_ns`, at most `max_bytes` of them (at least one), the newest or the oldest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct HistoryRequest {
    pub topic: String,
    pub from_ns: u64,
    pub to_ns: u64,
    pub period_ns: Option<u64>,
    pub max_bytes: u64,
    pub newest_first: bool,
}

/// The last reply to a [`HistoryRequest`] (the replies before it are the messages, each with
/// its log time and sequence number in its attachment).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize, Default)]
pub struct HistoryAnswer {
    /// Messages sent, and their bytes.
    pub messages: u64,
    pub bytes: u64,
    /// What is still to send of the range when `max_bytes` cut it short: `[from, to]`.
    pub rest: Option<(u64, u64)>,
    /// Log times of the first and last message of the topic the DNM's recording holds now;
    /// none if it holds none (the rover never recorded it, or lost its files).
    pub recorded: Option<(u64, u64)>,
}

/// Largest answer the recording sends to one request, whatever it asks.
pub const MAX_ANSWER_BYTES: u64 = 4 << 20;
