//! The Zenoh key-expression scheme of a system. Everything a DNM says on Zenoh lives under
//! `<system>/`:
//!
//! | key                                   | Zenoh primitive      | what                                                     |
//! |---------------------------------------|----------------------|----------------------------------------------------------|
//! | `<system>/dnm/<dnm>`                  | queryable, liveliness | the DNM's report (JSON): revision, task, CPU, modules, peers; `?brief`, `?glance`: smaller forms |
//! | `<system>/authority/station/<station>` | queryable           | station `<station>`'s uplinks (JSON `station::Uplink`), answered by the authority |
//! | `<system>/authority/beat`             | pub/sub              | the authority's heartbeat (JSON `station::Beat`): the DNMs' lease, its clock, the safing in force |
//! | `<system>/dnm/<dnm>/netlist`          | queryable            | the applied netlist (JSON: revision, digest, file, text) |
//! | `<system>/dnm/<dnm>/cmd`              | queryable            | commands (JSON request in the query payload; JSON reply) |
//! | `<system>/module/<dnm>/<module>`      | queryable, liveliness | one module's state and the last value of each output (JSON) |
//! | `<system>/dnm/<dnm>/wiring`           | queryable            | the wiring in force (JSON `dnm_netlist::Wiring`): DNMs, modules, ports' message types, tasks' links |
//! | `<system>/port/<dnm>/<module>/<port>` | pub/sub, queryable   | samples of outputs that cross DNMs; last value of any output |
//! | `<system>/watch/<dnm>/<module>/<port>/<rate>` | pub/sub      | any output, published only while subscribed; `<rate>` is `full`, `10hz` or `1hz`; images as JPEG |
//!
//! Port samples carry the message bytes as the module wrote them (the encoding names the schema,
//! e.g. `dnm-pod;dnm_msgs/Tick`) and a 32-byte attachment: send time (CLOCK_MONOTONIC ns of the
//! producing machine), sequence number, task word and send time as wall-clock (Unix) ns,
//! little-endian `u64`s. A DNM mirroring a sample from another machine stamps it with its own
//! monotonic clock from the wall-clock time, so ages are comparable wherever wall clocks agree.
//!
//! The netlist validates system, DNM and module names (a letter, then letters, digits, `_`,
//! `-`), so each is one key chunk. Port names come from the kinds: the built-in ones follow the
//! same rule; names an external executable declares are not checked yet.

/// `<system>/dnm/<dnm>`.
pub fn dnm(system: &str, dnm: &str) -> String {
    format!("{system}/dnm/{dnm}")
}

/// Every DNM of a system: `<system>/dnm/*`.
pub fn all_dnms(system: &str) -> String {
    format!("{system}/dnm/*")
}

/// Liveliness token a DNM declares as it stops in order, before its presence goes: the others
/// then log that it left, not that it was lost.
pub fn dnm_leaving(system: &str, dnm: &str) -> String {
    format!("{system}/dnm/{dnm}/leaving")
}

/// Every DNM's presence and leaving tokens (liveliness).
pub fn dnms_coming_and_going(system: &str) -> String {
    format!("{system}/dnm/*/**")
}

/// The DNM whose presence `key` is, and whether it is its leaving token (see [`dnm_leaving`]);
/// `None` for other keys.
pub fn presence_of(system: &str, key: &str) -> Option<(String, bool)> {
    let rest = key.strip_prefix(system)?.strip_prefix("/dnm/")?;
    match rest.split_once('/') {
        None if !rest.is_empty() => Some((rest.to_string(), false)),
        Some((name, "leaving")) if !name.is_empty() => Some((name.to_string(), true)),
        _ => None,
    }
}

/// `<system>/dnm/<dnm>/netlist`.
pub fn netlist(system: &str, dnm: &str) -> String {
    format!("{system}/dnm/{dnm}/netlist")
}

/// `<system>/dnm/<dnm>/wiring`; `dnm` may be `*`.
pub fn wiring(system: &str, dnm: &str) -> String {
    format!("{system}/dnm/{dnm}/wiring")
}

/// `<system>/dnm/<dnm>/cmd`; `dnm` may be `*` to address every DNM.
pub fn cmd(system: &str, dnm: &str) -> String {
    format!("{system}/dnm/{dnm}/cmd")
}

/// `<system>/authority/station/<station>`: where ground station `station` sends its uplinks.
/// The station's name is in the key, so the access control binds it to the station's
/// certificate: an operator may query only the key of its own common name.
pub fn authority_station(system: &str, station: &str) -> String {
    format!("{system}/authority/station/{station}")
}

/// Every station's uplink key: `<system>/authority/station/*`.
pub fn authority_stations(system: &str) -> String {
    format!("{system}/authority/station/*")
}

/// The station an uplink key names, if it is one.
pub fn station_of<'a>(system: &str, key: &'a str) -> Option<&'a str> {
    key.strip_prefix(system)?
        .strip_prefix("/authority/station/")
        .filter(|s| !s.is_empty() && !s.contains('/'))
}

/// `<system>/authority/beat`: the authority's heartbeat ([`crate::station::Beat`]), the lease
/// every DNM of the rover keeps on it (a DNM that stops hearing it makes itself safe).
pub fn authority_beat(system: &str) -> String {
    format!("{system}/authority/beat")
}

/// `<system>/authority/sequences`: every event of the rover's onboard sequences as it happens
/// ([`crate::station::SequenceEvent`], JSON), for monitors and tools.
pub fn authority_sequences(system: &str) -> String {
    format!("{system}/authority/sequences")
}

/// `<system>/module/<dnm>/<module>`.
pub fn module(system: &str, dnm: &str, module: &str) -> String {
    format!("{system}/module/{dnm}/{module}")
}

/// `<system>/port/<dnm>/<module>/<port>`.
pub fn port(system: &str, dnm: &str, module: &str, port: &str) -> String {
    format!("{system}/port/{dnm}/{module}/{port}")
}

/// How often a watched output is published: every sample, or at most 10 or 1 per second (the
/// newest sample of each period). A watcher picks one by the key it subscribes to, so the radio
/// carries only what some operator asked for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum WatchRate {
    Full,
    Hz10,
    Hz1,
}

impl WatchRate {
    pub const ALL: [WatchRate; 3] = [WatchRate::Full, WatchRate::Hz10, WatchRate::Hz1];

    /// The key chunk: `full`, `10hz`, `1hz`.
    pub fn chunk(self) -> &'static str {
        match self {
            WatchRate::Full => "full",
            WatchRate::Hz10 => "10hz",
            WatchRate::Hz1 => "1hz",
        }
    }

    pub fn parse(chunk: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|r| r.chunk() == chunk)
    }

    /// The shortest time between two samples published, ns (0: every sample).
    pub fn period_ns(self) -> u64 {
        match self {
            WatchRate::Full => 0,
            WatchRate::Hz10 => 100_000_000,
            WatchRate::Hz1 => 1_000_000_000,
        }
    }
}

/// `<system>/watch/<dnm>/<module>/<port>/<rate>`.
pub fn watch(system: &str, dnm: &str, module: &str, port: &str, rate: WatchRate) -> String {
    format!("{system}/watch/{dnm}/{module}/{port}/{}", rate.chunk())
}

/// Every watchable output of a system at `rate`: `<system>/watch/*/*/*/<rate>`.
pub fn watch_all(system: &str, rate: WatchRate) -> String {
    format!("{system}/watch/*/*/*/{}", rate.chunk())
}

/// (dnm, module, port, rate) of a key made by [`watch`].
pub fn parse_watch(system: &str, key: &str) -> Option<(String, String, String, WatchRate)> {
    let rest = key.strip_prefix(system)?.strip_prefix("/watch/")?;
    let mut it = rest.split('/');
    let (d, m, p, r) = (it.next()?, it.next()?, it.next()?, it.next()?);
    if it.next().is_some() || d.is_empty() || m.is_empty() || p.is_empty() {
        return None;
    }
    Some((d.into(), m.into(), p.into(), WatchRate::parse(r)?))
}

/// A recorded channel `topic` (`/<dnm>/<module>/<port>`, `/<dnm>/_events`...) as the downlink
/// sends it to the ground: `<system>/downlink/<dnm>/<module>/<port>`.
pub fn downlink(system: &str, topic: &str) -> String {
    format!("{system}/downlink/{}", topic.trim_start_matches('/'))
}

/// Every channel of a system's downlink: `<system>/downlink/**`.
pub fn downlink_all(system: &str) -> String {
    format!("{system}/downlink/**")
}

/// The description of downlinked channel `topic` (schema, encodings), published once:
/// `<system>/downlink_channels/<dnm>/<module>/<port>`.
pub fn downlink_channel(system: &str, topic: &str) -> String {
    format!(
        "{system}/downlink_channels/{}",
        topic.trim_start_matches('/')
    )
}

/// Every downlinked channel's description: `<system>/downlink_channels/**`.
pub fn downlink_channels(system: &str) -> String {
    format!("{system}/downlink_channels/**")
}

/// Where DNM `dnm`'s recording answers for what the ground missed:
/// `<system>/downlink_history/<dnm>`.
pub fn downlink_history(system: &str, dnm: &str) -> String {
    format!("{system}/downlink_history/{dnm}")
}

/// The recorded channel's topic of a key made by [`downlink`] or [`downlink_channel`].
pub fn downlink_topic(system: &str, key: &str) -> Option<String> {
    let rest = key.strip_prefix(system)?;
    let rest = rest
        .strip_prefix("/downlink/")
        .or_else(|| rest.strip_prefix("/downlink_channels/"))?;
    (!rest.is_empty() && !rest.split('/').any(str::is_empty)).then(|| format!("/{rest}"))
}

/// What a station filled in of its record of the rover (from the rover's recording, after a
/// gap), for the ground's monitors to draw where it belongs in time:
/// `<system>/ground_filled/<dnm>/<module>/<port>`, each message's fields as JSON, with
/// [`encode_downlink`]'s attachment.
pub fn ground_filled(system: &str, dnm: &str, module: &str, port: &str) -> String {
    format!("{system}/ground_filled/{dnm}/{module}/{port}")
}

/// Everything stations fill in: `<system>/ground_filled/**`.
pub fn ground_filled_all(system: &str) -> String {
    format!("{system}/ground_filled/**")
}

/// The (DNM, module, port) of a key made by [`ground_filled`].
pub fn ground_filled_port(system: &str, key: &str) -> Option<(String, String, String)> {
    let rest = key.strip_prefix(system)?.strip_prefix("/ground_filled/")?;
    let mut parts = rest.split('/');
    let (d, m, p) = (parts.next()?, parts.next()?, parts.next()?);
    let ok = parts.next().is_none() && ![d, m, p].iter().any(|s| s.is_empty());
    ok.then(|| (d.to_string(), m.to_string(), p.to_string()))
}

/// The attachment of a downlinked message: its log time (Unix ns) and sequence number, as
/// the rover's recording holds them.
pub fn encode_downlink(log_time: u64, sequence: u32) -> [u8; 12] {
    let mut out = [0u8; 12];
    out[0..8].copy_from_slice(&log_time.to_le_bytes());
    out[8..12].copy_from_slice(&sequence.to_le_bytes());
    out
}

/// Reads [`encode_downlink`]'s attachment.
pub fn decode_downlink(bytes: &[u8]) -> Option<(u64, u32)> {
    let time = u64::from_le_bytes(bytes.get(0..8)?.try_into().ok()?);
    let seq = u32::from_le_bytes(bytes.get(8..12)?.try_into().ok()?);
    (bytes.len() == 12).then_some((time, seq))
}

/// Encoding of a watched image: JPEG bytes.
pub const JPEG_ENCODING: &str = "image/jpeg";

/// The DNM name in a key under `<system>/dnm/`.
pub fn dnm_of(system: &str, key: &str) -> Option<String> {
    let rest = key.strip_prefix(system)?.strip_prefix("/dnm/")?;
    let name = rest.split('/').next()?;
    (!name.is_empty()).then(|| name.to_string())
}

/// The header of a port sample as it crosses Zenoh (the module SDK's `PortHeader`, field for
/// field).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SampleHeader {
    /// CLOCK_MONOTONIC time the producer sent it, ns (the producing machine's clock).
    pub stamp_ns: u64,
    /// Per-port sequence number.
    pub seq: u64,
    /// The task word the producer ran under.
    pub task_word: u64,
    /// Wall-clock (Unix) time of the send, ns; 0 if unknown. A receiving machine turns it into
    /// its own monotonic clock, so a sample's age means the same on every machine whose wall
    /// clocks agree (NTP, PTP).
    pub unix_ns: u64,
}

/// Bytes of a port sample's attachment.
pub const ATTACHMENT_BYTES: usize = 32;
/// Bytes of the attachment without the wall-clock time (still read).
pub const SHORT_ATTACHMENT_BYTES: usize = 24;

/// The attachment of a port sample: send time, sequence number, task word.
pub fn encode_header(h: &SampleHeader) -> [u8; ATTACHMENT_BYTES] {
    let mut out = [0u8; ATTACHMENT_BYTES];
    out[0..8].copy_from_slice(&h.stamp_ns.to_le_bytes());
    out[8..16].copy_from_slice(&h.seq.to_le_bytes());
    out[16..24].copy_from_slice(&h.task_word.to_le_bytes());
    out[24..32].copy_from_slice(&h.unix_ns.to_le_bytes());
    out
}

/// Reads a port sample's attachment; `None` if it is not one.
pub fn decode_header(bytes: &[u8]) -> Option<SampleHeader> {
    if bytes.len() != ATTACHMENT_BYTES && bytes.len() != SHORT_ATTACHMENT_BYTES {
        return None;
    }
    let word = |i: usize| {
        let mut b = [0u8; 8];
        b.copy_from_slice(&bytes[i * 8..i * 8 + 8]);
        u64::from_le_bytes(b)
    };
    Some(SampleHeader {
        stamp_ns: word(0),
        seq: word(1),
        task_word: word(2),
        unix_ns: if bytes.len() == ATTACHMENT_BYTES {
            word(3)
        } else {
            0
        },
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_downlinked_channel_keeps_its_topic() {
        let k = downlink("beetle", "/drive/odometry/odom");
        assert_eq!(k, "beetle/downlink/drive/odometry/odom");
        assert_eq!(
            downlink_topic("beetle", &k).as_deref(),
            Some("/drive/odometry/odom")
        );
        let c = downlink_channel("beetle", "/drive/_events");
        assert_eq!(
            downlink_topic("beetle", &c).as_deref(),
            Some("/drive/_events")
        );
        assert_eq!(downlink_topic("beetle", "beetle/downlink/"), None);
        assert_eq!(downlink_topic("other", &k), None);
        let a = encode_downlink(1_700_000_000_123_456_789, 42);
        assert_eq!(decode_downlink(&a), Some((1_700_000_000_123_456_789, 42)));
        assert_eq!(decode_downlink(&a[..11]), None);
    }

    #[test]
    fn keys_nest_under_the_system() {
        assert_eq!(dnm("rover", "drive"), "rover/dnm/drive");
        assert_eq!(cmd("rover", "*"), "rover/dnm/*/cmd");
        assert_eq!(port("rover", "drive", "m", "out"), "rover/port/drive/m/out");
        assert_eq!(
            dnm_of("rover", "rover/dnm/drive/netlist").as_deref(),
            Some("drive")
        );
        assert_eq!(dnm_of("rover", "other/dnm/drive"), None);
        let w = watch("rover", "vision", "camera", "image", WatchRate::Hz1);
        assert_eq!(w, "rover/watch/vision/camera/image/1hz");
        assert_eq!(
            parse_watch("rover", &w),
            Some((
                "vision".into(),
                "camera".into(),
                "image".into(),
                WatchRate::Hz1
            ))
        );
        assert_eq!(
            parse_watch("rover", "rover/watch/vision/camera/image/2hz"),
            None
        );
        assert_eq!(
            parse_watch("rover", "rover/watch/vision/camera/image/1hz/x"),
            None
        );
    }

    #[test]
    fn header_round_trips() {
        let h = SampleHeader {
            stamp_ns: 1,
            seq: u64::MAX,
            task_word: 7 << 16,
            unix_ns: 5,
        };
        let back = decode_header(&encode_header(&h)).unwrap();
        assert_eq!(
            (back.stamp_ns, back.seq, back.task_word, back.unix_ns),
            (1, u64::MAX, 7 << 16, 5)
        );
        assert_eq!(decode_header(&encode_header(&h)[..24]).unwrap().unix_ns, 0);
        assert!(decode_header(&[0; 3]).is_none());
    }

    #[test]
    fn filled_keys_name_their_port() {
        let k = ground_filled("rover", "main", "odometry", "odom");
        assert_eq!(k, "rover/ground_filled/main/odometry/odom");
        assert_eq!(
            ground_filled_port("rover", &k),
            Some(("main".into(), "odometry".into(), "odom".into()))
        );
        assert_eq!(ground_filled_port("rover", "rover/ground_filled/a/b"), None);
        assert_eq!(
            ground_filled_port("rover", "rover/ground_filled/a//c"),
            None
        );
        assert_eq!(ground_filled_port("other", &k), None);
    }
}
