//! How port samples look on Zenoh: their encoding, their header (the attachment) as it leaves
//! and enters a machine, and their traffic class.

use dnm_module::protocol::PortHeader;
use dnm_netlist::MessageType;
use dnm_proto::keys::SampleHeader;
use zenoh::qos::Priority;

/// Zenoh encoding of a port: the message encoding with the schema name as its schema.
pub fn encoding(message: &MessageType) -> String {
    format!("{};{}", message.encoding, message.schema_name)
}

/// Wall-clock time now, ns since the Unix epoch.
fn unix_now_ns() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_nanos() as u64)
}

/// The header as it leaves this machine: its send time also in wall-clock time.
pub fn to_wire(h: &PortHeader) -> SampleHeader {
    let age = dnm_module::protocol::monotonic_ns().saturating_sub(h.stamp_ns);
    SampleHeader {
        stamp_ns: h.stamp_ns,
        seq: h.seq,
        task_word: h.task_word,
        unix_ns: unix_now_ns().saturating_sub(age),
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
        now.saturating_sub(unix_now_ns().saturating_sub(h.unix_ns))
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
