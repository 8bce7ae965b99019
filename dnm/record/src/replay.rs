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
use dnm_netlist::{MessageType, Netlist, Payload};
use iceoryx2::prelude::*;

use crate::standard::Plan;

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

/// The port bytes a recorded message in the port's own type came from (the inverse of
/// [`crate::record::encode`]).
pub fn decode(message: &MessageType, data: &[u8]) -> Result<Vec<u8>, String> {
    if message.encoding == dnm_module::msg::POD_ENCODING {
        data.get(4..)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| "message shorter than its CDR header".into())
    } else if message.encoding == "application/json" {
        Ok(data.to_vec())
    } else if message.encoding == "dnm-image-rgb8" {
        image(data)
    } else {
        let len = data
            .get(4..8)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .ok_or("message shorter than its CDR header")?;
        data.get(8..8usize.saturating_add(len))
            .map(<[u8]>::to_vec)
            .ok_or_else(|| "CDR byte sequence runs past the message".into())
    }
}

/// A camera frame (12-byte header: width, height, step; then the rows) from the
/// `sensor_msgs/msg/Image` the recorder wrote.
fn image(data: &[u8]) -> Result<Vec<u8>, String> {
    let mut at = 4usize;
    let mut take = |align: usize, n: usize| -> Result<&[u8], String> {
        while !(at - 4).is_multiple_of(align) {
            at += 1;
        }
        let s = data
            .get(at..at.saturating_add(n))
            .ok_or("the image message ends early")?;
        at += n;
        Ok(s)
    };
    let u32_of = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
    if data.get(..2) != Some(&[0, 1]) {
        return Err("not little-endian CDR".into());
    }
    take(4, 8)?; // stamp
    let n = u32_of(take(4, 4)?) as usize;
    take(1, n)?; // frame id
    let height = u32_of(take(4, 4)?);
    let width = u32_of(take(4, 4)?);
    let n = u32_of(take(4, 4)?) as usize;
    let encoding = take(1, n)?;
    if encoding != b"rgb8\0" {
        return Err(format!(
            "image encoding {} is not rgb8",
            String::from_utf8_lossy(encoding)
        ));
    }
    take(1, 1)?; // is_bigendian
    let step = u32_of(take(4, 4)?);
    let n = u32_of(take(4, 4)?) as usize;
    let pixels = take(1, n)?;
    let mut out = Vec::with_capacity(12 + pixels.len());
    out.extend_from_slice(&width.to_le_bytes());
    out.extend_from_slice(&height.to_le_bytes());
    out.extend_from_slice(&step.to_le_bytes());
    out.extend_from_slice(pixels);
    Ok(out)
}

/// How a channel's messages become its port's bytes.
#[derive(Clone)]
pub(crate) enum Reading {
    Own,
    Standard(Arc<Plan>),
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
    /// `file` read from its start in file order.
    fn linear(mut file: File) -> Result<Self, String> {
        file.seek(SeekFrom::Start(0)).map_err(|e| e.to_string())?;
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

    fn open(path: &Path) -> Result<(Self, Option<mcap::Summary>), String> {
        let mut file = File::open(path).map_err(|e| e.to_string())?;
        let size = file.metadata().map_err(|e| e.to_string())?.len();
        let summary = crate::session::read_summary(&mut file, size).unwrap_or(None);
        let Some(summary) = summary else {
            tracing::warn!(file = %path.display(), "no summary (not closed): replayed in file order");
            return Ok((Source::linear(file)?, None));
        };
        for c in &summary.chunk_indexes {
            let end = c.chunk_start_offset.checked_add(c.chunk_length);
            if end.is_none_or(|e| e > size)
                || c.compressed_size > size
                || c.uncompressed_size > MAX_CHUNK
            {
                return Err(format!(
                    "corrupt index: the chunk at byte {} does not fit the file or claims {} bytes",
                    c.chunk_start_offset, c.uncompressed_size
                ));
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
            return Ok((Source::linear(file)?, Some(summary)));
        }
        let reader = mcap::sans_io::IndexedReader::new_with_options(
            &summary,
            mcap::sans_io::indexed_reader::IndexedReaderOptions::new()
                .with_order(mcap::sans_io::indexed_reader::ReadOrder::LogTime)
                .with_record_length_limit(MAX_CHUNK as usize),
        )
        .map_err(|e| e.to_string())?;
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

/// Files merged in log-time order.
pub(crate) struct Merge {
    sources: Vec<Source>,
    heads: Vec<Option<Msg>>,
    heap: BinaryHeap<Reverse<(u64, usize)>>,
    pub(crate) names: Vec<String>,
}

impl Merge {
    /// Opens `files`; returns each one's summary too (`None`: not closed).
    pub(crate) fn open(files: &[PathBuf]) -> Result<(Self, Vec<Option<mcap::Summary>>), String> {
        let mut sources = Vec::new();
        let mut summaries = Vec::new();
        let mut names = Vec::new();
        for f in files {
            let (source, summary) = Source::open(f).map_err(|e| format!("{}: {e}", f.display()))?;
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

/// How a message recorded as `schema` on a channel of `message`'s port becomes the port's
/// bytes (`raw`: the channel of its own bytes kept beside a standard message).
pub(crate) fn reading_of(
    message: &MessageType,
    schema: &str,
    raw: bool,
) -> Result<Reading, String> {
    let own = raw
        || schema == message.schema_name
        || (message.encoding == "dnm-image-rgb8" && schema == "sensor_msgs/msg/Image");
    if own {
        return Ok(Reading::Own);
    }
    match Plan::of(message) {
        Ok(Some(plan)) if plan.name() == schema => Ok(Reading::Standard(Arc::new(plan))),
        _ => Err(format!(
            "recorded as {schema}, which {} cannot be read back from",
            message.schema_name
        )),
    }
}

impl Reading {
    /// The port's bytes from a recorded message.
    pub(crate) fn read(&self, message: &MessageType, data: &[u8]) -> Result<Vec<u8>, String> {
        let p = match self {
            Reading::Own => decode(message, data)?,
            Reading::Standard(plan) => plan.decode(data)?,
        };
        let fits = match message.payload {
            Payload::Fixed { size_bytes } => p.len() == size_bytes,
            Payload::Bytes { max_bytes } => p.len() <= max_bytes,
        };
        if fits {
            Ok(p)
        } else {
            Err(format!("{} bytes do not fit {message}", p.len()))
        }
    }
}

struct Target {
    publisher: iceoryx2::port::publisher::Publisher<Svc, [u8], PortHeader>,
    notifier: iceoryx2::port::notifier::Notifier<Svc>,
    message: MessageType,
}

/// A channel's port topic and how to read it, or why it is not replayed (empty: silently).
type Decided = Result<(String, Reading), String>;

/// What a replay reads and where it publishes.
struct Plans<'a> {
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

impl Plans<'_> {
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
            let config = dnm_config(&dnm_prefix(&self.system, dnm))?;
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
pub fn inputs(path: &Path) -> Result<Vec<PathBuf>, String> {
    if path.is_dir() {
        let files = crate::session::files(path)?;
        if files.is_empty() {
            return Err(format!("{}: no recordings (.mcap) in it", path.display()));
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

/// Replays the recording at `path` (a session folder or one MCAP file) into system `system` on
/// this machine (default: the recorded one). `only` selects ports by topic (all when empty);
/// the recorded netlist gives each port's message type.
pub fn replay(
    path: &Path,
    system: Option<&str>,
    only: &[String],
    pace: Pace,
    parse: &crate::ParseNetlist<'_>,
) -> Result<ReplayReport, String> {
    let files = inputs(path)?;
    let text = recorded_netlist(&files).ok_or("the recording holds no netlist")?;
    let netlist = parse(Path::new("recorded.toml"), &text)?;
    let mut plans = Plans {
        system: system.unwrap_or(&netlist.system).to_string(),
        netlist: &netlist,
        only,
        nodes: BTreeMap::new(),
        targets: BTreeMap::new(),
        readings: HashMap::new(),
        raw_ports: BTreeSet::new(),
        skipped: BTreeMap::new(),
    };
    let (mut merge, summaries) = Merge::open(&files)?;
    for summary in summaries.iter().flatten() {
        for c in summary.channels.values() {
            if crate::is_raw(&c.topic) {
                plans
                    .raw_ports
                    .insert(c.topic.trim_end_matches(crate::RAW_SUFFIX).to_string());
            }
        }
    }
    // Every port is opened before the first sample, so subscribers connect in time.
    for summary in summaries.iter().flatten() {
        for c in summary.channels.values() {
            let schema: Arc<str> = Arc::from(c.schema.as_ref().map_or("", |s| s.name.as_str()));
            let topic: Arc<str> = Arc::from(c.topic.as_str());
            plans.reading(&topic, &schema);
        }
    }
    if let Some(e) = plans
        .skipped
        .iter()
        .find(|(t, _)| only.iter().any(|o| o == *t))
    {
        return Err(format!("{}: {}", e.0, e.1));
    }
    std::thread::sleep(Duration::from_millis(200));

    let mut report = ReplayReport {
        files: merge.names.clone(),
        ..Default::default()
    };
    let start = Instant::now();
    let mut t0 = None;
    let stdin = std::io::stdin();
    while let Some(m) = merge.next() {
        if crate::is_raw(&m.topic) {
            plans
                .raw_ports
                .insert(m.topic.trim_end_matches(crate::RAW_SUFFIX).to_string());
        }
        let Some((port_topic, reading)) = plans.reading(&m.topic, &m.schema) else {
            continue;
        };
        let Some(target) = plans.targets.get(&port_topic) else {
            continue;
        };
        let Ok(payload) = reading.read(&target.message, &m.data) else {
            report.unreadable += 1;
            continue;
        };
        let t0 = *t0.get_or_insert(m.time);
        match pace {
            Pace::Rate(factor) => {
                let due = Duration::from_nanos(
                    (m.time.saturating_sub(t0) as f64 / factor.max(1e-6)) as u64,
                );
                if let Some(wait) = due.checked_sub(start.elapsed()) {
                    std::thread::sleep(wait);
                }
            }
            Pace::Step => {
                eprintln!(
                    "+{:.3} s {port_topic} #{} ({} bytes) [Enter]",
                    m.time.saturating_sub(t0) as f64 / 1e9,
                    m.seq,
                    payload.len()
                );
                let mut line = String::new();
                if stdin.read_line(&mut line).map_or(true, |n| n == 0) {
                    break;
                }
            }
            Pace::Fast => {}
        }
        let sample = target
            .publisher
            .loan_slice_uninit(payload.len())
            .map_err(|e| format!("{port_topic}: {e:?}"))?;
        let mut sample = sample.write_from_slice(&payload);
        *sample.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq: u64::from(m.seq),
            task_word: 0,
        };
        sample.send().map_err(|e| format!("{port_topic}: {e:?}"))?;
        let _ = target.notifier.notify();
        report.messages += 1;
        if pace == Pace::Fast {
            // Let on-input consumers keep up (their buffers hold a few samples).
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    if report.messages == 0 {
        return Err(if only.is_empty() {
            "the recording holds no messages to replay".into()
        } else {
            format!("no messages on {}", only.join(", "))
        });
    }
    report.channels = plans.targets.keys().cloned().collect();
    report.skipped = plans
        .skipped
        .iter()
        .map(|(t, why)| format!("{t}: {why}"))
        .collect();
    report.seconds = start.elapsed().as_secs_f64();
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
