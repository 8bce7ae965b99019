//! The rover's recording as the ground's second source: a DNM answers requests for stretches
//! of what it recorded (`<system>/downlink_history/<dnm>`), decimated as the live downlink
//! decimates, so what the ground missed for longer than the publishers' caches hold still
//! reaches it. Requests are served one at a time on a thread of their own, from the files of
//! the DNM's recording session, read as a stream (never a whole file in memory); the replies
//! go at the priority of the request (the ground asks at `background`).

use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc;
use std::thread::JoinHandle;

use dnm_netlist::Decimator;
use dnm_proto::keys;
use zenoh::Wait;
use zenoh::query::Query;

use crate::protocol::{HistoryAnswer, HistoryRequest, MAX_ANSWER_BYTES};

/// Requests waiting to be served, at most; beyond it they are refused (the ground asks again).
const WAITING: usize = 8;
/// Longest record a recording file may hold, as the recorder writes them.
const MAX_RECORD: usize = 256 << 20;
/// Sessions whose manifest's word on this DNM's closed files is kept between requests, at
/// most; their files together, at most (about 100 bytes each: a few MB); and topic names.
const KNOWN: usize = 1024;
const KNOWN_FILES: usize = 30_000;
const MAX_TOPICS: usize = 4096;

/// Why a history server did not start.
#[derive(Debug, thiserror::Error)]
pub enum HistoryStartError {
    #[error("declaring the recording's queryable {key}: {reason}")]
    Queryable { key: String, reason: String },
    #[error("no thread for the recording's answers: {0}")]
    Thread(#[source] std::io::Error),
}

/// A DNM's recording, answering the ground. Dropped, it stops answering.
pub struct HistoryServer {
    queryable: Option<zenoh::query::Queryable<()>>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for HistoryServer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HistoryServer").finish_non_exhaustive()
    }
}

impl HistoryServer {
    /// Answers for DNM `dnm` of `system` from its recording files `rec-<dnm>[.n].mcap` in
    /// session folder `dir` and in the system's earlier sessions beside it.
    pub fn start(
        session: &zenoh::Session,
        system: &str,
        dnm: &str,
        dir: &Path,
    ) -> Result<Self, HistoryStartError> {
        let key = keys::downlink_history(system, dnm);
        let (tx, rx) = mpsc::sync_channel::<Query>(WAITING);
        let queryable = session
            .declare_queryable(key.clone())
            .callback(move |q| {
                if tx.try_send(q).is_err() {
                    tracing::debug!("history request refused: busy");
                }
            })
            .wait()
            .map_err(|e| HistoryStartError::Queryable {
                key: key.clone(),
                reason: e.to_string(),
            })?;
        let files = Files {
            dir: dir.to_path_buf(),
            system: system.to_string(),
            dnm: dnm.to_string(),
        };
        let thread = std::thread::Builder::new()
            .name(format!("history-{dnm}"))
            .spawn(move || {
                // Reading recordings gives way to the modules, as the recorder's writer does.
                // SAFETY: setpriority(2) on the calling thread (Linux: `who` 0 is the thread).
                unsafe { libc::setpriority(libc::PRIO_PROCESS, 0, 10) };
                let mut known = Known::default();
                while let Ok(q) = rx.recv() {
                    serve(&files, &mut known, &q);
                }
            })
            .map_err(HistoryStartError::Thread)?;
        Ok(Self {
            queryable: Some(queryable),
            thread: Some(thread),
        })
    }
}

impl Drop for HistoryServer {
    fn drop(&mut self) {
        // The queryable's callback holds the thread's queue.
        if let Some(q) = self.queryable.take() {
            let _ = q.undeclare().wait();
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A DNM's recording files: those of its session now, and of the system's earlier sessions
/// beside it (a rover that restarted still answers for what it recorded before).
struct Files {
    dir: PathBuf,
    system: String,
    dnm: String,
}

impl Files {
    /// The system's session folders beside the one now, oldest first, the one now last.
    fn sessions(&self) -> Vec<PathBuf> {
        let session = |p: &PathBuf| {
            p.file_name()
                .and_then(|n| n.to_str())
                .and_then(|n| dnm_record::session::session_of(&self.system, n))
        };
        let mut out: Vec<PathBuf> = self
            .dir
            .parent()
            .and_then(|root| std::fs::read_dir(root).ok())
            .into_iter()
            .flatten()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
            .map(|e| e.path())
            .filter(|p| *p != self.dir)
            .filter(|p| session(p).is_some())
            .collect();
        // By start time, then run (`-2` after the run that started within the same second).
        out.sort_by_cached_key(session);
        out.push(self.dir.clone());
        out
    }

    /// The DNM's files of session `dir`, in the order written.
    fn list(&self, dir: &Path) -> Vec<PathBuf> {
        dnm_record::session::files(dir)
            .unwrap_or_default()
            .into_iter()
            .filter(|p| {
                p.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| self.mine(n))
            })
            .collect()
    }

    /// Whether file `name` is one of the DNM's: `rec-<dnm>.mcap`, `rec-<dnm>.<n>.mcap`.
    fn mine(&self, name: &str) -> bool {
        name.strip_prefix("rec-")
            .and_then(|n| n.strip_prefix(self.dnm.as_str()))
            .and_then(|n| n.strip_suffix(".mcap"))
            .is_some_and(|n| {
                n.is_empty()
                    || n.strip_prefix('.')
                        .is_some_and(|k| k.parse::<u64>().is_ok())
            })
    }
}

/// What each session's manifest says of the DNM's closed files: per file, its time range and
/// the topics it holds. Walking a manifest is tens of milliseconds once a session has weeks of
/// files, and the ground asks a few times a second while it fills a gap; a manifest changes
/// only when a file closes (it is written anew, a new file: its size, time and inode say so),
/// so each is walked once between rotations, whatever the topics asked for.
#[derive(Default)]
struct Known {
    sessions: HashMap<PathBuf, Walked>,
    /// Topic names, numbered as the files' words name them.
    topics: HashMap<String, u32>,
    /// Walks made (for the tests).
    walks: u64,
    /// Requests served: how recently each session was used.
    clock: u64,
}

struct Walked {
    manifest: (u64, std::time::SystemTime, u64),
    files: Arc<HashMap<String, FileWord>>,
    used: u64,
}

/// A closed file as its session's manifest says.
struct FileWord {
    start: u64,
    end: u64,
    /// The topics it holds messages of (numbers of [`Known::topics`]).
    topics: Box<[u32]>,
}

impl FileWord {
    /// Its time range, if it holds `topic` (`None`: a topic no file named).
    fn range_of(&self, topic: Option<u32>) -> Option<(u64, u64)> {
        topic
            .is_some_and(|t| self.topics.contains(&t))
            .then_some((self.start, self.end))
    }
}

impl Known {
    /// The number of `topic`, if a file walked so far holds it.
    fn topic(&self, topic: &str) -> Option<u32> {
        self.topics.get(topic).copied()
    }

    /// Forgets the sessions not in `sessions` (folders removed since).
    fn keep_only(&mut self, sessions: &[PathBuf]) {
        self.sessions.retain(|dir, _| sessions.contains(dir));
    }

    /// The closed files of session `dir`, as its manifest says.
    fn closed(&mut self, files: &Files, dir: &Path) -> Arc<HashMap<String, FileWord>> {
        use std::os::unix::fs::MetadataExt;
        self.clock += 1;
        let manifest = std::fs::metadata(dir.join(dnm_record::session::MANIFEST))
            .ok()
            .and_then(|m| Some((m.len(), m.modified().ok()?, m.ino())));
        if let (Some(m), Some(w)) = (manifest, self.sessions.get_mut(dir))
            && w.manifest == m
        {
            w.used = self.clock;
            return w.files.clone();
        }
        self.walks += 1;
        let mut closed = HashMap::new();
        let topics = &mut self.topics;
        let _ = dnm_record::session::for_each_entry(dir, |e| {
            if e.complete && e.error.is_none() && files.mine(&e.name) {
                let mut held: Vec<u32> = Vec::new();
                for (topic, _) in e.channels.iter().filter(|(_, n)| **n > 0) {
                    let number = match topics.get(topic) {
                        Some(t) => Some(*t),
                        None if topics.len() < MAX_TOPICS => {
                            let next = topics.len() as u32;
                            topics.insert(topic.clone(), next);
                            Some(next)
                        }
                        None => None,
                    };
                    held.extend(number);
                }
                let word = FileWord {
                    start: e.start_unix_ns.unwrap_or(0),
                    end: e.end_unix_ns.unwrap_or(0),
                    topics: held.into(),
                };
                closed.insert(e.name, word);
            }
        });
        let closed = Arc::new(closed);
        self.sessions.remove(dir);
        let full = |sessions: &HashMap<PathBuf, Walked>| {
            sessions.len() >= KNOWN
                || sessions.values().map(|w| w.files.len()).sum::<usize>() + closed.len()
                    > KNOWN_FILES
        };
        // When full, the session now (the one that changes, and is asked for most) makes room
        // by the least recently used; an earlier one is then walked each time (every request
        // goes through the sessions in turn: a rotation among them would walk them all).
        let current = dir == files.dir;
        if let Some(m) = manifest
            && closed.len() <= KNOWN_FILES
            && (current || !full(&self.sessions))
        {
            while full(&self.sessions) {
                let Some(oldest) = self
                    .sessions
                    .iter()
                    .min_by_key(|(_, w)| w.used)
                    .map(|(k, _)| k.clone())
                else {
                    break;
                };
                self.sessions.remove(&oldest);
            }
            self.sessions.insert(
                dir.to_path_buf(),
                Walked {
                    manifest: m,
                    files: closed.clone(),
                    used: self.clock,
                },
            );
        }
        closed
    }
}

/// Answers one request: the messages, then the [`HistoryAnswer`]. A request that cannot be
/// read is answered with an error.
fn serve(files: &Files, known: &mut Known, q: &Query) {
    let request = q
        .payload()
        .map(|p| p.to_bytes())
        .and_then(|b| serde_json::from_slice::<HistoryRequest>(&b).ok());
    let Some(request) = request else {
        let _ = q
            .reply_err("not a history request: send the JSON of a HistoryRequest")
            .wait();
        return;
    };
    let started = std::time::Instant::now();
    let (kept, answer) = read(files, known, &request);
    tracing::debug!(
        topic = %request.topic,
        messages = answer.messages,
        bytes = answer.bytes,
        ms = started.elapsed().as_millis() as u64,
        "recording asked for a stretch"
    );
    let key = q.key_expr().clone();
    for (time, seq, data) in kept {
        let sent = q
            .reply(key.clone(), data)
            .attachment(keys::encode_downlink(time, seq).to_vec())
            .wait();
        if sent.is_err() {
            return;
        }
    }
    if let Ok(json) = serde_json::to_vec(&answer) {
        let _ = q.reply(key, json).wait();
    }
}

/// The messages `request` asks for (log time, sequence, bytes), oldest first, and the answer
/// that ends them: every session of the system in turn, each DNM's files in the order written.
fn read(
    files: &Files,
    known: &mut Known,
    request: &HistoryRequest,
) -> (Vec<(u64, u32, Vec<u8>)>, HistoryAnswer) {
    let mut c = Collect {
        request,
        budget: request.max_bytes.clamp(1, MAX_ANSWER_BYTES),
        decimator: None,
        kept: VecDeque::new(),
        bytes: 0,
        cut: false,
        recorded: None,
    };
    let sessions = files.sessions();
    known.keep_only(&sessions);
    for dir in sessions {
        // Each session was recorded by a recorder of its own: its decimation starts afresh.
        c.decimator = request.period_ns.map(Decimator::new);
        // Closed files are known by their summaries: what of the topic each holds, its time
        // range if any (as the session's manifest says; a file closed since is read).
        let list = files.list(&dir);
        let closed = known.closed(files, &dir);
        let topic = known.topic(&request.topic);
        for path in &list {
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            // A closed file that holds nothing of the topic in the stretch is not read (the
            // first message after it may then be sent though the live downlink, knowing the one
            // before it, did not keep it).
            if let Some(range) = closed.get(name).map(|w| w.range_of(topic)) {
                let holds = range.is_some();
                let (start, end) = range.unwrap_or((0, 0));
                if holds {
                    c.widen(start, end);
                }
                if !holds || end < request.from_ns || start > request.to_ns {
                    c.decimator = request.period_ns.map(Decimator::new);
                    continue;
                }
            }
            let Ok(file) = File::open(path) else {
                continue;
            };
            for m in Stream::new(file).filter(|m| m.topic == request.topic) {
                c.offer(m);
            }
        }
    }
    c.finish()
}

/// What a request's answer gathers as the recording is read.
struct Collect<'r> {
    request: &'r HistoryRequest,
    budget: u64,
    decimator: Option<Decimator>,
    kept: VecDeque<(u64, u32, Vec<u8>)>,
    bytes: u64,
    /// The budget left some of the stretch out.
    cut: bool,
    /// First and last log times of the topic seen.
    recorded: Option<(u64, u64)>,
}

impl Collect<'_> {
    fn widen(&mut self, a: u64, b: u64) {
        self.recorded = Some(self.recorded.map_or((a, b), |(x, y)| (x.min(a), y.max(b))));
    }

    /// A message of the topic, in the order recorded.
    fn offer(&mut self, m: Msg) {
        self.widen(m.time, m.time);
        let keep = self.decimator.as_mut().is_none_or(|d| d.keep(m.time));
        let r = self.request;
        if !keep || m.time < r.from_ns || m.time > r.to_ns {
            return;
        }
        if !r.newest_first && self.bytes >= self.budget {
            self.cut = true;
            return;
        }
        self.bytes += m.data.len() as u64;
        self.kept.push_back((m.time, m.seq, m.data));
        // Newest first: the oldest give way to newer ones beyond the budget.
        while r.newest_first && self.bytes > self.budget && self.kept.len() > 1 {
            if let Some((_, _, d)) = self.kept.pop_front() {
                self.bytes -= d.len() as u64;
                self.cut = true;
            }
        }
    }

    fn finish(self) -> (Vec<(u64, u32, Vec<u8>)>, HistoryAnswer) {
        let r = self.request;
        let rest = match (self.cut, self.kept.front(), self.kept.back()) {
            (true, Some(first), Some(last)) => Some(if r.newest_first {
                (r.from_ns, first.0.saturating_sub(1))
            } else {
                (last.0.saturating_add(1), r.to_ns)
            }),
            _ => None,
        };
        let answer = HistoryAnswer {
            messages: self.kept.len() as u64,
            bytes: self.bytes,
            rest,
            recorded: self.recorded,
        };
        (self.kept.into(), answer)
    }
}

/// One message of a recording file.
struct Msg {
    topic: String,
    time: u64,
    seq: u32,
    data: Vec<u8>,
}

/// A recording file's messages in file order, read as a stream; a file cut short (still being
/// written, or its DNM killed) ends with its last whole chunk.
struct Stream {
    file: File,
    reader: mcap::sans_io::MessageReader,
}

impl Stream {
    fn new(file: File) -> Self {
        Self {
            file,
            reader: mcap::sans_io::MessageReader::new_with_options(
                mcap::sans_io::LinearReaderOptions::default()
                    .with_record_length_limit(MAX_RECORD)
                    .with_skip_end_magic(true),
            ),
        }
    }
}

impl Iterator for Stream {
    type Item = Msg;

    fn next(&mut self) -> Option<Msg> {
        use mcap::sans_io::MessageReadEvent;
        loop {
            match self.reader.next_event()? {
                Err(_) => return None,
                Ok(MessageReadEvent::ReadRequest(n)) => {
                    let buf = self.reader.insert(n);
                    match self.file.read(buf) {
                        // The end of what is written (a chunk still open ends it too).
                        Ok(0) | Err(_) => return None,
                        Ok(k) => self.reader.notify_read(k),
                    }
                }
                Ok(MessageReadEvent::Message(m)) => {
                    return Some(Msg {
                        topic: m.channel.topic.clone(),
                        time: m.log_time,
                        seq: m.sequence,
                        data: m.data.into_owned(),
                    });
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    const TOPIC: &str = "/rover/src/out";

    /// Writes `rec-rover[.n].mcap` with messages of `TOPIC` at `times` (s), and another topic.
    fn write_file(dir: &Path, n: u64, times: std::ops::Range<u64>) {
        let name = if n == 0 {
            "rec-rover.mcap".to_string()
        } else {
            format!("rec-rover.{n}.mcap")
        };
        let file = File::create(dir.join(name)).unwrap();
        let mut w = mcap::WriteOptions::new()
            .create(std::io::BufWriter::new(file))
            .unwrap();
        let mine = w
            .add_channel(0, TOPIC, "application/octet-stream", &Default::default())
            .unwrap();
        let other = w
            .add_channel(
                0,
                "/rover/other/out",
                "application/octet-stream",
                &Default::default(),
            )
            .unwrap();
        for t in times {
            for channel_id in [mine, other] {
                let header = mcap::records::MessageHeader {
                    channel_id,
                    sequence: t as u32,
                    log_time: t * 1_000_000_000,
                    publish_time: t * 1_000_000_000,
                };
                w.write_to_known_channel(&header, &t.to_le_bytes()).unwrap();
            }
        }
        w.finish().unwrap();
    }

    fn request(from_s: u64, to_s: u64) -> HistoryRequest {
        HistoryRequest {
            topic: TOPIC.into(),
            from_ns: from_s * 1_000_000_000,
            to_ns: to_s * 1_000_000_000,
            period_ns: None,
            max_bytes: 1 << 20,
            newest_first: false,
        }
    }

    #[test]
    fn a_manifest_is_walked_once_until_a_file_closes_whatever_the_topics() {
        let root = std::env::temp_dir().join(format!("dnm-history-known-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let dir = root.join("sys-20261127T000000Z");
        std::fs::create_dir_all(&dir).unwrap();
        write_file(&dir, 0, 0..10);
        write_file(&dir, 1, 10..20);
        dnm_record::session::write_manifest(&dir).unwrap();
        let files = Files {
            dir: dir.clone(),
            system: "sys".into(),
            dnm: "rover".into(),
        };
        let mut known = Known::default();
        // The same answer as a walk of its own each time; one walk for three requests.
        for (from, to) in [(0, 100), (12, 15), (3, 4)] {
            let cached = read(&files, &mut known, &request(from, to));
            let fresh = read(&files, &mut Known::default(), &request(from, to));
            assert_eq!(cached.0, fresh.0);
            assert_eq!(cached.1.recorded, fresh.1.recorded);
            assert_eq!(
                cached.0.len() as u64,
                to.min(19) - from + 1,
                "{from}..{to}: {:?}",
                cached.1
            );
        }
        assert_eq!(known.walks, 1);
        // A file closes and the manifest is written anew: walked again, and the file is in.
        write_file(&dir, 2, 20..30);
        dnm_record::session::write_manifest(&dir).unwrap();
        let (kept, answer) = read(&files, &mut known, &request(0, 100));
        assert_eq!(kept.len(), 30);
        assert_eq!(answer.recorded, Some((0, 29_000_000_000)));
        assert_eq!(known.walks, 2);
        // A file closed and not yet in the manifest is read all the same.
        write_file(&dir, 3, 30..40);
        let (kept, _) = read(&files, &mut known, &request(25, 35));
        assert_eq!(kept.len(), 11);
        assert_eq!(known.walks, 2);
        // Another topic needs no walk of its own.
        let mut other = request(0, 100);
        other.topic = "/rover/other/out".into();
        assert_eq!(read(&files, &mut known, &other).0.len(), 40);
        let fresh = read(&files, &mut Known::default(), &other);
        assert_eq!(fresh.0.len(), 40);
        assert_eq!(known.walks, 2);
        // A topic no file holds: nothing, as a walk of its own finds.
        let mut none = request(0, 100);
        none.topic = "/rover/none/out".into();
        assert!(read(&files, &mut known, &none).0.is_empty());
        assert_eq!(known.walks, 2);
        // Earlier sessions of the system beside it: each walked once, then known; one removed
        // is forgotten.
        let earlier = root.join("sys-20261126T000000Z");
        let before = root.join("sys-20261125T000000Z");
        for (dir, from) in [(&earlier, 100), (&before, 200)] {
            std::fs::create_dir_all(dir).unwrap();
            write_file(dir, 0, from..from + 10);
            dnm_record::session::write_manifest(dir).unwrap();
        }
        for _ in 0..3 {
            assert_eq!(read(&files, &mut known, &request(0, 1000)).0.len(), 60);
        }
        assert_eq!(known.walks, 4);
        std::fs::remove_dir_all(&before).unwrap();
        assert_eq!(read(&files, &mut known, &request(0, 1000)).0.len(), 50);
        assert_eq!(known.sessions.len(), 2);
        assert_eq!(known.walks, 4);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn only_the_dnms_own_files_are_its() {
        let files = Files {
            dir: PathBuf::new(),
            system: "sys".into(),
            dnm: "rover".into(),
        };
        for name in ["rec-rover.mcap", "rec-rover.1.mcap", "rec-rover.12.mcap"] {
            assert!(files.mine(name), "{name}");
        }
        for name in [
            "rec-rover-2.mcap",
            "rec-rover.x.mcap",
            "rec-rover..mcap",
            "rec-drive.mcap",
            "rec-rover.mcap.tmp",
        ] {
            assert!(!files.mine(name), "{name}");
        }
    }
}
