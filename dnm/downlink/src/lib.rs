//! The ground's own record of the rover.
//!
//! On the rover, each DNM's recorder hands the messages of the netlist's downlink plan (each
//! entry decimated to its rate on the samples' send stamps) and every task switch, module
//! event and sequence event to a [`DownlinkTap`], exactly as it writes them to its file. The
//! tap publishes each recorded channel on `<system>/downlink/<dnm>/<module>/<port>` through a
//! Zenoh advanced publisher: a cache of the last [`CACHE_SECONDS`] of it, sample-miss detection
//! with a heartbeat, at the `background` priority (below every command and every route between
//! DNMs), and the channel's description (schema, encodings) on
//! `<system>/downlink_channels/...`.
//!
//! At the ground station, a [`GroundRecord`] subscribes with history (late joiners, a
//! restarted station) and recovery (what the radio lost, from the publishers' caches), and
//! writes what it receives to its own session folder: MCAP files with the rover's channels,
//! the rover's bytes, at the rover's send times, so `dnm stats`, `dnm replay`, Rerun and
//! Foxglove read it like a rover session. A message it already holds (a restarted station
//! getting the cache again) is not written twice.

mod backfill;
mod copy;
mod ground;
mod history;
pub mod protocol;
mod rover;

pub use copy::{ChannelStatus, Gap, RecordStatus};
pub use ground::{GroundRecord, GroundRecordError, GroundRecordOptions, StatusSource};
pub use history::{HistoryServer, HistoryStartError};
pub use rover::{CACHE_SECONDS, DownlinkTap};
