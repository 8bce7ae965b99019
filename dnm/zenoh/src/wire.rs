//! How port samples look on Zenoh: their encoding, their header (the attachment) as it leaves
//! and enters a machine, and their traffic class.

use dnm_module::protocol::PortHeader;
use dnm_netlist::MessageType;
use dnm_proto::clock::now_unix_ns as unix_now_ns;
use dnm_proto::keys::SampleHeader;
use zenoh::qos::Priority;

/// Zenoh encoding of a port: the message encoding with the schema name as its schema.
pub fn encoding(message: &MessageType) -> String {
    format!("{};{}", message.encoding, message.schema_name)
}

/// Unix time minus CLOCK_MONOTONIC, ns, as last measured, and when (monotonic ns).
static OFFSET: std::sync::atomic::AtomicI64 = std::sync::atomic::AtomicI64::new(0);
static MEASURED: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// Unix time minus CLOCK_MONOTONIC, measured at most once a second from the tightest of a few
/// readings of both clocks: every sample converted within that second shifts by the same
/// amount, so the time between two samples crosses machines unchanged (a conversion per sample
/// would add the scheduling delay between two clock reads, tens of microseconds on a busy
/// computer).
fn unix_minus_mono(mono_now: u64) -> i64 {
    use std::sync::atomic::Ordering::{Acquire, Relaxed, Release};
    // Acquire/Release: whoever sees the time of a measurement sees its offset.
    let at = MEASURED.load(Acquire);
    if at != 0 && mono_now.saturating_sub(at) < 1_000_000_000 {
        return OFFSET.load(Relaxed);
    }
    let mut best: Option<(u64, i64)> = None;
    for _ in 0..4 {
        let a = dnm_module::protocol::monotonic_ns();
        let unix = unix_now_ns();
        let b = dnm_module::protocol::monotonic_ns();
        let gap = b.saturating_sub(a);
        let offset = unix as i64 - (a / 2 + b / 2) as i64;
        if best.is_none_or(|(g, _)| gap < g) {
            best = Some((gap, offset));
        }
    }
    let offset = best.map_or(0, |(_, o)| o);
    OFFSET.store(offset, Relaxed);
    MEASURED.store(mono_now.max(1), Release);
    offset
}

/// The header as it leaves this machine: its send time also in wall-clock time.
pub fn to_wire(h: &PortHeader) -> SampleHeader {
    let offset = unix_minus_mono(dnm_module::protocol::monotonic_ns());
    SampleHeader {
        stamp_ns: h.stamp_ns,
        seq: h.seq,
        task_word: h.task_word,
        unix_ns: (h.stamp_ns as i64).saturating_add(offset).max(0) as u64,
    }
}

/// The header as it enters this machine: the send time on this machine's monotonic clock, so
/// modules judge the sample's age as they judge local ones (assumes synchronised wall clocks;
/// a send time ahead of this machine's clock counts as now). A sample without a wall-clock time
/// (an older sender, a foreign publisher) is stamped with its arrival: Zenoh delivers it live.
pub fn from_wire(h: SampleHeader) -> PortHeader {
    let now = dnm_module::protocol::monotonic_ns();
    let stamp_ns = if h.unix_ns == 0 {
        now
    } else {
        let offset = unix_minus_mono(now);
        ((h.unix_ns as i64).saturating_sub(offset).max(0) as u64).min(now)
    };
    PortHeader {
        stamp_ns,
        seq: h.seq,
        task_word: h.task_word,
    }
}

/// The Zenoh priority of a port's samples: they never hold up commands (which go at
/// interactive-high and block), and large payloads (camera frames) go last. Every sample is
/// dropped rather than queued when the link is congested: a newer one follows.
pub fn traffic_class(message: &MessageType) -> Priority {
    if message.payload.max_bytes() > LARGE_SAMPLE {
        Priority::Background
    } else {
        Priority::Data
    }
}

/// Samples larger than this are bulk (images, point clouds).
const LARGE_SAMPLE: usize = 16 * 1024;
