//! The ground's side of the downlink: what the rover sends of its recording, received live and
//! recovered after gaps, written to the station's own session folder.

use std::collections::{BTreeMap, HashMap, HashSet};
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_proto::keys;
use dnm_record::tap::ChannelDesc;
use serde::Serialize;
use zenoh::Wait;
use zenoh_ext::{AdvancedSubscriber, AdvancedSubscriberBuilderExt, HistoryConfig, RecoveryConfig};

/// Messages received and not written yet, at most; beyond it the newest are let go (and the
/// publishers' caches hold them still).
const QUEUE: usize = 65_536;
/// Messages of a channel whose description has not arrived yet, kept until it does.
const PENDING: usize = 10_000;
/// Longest a chunk of the ground's file stays open: what a killed station loses (and gets
/// again from the caches when it restarts).
const CHUNK_PERIOD: Duration = Duration::from_secs(1);
/// File names of the ground's session: `ground-<n>.mcap`.
const STEM: &str = "ground";

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

/// How complete the ground's copy of one channel is.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize)]
pub struct ChannelStatus {
    pub topic: String,
    /// Messages held (written in this run or found in the session's files).
    pub received: u64,
    /// Rover send times of the oldest and newest held, Unix ns.
    pub first_unix_ns: Option<u64>,
    pub last_unix_ns: Option<u64>,
    /// Messages received again that the session already held.
    pub duplicates: u64,
}

enum Item {
    Channel(ChannelDesc),
    Message {
        topic: String,
        log_time: u64,
        sequence: u32,
        data: Vec<u8>,
    },
}

/// A station's record of the rover (see the crate's docs). Dropping it finishes its file and
/// the session's manifest.
pub struct GroundRecord {
    dir: PathBuf,
    status: Arc<Mutex<BTreeMap<String, ChannelStatus>>>,
    missed: Arc<AtomicU64>,
    data: Option<AdvancedSubscriber<()>>,
    channels: Option<AdvancedSubscriber<()>>,
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
    /// Starts recording what `system`'s rover downlinks into session folder `dir` (made if
    /// missing; a folder of an earlier run is resumed: what it holds is not written again).
    pub fn start(
        session: &zenoh::Session,
        system: &str,
        dir: &Path,
    ) -> Result<Self, GroundRecordError> {
        std::fs::create_dir_all(dir).map_err(|source| GroundRecordError::Folder {
            dir: dir.to_path_buf(),
            source,
        })?;
        let (held, next_index) = held(dir);
        let status = Arc::new(Mutex::new(status_of(&held)));
        let (tx, rx) = mpsc::sync_channel::<Item>(QUEUE);
        let writer = {
            let mut w = Writer {
                dir: dir.to_path_buf(),
                index: next_index,
                file: None,
                descs: HashMap::new(),
                pending: HashMap::new(),
                held: held.into_iter().collect(),
                status: status.clone(),
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
        let channels = subscribe(session, &keys::downlink_channels(system), {
            let tx = tx.clone();
            move |s| {
                if let Ok(desc) = serde_json::from_slice::<ChannelDesc>(&s.payload().to_bytes()) {
                    let _ = tx.try_send(Item::Channel(desc));
                }
            }
        })?;
        let data = subscribe(session, &keys::downlink_all(system), {
            let system = system.to_string();
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
                let _ = tx.try_send(Item::Message {
                    topic,
                    log_time,
                    sequence,
                    data: s.payload().to_bytes().into_owned(),
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
        Ok(Self {
            dir: dir.to_path_buf(),
            status,
            missed,
            data: Some(data),
            channels: Some(channels),
            writer: Some(writer),
        })
    }

    /// The session folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// How complete the copy of each channel is, by topic.
    pub fn status(&self) -> Vec<ChannelStatus> {
        self.status
            .lock()
            .map(|s| s.values().cloned().collect())
            .unwrap_or_default()
    }

    /// Messages the rover's publishers could no longer give (gone from their caches).
    pub fn missed(&self) -> u64 {
        self.missed.load(Ordering::Relaxed)
    }
}

impl Drop for GroundRecord {
    fn drop(&mut self) {
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
/// station) and recovery of lost samples.
fn subscribe(
    session: &zenoh::Session,
    key: &str,
    callback: impl Fn(zenoh::sample::Sample) + Send + Sync + 'static,
) -> Result<AdvancedSubscriber<()>, GroundRecordError> {
    session
        .declare_subscriber(key.to_string())
        .callback(callback)
        .history(HistoryConfig::default().detect_late_publishers())
        .recovery(RecoveryConfig::default().heartbeat())
        .subscriber_detection()
        .wait()
        .map_err(|e| GroundRecordError::Subscribe(format!("{key}: {e}")))
}

/// What the session's files already hold: (topic, log time, sequence) of every message, and
/// the index of the next file.
fn held(dir: &Path) -> (Vec<(String, u64, u32)>, u64) {
    let mut held = Vec::new();
    let mut next = 0;
    let files = dnm_record::session::files(dir).unwrap_or_default();
    for path in files {
        let Some(n) = path
            .file_stem()
            .and_then(|s| s.to_str())
            .and_then(|s| s.strip_prefix(&format!("{STEM}-")))
            .and_then(|n| n.parse::<u64>().ok())
        else {
            continue;
        };
        next = next.max(n + 1);
        let Ok(bytes) = std::fs::read(&path) else {
            continue;
        };
        if dnm_record::check_layout(&bytes).is_err() {
            tracing::warn!(file = %path.display(), "not read: its layout is not MCAP's");
            continue;
        }
        // A file of a killed station ends with its last whole chunk.
        for m in dnm_record::messages(&bytes).map_while(Result::ok) {
            held.push((m.channel.topic.clone(), m.log_time, m.sequence));
        }
    }
    (held, next)
}

fn status_of(held: &[(String, u64, u32)]) -> BTreeMap<String, ChannelStatus> {
    let mut out: BTreeMap<String, ChannelStatus> = BTreeMap::new();
    for (topic, time, _) in held {
        out.entry(topic.clone())
            .or_insert_with(|| ChannelStatus {
                topic: topic.clone(),
                ..ChannelStatus::default()
            })
            .count(*time);
    }
    out
}

impl ChannelStatus {
    fn count(&mut self, time: u64) {
        self.received += 1;
        self.first_unix_ns = Some(self.first_unix_ns.map_or(time, |t| t.min(time)));
        self.last_unix_ns = Some(self.last_unix_ns.map_or(time, |t| t.max(time)));
    }
}

type McapWriter = mcap::Writer<BufWriter<File>>;

struct OpenFile {
    writer: McapWriter,
    /// Channel ids by topic.
    channels: HashMap<String, u16>,
    last_flush: Instant,
}

/// The writer thread's state.
struct Writer {
    dir: PathBuf,
    /// Of the next file.
    index: u64,
    file: Option<OpenFile>,
    descs: HashMap<String, ChannelDesc>,
    /// Messages of channels whose description has not arrived yet.
    pending: HashMap<String, Vec<(u64, u32, Vec<u8>)>>,
    held: HashSet<(String, u64, u32)>,
    status: Arc<Mutex<BTreeMap<String, ChannelStatus>>>,
}

impl Writer {
    /// Writes what arrives until both subscribers are gone, then finishes the file.
    fn run(&mut self, items: &Receiver<Item>) -> Result<(), String> {
        loop {
            match items.recv_timeout(CHUNK_PERIOD) {
                Ok(Item::Channel(desc)) => {
                    let topic = desc.topic.clone();
                    self.descs.insert(topic.clone(), desc);
                    for (time, seq, data) in self.pending.remove(&topic).unwrap_or_default() {
                        self.write(&topic, time, seq, &data)?;
                    }
                }
                Ok(Item::Message {
                    topic,
                    log_time,
                    sequence,
                    data,
                }) => {
                    if self.descs.contains_key(&topic) {
                        self.write(&topic, log_time, sequence, &data)?;
                    } else {
                        let p = self.pending.entry(topic).or_default();
                        if p.len() < PENDING {
                            p.push((log_time, sequence, data));
                        }
                    }
                }
                Err(mpsc::RecvTimeoutError::Timeout) => {}
                Err(mpsc::RecvTimeoutError::Disconnected) => break,
            }
            self.flush_if_due()?;
        }
        self.close()
    }

    /// Writes one message, unless the session holds it already.
    fn write(&mut self, topic: &str, time: u64, seq: u32, data: &[u8]) -> Result<(), String> {
        let fresh = self.held.insert((topic.to_string(), time, seq));
        if let Ok(mut status) = self.status.lock() {
            let s = status
                .entry(topic.to_string())
                .or_insert_with(|| ChannelStatus {
                    topic: topic.to_string(),
                    ..ChannelStatus::default()
                });
            if fresh {
                s.count(time);
            } else {
                s.duplicates += 1;
            }
        }
        if !fresh {
            return Ok(());
        }
        if self.file.is_none() {
            self.file = Some(self.open()?);
        }
        let Some(desc) = self.descs.get(topic) else {
            return Ok(());
        };
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
                    .add_channel(schema, topic, &desc.message_encoding, &desc.metadata)
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
            .map_err(|e| e.to_string())
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
        })
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

    /// Finishes the file (summary, footer) and the session's manifest.
    fn close(&mut self) -> Result<(), String> {
        use std::io::Write;
        if let Some(f) = self.file.take() {
            let mut writer = f.writer;
            writer.finish().map_err(|e| e.to_string())?;
            writer.into_inner().flush().map_err(|e| e.to_string())?;
        }
        dnm_record::session::write_manifest(&self.dir).map_err(|e| e.to_string())?;
        Ok(())
    }
}
