//! The ground's side of the downlink: what the rover sends of its recording, received live and
//! recovered after gaps, written to the station's own session folder.

use std::collections::HashMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_proto::keys;

use crate::backfill;
use crate::copy::{Copies, RecordStatus, channel_statuses};
use crate::filled::{Filled, Teller};
use crate::pace::LinkProbe;
use crate::protocol::Announce;
use crate::resume::{held, plan_metadata};
use zenoh::Wait;
use zenoh_ext::{AdvancedSubscriber, AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

/// Topics heard of whose announcement has not arrived.
pub(crate) type Unknown = Arc<Mutex<std::collections::BTreeSet<String>>>;

/// Messages received and not written yet, at most; beyond it the newest are let go (a plan
/// entry's show as a gap, filled in from the recording; a switch or an event is lost).
const QUEUE: usize = 65_536;
/// Messages of a channel whose description has not arrived yet, kept until it does...
const PENDING: usize = 10_000;
/// ...of such channels at most, and their bytes together at most (beyond, what arrives is let
/// go, and filled in from the rover's recording once the channel is known).
const PENDING_TOPICS: usize = 256;
const PENDING_BYTES: usize = 64 << 20;
/// Channels a session holds at most (an announcement beyond is ignored, and said so).
const TOPICS: usize = 4096;
/// Longest a chunk of the ground's file stays open: what a killed station loses (and gets
/// again from the caches when it restarts).
const CHUNK_PERIOD: Duration = Duration::from_secs(1);
/// File names of the ground's session: `ground-<n>.mcap`.
pub(crate) const STEM: &str = "ground";
/// A file of the session is closed and the next begun after this many bytes of messages...
const ROTATE_BYTES: u64 = 512 << 20;
/// ...or this long.
const ROTATE_AFTER: Duration = Duration::from_secs(3600);

/// Why the ground's record did not start.
#[derive(Debug, thiserror::Error)]
pub enum GroundRecordError {
    #[error("ground session folder {}: {source}", dir.display())]
    Folder {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("subscribing to the rover's downlink: {0}")]
    Subscribe(String),
    #[error("no thread for the ground's writer: {0}")]
    Thread(#[source] std::io::Error),
}

/// How a station keeps its record of the rover.
#[derive(Debug, Clone)]
pub struct GroundRecordOptions {
    /// The session folder (made if missing; a folder of an earlier run is resumed).
    pub dir: PathBuf,
    /// The downlink's budget in bytes a second (live and backfill together); none: what the
    /// link carries.
    pub budget_bytes_per_s: Option<u64>,
    /// What the station measures of its command link: the backfill slows down when the
    /// commands' round trips grow (none: it keeps to the budget alone).
    pub link: Option<LinkProbe>,
}

pub(crate) enum Item {
    Announce(Announce),
    /// The netlist in force on the rover: kept in each file of the session, as the rover's
    /// recorder keeps it (what a replay needs).
    Netlist(dnm_proto::NetlistState),
    Message {
        topic: String,
        log_time: u64,
        sequence: u32,
        data: Vec<u8>,
        /// It came from the rover's recording, not live.
        backfilled: bool,
    },
    /// Answered once everything before it is written.
    Barrier(SyncSender<()>),
}

/// A station's record of the rover (see the crate's docs). Dropping it finishes its file and
/// the session's manifest.
pub struct GroundRecord {
    dir: PathBuf,
    status: StatusSource,
    data: Option<AdvancedSubscriber<()>>,
    channels: Option<zenoh::pubsub::Subscriber<()>>,
    /// Dropped, the backfill stops.
    stop_backfill: Option<SyncSender<()>>,
    backfill: Option<JoinHandle<()>>,
    writer: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for GroundRecord {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GroundRecord")
            .field("dir", &self.dir)
            .finish_non_exhaustive()
    }
}

impl GroundRecord {
    /// Starts recording what `system`'s rover downlinks, as `options` say.
    pub fn start(
        session: &zenoh::Session,
        system: &str,
        options: &GroundRecordOptions,
    ) -> Result<Self, GroundRecordError> {
        let dir = options.dir.as_path();
        std::fs::create_dir_all(dir).map_err(|source| GroundRecordError::Folder {
            dir: dir.to_path_buf(),
            source,
        })?;
        let (copies, next_index, announces) = held(dir);
        if next_index > 0 {
            // A station killed before it finished a file left no manifest of it.
            if let Err(e) = dnm_record::session::write_manifest(dir) {
                tracing::warn!("the ground session's manifest: {e}");
            }
        }
        let copies = Arc::new(Mutex::new(copies));
        let received = Arc::new(AtomicU64::new(0));
        let unknown: Unknown = Arc::default();
        let (tx, rx) = mpsc::sync_channel::<Item>(QUEUE);
        let teller = Teller::start(session, system).map_err(GroundRecordError::Thread)?;
        let writer = {
            let mut w = Writer {
                teller,
                dir: dir.to_path_buf(),
                index: next_index,
                file: None,
                netlist: None,
                announces,
                pending: HashMap::new(),
                pending_bytes: 0,
                unknown: unknown.clone(),
                copies: copies.clone(),
            };
            std::thread::Builder::new()
                .name("ground-record".into())
                .spawn(move || {
                    if let Err(e) = w.run(&rx) {
                        tracing::error!("the ground's record stopped: {e}");
                    }
                })
                .map_err(GroundRecordError::Thread)?
        };
        // Announcements heard as they are made; the ones made before (or lost) are asked for
        // by the backfill.
        let channels = {
            let tx = tx.clone();
            session
                .declare_subscriber(keys::downlink_channels(system))
                .callback(move |s| {
                    if let Ok(a) = serde_json::from_slice::<Announce>(&s.payload().to_bytes()) {
                        let _ = tx.try_send(Item::Announce(a));
                    }
                })
                .wait()
                .map_err(|e| GroundRecordError::Subscribe(e.to_string()))?
        };
        let data = subscribe(session, &keys::downlink_all(system), {
            let system = system.to_string();
            let tx = tx.clone();
            let received = received.clone();
            move |s| {
                let Some(topic) = keys::downlink_topic(&system, s.key_expr().as_str()) else {
                    return;
                };
                let Some((log_time, sequence)) = s
                    .attachment()
                    .and_then(|a| keys::decode_downlink(&a.to_bytes()))
                else {
                    return;
                };
                let data = s.payload().to_bytes().into_owned();
                received.fetch_add(data.len() as u64, Ordering::Relaxed);
                let _ = tx.try_send(Item::Message {
                    topic,
                    log_time,
                    sequence,
                    data,
                    backfilled: false,
                });
            }
        })?;
        let missed = Arc::new(AtomicU64::new(0));
        {
            let missed = missed.clone();
            data.sample_miss_listener()
                .callback(move |m| {
                    missed.fetch_add(u64::from(m.nb()), Ordering::Relaxed);
                })
                .background()
                .wait()
                .map_err(|e| GroundRecordError::Subscribe(e.to_string()))?;
        }
        let measured = Arc::new(AtomicU64::new(0));
        let request_bytes = Arc::new(AtomicU64::new(0));
        let delivered = Arc::new(AtomicU64::new(0));
        let (stop_backfill, stop) = mpsc::sync_channel::<()>(1);
        let backfill = {
            let shared = backfill::Shared {
                copies: copies.clone(),
                received,
                measured: measured.clone(),
                budget_bytes_per_s: options.budget_bytes_per_s,
                probe: options.link.clone(),
                request_bytes: request_bytes.clone(),
                delivered: delivered.clone(),
                unknown,
            };
            let session = session.clone();
            let system = system.to_string();
            std::thread::Builder::new()
                .name("ground-backfill".into())
                .spawn(move || backfill::run(&session, &system, &shared, &tx, &stop))
                .map_err(GroundRecordError::Thread)?
        };
        Ok(Self {
            dir: dir.to_path_buf(),
            status: StatusSource {
                dir: dir.to_path_buf(),
                copies,
                missed,
                measured,
                request_bytes,
                delivered,
                budget_bytes_per_s: options.budget_bytes_per_s,
            },
            data: Some(data),
            channels: Some(channels),
            stop_backfill: Some(stop_backfill),
            backfill: Some(backfill),
            writer: Some(writer),
        })
    }

    /// The session folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// How complete the copy is: each channel, the budget, the backlog.
    pub fn status(&self) -> RecordStatus {
        self.status.status()
    }

    /// What reads the status from elsewhere (an API's thread), without holding the record.
    pub fn status_source(&self) -> StatusSource {
        self.status.clone()
    }
}

/// Reads a [`GroundRecord`]'s status; it outlives the record harmlessly.
#[derive(Clone)]
pub struct StatusSource {
    dir: PathBuf,
    copies: Arc<Mutex<Copies>>,
    missed: Arc<AtomicU64>,
    measured: Arc<AtomicU64>,
    request_bytes: Arc<AtomicU64>,
    delivered: Arc<AtomicU64>,
    budget_bytes_per_s: Option<u64>,
}

impl std::fmt::Debug for StatusSource {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("StatusSource")
            .field("dir", &self.dir)
            .finish_non_exhaustive()
    }
}

impl StatusSource {
    /// How complete the copy is: each channel, the budget, the backlog.
    pub fn status(&self) -> RecordStatus {
        let settled =
            dnm_proto::clock::now_unix_ns().saturating_sub(backfill::SETTLE.as_nanos() as u64);
        let channels = self
            .copies
            .lock()
            .map(|c| channel_statuses(&c, settled))
            .unwrap_or_default();
        let backlog_bytes = channels.iter().map(|c| c.backlog_bytes).sum();
        let delivered = f64::from_bits(self.delivered.load(Ordering::Relaxed));
        let delivered = (delivered > 0.0).then_some(delivered);
        // At the budget, or at what the link delivered lately if that is less.
        let rate = match (self.budget_bytes_per_s.map(|b| b as f64), delivered) {
            (Some(b), Some(d)) => Some(b.min(d)),
            (b, d) => b.or(d),
        };
        RecordStatus {
            dir: self.dir.display().to_string(),
            channels,
            budget_bytes_per_s: self.budget_bytes_per_s,
            measured_bytes_per_s: f64::from_bits(self.measured.load(Ordering::Relaxed)),
            request_bytes: self.request_bytes.load(Ordering::Relaxed),
            delivered_bytes_per_s: delivered,
            backlog_bytes,
            seconds_to_clear: rate.filter(|r| *r > 0.0).map(|r| backlog_bytes as f64 / r),
            missed_live: self.missed.load(Ordering::Relaxed),
        }
    }
}

impl Drop for GroundRecord {
    fn drop(&mut self) {
        drop(self.stop_backfill.take());
        if let Some(b) = self.backfill.take() {
            let _ = b.join();
        }
        // The subscribers hold the writer's queue: undeclared, the writer finishes its file.
        if let Some(s) = self.data.take() {
            let _ = s.undeclare().wait();
        }
        if let Some(s) = self.channels.take() {
            let _ = s.undeclare().wait();
        }
        if let Some(w) = self.writer.take() {
            let _ = w.join();
        }
    }
}

/// An advanced subscriber on `key` with history (publishers that join late, a restarted
/// station: their last seconds) and recovery of lost samples.
fn subscribe(
    session: &zenoh::Session,
    key: &str,
    callback: impl Fn(zenoh::sample::Sample) + Send + Sync + 'static,
) -> Result<AdvancedSubscriber<()>, GroundRecordError> {
    session
        .declare_subscriber(key.to_string())
        .callback(callback)
        // The publishers' caches give their last seconds (what the recording is not asked
        // for yet); older messages come from the recording, within the budget. (Samples of
        // sessions without timestamps carry none: the whole cache comes, a few seconds' worth.)
        .history(
            HistoryConfig::default()
                .detect_late_publishers()
                .max_age(backfill::SETTLE.as_secs_f64()),
        )
        .recovery(RecoveryConfig::default().heartbeat())
        .subscriber_detection()
        .wait()
        .map_err(|e| GroundRecordError::Subscribe(format!("{key}: {e}")))
}

type McapWriter = mcap::Writer<BufWriter<File>>;

struct OpenFile {
    writer: McapWriter,
    /// Channel ids by topic.
    channels: HashMap<String, u16>,
    last_flush: Instant,
    opened: Instant,
    /// Bytes of messages written to it.
    bytes: u64,
    /// Revisions of the netlists it holds.
    netlists: std::collections::BTreeSet<u64>,
}

/// A message waiting for its channel's announcement: (log time, sequence, bytes, backfilled).
type Pending = (u64, u32, Vec<u8>, bool);

/// The writer thread's state.
struct Writer {
    /// Tells the ground's monitors what was filled in.
    teller: Teller,
    dir: PathBuf,
    /// Of the next file.
    index: u64,
    file: Option<OpenFile>,
    /// The newest netlist heard from the rover: (revision, file, text).
    netlist: Option<(u64, String, String)>,
    /// Each channel's announcement (the newest heard, or as the session's files hold it).
    announces: HashMap<String, Announce>,
    /// Messages of channels whose description has not arrived yet, and their bytes.
    pending: HashMap<String, Vec<Pending>>,
    pending_bytes: usize,
    /// Their topics, for the backfill to ask for their announcements.
    unknown: Unknown,
    copies: Arc<Mutex<Copies>>,
}

impl Writer {
    /// Writes what arrives until both subscribers are gone, then finishes the file.
    fn run(&mut self, items: &Receiver<Item>) -> Result<(), String> {
        loop {
            match items.recv_timeout(CHUNK_PERIOD) {
                Ok(Item::Barrier(done)) => {
                    let _ = done.send(());
                }
                Ok(Item::Netlist(n)) => {
                    if let Some(text) = n.text {
                        let newer = self
                            .netlist
                            .as_ref()
                            .is_none_or(|(r, _, _)| n.revision > *r);
                        if newer {
                            self.netlist = Some((n.revision, n.file.unwrap_or_default(), text));
                        }
                        self.write_netlist()?;
                    }
                }
                Ok(Item::Announce(a)) => self.announce(a)?,
                Ok(Item::Message {
                    topic,
                    log_time,
                    sequence,
                    data,
                    backfilled,
                }) => self.message(topic, log_time, sequence, data, backfilled)?,
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
            self.flush_if_due()?;
        }
        self.close()
    }

    /// A channel described: kept, and what of it waited is written.
    fn announce(&mut self, a: Announce) -> Result<(), String> {
        let topic = a.desc.topic.clone();
        if !self.announces.contains_key(&topic) && self.announces.len() >= TOPICS {
            tracing::warn!(
                %topic,
                "the ground's record holds {TOPICS} channels: this one is not kept"
            );
            // Nor what of it waited, nor is its announcement asked for again.
            if let Some(p) = self.pending.remove(&topic) {
                let bytes: usize = p.iter().map(|m| m.2.len()).sum();
                self.pending_bytes = self.pending_bytes.saturating_sub(bytes);
            }
            if let Ok(mut u) = self.unknown.lock() {
                u.remove(&topic);
            }
            return Ok(());
        }
        self.announces.insert(topic.clone(), a.clone());
        if let Ok(mut u) = self.unknown.lock() {
            u.remove(&topic);
        }
        if let Ok(mut copies) = self.copies.lock() {
            copies.entry(topic.clone()).or_default().announce = Some(a);
        }
        for (time, seq, data, backfilled) in self.pending.remove(&topic).unwrap_or_default() {
            self.pending_bytes = self.pending_bytes.saturating_sub(data.len());
            self.write(&topic, time, seq, &data, backfilled)?;
        }
        Ok(())
    }

    /// A message: written if its channel is described, else kept until it is (within
    /// [`PENDING`], [`PENDING_TOPICS`] and [`PENDING_BYTES`]).
    fn message(
        &mut self,
        topic: String,
        time: u64,
        seq: u32,
        data: Vec<u8>,
        backfilled: bool,
    ) -> Result<(), String> {
        if self.announces.contains_key(&topic) {
            return self.write(&topic, time, seq, &data, backfilled);
        }
        if !self.pending.contains_key(&topic) && self.pending.len() >= PENDING_TOPICS {
            return Ok(());
        }
        if let Ok(mut u) = self.unknown.lock() {
            u.insert(topic.clone());
        }
        if self.pending_bytes + data.len() > PENDING_BYTES {
            return Ok(());
        }
        let p = self.pending.entry(topic).or_default();
        if p.len() < PENDING {
            self.pending_bytes += data.len();
            p.push((time, seq, data, backfilled));
        }
        Ok(())
    }

    /// Writes one message, unless the session holds it already.
    fn write(
        &mut self,
        topic: &str,
        time: u64,
        seq: u32,
        data: &[u8],
        backfilled: bool,
    ) -> Result<(), String> {
        let fresh = self.copies.lock().is_ok_and(|mut c| {
            c.entry(topic.to_string())
                .or_default()
                .take(time, seq, data.len(), backfilled)
        });
        if !fresh {
            return Ok(());
        }
        if self.file.is_none() {
            self.file = Some(self.open()?);
            self.write_netlist()?;
        }
        let Some(a) = self.announces.get(topic) else {
            return Ok(());
        };
        let desc = &a.desc;
        let Some(f) = self.file.as_mut() else {
            return Ok(());
        };
        let channel_id = match f.channels.get(topic) {
            Some(id) => *id,
            None => {
                let schema = f
                    .writer
                    .add_schema(
                        &desc.schema_name,
                        &desc.schema_encoding,
                        desc.schema.as_bytes(),
                    )
                    .map_err(|e| e.to_string())?;
                let id = f
                    .writer
                    .add_channel(schema, topic, &desc.message_encoding, &plan_metadata(a))
                    .map_err(|e| e.to_string())?;
                f.channels.insert(topic.to_string(), id);
                id
            }
        };
        let header = mcap::records::MessageHeader {
            channel_id,
            sequence: seq,
            log_time: time,
            publish_time: time,
        };
        f.writer
            .write_to_known_channel(&header, data)
            .map_err(|e| e.to_string())?;
        f.bytes += data.len() as u64;
        if backfilled {
            self.teller.tell(Filled {
                topic: topic.to_string(),
                log_time: time,
                sequence: seq,
                data: data.to_vec(),
            });
        }
        // A session that runs for weeks is a series of files, each closed whole.
        if f.bytes >= ROTATE_BYTES || f.opened.elapsed() >= ROTATE_AFTER {
            self.finish_file()?;
        }
        Ok(())
    }

    /// Opens the next file of the session.
    fn open(&mut self) -> Result<OpenFile, String> {
        let path = self.dir.join(format!("{STEM}-{}.mcap", self.index));
        self.index += 1;
        let file = File::options()
            .write(true)
            .create_new(true)
            .open(&path)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        let writer = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .compression_level(1)
            .profile("ros2")
            .library("dnm ground")
            .chunk_size(Some(1 << 20))
            .create(BufWriter::new(file))
            .map_err(|e| e.to_string())?;
        Ok(OpenFile {
            writer,
            channels: HashMap::new(),
            last_flush: Instant::now(),
            opened: Instant::now(),
            bytes: 0,
            netlists: Default::default(),
        })
    }

    /// Keeps the newest netlist heard in the file open, as the rover's recorder does: an
    /// attachment `netlist-r<revision>.toml` and a `dnm.netlist` metadata record.
    fn write_netlist(&mut self) -> Result<(), String> {
        let (Some(f), Some((revision, file, text))) = (self.file.as_mut(), self.netlist.as_ref())
        else {
            return Ok(());
        };
        if !f.netlists.insert(*revision) {
            return Ok(());
        }
        let now = dnm_proto::clock::now_unix_ns();
        dnm_record::record::netlist_records(&mut f.writer, now, *revision, file, text)
            .map_err(|e| e.to_string())
    }

    /// Finishes a chunk every [`CHUNK_PERIOD`]: a killed station leaves a readable file.
    fn flush_if_due(&mut self) -> Result<(), String> {
        if let Some(f) = self.file.as_mut()
            && f.last_flush.elapsed() >= CHUNK_PERIOD
        {
            f.last_flush = Instant::now();
            f.writer.flush().map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// Finishes the file open (summary, footer) and the session's manifest; the next message
    /// begins the next file.
    fn finish_file(&mut self) -> Result<(), String> {
        use std::io::Write;
        if let Some(f) = self.file.take() {
            let mut writer = f.writer;
            writer.finish().map_err(|e| e.to_string())?;
            writer.into_inner().flush().map_err(|e| e.to_string())?;
            dnm_record::session::write_manifest(&self.dir).map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    /// Finishes the file and the session's manifest.
    fn close(&mut self) -> Result<(), String> {
        self.finish_file()?;
        dnm_record::session::write_manifest(&self.dir).map_err(|e| e.to_string())?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use zenoh::Wait;

    #[test]
    fn what_waits_for_its_channel_is_bounded_in_channels_and_bytes() {
        let dir = std::env::temp_dir().join(format!("dnm-ground-pending-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let mut c = zenoh::Config::default();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5("listen/endpoints", "[]").unwrap();
        let session = zenoh::open(c).wait().unwrap();
        let mut w = Writer {
            teller: Teller::start(&session, "pending").unwrap(),
            dir: dir.clone(),
            index: 0,
            file: None,
            netlist: None,
            announces: HashMap::new(),
            pending: HashMap::new(),
            pending_bytes: 0,
            unknown: Unknown::default(),
            copies: Arc::default(),
        };
        let held = |w: &Writer| -> usize { w.pending.values().flatten().map(|p| p.2.len()).sum() };
        // Messages on more channels than are kept waiting: the ones beyond are let go.
        for i in 0..PENDING_TOPICS + 10 {
            w.message(format!("/t{i}"), 1, 1, vec![0; 8], false)
                .unwrap();
        }
        assert_eq!(w.pending.len(), PENDING_TOPICS);
        // Large messages on one channel: kept up to the bytes allowed.
        for seq in 0..100u32 {
            w.message(
                "/t0".into(),
                2 + u64::from(seq),
                seq,
                vec![0; 1 << 20],
                false,
            )
            .unwrap();
        }
        assert!(w.pending_bytes <= PENDING_BYTES, "{}", w.pending_bytes);
        assert!(w.pending_bytes > PENDING_BYTES - (2 << 20));
        assert_eq!(w.pending_bytes, held(&w));
        // Its description arrives: what waited is written, and its bytes are free again.
        w.announce(Announce {
            dnm: "rover".into(),
            desc: dnm_record::tap::ChannelDesc {
                topic: "/t0".into(),
                schema_name: "blob".into(),
                schema_encoding: String::new(),
                schema: String::new(),
                message_encoding: "application/octet-stream".into(),
                metadata: Default::default(),
            },
            period_ns: None,
            priority: 1,
            newest_first: true,
        })
        .unwrap();
        assert!(!w.pending.contains_key("/t0"));
        assert_eq!(w.pending_bytes, held(&w));
        assert_eq!(w.pending_bytes, (PENDING_TOPICS - 1) * 8);
        w.close().unwrap();
        drop(w);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
