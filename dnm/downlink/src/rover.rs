//! The rover's side of the downlink: the recorder's [`Tap`] publishing each recorded channel
//! through a Zenoh advanced publisher with a cache.

use std::collections::HashMap;
use std::sync::Mutex;
use std::time::Duration;

use dnm_proto::keys;
use dnm_record::tap::{ChannelDesc, Tap, Tapped};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};
use zenoh_ext::{
    AdvancedPublisher, AdvancedPublisherBuilderExt, CacheConfig, MissDetectionConfig, RepliesConfig,
};

/// How much of each channel its publisher keeps for the ground to recover: a gap in the link
/// shorter than this is filled from the cache.
pub const CACHE_SECONDS: u64 = 120;
/// Samples kept of a channel whose rate is not known (events, switches).
const UNTIMED_CACHE: usize = 1000;
/// How often a publisher tells subscribers its last sequence number, so a lost last sample
/// is noticed too.
const HEARTBEAT: Duration = Duration::from_secs(1);

/// One downlinked channel: its data publisher and the publisher of its description.
struct Channel {
    data: AdvancedPublisher<'static>,
    _desc: AdvancedPublisher<'static>,
}

/// A recorder's [`Tap`] that sends what it is handed to the ground (see the crate's docs).
pub struct DownlinkTap {
    session: zenoh::Session,
    system: String,
    channels: Mutex<HashMap<String, Option<Channel>>>,
}

impl std::fmt::Debug for DownlinkTap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DownlinkTap")
            .field("system", &self.system)
            .finish_non_exhaustive()
    }
}

impl DownlinkTap {
    /// A tap of `system` publishing on `session`.
    pub fn new(session: zenoh::Session, system: &str) -> Self {
        Self {
            session,
            system: system.to_string(),
            channels: Mutex::new(HashMap::new()),
        }
    }

    /// Declares the publishers of `desc`'s channel, with a cache of [`CACHE_SECONDS`] at one
    /// message every `period_ns`.
    fn open(&self, desc: &ChannelDesc, period_ns: Option<u64>) -> Result<Channel, String> {
        let samples = period_ns.map_or(UNTIMED_CACHE, |p| {
            (CACHE_SECONDS * 1_000_000_000).div_ceil(p.max(1)) as usize
        });
        let replies = RepliesConfig::default().priority(Priority::Background);
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
        let desc_pub = self
            .session
            .declare_publisher(keys::downlink_channel(&self.system, &desc.topic))
            .priority(Priority::Background)
            .cache(
                CacheConfig::default()
                    .max_samples(1)
                    .replies_config(replies),
            )
            // Sequence numbers rather than timestamps (which the session may not make).
            .sample_miss_detection(MissDetectionConfig::default())
            .publisher_detection()
            .wait()
            .map_err(|e| format!("downlink channel of {}: {e}", desc.topic))?;
        let json = serde_json::to_vec(desc).map_err(|e| e.to_string())?;
        desc_pub
            .put(json)
            .wait()
            .map_err(|e| format!("downlink channel of {}: {e}", desc.topic))?;
        Ok(Channel {
            data,
            _desc: desc_pub,
        })
    }
}

impl Tap for DownlinkTap {
    fn message(&self, m: Tapped<'_>) {
        let Ok(mut channels) = self.channels.lock() else {
            return;
        };
        let channel = channels.entry(m.channel.topic.clone()).or_insert_with(|| {
            match self.open(m.channel, m.period_ns) {
                Ok(c) => Some(c),
                // Said once: the channel is not downlinked while this DNM runs.
                Err(e) => {
                    tracing::error!("not downlinked: {e}");
                    None
                }
            }
        });
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
