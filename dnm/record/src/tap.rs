//! What a recorder hands on as it writes: the messages of the netlist's downlink plan (each
//! entry decimated by [`dnm_netlist::Decimator`] on its send stamps), and every task switch,
//! module event and sequence event, exactly as they go into the file. A copy made of them
//! elsewhere (the ground's session) holds the same bytes, on the same channels, at the same
//! times as the rover's recording.

use std::collections::BTreeMap;

use dnm_netlist::DownlinkEntry;
use serde::{Deserialize, Serialize};

/// An MCAP channel as a recorder writes it: what a copy of its messages needs to write them to
/// a file of its own.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ChannelDesc {
    /// `/<dnm>/<module>/<port>` (and `…/raw` beside a standard message that cannot hold our
    /// bytes exactly), or `/<dnm>/_switches`, `/<dnm>/_events`, `/<dnm>/_sequences`.
    pub topic: String,
    pub schema_name: String,
    pub schema_encoding: String,
    /// The schema's text (ROS 2 `.msg`, JSON schema, or our own declaration).
    pub schema: String,
    pub message_encoding: String,
    pub metadata: BTreeMap<String, String>,
}

/// One message as written: on `channel`, sent at `log_time` (Unix ns), its sequence number.
#[derive(Debug, Clone, Copy)]
pub struct Tapped<'a> {
    pub channel: &'a ChannelDesc,
    pub log_time: u64,
    pub sequence: u32,
    pub data: &'a [u8],
    /// The downlink plan's entry of the channel's port (none for switches and events, which
    /// all go).
    pub plan: Option<&'a DownlinkEntry>,
}

/// Where a recorder hands the messages of the downlink plan. Called on the recorder's writer
/// thread, once per message: it must not block.
pub trait Tap: Send + Sync + std::fmt::Debug {
    fn message(&self, message: Tapped<'_>);
}
