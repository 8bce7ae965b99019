//! The ground's own record of the rover: what the netlist's downlink plan names (and every
//! task switch, module event and sequence event) reaches the ground live, and what the link
//! lost, or the station missed while it was down, is filled in afterwards.
//!
//! - **Rover** ([`DownlinkTap`]): each DNM's recorder hands the plan's messages (each entry
//!   decimated to its rate on the samples' send stamps) to the tap exactly as it writes them to
//!   its file. The tap publishes each recorded channel on `<system>/downlink/<dnm>/<module>/<port>`
//!   through a Zenoh advanced publisher: a cache of the last [`CACHE_SECONDS`] of it by default,
//!   sample-miss detection with a heartbeat, at the `background` priority (below every command
//!   and every route between DNMs). Each channel is announced (schema, encodings, plan) on
//!   `<system>/downlink_channels/...`, and a queryable there answers stations that join later.
//! - **Rover** ([`HistoryServer`]): each DNM's recording answers requests for stretches of a
//!   channel (`<system>/downlink_history/<dnm>`), decimated as the live downlink decimates.
//! - **Ground** ([`GroundRecord`]): advanced subscribers with history (the publishers' last
//!   seconds: late joiners, a restarted station) and recovery (what the radio lost, from the
//!   caches) write what arrives to the station's own session folder: MCAP files with the
//!   rover's channels, the rover's bytes, at the rover's send times: a session in the
//!   rover's format. A backfill thread finds the
//!   gaps the caches could not fill and asks the recordings for them, entries by priority,
//!   newest or oldest first, at the `background` priority, within the byte budget the operator
//!   sets (live traffic spends it too), and slower when the station's commands show the link
//!   queueing (see [`LinkProbe`]). A message held already is never written twice; a
//!   stretch the rover recorded nothing of is reported as a gap, not silently absent. What is
//!   filled in is told to the ground's monitors, decoded, on `<system>/ground_filled/...`, for
//!   them to draw where it belongs in time.

mod backfill;
mod copy;
mod filled;
mod ground;
mod history;
mod pace;
pub mod protocol;
mod resume;
mod rover;

pub use copy::{ChannelStatus, Gap, RecordStatus, TIMELINE_BINS, Timeline};
pub use ground::{GroundRecord, GroundRecordError, GroundRecordOptions, StatusSource};
pub use history::{HistoryServer, HistoryStartError};
pub use pace::{LinkProbe, LinkSample};
pub use rover::{CACHE_SECONDS, DownlinkTap};
