//! Recording a DNM's output ports to MCAP, off the hot path.
//!
//! A reader thread holds its own subscriber on every recorded port and drains them every 10 ms
//! (it does not wake per sample); it copies each sample into a bounded queue and never blocks:
//! if the queue is full the sample is counted as dropped, and samples a slow reader missed are
//! counted from gaps in the per-port sequence numbers. Samples are copied into buffers the writer
//! hands back (in normal operation the reader alone allocates and frees them, and a sample
//! costs no allocation once they are in use); large samples (camera frames) are encoded
//! straight from shared memory. A writer thread at nice 10 turns the queue into an MCAP file:
//! one channel per output port (`/<dnm>/<module>/<port>`), zstd-compressed chunks finished
//! every second, so a killed DNM leaves a file readable up to its last second. Files rotate by size and age.
//!
//! Encodings the robotics tools read without our code: fixed-size messages are ROS 2 `.msg`
//! schemas with CDR messages (their `repr(C)` layout of 8-byte fields is CDR's, after the
//! 4-byte encapsulation header); images become `sensor_msgs/msg/Image`; JSON stays JSON with a
//! JSON schema; other bytes are `uint8[] data` in CDR ([`crate::codec`]). A fixed-size type
//! that declares its standard ROS 2 equivalent (odometry, IMU, battery, range, twist, joints,
//! transforms) is recorded as that message ([`crate::standard`]); when it cannot hold our fields
//! exactly, our bytes are kept beside it on `<topic>/raw`. Log and publish times are the producer's
//! send stamps, mapped from CLOCK_MONOTONIC to Unix time. The netlist of each revision is an
//! attachment and a metadata record; task switches are a JSON channel `/<dnm>/_switches`, module events `/<dnm>/_events`, and the
//! authority's onboard sequence events `/<dnm>/_sequences` (step started, condition met, guard
//! fired, finished, aborted...).

use std::collections::BTreeMap;
use std::fs::File;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{self, Receiver, SyncSender, TrySendError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use dnm_module::port_service;
use dnm_module::protocol::LARGE_PAYLOAD_BYTES;
use dnm_module::protocol::{PortHeader, monotonic_ns, output_service};
use dnm_netlist::{Decimator, DownlinkEntry, MessageType, Netlist};
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

pub use crate::codec::{encode, encode_into, mcap_encoding};
use crate::standard::{Cdr, StandardMapping};
pub use crate::tap::{ChannelDesc, Tap, Tapped};
use dnm_core::worker::{Control, Sets, Worker, dbg};
use dnm_core::{Context, DnmReport, ModuleEvent, Plugin, SwitchRecord};
pub use dnm_proto::RecordReport;
use iceoryx2::identifiers::UniquePublisherId;
use std::collections::HashMap;

type Svc = ipc::Service;

/// Event service that wakes a DNM's recorder after its port set changed.
const RECORDER_EVENT: &str = "_dnm/recorder";
/// Samples queued between the reader and the writer...
const QUEUE: usize = 65_536;
/// ...and at most this many bytes of them: beyond it, new samples are dropped (and counted).
const QUEUE_BYTES: u64 = 256 << 20;
/// Longest a chunk stays open: what a crash can lose.
const CHUNK_PERIOD: Duration = Duration::from_secs(1);
/// Most files a DNM numbers in one folder: past it, a file that exists is an error.
const MAX_FILES: u64 = 1_000_000;
/// Buffers the reader keeps for reuse: small samples' (up to [`LARGE_PAYLOAD_BYTES`])...
const SPARE_SMALL: usize = 256;
/// ...and large samples' (a camera frame then costs no allocation and no fresh pages).
const SPARE_LARGE: usize = 8;

/// Where and what a DNM records.
#[derive(Debug, Clone)]
pub struct RecordOptions {
    /// Folder of the files (`recordings/` by default).
    pub dir: PathBuf,
    /// File name stem; files are `<stem>-<dnm>[.n].mcap`.
    pub stem: String,
    /// Record only these modules or `module/port`s (all when empty).
    pub only: Vec<String>,
    /// Start a new file after this many bytes...
    pub rotate_bytes: u64,
    /// ...or this long.
    pub rotate_after: Duration,
    /// `dir` is a session folder: keep its manifest current as files close.
    pub session: bool,
    /// Where the downlink plan's messages (and the switches and events) go as they are
    /// written.
    pub tap: Option<Arc<dyn Tap>>,
    /// zstd worker threads beside each file's writer; 0 (the default): the writer compresses
    /// on its own thread, which costs a rover computer no threads or buffers of their own.
    pub compression_workers: u32,
}

impl RecordOptions {
    /// `recordings/<UTC timestamp>`, 1 GiB or 1 hour per file.
    pub fn timestamped(dir: &Path) -> Self {
        let secs = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        Self {
            dir: dir.to_path_buf(),
            stem: format!("rec-{secs}"),
            only: Vec::new(),
            rotate_bytes: 1 << 30,
            rotate_after: Duration::from_secs(3600),
            session: false,
            tap: None,
            compression_workers: 0,
        }
    }

    /// A session of `system` under `root`: `root/<system>-<UTC time>/rec-<dnm>[.n].mcap` and
    /// its manifest (see [`crate::session`]), 1 GiB or 1 hour per file. The folder is made here
    /// and is this run's alone: one of that name already there (a run started within the same
    /// second, as a process restarted at once after a crash is) makes this one
    /// `<system>-<UTC time>-2`, and so on.
    pub fn session(root: &Path, system: &str) -> Self {
        let secs = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_secs());
        Self {
            dir: crate::session::claim_folder(root, &crate::session::session_name(system, secs)),
            stem: "rec".into(),
            session: true,
            ..Self::timestamped(root)
        }
    }

    /// These options, recording into a session of `system` under their folder.
    pub fn into_session(self, system: &str) -> Self {
        Self {
            only: self.only,
            rotate_bytes: self.rotate_bytes,
            rotate_after: self.rotate_after,
            tap: self.tap,
            compression_workers: self.compression_workers,
            ..Self::session(&self.dir, system)
        }
    }

    fn wants(&self, module: &str, port: &str) -> bool {
        self.only.is_empty()
            || self
                .only
                .iter()
                .any(|s| s == module || *s == format!("{module}/{port}"))
    }
}

#[derive(Debug, Default)]
struct Counters {
    /// Bytes of samples queued for the writer.
    queued: AtomicU64,
    messages: AtomicU64,
    bytes: AtomicU64,
    dropped: AtomicU64,
    files: AtomicU64,
    file: std::sync::Mutex<String>,
    /// Why the writer stopped, if it did.
    error: std::sync::Mutex<Option<String>>,
}

#[derive(Debug, Clone, PartialEq)]
struct RecPort {
    module: String,
    port: String,
    message: MessageType,
    /// Its entry in the downlink plan, if the plan names it.
    downlink: Option<DownlinkEntry>,
}

enum Item {
    Sample {
        port: usize,
        header: PortHeader,
        bytes: Vec<u8>,
        /// Already the message as written (large samples, encoded by the reader).
        encoded: bool,
    },
    Ports(Vec<RecPort>),
    Netlist {
        revision: u64,
        file: String,
        text: String,
    },
    Switch(String),
    Event(String),
    /// An onboard sequence's event (the authority's DNM records them).
    Sequence(String),
}

/// Where the authority's onboard sequence events go into this recorder's files (a channel
/// `/<dnm>/_sequences`), from any thread. It does not keep the recorder's queue open: once the
/// recorder stops, events are let go.
#[derive(Debug, Clone)]
pub struct SequenceRecorder(Arc<std::sync::Mutex<Option<SyncSender<Item>>>>);

impl SequenceRecorder {
    /// Records one event (JSON); dropped if the recorder's queue is full or it stopped.
    pub fn record(&self, json: String) {
        if let Ok(q) = self.0.lock()
            && let Some(q) = q.as_ref()
        {
            let _ = q.try_send(Item::Sequence(json));
        }
    }
}

/// Why a recorder did not start.
#[derive(Debug, thiserror::Error)]
pub enum RecorderStartError {
    /// The recordings folder could not be made.
    #[error("recordings folder {}: {source}", dir.display())]
    Folder {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// No thread for the writer.
    #[error("{0}")]
    WriterThread(#[source] std::io::Error),
    /// The reader (its thread, or its node in the DNM's shared memory) did not start.
    #[error("{0}")]
    Reader(String),
}

/// A DNM's recorder: the reader and writer threads.
pub struct Recorder {
    queue: SyncSender<Item>,
    /// The queue as sequence events reach it (closed before the writer is waited for).
    sequences: SequenceRecorder,
    counters: Arc<Counters>,
    options: RecordOptions,
    reader: Option<Worker<RecPort>>,
    writer: Option<JoinHandle<()>>,
    /// The revision in force (netlist, revision) and the one prepared, if any: ports are
    /// recorded from the prepare on, so a module's first samples are in the recording.
    in_force: Option<(Arc<Netlist>, u64)>,
    prepared: Option<u64>,
}

impl std::fmt::Debug for Recorder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("options", &self.options)
            .finish_non_exhaustive()
    }
}

impl Recorder {
    /// Starts recording DNM `dnm`, whose shared-memory namespace is `prefix`; ports follow
    /// each committed revision.
    pub fn start(
        dnm: &str,
        prefix: &str,
        options: RecordOptions,
    ) -> Result<Self, RecorderStartError> {
        std::fs::create_dir_all(&options.dir).map_err(|source| RecorderStartError::Folder {
            dir: options.dir.clone(),
            source,
        })?;
        let counters = Arc::new(Counters::default());
        let clock = Clock::new();
        let (queue, items) = mpsc::sync_channel::<Item>(QUEUE);
        // Sample buffers go back to the reader, which reuses them and frees the ones it does not
        // keep: in normal operation the writer takes no lock of the reader's allocator arena.
        // Room for as many as the reader keeps (a bounded channel reserves its slots up front).
        let (spare, spares) = mpsc::sync_channel::<Vec<u8>>(SPARE_SMALL + SPARE_LARGE);
        let writer = {
            let counters = counters.clone();
            let options = options.clone();
            let dnm = dnm.to_string();
            std::thread::Builder::new()
                .name(format!("record-{dnm}"))
                .spawn(move || {
                    if let Err(e) = write_loop(&dnm, &options, &items, &spare, &counters, clock) {
                        tracing::error!(dnm, "recording stopped: {e}");
                        if let Ok(mut err) = counters.error.lock() {
                            *err = Some(e);
                        }
                    }
                })
                .map_err(RecorderStartError::WriterThread)?
        };
        let reader = {
            let counters = counters.clone();
            let queue = queue.clone();
            Worker::spawn(
                format!("record-in-{dnm}"),
                prefix,
                RECORDER_EVENT,
                move |control| read_loop(&control, &queue, &spares, &counters, clock),
            )
            .map_err(|e| RecorderStartError::Reader(e.to_string()))?
        };
        Ok(Self {
            sequences: SequenceRecorder(Arc::new(std::sync::Mutex::new(Some(queue.clone())))),
            queue,
            counters,
            options,
            reader: Some(reader),
            writer: Some(writer),
            in_force: None,
            prepared: None,
        })
    }

    /// After a revision is committed: record its netlist and exactly the wanted ports of the
    /// DNM's modules.
    pub fn commit(&mut self, netlist: &Netlist, dnm: &str, revision: u64) {
        let ports: Vec<RecPort> = netlist
            .modules_on(dnm)
            .filter_map(|m| netlist.kind_of(&m.name).map(|k| (m, k)))
            .flat_map(|(m, k)| {
                k.outputs
                    .iter()
                    .filter(|p| self.options.wants(&m.name, &p.name))
                    .map(|p| RecPort {
                        module: m.name.clone(),
                        port: p.name.clone(),
                        message: p.message.clone(),
                        downlink: netlist
                            .downlink
                            .iter()
                            .find(|d| d.output.module == m.name && d.output.port == p.name)
                            .cloned(),
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        // Never blocks the DNM: a writer that cannot keep up loses the netlist record of this
        // revision (its samples are counted as dropped anyway).
        let item = Item::Netlist {
            revision,
            file: netlist.file.display().to_string(),
            text: netlist.text.clone(),
        };
        if let Err(TrySendError::Full(_)) = self.queue.try_send(item) {
            tracing::warn!(dnm, revision, "recorder queue full: netlist not recorded");
        }
        // The reader announces the new port set to the writer itself, in queue order, so no
        // sample read under the old set is written to a channel of the new one.
        if let Some(reader) = &self.reader {
            reader.send(ports);
        }
    }

    /// Records a task switch.
    pub fn switch(&self, record: &SwitchRecord) {
        if let Ok(json) = serde_json::to_string(record) {
            let _ = self.queue.try_send(Item::Switch(json));
        }
    }

    /// A handle that records onboard sequence events in this recorder's files.
    pub fn sequence_recorder(&self) -> SequenceRecorder {
        self.sequences.clone()
    }

    /// Records a module event (exit, hang, restart).
    pub fn module_event(&self, event: &ModuleEvent) {
        if let Ok(json) = serde_json::to_string(event) {
            let _ = self.queue.try_send(Item::Event(json));
        }
    }

    pub fn report(&self) -> RecordReport {
        RecordReport {
            file: self
                .counters
                .file
                .lock()
                .map(|f| f.clone())
                .unwrap_or_default(),
            messages: self.counters.messages.load(Ordering::Relaxed),
            bytes: self.counters.bytes.load(Ordering::Relaxed),
            dropped: self.counters.dropped.load(Ordering::Relaxed),
            files: self.counters.files.load(Ordering::Relaxed),
            error: self.counters.error.lock().ok().and_then(|e| e.clone()),
        }
    }
}

impl Plugin for Recorder {
    fn name(&self) -> &'static str {
        "recorder"
    }

    fn prepare(
        &mut self,
        ctx: &Context<'_>,
        netlist: &Netlist,
        revision: u64,
    ) -> Result<(), dnm_core::PluginPrepareError> {
        // Subscribed before the modules of the revision run: their first samples are recorded.
        Recorder::commit(self, netlist, ctx.dnm, revision);
        self.prepared = Some(revision);
        Ok(())
    }

    fn abort(&mut self, ctx: &Context<'_>, revision: u64) {
        if self.prepared.take() != Some(revision) {
            return;
        }
        match self.in_force.clone() {
            Some((netlist, in_force)) => Recorder::commit(self, &netlist, ctx.dnm, in_force),
            // Nothing in force: nothing to record.
            None => {
                if let Some(reader) = &self.reader {
                    reader.send(Vec::new());
                }
            }
        }
    }

    fn commit(&mut self, ctx: &Context<'_>, netlist: &Netlist, revision: u64) {
        if self.prepared.take() != Some(revision) {
            Recorder::commit(self, netlist, ctx.dnm, revision);
        }
        self.in_force = Some((Arc::new(netlist.clone()), revision));
    }

    fn switch(&mut self, record: &SwitchRecord) {
        Recorder::switch(self, record);
    }

    fn module_event(&mut self, event: &ModuleEvent) {
        Recorder::module_event(self, event);
    }

    fn report(&self, report: &mut DnmReport) {
        report.recording = Some(Recorder::report(self));
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        // Stops the reader first.
        self.reader.take();
        if let Ok(mut q) = self.sequences.0.lock() {
            q.take();
        }
        // The reader held the other queue sender; dropping ours ends the writer, which
        // finishes the file (summary and footer).
        drop(std::mem::replace(&mut self.queue, mpsc::sync_channel(1).0));
        if let Some(t) = self.writer.take() {
            let _ = t.join();
        }
        // The session's manifest lists the file just closed before the process may end.
        if self.options.session {
            crate::session::settle();
        }
    }
}

/// How often the reader drains its subscribers. It does not wake per sample (that would compete
/// with the modules' own wake-ups for the CPU); its subscribers hold
/// [`dnm_module::protocol::recorder_buffer`] samples, more than a port sends in this time at the
/// rates the DNM is built for (1 kHz small messages, 500 Hz up to 64 KiB).
const DRAIN_PERIOD: Duration = Duration::from_millis(10);

fn read_loop(
    control: &Control<RecPort>,
    queue: &SyncSender<Item>,
    spares: &Receiver<Vec<u8>>,
    counters: &Counters,
    clock: Clock,
) -> Result<(), String> {
    // Normal priority: its drains are short, and a starved reader would lose samples.
    let mut reader = Reader {
        queue,
        counters,
        clock,
        wanted: Vec::new(),
        previous: Vec::new(),
        buffers: Buffers::default(),
    };
    loop {
        // If the writer is gone (disk full, folder removed), the ports are still drained and
        // every sample counted as dropped.
        let _ = queue.send(Item::Ports(reader.wanted.clone()));
        let mut ports = reader.subscribe(&control.node);
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Svc>()
            .map_err(dbg("recorder waitset"))?;
        let _control_guard = waitset
            .attach_notification(&control.listener)
            .map_err(dbg("attach"))?;
        let _tick_guard = waitset
            .attach_interval(DRAIN_PERIOD)
            .map_err(dbg("attach"))?;
        reader.previous.clear();
        loop {
            // Sets sent before the waitset was attached count too.
            match control.newest() {
                Sets::Closed => return Ok(()),
                Sets::New(set) => {
                    reader.replace(set, ports);
                    break;
                }
                Sets::Same => {}
            }
            waitset
                .wait_and_process_once(|_| CallbackProgression::Continue)
                .map_err(dbg("recorder wait"))?;
            reader.buffers.take(spares);
            reader.drain(&mut ports);
        }
    }
}

/// A recorded port's subscriber (`None`: it could not be subscribed to) and the next sequence
/// number expected from each of its publishers (a replay or a replacement publishes beside the
/// module).
struct Subscribed {
    subscriber: Option<PortSubscriber>,
    next_seq: SeqByPublisher,
}

/// The reader thread's state: the port set recorded, and the buffers its samples are copied
/// into.
struct Reader<'a> {
    queue: &'a SyncSender<Item>,
    counters: &'a Counters,
    clock: Clock,
    wanted: Vec<RecPort>,
    /// The previous set's subscribers, with their sequence numbers: a port in both sets keeps
    /// its subscriber, so nothing it sends while the set changes (an apply) is missed.
    previous: Vec<(RecPort, Subscribed)>,
    buffers: Buffers,
}

impl Reader<'_> {
    /// One slot per wanted port, aligned with the writer's channels; a port that cannot be
    /// subscribed to (all its subscriber slots taken) is reported and left out.
    fn subscribe(&mut self, node: &Node<Svc>) -> Vec<Subscribed> {
        let mut ports = Vec::with_capacity(self.wanted.len());
        for p in &self.wanted {
            if let Some(i) = self
                .previous
                .iter()
                .position(|(q, s)| q == p && s.subscriber.is_some())
            {
                ports.push(self.previous.swap_remove(i).1);
                continue;
            }
            let service = output_service(&p.module, &p.port);
            let subscriber = port_service(node, &service, &p.message.payload)
                .map_err(|e| e.to_string())
                .and_then(|s| {
                    s.subscriber_builder()
                        .buffer_size(dnm_module::protocol::recorder_buffer(&p.message.payload))
                        .create()
                        .map_err(dbg("subscriber"))
                });
            let subscriber = match subscriber {
                Ok(subscriber) => Some(subscriber),
                Err(e) => {
                    tracing::error!(port = %service, "not recorded: {e}");
                    None
                }
            };
            ports.push(Subscribed {
                subscriber,
                next_seq: HashMap::new(),
            });
        }
        ports
    }

    /// A new port set: the current one's subscribers become the previous ones.
    fn replace(&mut self, set: Vec<RecPort>, ports: Vec<Subscribed>) {
        self.previous = std::mem::take(&mut self.wanted)
            .into_iter()
            .zip(ports)
            .collect();
        self.wanted = set;
    }

    /// Takes the samples waiting on `ports` (the wanted ones, in order): what a port's
    /// subscriber holds, twice over at most, so a module publishing without pause costs its
    /// own port samples (counted as dropped) and never the other ports theirs.
    fn drain(&mut self, ports: &mut [Subscribed]) {
        for (i, port) in ports.iter_mut().enumerate() {
            let Some(subscriber) = &port.subscriber else {
                continue;
            };
            let most = self.wanted.get(i).map_or(1, |p| {
                2 * dnm_module::protocol::recorder_buffer(&p.message.payload)
            });
            for _ in 0..most {
                let Ok(Some(s)) = subscriber.receive() else {
                    break;
                };
                let header = *s.user_header();
                if let Some(expected) = port.next_seq.insert(s.origin(), header.seq.wrapping_add(1))
                {
                    // Samples overwritten before we read them.
                    self.counters
                        .dropped
                        .fetch_add(header.seq.saturating_sub(expected), Ordering::Relaxed);
                }
                self.queue_sample(i, header, s.payload());
            }
        }
    }

    /// Queues a sample of port `i` for the writer, in a buffer of its own; one the queue has
    /// no room for is counted as dropped.
    fn queue_sample(&mut self, i: usize, header: PortHeader, payload: &[u8]) {
        let counters = self.counters;
        let len = payload.len() as u64;
        if counters.queued.load(Ordering::Relaxed) + len > QUEUE_BYTES {
            counters.dropped.fetch_add(1, Ordering::Relaxed);
            return;
        }
        // Large samples (camera frames) are encoded here, straight from shared memory: one
        // copy of the frame less.
        let frame = self.wanted.get(i).filter(|p| {
            p.message.payload.max_bytes() > LARGE_PAYLOAD_BYTES && p.message.standard.is_none()
        });
        let mut bytes = self.buffers.fitting(payload.len());
        match frame {
            Some(p) => encode_into(
                &mut bytes,
                &p.message,
                &p.module,
                self.clock.unix(header.stamp_ns),
                payload,
            ),
            None => bytes.extend_from_slice(payload),
        }
        // What the writer subtracts when it takes the item: the memory held, not the bytes
        // used.
        let len = bytes.capacity() as u64;
        let item = Item::Sample {
            port: i,
            header,
            bytes,
            encoded: frame.is_some(),
        };
        counters.queued.fetch_add(len, Ordering::Relaxed);
        if let Err(TrySendError::Full(item) | TrySendError::Disconnected(item)) =
            self.queue.try_send(item)
        {
            counters.queued.fetch_sub(len, Ordering::Relaxed);
            counters.dropped.fetch_add(1, Ordering::Relaxed);
            if let Item::Sample { bytes, .. } = item {
                self.buffers.keep(bytes);
            }
        }
    }
}

/// Sample buffers the writer gave back, kept by size for the reader's next samples.
#[derive(Default)]
struct Buffers {
    small: Vec<Vec<u8>>,
    large: Vec<Vec<u8>>,
}

impl Buffers {
    /// Takes what the writer gave back; what is not kept is freed here, by the thread that
    /// allocated it.
    fn take(&mut self, spares: &Receiver<Vec<u8>>) {
        while let Ok(b) = spares.try_recv() {
            self.keep(b);
        }
    }

    fn keep(&mut self, b: Vec<u8>) {
        if b.capacity() > LARGE_PAYLOAD_BYTES {
            if self.large.len() < SPARE_LARGE {
                self.large.push(b);
            }
        } else if self.small.len() < SPARE_SMALL {
            self.small.push(b);
        }
    }

    /// An empty buffer for a sample of `len` bytes: a kept one if it is not much larger (a
    /// large buffer never carries a small sample through the queue), else a new one.
    fn fitting(&mut self, len: usize) -> Vec<u8> {
        let pool = if len > LARGE_PAYLOAD_BYTES {
            &mut self.large
        } else {
            &mut self.small
        };
        match pool.pop() {
            Some(mut b) if b.capacity() <= (4 * len).max(256) => {
                b.clear();
                b
            }
            // Too large for this sample: freed here.
            _ => Vec::with_capacity(len + 64),
        }
    }
}

/// Runs the recorder's writer at nice 10 (or its process's, if lower): it encodes and
/// compresses mostly on time the modules leave, and when the computer is saturated its queue
/// fills and what does not fit is counted as dropped. Not `SCHED_IDLE`: a thread of that class
/// gets almost no CPU while the computer is busy, and if it is stopped holding a lock the DNM's
/// other threads need (an allocator arena's, above all), they wait with it. That is our reading
/// of a recording whose reader stopped for 0.7 s, losing samples of every port of its DNM, on
/// a saturated machine.
fn low_priority() {
    // SAFETY: getpriority(2)/setpriority(2) on the calling thread (its thread id); no memory is
    // passed.
    let r = unsafe {
        let tid = libc::gettid() as libc::id_t;
        let now = libc::getpriority(libc::PRIO_PROCESS, tid);
        libc::setpriority(libc::PRIO_PROCESS, tid, now.max(10))
    };
    if r != 0 {
        tracing::debug!(
            "recorder thread keeps its priority: {}",
            std::io::Error::last_os_error()
        );
    }
}

/// A recorder's subscriber on a port.
type PortSubscriber = Subscriber<Svc, [u8], PortHeader>;

/// Next expected sequence number of a port's samples, per publisher.
type SeqByPublisher = HashMap<UniquePublisherId, u64>;

/// CLOCK_MONOTONIC → Unix time, fixed when the recorder starts.
#[derive(Debug, Clone, Copy)]
struct Clock {
    unix_minus_mono: i128,
}

impl Clock {
    fn new() -> Self {
        let unix = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos() as i128);
        Self {
            unix_minus_mono: unix - i128::from(monotonic_ns()),
        }
    }

    fn unix(&self, mono: u64) -> u64 {
        (i128::from(mono) + self.unix_minus_mono).max(0) as u64
    }
}

/// The MCAP writer of a recorder's file.
type McapWriter = mcap::Writer<Counting<BufWriter<File>>>;

struct OpenFile {
    writer: McapWriter,
    path: PathBuf,
    opened: Instant,
    /// Bytes written to the file so far.
    written: Arc<AtomicU64>,
    channels: Vec<Channel>,
    switches: u16,
    events: u16,
    sequences: u16,
    /// The JSON channels as a [`Tap`] is told of them: switches, events, sequences.
    json: [ChannelDesc; 3],
}

/// The JSON channels of a file.
#[derive(Debug, Clone, Copy)]
enum Json {
    Switch,
    Event,
    Sequence,
}

/// A port's channel in a file: the standard message where its type declares one (and our
/// bytes beside it when that is not exact), else our own message.
struct Channel {
    id: u16,
    raw: Option<u16>,
    standard: Option<StandardMapping>,
    /// The channel and its `raw` one as a [`Tap`] is told of them.
    desc: ChannelDesc,
    raw_desc: Option<ChannelDesc>,
}

/// Counts the bytes that reach the file (compressed chunks, indexes), for rotation by size.
struct Counting<W> {
    inner: W,
    written: Arc<AtomicU64>,
}

impl<W: std::io::Write> std::io::Write for Counting<W> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.written.fetch_add(n as u64, Ordering::Relaxed);
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

impl<W: std::io::Seek> std::io::Seek for Counting<W> {
    fn seek(&mut self, pos: std::io::SeekFrom) -> std::io::Result<u64> {
        self.inner.seek(pos)
    }
}

/// Creates DNM `dnm`'s file number `index` in `options.dir`, or the first number after it that
/// no file has: an existing file is never overwritten. (A session's folder is its run's alone;
/// files of one stem in a folder given by the operator can be another run's.) `index` becomes
/// the number used.
fn create_file(
    dnm: &str,
    options: &RecordOptions,
    index: &mut u64,
) -> Result<(PathBuf, File), String> {
    loop {
        // `.n` numbers a DNM's later files: a DNM's name has no dot, so `rec-cam.2.mcap` is
        // never another DNM's first file.
        let name = if *index == 0 {
            format!("{}-{dnm}.mcap", options.stem)
        } else {
            format!("{}-{dnm}.{index}.mcap", options.stem)
        };
        let path = options.dir.join(name);
        match File::options().write(true).create_new(true).open(&path) {
            Ok(file) => return Ok((path, file)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && *index < MAX_FILES => {
                tracing::warn!(
                    file = %path.display(),
                    "a file of this name exists (an earlier run's): numbering after it"
                );
                *index += 1;
            }
            Err(e) => return Err(format!("{}: {e}", path.display())),
        }
    }
}

fn open_file(
    dnm: &str,
    options: &RecordOptions,
    index: &mut u64,
    ports: &[RecPort],
    netlist: Option<&(u64, String, String)>,
    clock: Clock,
) -> Result<OpenFile, String> {
    let (path, file) = create_file(dnm, options, index)?;
    let written = Arc::new(AtomicU64::new(0));
    let mut writer = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        // The fastest zstd, by default on the writer's own thread: a recorder shares the
        // computer with the modules. The mcap crate's default, one zstd worker per core, kept
        // worker threads and their buffers (some 13 MB a DNM, reserved) alive for nothing a
        // 1 MiB chunk needs.
        .compression_level(1)
        .compression_threads(options.compression_workers)
        .profile("ros2")
        .library("dnm")
        .chunk_size(Some(1 << 20))
        .create(Counting {
            inner: BufWriter::new(file),
            written: written.clone(),
        })
        .map_err(|e| e.to_string())?;
    let mut channels = Vec::new();
    // Modules whose body is written (once per file, whatever their ports).
    let mut bodies: Vec<&str> = Vec::new();
    for p in ports {
        channels.push(add_port(&mut writer, dnm, p)?);
        if let Some(body) = p.message.standard.as_ref().and_then(|s| s.body.as_deref())
            && !bodies.contains(&p.module.as_str())
        {
            bodies.push(&p.module);
            write_body(&mut writer, dnm, &p.module, body, clock)?;
        }
    }
    let switches = add_json_channel(
        &mut writer,
        "dnm/TaskSwitch",
        r#"{"type":"object","properties":{"dnm":{"type":"string"},"revision":{"type":"integer"},"from":{"type":["string","null"]},"to":{"type":"string"},"duration_ns":{"type":"integer"},"at_ns":{"type":"integer"}}}"#,
        &format!("/{dnm}/_switches"),
    )?;
    let events = add_json_channel(
        &mut writer,
        "dnm/ModuleEvent",
        r#"{"type":"object","properties":{"dnm":{"type":"string"},"module":{"type":"string"},"what":{"type":"string"},"detail":{"type":"string"},"at_ns":{"type":"integer"}}}"#,
        &format!("/{dnm}/_events"),
    )?;
    let sequences = add_json_channel(
        &mut writer,
        "dnm/SequenceEvent",
        r#"{"type":"object","properties":{"at_unix_ns":{"type":"integer"},"sequence":{"type":"string"},"run":{"type":"integer"},"what":{"type":"string"},"step":{"type":["integer","null"]},"detail":{"type":"string"}}}"#,
        &format!("/{dnm}/_sequences"),
    )?;
    let mut f = OpenFile {
        writer,
        path,
        opened: Instant::now(),
        written,
        channels,
        switches: switches.0,
        events: events.0,
        sequences: sequences.0,
        json: [switches.1, events.1, sequences.1],
    };
    if let Some((revision, file, text)) = netlist {
        write_netlist(&mut f, *revision, file, text)?;
    }
    Ok(f)
}

/// Adds port `p`'s channel (`/<dnm>/<module>/<port>`) to the file, and the channel of its own
/// bytes beside it where its standard message cannot hold them exactly.
fn add_port(writer: &mut McapWriter, dnm: &str, p: &RecPort) -> Result<Channel, String> {
    let topic = format!("/{dnm}/{}/{}", p.module, p.port);
    let mut meta = BTreeMap::new();
    meta.insert("dnm".to_string(), dnm.to_string());
    meta.insert("dnm_encoding".to_string(), p.message.encoding.clone());
    meta.insert("dnm_schema".to_string(), p.message.schema_name.clone());
    let standard = match StandardMapping::of(&p.message) {
        Ok(mapping) => mapping,
        Err(e) => {
            tracing::warn!(%topic, "recorded as it is, not as its standard message: {e}");
            None
        }
    };
    let (schema_name, schema_encoding, schema, message_encoding) = match &standard {
        Some(mapping) => (
            mapping.name().to_string(),
            "ros2msg",
            mapping.schema().to_string(),
            "cdr",
        ),
        None => mcap_encoding(&p.message),
    };
    let schema_id = writer
        .add_schema(&schema_name, schema_encoding, schema.as_bytes())
        .map_err(|e| e.to_string())?;
    let id = writer
        .add_channel(schema_id, &topic, message_encoding, &meta)
        .map_err(|e| e.to_string())?;
    let desc = ChannelDesc {
        topic: topic.clone(),
        schema_name,
        schema_encoding: schema_encoding.to_string(),
        schema,
        message_encoding: message_encoding.to_string(),
        metadata: meta.clone(),
    };
    // Our own bytes beside a standard message that cannot hold them exactly: what a
    // replay feeds modules.
    let (raw, raw_desc) = match &standard {
        Some(mapping) if !mapping.exact() => {
            let (schema_name, schema_encoding, schema, message_encoding) =
                mcap_encoding(&p.message);
            let schema_id = writer
                .add_schema(&schema_name, schema_encoding, schema.as_bytes())
                .map_err(|e| e.to_string())?;
            let mut meta = meta.clone();
            meta.insert("dnm_raw_of".to_string(), topic.clone());
            let raw_topic = format!("{topic}{}", crate::RAW_SUFFIX);
            let id = writer
                .add_channel(schema_id, &raw_topic, message_encoding, &meta)
                .map_err(|e| e.to_string())?;
            let desc = ChannelDesc {
                topic: raw_topic,
                schema_name,
                schema_encoding: schema_encoding.to_string(),
                schema,
                message_encoding: message_encoding.to_string(),
                metadata: meta,
            };
            (Some(id), Some(desc))
        }
        _ => (None, None),
    };
    Ok(Channel {
        id,
        raw,
        standard,
        desc,
        raw_desc,
    })
}

/// Adds a JSON channel `topic` of JSON schema `schema` (named `name`) to the file.
fn add_json_channel(
    writer: &mut McapWriter,
    name: &str,
    schema: &str,
    topic: &str,
) -> Result<(u16, ChannelDesc), String> {
    let schema_id = writer
        .add_schema(name, "jsonschema", schema.as_bytes())
        .map_err(|e| e.to_string())?;
    let id = writer
        .add_channel(schema_id, topic, "json", &BTreeMap::new())
        .map_err(|e| e.to_string())?;
    let desc = ChannelDesc {
        topic: topic.to_string(),
        schema_name: name.to_string(),
        schema_encoding: "jsonschema".into(),
        schema: schema.to_string(),
        message_encoding: "json".into(),
        metadata: BTreeMap::new(),
    };
    Ok((id, desc))
}

/// Topic of the body a module's poses move (see [`dnm_netlist::Standard::body`]):
/// `robot_description` in the topic is what tools look for; the `_` keeps it apart from ports.
fn body_topic(dnm: &str, module: &str) -> String {
    format!("/{dnm}/_robot_description/{module}")
}

/// Writes `body` (a URDF document) once, as a `std_msgs/msg/String`, at the file's start.
fn write_body(
    writer: &mut McapWriter,
    dnm: &str,
    module: &str,
    body: &str,
    clock: Clock,
) -> Result<(), String> {
    let schema_id = writer
        .add_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        .map_err(|e| e.to_string())?;
    let mut meta = BTreeMap::new();
    meta.insert("dnm".to_string(), dnm.to_string());
    let channel = writer
        .add_channel(schema_id, &body_topic(dnm, module), "cdr", &meta)
        .map_err(|e| e.to_string())?;
    let mut cdr = Cdr::new(body.len() + 4);
    cdr.string(body);
    // On the recorder's clock, like the samples: a step of the system clock since the recorder
    // started does not set the body apart from the data.
    let now = clock.unix(monotonic_ns());
    let header = mcap::records::MessageHeader {
        channel_id: channel,
        sequence: 0,
        log_time: now,
        publish_time: now,
    };
    writer
        .write_to_known_channel(&header, &cdr.0)
        .map_err(|e| e.to_string())
}

/// Writes the summary and footer and flushes the file, reporting any error (a full disk);
/// then, in a session, its manifest.
fn close(f: OpenFile, options: &RecordOptions) -> Result<(), String> {
    use std::io::Write;
    let path = f.path.clone();
    let mut writer = f.writer;
    writer
        .finish()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    writer
        .into_inner()
        .flush()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    if options.session {
        crate::session::request_manifest(&options.dir);
    }
    Ok(())
}

fn write_netlist(f: &mut OpenFile, revision: u64, file: &str, text: &str) -> Result<(), String> {
    let now = Clock::new().unix(monotonic_ns());
    netlist_records(&mut f.writer, now, revision, file, text).map_err(|e| e.to_string())
}

/// Keeps netlist `revision` (from `file`, its `text`) in a recording as every recording of
/// ours does: an attachment `netlist-r<revision>.toml` and a `dnm.netlist` metadata record.
pub fn netlist_records<W: std::io::Write + std::io::Seek>(
    writer: &mut mcap::Writer<W>,
    now_unix_ns: u64,
    revision: u64,
    file: &str,
    text: &str,
) -> Result<(), mcap::McapError> {
    writer.attach(&mcap::Attachment {
        log_time: now_unix_ns,
        create_time: now_unix_ns,
        name: format!("netlist-r{revision}.toml"),
        media_type: "application/toml".into(),
        data: std::borrow::Cow::Borrowed(text.as_bytes()),
    })?;
    let mut meta = BTreeMap::new();
    meta.insert("revision".to_string(), revision.to_string());
    meta.insert("file".to_string(), file.to_string());
    meta.insert("text".to_string(), text.to_string());
    writer.write_metadata(&mcap::records::Metadata {
        name: "dnm.netlist".into(),
        metadata: meta,
    })
}

fn write_loop(
    dnm: &str,
    options: &RecordOptions,
    items: &Receiver<Item>,
    spares: &SyncSender<Vec<u8>>,
    counters: &Counters,
    clock: Clock,
) -> Result<(), String> {
    low_priority();
    let mut w = Writer {
        dnm,
        options,
        spares,
        counters,
        clock,
        ports: Vec::new(),
        netlist: None,
        index: 0,
        file: None,
        last_flush: Instant::now(),
        decimators: Vec::new(),
    };
    loop {
        let item = match items.recv_timeout(CHUNK_PERIOD) {
            Ok(item) => Some(item),
            Err(mpsc::RecvTimeoutError::Timeout) => None,
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        };
        match item {
            Some(Item::Ports(p)) => {
                // A new port set starts a new file: channels are fixed per file.
                w.close_file()?;
                w.decimators = carried_decimators(&w.ports, &w.decimators, &p);
                w.ports = p;
                // Nothing to record (yet): no file.
                if w.ports.is_empty() {
                    continue;
                }
                w.open_file()?;
            }
            Some(Item::Netlist {
                revision,
                file,
                text,
            }) => {
                // Written into the file the revision's port set opens (it always follows), so
                // each file holds the netlist of its own data.
                w.netlist = Some((revision, file, text));
            }
            Some(Item::Switch(json)) => w.write_json(&json, Json::Switch)?,
            Some(Item::Event(json)) => w.write_json(&json, Json::Event)?,
            Some(Item::Sequence(json)) => w.write_json(&json, Json::Sequence)?,
            Some(Item::Sample {
                port,
                header,
                bytes,
                encoded,
            }) => {
                // Not written (no file, or no such port): on to the next item.
                let written = w.write_sample(port, header, bytes, encoded)?;
                if !written {
                    continue;
                }
            }
            None => {}
        }
        w.flush_if_due()?;
        w.rotate_if_due()?;
    }
    w.close_file()
}

/// The decimators of port set `new` for the downlink plan: a port kept at the same rate goes on
/// from where it was (its next sample is judged by the last it saw), a new or re-rated one
/// starts afresh.
fn carried_decimators(
    old: &[RecPort],
    decimators: &[Option<Decimator>],
    new: &[RecPort],
) -> Vec<Option<Decimator>> {
    new.iter()
        .map(|p| {
            let entry = p.downlink.as_ref()?;
            let before = old
                .iter()
                .position(|o| o.module == p.module && o.port == p.port && o.downlink == p.downlink)
                .and_then(|i| decimators.get(i).copied().flatten());
            Some(before.unwrap_or_else(|| Decimator::new(entry.period_ns())))
        })
        .collect()
}

/// The writer thread's state: the port set, the netlist each new file starts with, and the
/// file open.
struct Writer<'a> {
    dnm: &'a str,
    options: &'a RecordOptions,
    /// Sample buffers go back to the reader through it.
    spares: &'a SyncSender<Vec<u8>>,
    counters: &'a Counters,
    clock: Clock,
    ports: Vec<RecPort>,
    /// (revision, file, text).
    netlist: Option<(u64, String, String)>,
    /// Of the next file: its `.n`.
    index: u64,
    file: Option<OpenFile>,
    last_flush: Instant,
    /// Per port (as `ports`): which samples the downlink plan keeps, for the ports it names.
    decimators: Vec<Option<Decimator>>,
}

impl Writer<'_> {
    /// Opens the next file, for the port set.
    fn open_file(&mut self) -> Result<(), String> {
        let f = open_file(
            self.dnm,
            self.options,
            &mut self.index,
            &self.ports,
            self.netlist.as_ref(),
            self.clock,
        )?;
        self.counters.files.fetch_add(1, Ordering::Relaxed);
        if let Ok(mut name) = self.counters.file.lock() {
            *name = f.path.display().to_string();
        }
        self.file = Some(f);
        Ok(())
    }

    /// Closes the file open, if any: the next one is numbered after it.
    fn close_file(&mut self) -> Result<(), String> {
        if let Some(f) = self.file.take() {
            close(f, self.options)?;
            self.index += 1;
        }
        Ok(())
    }

    /// Writes a task switch or (`event`) a module event to the file open.
    fn write_json(&mut self, json: &str, channel: Json) -> Result<(), String> {
        if let Some(f) = self.file.as_mut() {
            let now = self.clock.unix(monotonic_ns());
            let (channel_id, desc) = match channel {
                Json::Switch => (f.switches, &f.json[0]),
                Json::Event => (f.events, &f.json[1]),
                Json::Sequence => (f.sequences, &f.json[2]),
            };
            let header = mcap::records::MessageHeader {
                channel_id,
                sequence: 0,
                log_time: now,
                publish_time: now,
            };
            f.writer
                .write_to_known_channel(&header, json.as_bytes())
                .map_err(|e| e.to_string())?;
            if let Some(tap) = &self.options.tap {
                tap.message(Tapped {
                    channel: desc,
                    log_time: now,
                    sequence: 0,
                    data: json.as_bytes(),
                    plan: None,
                });
            }
        }
        Ok(())
    }

    /// Writes a sample of port `port` to the file open (`encoded`: `bytes` are the message as
    /// written) and gives its buffer back to the reader; `false`: there was no file or no
    /// such port to write it to.
    fn write_sample(
        &mut self,
        port: usize,
        header: PortHeader,
        bytes: Vec<u8>,
        encoded: bool,
    ) -> Result<bool, String> {
        self.counters
            .queued
            .fetch_sub(bytes.capacity() as u64, Ordering::Relaxed);
        let (Some(f), Some(p)) = (self.file.as_mut(), self.ports.get(port)) else {
            let _ = self.spares.try_send(bytes);
            return Ok(false);
        };
        let time = self.clock.unix(header.stamp_ns);
        let channel = &f.channels[port];
        let mut head = mcap::records::MessageHeader {
            channel_id: channel.id,
            sequence: header.seq as u32,
            log_time: time,
            publish_time: time,
        };
        let mut written = 0;
        let native = || encode(&p.message, &p.module, time, &bytes);
        let encoded_here;
        let data: &[u8] = match &channel.standard {
            _ if encoded => &bytes,
            Some(mapping) => {
                encoded_here = mapping.encode(&bytes, time, &p.module);
                &encoded_here
            }
            None => {
                encoded_here = native();
                &encoded_here
            }
        };
        // The downlink plan's samples go on to the tap as they are written.
        let tap = match (&self.options.tap, self.decimators.get_mut(port)) {
            (Some(tap), Some(Some(d))) => d.keep(time).then_some(tap),
            _ => None,
        };
        if let Some(raw) = channel.raw {
            let data = native();
            let h = mcap::records::MessageHeader {
                channel_id: raw,
                ..head
            };
            f.writer
                .write_to_known_channel(&h, &data)
                .map_err(|e| e.to_string())?;
            written += data.len();
            if let (Some(tap), Some(desc)) = (tap, &channel.raw_desc) {
                tap.message(Tapped {
                    channel: desc,
                    log_time: time,
                    sequence: head.sequence,
                    data: &data,
                    plan: p.downlink.as_ref(),
                });
            }
        }
        head.channel_id = channel.id;
        f.writer
            .write_to_known_channel(&head, data)
            .map_err(|e| e.to_string())?;
        written += data.len();
        if let Some(tap) = tap {
            tap.message(Tapped {
                channel: &channel.desc,
                log_time: time,
                sequence: head.sequence,
                data,
                plan: p.downlink.as_ref(),
            });
        }
        self.counters.messages.fetch_add(1, Ordering::Relaxed);
        self.counters
            .bytes
            .fetch_add(written as u64, Ordering::Relaxed);
        // The buffer goes back to the reader.
        let _ = self.spares.try_send(bytes);
        Ok(true)
    }

    /// Flushes the file every [`CHUNK_PERIOD`]: a chunk is finished.
    fn flush_if_due(&mut self) -> Result<(), String> {
        if self.last_flush.elapsed() >= CHUNK_PERIOD {
            self.last_flush = Instant::now();
            if let Some(f) = self.file.as_mut() {
                f.writer.flush().map_err(|e| e.to_string())?;
            }
        }
        Ok(())
    }

    /// Starts a new file when the one open is large or old enough.
    fn rotate_if_due(&mut self) -> Result<(), String> {
        let rotate = self.file.as_ref().is_some_and(|f| {
            f.written.load(Ordering::Relaxed) >= self.options.rotate_bytes
                || f.opened.elapsed() >= self.options.rotate_after
        });
        if rotate {
            self.close_file()?;
            self.open_file()?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dnm_module::msg::{Message, Tick};

    /// Writes `n` ticks (origin from `origin(seq)`) with rotation at `rotate_bytes`; returns the
    /// files, each checked to read whole, and every sequence number found.
    fn write_ticks(
        name: &str,
        n: u64,
        rotate_bytes: u64,
        origin: impl Fn(u64) -> u64,
    ) -> (Vec<PathBuf>, Vec<u32>) {
        write_samples(name, n, rotate_bytes, Tick::message_type(), |seq| {
            bytemuck::bytes_of(&Tick {
                origin: origin(seq),
                seq,
            })
            .to_vec()
        })
    }

    /// Writes `n` samples of `message` made by `payload(seq)`, rotating at `rotate_bytes`.
    fn write_samples(
        name: &str,
        n: u64,
        rotate_bytes: u64,
        message: MessageType,
        payload: impl Fn(u64) -> Vec<u8>,
    ) -> (Vec<PathBuf>, Vec<u32>) {
        let dir = std::env::temp_dir().join(format!("dnm-rotate-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        write_run(&dir, n, rotate_bytes, message, &payload);
        let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
            .collect();
        files.sort();
        // The session's manifest lists exactly these files, closed, with every message.
        let manifest: crate::session::Manifest =
            serde_json::from_slice(&std::fs::read(dir.join(crate::session::MANIFEST)).unwrap())
                .unwrap();
        let names: Vec<String> = files
            .iter()
            .map(|f| f.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        let mut listed: Vec<String> = manifest.files.iter().map(|f| f.name.clone()).collect();
        listed.sort();
        assert_eq!(listed, names);
        assert!(
            manifest
                .files
                .iter()
                .all(|f| f.complete && f.revisions == [1])
        );
        assert_eq!(manifest.messages, n);
        assert_eq!(manifest.dnms, ["d"]);
        assert_eq!(manifest.netlists.len(), 1);
        assert!(manifest.netlists[0].text.contains("name = \"t\""));
        let mut seqs = Vec::new();
        for f in &files {
            let bytes = std::fs::read(f).unwrap();
            let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
            assert!(
                summary
                    .metadata_indexes
                    .iter()
                    .any(|m| m.name == "dnm.netlist")
            );
            for m in mcap::MessageStream::new(&bytes).unwrap() {
                seqs.push(m.unwrap().sequence);
            }
        }
        seqs.sort_unstable();
        let _ = std::fs::remove_dir_all(&dir);
        (files, seqs)
    }

    /// One recorder's run of `n` samples into session folder `dir`, as [`write_samples`] makes
    /// them.
    fn write_run(
        dir: &Path,
        n: u64,
        rotate_bytes: u64,
        message: MessageType,
        payload: &impl Fn(u64) -> Vec<u8>,
    ) {
        let options = RecordOptions {
            dir: dir.to_path_buf(),
            stem: "t".into(),
            only: Vec::new(),
            rotate_bytes,
            rotate_after: Duration::from_secs(3600),
            session: true,
            tap: None,
            compression_workers: 0,
        };
        let (tx, rx) = mpsc::sync_channel(n as usize + 2);
        tx.send(Item::Netlist {
            revision: 1,
            file: "t.toml".into(),
            text: "[system]\nname = \"t\"\n".into(),
        })
        .unwrap();
        tx.send(Item::Ports(vec![RecPort {
            downlink: None,
            module: "m".into(),
            port: "out".into(),
            message,
        }]))
        .unwrap();
        for seq in 0..n {
            tx.send(Item::Sample {
                port: 0,
                header: PortHeader {
                    stamp_ns: monotonic_ns(),
                    seq,
                    task_word: 0,
                },
                bytes: payload(seq),
                encoded: false,
            })
            .unwrap();
        }
        drop(tx);
        let counters = Counters::default();
        let (spare, _spares) = mpsc::sync_channel(n as usize);
        write_loop("d", &options, &rx, &spare, &counters, Clock::new()).unwrap();
        crate::session::settle();
        assert_eq!(counters.messages.load(Ordering::Relaxed), n);
    }

    #[test]
    fn a_recorder_numbers_its_files_after_those_an_earlier_run_left_in_its_folder() {
        let dir = std::env::temp_dir().join(format!("dnm-rerun-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        // Random origins do not compress: the first run rotates through several files.
        let mut x = 0x9e37_79b9_7f4a_7c15_u64;
        let random = std::sync::Mutex::new(move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        });
        let tick = |seq: u64| {
            let origin = random.lock().unwrap()();
            bytemuck::bytes_of(&Tick { origin, seq }).to_vec()
        };
        let mcaps = || {
            let mut names: Vec<String> = std::fs::read_dir(&dir)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .filter(|n| n.ends_with(".mcap"))
                .collect();
            names.sort();
            names
        };
        write_run(&dir, 300_000, 1 << 20, Tick::message_type(), &tick);
        let first = mcaps().len();
        assert!(first >= 2, "{:?}", mcaps());
        // A second run of DNM `d` with the same stem in the same folder: its files follow.
        write_run(&dir, 300_000, 1 << 20, Tick::message_type(), &tick);
        crate::session::settle();
        let names = mcaps();
        assert!(names.len() > first, "{names:?}");
        let mut expected: Vec<String> = (1..names.len()).map(|n| format!("t-d.{n}.mcap")).collect();
        expected.push("t-d.mcap".into());
        expected.sort();
        assert_eq!(names, expected);
        let manifest: crate::session::Manifest =
            serde_json::from_slice(&std::fs::read(dir.join(crate::session::MANIFEST)).unwrap())
                .unwrap();
        assert_eq!(manifest.messages, 600_000);
        assert!(manifest.files.iter().all(|f| f.complete));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_kept_buffer_is_reused_only_for_a_sample_of_about_its_size() {
        let mut buffers = Buffers::default();
        buffers.keep(Vec::with_capacity(60 << 10));
        buffers.keep(Vec::with_capacity(300 << 10));
        // A 16-byte sample does not carry a 60 KiB buffer through the queue...
        let small = buffers.fitting(16);
        assert!(small.capacity() < 1024, "{}", small.capacity());
        assert!(buffers.small.is_empty());
        // ...and a camera frame takes the kept large buffer, emptied.
        let large = buffers.fitting(225 << 10);
        assert_eq!(large.capacity(), 300 << 10);
        assert!(large.is_empty());
        // Beyond what is kept, buffers given back are freed.
        for _ in 0..SPARE_LARGE + 3 {
            buffers.keep(Vec::with_capacity(100 << 10));
        }
        assert_eq!(buffers.large.len(), SPARE_LARGE);
    }

    #[test]
    fn rotation_counts_the_bytes_on_disk_not_the_uncompressed_ones() {
        // 40 frames of 64 KiB of one colour are 2.5 MiB before compression and a few KiB on
        // disk: with rotation at 1 MiB they fit one file.
        struct Frame;
        impl dnm_module::msg::BytesMessage for Frame {
            const SCHEMA_NAME: &'static str = "test/Frame";
            const ENCODING: &'static str = "application/octet-stream";
            const SCHEMA: &'static str = "uint8[] data";
        }
        use dnm_module::msg::BytesMessage;
        let (files, seqs) = write_samples(
            "compressible",
            40,
            1 << 20,
            Frame::message_type(64 << 10),
            |_| vec![0x5a; 64 << 10],
        );
        assert_eq!(files.len(), 1, "{files:?}");
        assert_eq!(seqs, (0..40).collect::<Vec<u32>>());
    }

    #[test]
    fn files_rotate_by_size_and_each_one_reads_whole() {
        // Random origins do not compress: 300,000 ticks are several MiB on disk.
        let mut x = 0x9e37_79b9_7f4a_7c15_u64;
        let random = move |_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let random = std::sync::Mutex::new(random);
        let (files, seqs) = write_ticks("random", 300_000, 1 << 20, |s| random.lock().unwrap()(s));
        assert!(files.len() >= 2, "{files:?}");
        assert_eq!(seqs, (0..300_000).collect::<Vec<u32>>());
    }
}
