//! Replaying recordings into the ports of a running system: each recorded channel
//! `/<dnm>/<module>/<port>` is published again on that port in that DNM's shared memory, with its
//! event, so downstream modules run on the recorded data as if the producer were live.
//!
//! A whole session (a folder) is replayed: every DNM's files merged in log-time order, read from
//! disk a chunk at a time (closed files through their index, a file cut short by a crash in
//! file order), so memory stays bounded whatever the session's size. Standard messages are
//! mapped back to the port's own type (or taken from the bytes kept beside them), camera frames
//! from `sensor_msgs/msg/Image`.

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap, HashMap};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use dnm_module::protocol::{PortHeader, dnm_config, dnm_prefix, monotonic_ns, output_event};
use dnm_module::{event_service, port_service};
use dnm_netlist::{MessageType, Netlist};
use iceoryx2::prelude::*;

pub use crate::codec::decode;
use crate::codec::{Reading, reading_of};
use crate::session::SessionError;

type Svc = ipc::Service;

/// Largest chunk (decompressed) a replay reads; ours are about 1 MiB.
const MAX_CHUNK: u64 = 256 << 20;

/// How fast to replay.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pace {
    /// At `factor` times the recorded speed (1.0: as recorded).
    Rate(f64),
    /// As fast as possible.
    Fast,
    /// One message each time a line is read from standard input (end of input stops).
    Step,
}

/// What a replay did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReplayReport {
    pub messages: u64,
    /// Ports published on.
    pub channels: Vec<String>,
    pub files: Vec<String>,
    /// Channels not replayed, with the reason.
    pub skipped: Vec<String>,
    /// Messages that could not be read back into their port's type.
    pub unreadable: u64,
    pub seconds: f64,
}

/// Why a path holds no recording to read.
#[derive(Debug, thiserror::Error)]
pub enum RecordingFilesError {
    #[error(transparent)]
    Session(#[from] SessionError),
    /// A folder without MCAP files: give a session folder or one file.
    #[error("{}: no recordings (.mcap) in it", dir.display())]
    Empty { dir: PathBuf },
}

/// Why a file of a recording could not be opened for reading.
#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error("{}: {source}", file.display())]
    Io {
        file: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Its index is damaged: a chunk lies beyond the file's end or is larger than a replay
    /// reads.
    #[error(
        "{}: corrupt index: the chunk at byte {offset} does not fit the file or claims \
         {uncompressed} bytes",
        file.display()
    )]
    CorruptIndex {
        file: PathBuf,
        offset: u64,
        uncompressed: u64,
    },
    #[error("{}: {source}", file.display())]
    Mcap {
        file: PathBuf,
        #[source]
        source: mcap::McapError,
    },
}

/// Why a replay did not run, or stopped.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    #[error(transparent)]
    Files(#[from] RecordingFilesError),
    #[error("the recording holds no netlist")]
    NoNetlist,
    /// The recorded netlist does not parse or validate.
    #[error(transparent)]
    Netlist(dnm_netlist::NetlistError),
    #[error(transparent)]
    Open(#[from] OpenError),
    /// A port asked for by topic cannot be replayed, and why.
    #[error("{topic}: {why}")]
    NotReplayable { topic: String, why: String },
    /// The port's shared memory gave no sample to write into.
    #[error("{topic}: {source:?}")]
    Loan {
        topic: String,
        #[source]
        source: iceoryx2::port::LoanError,
    },
    #[error("{topic}: {source:?}")]
    Send {
        topic: String,
        #[source]
        source: iceoryx2::port::SendError,
    },
    #[error("the recording holds no messages to replay")]
    NoMessages,
    /// None of the ports asked for (`only`) has a message in the recording.
    #[error("no messages on {}", only.join(", "))]
    NoMessagesOn { only: Vec<String> },
}

/// One recorded message, on its way to a port.
pub(crate) struct Msg {
    pub(crate) time: u64,
    pub(crate) seq: u32,
    /// The channel's topic and schema name.
    pub(crate) topic: Arc<str>,
    pub(crate) schema: Arc<str>,
    pub(crate) data: Vec<u8>,
}

/// One file's messages in log-time order (closed files) or file order (a file cut short).
enum Source {
    Indexed {
        file: File,
        reader: Box<mcap::sans_io::IndexedReader>,
        channels: HashMap<u16, (Arc<str>, Arc<str>)>,
        buf: Vec<u8>,
    },
    Linear {
        file: File,
        reader: Box<mcap::sans_io::MessageReader>,
    },
}

impl Source {
    /// `file` (at `path`) read from its start in file order.
    fn linear(mut file: File, path: &Path) -> Result<Self, OpenError> {
        file.seek(SeekFrom::Start(0)).map_err(io_error(path))?;
        let reader = mcap::sans_io::MessageReader::new_with_options(
            mcap::sans_io::LinearReaderOptions::default()
                .with_record_length_limit(MAX_CHUNK as usize)
                .with_skip_end_magic(true),
        );
        Ok(Source::Linear {
            file,
            reader: Box::new(reader),
        })
    }

    fn open(path: &Path) -> Result<(Self, Option<mcap::Summary>), OpenError> {
        let mut file = File::open(path).map_err(io_error(path))?;
        let size = file.metadata().map_err(io_error(path))?.len();
        let summary = crate::session::read_summary(&mut file, size).unwrap_or(None);
        let Some(summary) = summary else {
            tracing::warn!(file = %path.display(), "no summary (not closed): replayed in file order");
            return Ok((Source::linear(file, path)?, None));
        };
        for c in &summary.chunk_indexes {
            let end = c.chunk_start_offset.checked_add(c.chunk_length);
            if end.is_none_or(|e| e > size)
                || c.compressed_size > size
                || c.uncompressed_size > MAX_CHUNK
            {
                return Err(OpenError::CorruptIndex {
                    file: path.to_path_buf(),
                    offset: c.chunk_start_offset,
                    uncompressed: c.uncompressed_size,
                });
            }
        }
        // In log-time order the reader holds every chunk whose time range overlaps the next
        // message's: a file whose chunks overlap too much (or a damaged index) is read in file
        // order instead, so memory stays bounded.
        let overlap = {
            // Sweep over the chunks' time ranges: the most decompressed bytes held at once.
            let mut events: Vec<(u64, bool, u64)> = Vec::new();
            for c in &summary.chunk_indexes {
                events.push((c.message_start_time, false, c.uncompressed_size));
                events.push((c.message_end_time, true, c.uncompressed_size));
            }
            // Starts before ends at one instant: ranges that touch overlap.
            events.sort_unstable();
            let (mut held, mut worst) = (0u64, 0u64);
            for (_, end, size) in events {
                if end {
                    held = held.saturating_sub(size);
                } else {
                    held = held.saturating_add(size);
                    worst = worst.max(held);
                }
            }
            worst
        };
        let disordered = summary
            .chunk_indexes
            .iter()
            .any(|c| c.message_start_time > c.message_end_time);
        if overlap > MAX_CHUNK || disordered {
            tracing::warn!(file = %path.display(), "chunks overlap in time: replayed in file order");
            return Ok((Source::linear(file, path)?, Some(summary)));
        }
        let reader = mcap::sans_io::IndexedReader::new_with_options(
            &summary,
            mcap::sans_io::indexed_reader::IndexedReaderOptions::new()
                .with_order(mcap::sans_io::indexed_reader::ReadOrder::LogTime)
                .with_record_length_limit(MAX_CHUNK as usize),
        )
        .map_err(|source| OpenError::Mcap {
            file: path.to_path_buf(),
            source,
        })?;
        let channels = summary
            .channels
            .iter()
            .map(|(id, c)| {
                let schema = c.schema.as_ref().map_or("", |s| s.name.as_str());
                (*id, (Arc::from(c.topic.as_str()), Arc::from(schema)))
            })
            .collect();
        Ok((
            Source::Indexed {
                file,
                reader: Box::new(reader),
                channels,
                buf: Vec::new(),
            },
            Some(summary),
        ))
    }

    fn next(&mut self) -> Option<Result<Msg, String>> {
        use mcap::sans_io::indexed_reader::IndexedReadEvent;
        match self {
            Source::Indexed {
                file,
                reader,
                channels,
                buf,
            } => loop {
                match reader.next_event()? {
                    Err(e) => return Some(Err(e.to_string())),
                    Ok(IndexedReadEvent::ReadChunkRequest { offset, length }) => {
                        buf.resize(length, 0);
                        if let Err(e) = file
                            .seek(SeekFrom::Start(offset))
                            .and_then(|_| file.read_exact(buf))
                        {
                            return Some(Err(e.to_string()));
                        }
                        if let Err(e) = reader.insert_chunk_record_data(offset, buf) {
                            return Some(Err(e.to_string()));
                        }
                    }
                    Ok(IndexedReadEvent::Message { header, data }) => {
                        let Some((topic, schema)) = channels.get(&header.channel_id) else {
                            continue;
                        };
                        return Some(Ok(Msg {
                            time: header.log_time,
                            seq: header.sequence,
                            topic: topic.clone(),
                            schema: schema.clone(),
                            data: data.to_vec(),
                        }));
                    }
                }
            },
            Source::Linear { file, reader } => loop {
                use mcap::sans_io::MessageReadEvent;
                match reader.next_event()? {
                    Err(_) => return None, // cut short: its last whole message was the end
                    Ok(MessageReadEvent::ReadRequest(n)) => {
                        let buf = reader.insert(n);
                        match file.read(buf) {
                            Ok(k) => reader.notify_read(k),
                            Err(e) => return Some(Err(e.to_string())),
                        }
                    }
                    Ok(MessageReadEvent::Message(m)) => {
                        let schema = m.channel.schema.as_ref().map_or("", |s| s.name.as_str());
                        return Some(Ok(Msg {
                            time: m.log_time,
                            seq: m.sequence,
                            topic: Arc::from(m.channel.topic.as_str()),
                            schema: Arc::from(schema),
                            data: m.data.into_owned(),
                        }));
                    }
                }
            },
        }
    }
}

/// An I/O error on the file at `path`, as an [`OpenError`].
fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> OpenError + '_ {
    move |source| OpenError::Io {
        file: path.to_path_buf(),
        source,
    }
}

/// Files merged in log-time order.
pub(crate) struct Merge {
    sources: Vec<Source>,
    heads: Vec<Option<Msg>>,
    heap: BinaryHeap<Reverse<(u64, usize)>>,
    pub(crate) names: Vec<String>,
}

impl Merge {
    /// Opens `files`; returns each one's summary too (`None`: not closed).
    pub(crate) fn open(files: &[PathBuf]) -> Result<(Self, Vec<Option<mcap::Summary>>), OpenError> {
        let mut sources = Vec::new();
        let mut summaries = Vec::new();
        let mut names = Vec::new();
        for f in files {
            let (source, summary) = Source::open(f)?;
            sources.push(source);
            summaries.push(summary);
            names.push(
                f.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            );
        }
        let mut heads = Vec::with_capacity(sources.len());
        let mut heap = BinaryHeap::new();
        for (i, s) in sources.iter_mut().enumerate() {
            let head = next_ok(s, &names[i]);
            if let Some(m) = &head {
                heap.push(Reverse((m.time, i)));
            }
            heads.push(head);
        }
        Ok((
            Self {
                sources,
                heads,
                heap,
                names,
            },
            summaries,
        ))
    }

    pub(crate) fn next(&mut self) -> Option<Msg> {
        loop {
            let Reverse((_, i)) = self.heap.pop()?;
            let Some(m) = self.heads[i].take() else {
                continue;
            };
            self.heads[i] = next_ok(&mut self.sources[i], &self.names[i]);
            if let Some(n) = &self.heads[i] {
                self.heap.push(Reverse((n.time, i)));
            }
            return Some(m);
        }
    }
}

/// A port a replay publishes on.
struct Target {
    publisher: iceoryx2::port::publisher::Publisher<Svc, [u8], PortHeader>,
    notifier: iceoryx2::port::notifier::Notifier<Svc>,
    message: MessageType,
}

impl Target {
    /// Publishes `payload` on the port (`topic`) as sample `seq`, and wakes its readers.
    fn publish(&self, topic: &str, payload: &[u8], seq: u32) -> Result<(), ReplayError> {
        let sample = self
            .publisher
            .loan_slice_uninit(payload.len())
            .map_err(|source| ReplayError::Loan {
                topic: topic.to_string(),
                source,
            })?;
        let mut sample = sample.write_from_slice(payload);
        *sample.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq: u64::from(seq),
            task_word: 0,
        };
        sample.send().map_err(|source| ReplayError::Send {
            topic: topic.to_string(),
            source,
        })?;
        let _ = self.notifier.notify();
        Ok(())
    }
}

/// A recorded channel's topic taken apart: `/<dnm>/<module>/<port>`, or its `/raw` companion.
pub(crate) struct PortTopic<'t> {
    /// The channel keeps the port's own bytes beside its standard message.
    pub(crate) raw: bool,
    /// The port's topic (without `/raw`).
    pub(crate) port_topic: &'t str,
    pub(crate) dnm: &'t str,
    pub(crate) module: &'t str,
    pub(crate) port: &'t str,
}

impl<'t> PortTopic<'t> {
    pub(crate) fn of(topic: &'t str) -> Result<Self, String> {
        let raw = crate::is_raw(topic);
        let port_topic = topic
            .strip_suffix(crate::RAW_SUFFIX)
            .filter(|_| raw)
            .unwrap_or(topic);
        let mut parts = port_topic.trim_start_matches('/').splitn(3, '/');
        let (Some(dnm), Some(module), Some(port)) = (parts.next(), parts.next(), parts.next())
        else {
            return Err(format!("`{topic}` is not /<dnm>/<module>/<port>"));
        };
        Ok(Self {
            raw,
            port_topic,
            dnm,
            module,
            port,
        })
    }
}

/// A channel's port topic and how to read it, or why it is not replayed (empty: silently).
type Decided = Result<(String, Reading), String>;

/// What a replay reads and where it publishes.
struct Routes<'a> {
    netlist: &'a Netlist,
    system: String,
    only: &'a [String],
    nodes: BTreeMap<String, Node<Svc>>,
    targets: BTreeMap<String, Target>,
    /// Per (topic, schema): how to read it and into which port, or why not.
    readings: HashMap<(Arc<str>, Arc<str>), Decided>,
    /// Ports whose own bytes are recorded beside their standard message.
    raw_ports: BTreeSet<String>,
    skipped: BTreeMap<String, String>,
}

impl<'a> Routes<'a> {
    fn new(netlist: &'a Netlist, system: Option<&str>, only: &'a [String]) -> Self {
        Self {
            system: system.unwrap_or(&netlist.system).to_string(),
            netlist,
            only,
            nodes: BTreeMap::new(),
            targets: BTreeMap::new(),
            readings: HashMap::new(),
            raw_ports: BTreeSet::new(),
            skipped: BTreeMap::new(),
        }
    }

    /// Opens the port of every channel the files' summaries list.
    fn open_all(&mut self, summaries: &[Option<mcap::Summary>]) {
        for summary in summaries.iter().flatten() {
            for c in summary.channels.values() {
                self.note_raw(&c.topic);
            }
        }
        // Every port is opened before the first sample, so subscribers connect in time.
        for summary in summaries.iter().flatten() {
            for c in summary.channels.values() {
                let schema: Arc<str> = Arc::from(c.schema.as_ref().map_or("", |s| s.name.as_str()));
                let topic: Arc<str> = Arc::from(c.topic.as_str());
                self.reading(&topic, &schema);
            }
        }
    }

    /// Notes a channel of a port's own bytes, replayed instead of its standard message.
    fn note_raw(&mut self, topic: &str) {
        if crate::is_raw(topic) {
            self.raw_ports
                .insert(topic.trim_end_matches(crate::RAW_SUFFIX).to_string());
        }
    }

    /// How `topic` (recorded as `schema`) is replayed: its port's topic and how to read it.
    fn reading(&mut self, topic: &Arc<str>, schema: &Arc<str>) -> Option<(String, Reading)> {
        let key = (topic.clone(), schema.clone());
        if !self.readings.contains_key(&key) {
            let r = self.decide(topic, schema);
            if let Err(why) = &r
                && !why.is_empty()
            {
                tracing::warn!(%topic, "not replayed: {why}");
                self.skipped.insert(topic.to_string(), why.clone());
            }
            self.readings.insert(key.clone(), r);
        }
        self.readings.get(&key)?.as_ref().ok().cloned()
    }

    fn decide(&mut self, topic: &str, schema: &str) -> Result<(String, Reading), String> {
        let PortTopic {
            raw,
            port_topic,
            dnm,
            module,
            port,
        } = PortTopic::of(topic)?;
        if module.starts_with('_') || port.starts_with('_') {
            return Err(String::new()); // switches and events: not port data
        }
        if !self.only.is_empty() && !self.only.iter().any(|o| o == port_topic) {
            return Err(String::new());
        }
        if !raw && self.raw_ports.contains(port_topic) {
            return Err(String::new()); // the bytes beside it are replayed instead
        }
        let message = self
            .netlist
            .kind_of(module)
            .and_then(|k| k.outputs.iter().find(|p| p.name == port))
            .map(|p| p.message.clone())
            .ok_or_else(|| format!("the recorded netlist has no output {module}.{port}"))?;
        let reading = reading_of(&message, schema, raw)?;
        if !self.targets.contains_key(port_topic) {
            self.target(dnm, module, port, port_topic, message)?;
        }
        Ok((port_topic.to_string(), reading))
    }

    fn target(
        &mut self,
        dnm: &str,
        module: &str,
        port: &str,
        topic: &str,
        message: MessageType,
    ) -> Result<(), String> {
        if !self.nodes.contains_key(dnm) {
            let config = dnm_config(&dnm_prefix(&self.system, dnm)).map_err(|e| e.to_string())?;
            let node = NodeBuilder::new()
                .config(&config)
                .create::<Svc>()
                .map_err(|e| format!("node: {e:?}"))?;
            self.nodes.insert(dnm.to_string(), node);
        }
        let node = &self.nodes[dnm];
        let system = &self.system;
        let publisher = port_service(node, &format!("{module}/{port}"), &message.payload)
            .map_err(|e| format!("{topic}: {e} (is system `{system}` running here?)"))?
            .publisher_builder()
            .initial_max_slice_len(message.payload.max_bytes())
            .create()
            .map_err(|e| format!("{topic}: publisher: {e:?}"))?;
        let notifier = event_service(node, &output_event(module, port))
            .map_err(|e| e.to_string())?
            .notifier_builder()
            .create()
            .map_err(|e| format!("{topic}: notifier: {e:?}"))?;
        self.targets.insert(
            topic.to_string(),
            Target {
                publisher,
                notifier,
                message,
            },
        );
        Ok(())
    }
}

/// The recording's files: a session folder's, or one file.
pub fn inputs(path: &Path) -> Result<Vec<PathBuf>, RecordingFilesError> {
    if path.is_dir() {
        let files = crate::session::files(path)?;
        if files.is_empty() {
            return Err(RecordingFilesError::Empty {
                dir: path.to_path_buf(),
            });
        }
        Ok(files)
    } else {
        Ok(vec![path.to_path_buf()])
    }
}

/// The newest netlist the files recorded.
pub fn recorded_netlist(files: &[PathBuf]) -> Option<String> {
    let mut netlists = BTreeMap::new();
    for f in files {
        crate::session::file_entry(f, &mut netlists);
    }
    netlists.into_values().next_back().map(|n| n.text)
}

/// Keeps a replay to its [`Pace`].
struct Pacer {
    pace: Pace,
    start: Instant,
    /// When the first message replayed was recorded.
    t0: Option<u64>,
    stdin: std::io::Stdin,
}

impl Pacer {
    fn new(pace: Pace) -> Self {
        Self {
            pace,
            start: Instant::now(),
            t0: None,
            stdin: std::io::stdin(),
        }
    }

    /// Waits until the message recorded at `time` (sample `seq` of `topic`, `len` bytes) is
    /// due; `false`: the replay is to stop (end of standard input, stepping).
    fn wait(&mut self, time: u64, topic: &str, seq: u32, len: usize) -> bool {
        let t0 = *self.t0.get_or_insert(time);
        match self.pace {
            Pace::Rate(factor) => {
                let due = Duration::from_nanos(
                    (time.saturating_sub(t0) as f64 / factor.max(1e-6)) as u64,
                );
                if let Some(wait) = due.checked_sub(self.start.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
            Pace::Step => {
                eprintln!(
                    "+{:.3} s {topic} #{seq} ({len} bytes) [Enter]",
                    time.saturating_sub(t0) as f64 / 1e9,
                );
                let mut line = String::new();
                if self.stdin.read_line(&mut line).map_or(true, |n| n == 0) {
                    return false;
                }
            }
            Pace::Fast => {}
        }
        true
    }
}

/// Replays the recording at `path` (a session folder or one MCAP file) into system `system` on
/// this machine (default: the recorded one). `only` selects ports by topic (all when empty);
/// the recorded netlist gives each port's message type.
pub fn replay(
    path: &Path,
    system: Option<&str>,
    only: &[String],
    pace: Pace,
    parse: &crate::ParseNetlist,
) -> Result<ReplayReport, ReplayError> {
    let files = inputs(path)?;
    let text = recorded_netlist(&files).ok_or(ReplayError::NoNetlist)?;
    let netlist = parse(Path::new("recorded.toml"), &text).map_err(ReplayError::Netlist)?;
    let mut routes = Routes::new(&netlist, system, only);
    let (mut merge, summaries) = Merge::open(&files)?;
    routes.open_all(&summaries);
    if let Some((topic, why)) = routes
        .skipped
        .iter()
        .find(|(t, _)| only.iter().any(|o| o == *t))
    {
        return Err(ReplayError::NotReplayable {
            topic: topic.clone(),
            why: why.clone(),
        });
    }
    std::thread::sleep(Duration::from_millis(200));

    let mut report = ReplayReport {
        files: merge.names.clone(),
        ..Default::default()
    };
    let mut pacer = Pacer::new(pace);
    while let Some(m) = merge.next() {
        routes.note_raw(&m.topic);
        let Some((port_topic, reading)) = routes.reading(&m.topic, &m.schema) else {
            continue;
        };
        let Some(target) = routes.targets.get(&port_topic) else {
            continue;
        };
        let Ok(payload) = reading.read(&target.message, &m.data) else {
            report.unreadable += 1;
            continue;
        };
        if !pacer.wait(m.time, &port_topic, m.seq, payload.len()) {
            break;
        }
        target.publish(&port_topic, &payload, m.seq)?;
        report.messages += 1;
        if pace == Pace::Fast {
            // Let on-input consumers keep up (their buffers hold a few samples).
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    if report.messages == 0 {
        return Err(if only.is_empty() {
            ReplayError::NoMessages
        } else {
            ReplayError::NoMessagesOn {
                only: only.to_vec(),
            }
        });
    }
    report.channels = routes.targets.keys().cloned().collect();
    report.skipped = routes
        .skipped
        .iter()
        .map(|(t, why)| format!("{t}: {why}"))
        .collect();
    report.seconds = pacer.start.elapsed().as_secs_f64();
    Ok(report)
}

/// The next message of a file; a read error ends that file (said once).
fn next_ok(s: &mut Source, name: &str) -> Option<Msg> {
    match s.next()? {
        Ok(m) => Some(m),
        Err(e) => {
            tracing::warn!(file = name, "stops here: {e}");
            None
        }
    }
}
