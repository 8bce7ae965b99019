//! The rover's side of the downlink: the recorder's [`Tap`] publishing each recorded channel
//! through a Zenoh advanced publisher with a cache.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dnm_netlist::{Backfill, DownlinkEntry};
use dnm_proto::keys;

use crate::protocol::Announce;
use dnm_record::tap::{ChannelDesc, Tap, Tapped};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};
use zenoh_ext::{
    AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig, RepliesConfig,
};

/// How much of each channel its publisher keeps for the ground to recover by default: a gap
/// in the link shorter than this is filled from the cache at once, a longer one from the
/// recording, within the downlink's budget.
pub const CACHE_SECONDS: u64 = 10;
/// Samples kept of a channel whose rate is not known (events, switches).
const UNTIMED_CACHE: usize = 1000;
/// How often a publisher tells subscribers its last sequence number, so a lost last sample
/// is noticed too.
const HEARTBEAT: Duration = Duration::from_secs(1);

/// One downlinked channel's publisher.
struct Channel {
    data: AdvancedPublisher<'static>,
}

/// The announcements of a DNM's downlinked channels, by key, as its queryable answers them.
type Announcements = Arc<Mutex<BTreeMap<String, Vec<u8>>>>;

/// A recorder's [`Tap`] that sends what it is handed to the ground (see the crate's docs).
pub struct DownlinkTap {
    session: zenoh::Session,
    system: String,
    dnm: String,
    cache: Duration,
    channels: Mutex<HashMap<String, Option<Channel>>>,
    announcements: Announcements,
    /// Answers `<system>/downlink_channels/<dnm>/**` with the announcements.
    _queryable: Option<zenoh::query::Queryable<()>>,
}

impl std::fmt::Debug for DownlinkTap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DownlinkTap")
            .field("system", &self.system)
            .finish_non_exhaustive()
    }
}

impl DownlinkTap {
    /// The tap of DNM `dnm` of `system`, publishing on `session` with a cache of `cache` per
    /// channel.
    pub fn new(session: zenoh::Session, system: &str, dnm: &str, cache: Duration) -> Self {
        let announcements = Announcements::default();
        // A station that joins (or whose subscription was not there yet when a channel was
        // announced) asks for the announcements.
        let key = format!("{}/**", keys::downlink_channel(system, &format!("/{dnm}")));
        let queryable = {
            let announcements = announcements.clone();
            session
                .declare_queryable(key.clone())
                .callback(move |q| {
                    let held: Vec<(String, Vec<u8>)> = announcements
                        .lock()
                        .map(|a| a.iter().map(|(k, v)| (k.clone(), v.clone())).collect())
                        .unwrap_or_default();
                    for (k, json) in held {
                        let matches = zenoh::key_expr::KeyExpr::try_from(k.as_str())
                            .is_ok_and(|ke| q.key_expr().intersects(&ke));
                        if matches {
                            let _ = q.reply(k, json).wait();
                        }
                    }
                })
                .wait()
        };
        let queryable = match queryable {
            Ok(q) => Some(q),
            Err(e) => {
                tracing::error!("the downlink's channels cannot be asked for ({key}): {e}");
                None
            }
        };
        Self {
            session,
            system: system.to_string(),
            dnm: dnm.to_string(),
            cache,
            channels: Mutex::new(HashMap::new()),
            announcements,
            _queryable: queryable,
        }
    }

    /// Declares the publishers of `desc`'s channel, with a cache of `self.cache` at its plan's
    /// rate, and announces it.
    fn open(&self, desc: &ChannelDesc, plan: Option<&DownlinkEntry>) -> Result<Channel, String> {
        let period_ns = plan.map(DownlinkEntry::period_ns);
        let samples = period_ns.map_or(UNTIMED_CACHE, |p| {
            (self.cache.as_nanos() as u64).div_ceil(p.max(1)) as usize
        });
        // A recovery answer the link cannot take now is dropped, never waited for: a waiting
        // reply would hold the cache (and the recorder's writer putting into it) and Zenoh's
        // own receive task. What it dropped is asked for again, or from the recording.
        let replies = RepliesConfig::default()
            .priority(Priority::Background)
            .congestion_control(CongestionControl::Drop);
        let data = self
            .session
            .declare_publisher(keys::downlink(&self.system, &desc.topic))
            .priority(Priority::Background)
            // A sample the link cannot take now is recovered from the cache later.
            .congestion_control(CongestionControl::Drop)
            .cache(
                CacheConfig::default()
                    .max_samples(samples.max(1))
                    .replies_config(replies.clone()),
            )
            .sample_miss_detection(MissDetectionConfig::default().heartbeat(HEARTBEAT))
            .publisher_detection()
            .wait()
            .map_err(|e| format!("downlink publisher of {}: {e}", desc.topic))?;
        let announce = Announce {
            dnm: self.dnm.clone(),
            desc: desc.clone(),
            period_ns,
            priority: plan.map_or(1, |p| p.priority),
            newest_first: plan.is_none_or(|p| p.backfill == Backfill::NewestFirst),
        };
        let json = serde_json::to_vec(&announce).map_err(|e| e.to_string())?;
        let key = keys::downlink_channel(&self.system, &desc.topic);
        if let Ok(mut a) = self.announcements.lock() {
            a.insert(key.clone(), json.clone());
        }
        // Stations listening now hear it at once; the others ask.
        self.session
            .put(key, json)
            .priority(Priority::Background)
            .wait()
            .map_err(|e| format!("downlink channel of {}: {e}", desc.topic))?;
        Ok(Channel { data })
    }
}

impl Tap for DownlinkTap {
    fn message(&self, m: Tapped<'_>) {
        let Ok(mut channels) = self.channels.lock() else {
            return;
        };
        // Opened at a channel's first message (its topic copied once, not per message).
        if !channels.contains_key(&m.channel.topic) {
            let opened = match self.open(m.channel, m.plan) {
                Ok(c) => Some(c),
                // Said once: the channel is not downlinked while this DNM runs.
                Err(e) => {
                    tracing::error!("not downlinked: {e}");
                    None
                }
            };
            channels.insert(m.channel.topic.clone(), opened);
        }
        let channel = channels.get(&m.channel.topic).and_then(Option::as_ref);
        if let Some(c) = channel
            && let Err(e) = c
                .data
                .put(m.data.to_vec())
                .attachment(keys::encode_downlink(m.log_time, m.sequence).to_vec())
                .wait()
        {
            tracing::debug!(topic = %m.channel.topic, "downlink put: {e}");
        }
    }
}
