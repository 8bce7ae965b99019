//! A recording session is one folder, `recordings/<system>-<UTC time>[-<n>]/` (see
//! [`claim_folder`]): every DNM's MCAP files of one run and a manifest (`manifest.json`, in the
//! spirit of rosbag2's `metadata.yaml`): the files, the DNMs, the revisions, the time range,
//! message counts per file and channel, and the netlists. The manifest is built from the files'
//! own MCAP summaries (read with seeks, so a file of any size costs a few reads), written when a
//! recorder closes a file, and can be built again at any time (`dnm recordings DIR`). It is one
//! JSON document with a line per file; it is read and written as a stream (a closed file's
//! entry carried over from the manifest before), so a session of weeks of files costs each
//! rotation no more memory than a session of one.

use std::collections::{BTreeMap, BTreeSet};
use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use mcap::sans_io::summary_reader::{SummaryReadEvent, SummaryReader, SummaryReaderOptions};
use serde::{Deserialize, Serialize};

/// The manifest's file name in a session folder.
pub const MANIFEST: &str = "manifest.json";

/// Largest summary record and netlist read from a file (a corrupt length must not allocate
/// gigabytes).
const MAX_RECORD: usize = 64 << 20;
/// Most bytes read to find a file's summary: a damaged footer pointing into the data must not
/// make indexing read (and decompress) the whole file.
const MAX_SUMMARY_READ: usize = 64 << 20;
/// Netlists read from one file at most, and their bytes in all.
const MAX_NETLISTS: usize = 64;
const MAX_NETLIST_BYTES: usize = 16 << 20;
/// The MCAP opcode of an attachment record.
const ATTACHMENT_OP: u8 = 0x09;

/// One MCAP file of a session.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    /// Its name in the session folder.
    pub name: String,
    pub bytes: u64,
    /// The DNM that wrote it (from its channels).
    pub dnm: Option<String>,
    /// Whether it was closed (summary and footer written); a file cut short by a crash is
    /// listed without counts.
    pub complete: bool,
    pub messages: u64,
    pub start_unix_ns: Option<u64>,
    pub end_unix_ns: Option<u64>,
    /// Netlist revisions whose data it holds.
    pub revisions: Vec<u64>,
    /// Messages per channel (topic).
    pub channels: BTreeMap<String, u64>,
    /// What is wrong with it, if something is.
    pub error: Option<String>,
}

/// A netlist a session ran, as recorded.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RecordedNetlist {
    pub revision: u64,
    /// The first file, in the order written, that holds it.
    pub file: String,
    pub text: String,
}

/// What a session folder holds.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: u32,
    /// The session's name: its folder's.
    pub session: String,
    pub files: Vec<FileEntry>,
    pub dnms: Vec<String>,
    pub revisions: Vec<u64>,
    pub start_unix_ns: Option<u64>,
    pub end_unix_ns: Option<u64>,
    pub messages: u64,
    pub bytes: u64,
    pub netlists: Vec<RecordedNetlist>,
}

/// Why a session folder's files or manifest could not be listed, read or written.
#[derive(Debug, thiserror::Error)]
pub enum SessionError {
    /// The folder (a session's, or the folder of sessions) could not be listed.
    #[error("{}: {source}", dir.display())]
    ListFolder {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The manifest could not be written as JSON.
    #[error("{0}")]
    Serialize(#[source] serde_json::Error),
    /// The manifest could not be written into the session's folder.
    #[error("{}: {source}", path.display())]
    WriteManifest {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Makes this run's session folder `root/<name>`, or `root/<name>-2`, `-3`, ... when a folder of
/// that name exists (another run's, started within the same second). Made with `mkdir`, so two
/// processes never take the same one. A folder that cannot be made (no permission, no space)
/// is returned as it is, for the recorder's start to report.
pub fn claim_folder(root: &Path, name: &str) -> PathBuf {
    let _ = std::fs::create_dir_all(root);
    for n in 1..=MAX_RUNS_PER_SECOND {
        let dir = if n == 1 {
            root.join(name)
        } else {
            root.join(format!("{name}-{n}"))
        };
        match std::fs::create_dir(&dir) {
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            _ => return dir,
        }
    }
    root.join(name)
}

/// Runs of one system whose sessions may start within one second (see [`claim_folder`]).
const MAX_RUNS_PER_SECOND: u32 = 1000;

/// The session's start time and its run within that second, from a session folder's name
/// (`<system>-<YYYYMMDDTHHMMSSZ>[-<n>]`, see [`claim_folder`]), if it is one of `system`'s:
/// another system whose name extends this one's is not taken for it.
pub fn session_of(system: &str, folder: &str) -> Option<(String, u32)> {
    let t = folder.strip_prefix(system)?.strip_prefix('-')?;
    let (time, run) = match t.split_once("Z-") {
        Some((time, n)) => (
            format!("{time}Z"),
            n.parse::<u32>().ok().filter(|n| *n >= 2)?,
        ),
        None => (t.to_string(), 1),
    };
    let b = time.as_bytes();
    let stamp = b.len() == 16
        && b[8] == b'T'
        && b[15] == b'Z'
        && b[..8].iter().chain(&b[9..15]).all(u8::is_ascii_digit);
    stamp.then_some((time, run))
}

/// `<system>-<YYYYMMDDTHHMMSSZ>` for a session started at `unix_s`.
pub fn session_name(system: &str, unix_s: u64) -> String {
    let days = (unix_s / 86_400) as i64;
    let secs = unix_s % 86_400;
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{system}-{y:04}{m:02}{d:02}T{:02}{:02}{:02}Z",
        secs / 3600,
        secs % 3600 / 60,
        secs % 60
    )
}

/// The MCAP summary of a file, read with seeks (`None`: the file has no summary, e.g. it was
/// not closed).
pub(crate) fn read_summary(file: &mut File, size: u64) -> Result<Option<mcap::Summary>, String> {
    let mut reader = SummaryReader::new_with_options(
        SummaryReaderOptions::default()
            .with_file_size(size)
            .with_record_length_limit(MAX_RECORD),
    );
    let mut total = 0usize;
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            SummaryReadEvent::ReadRequest(n) => {
                total = total.saturating_add(n);
                if total > MAX_SUMMARY_READ {
                    return Err(format!(
                        "its summary would take over {} MiB to read: damaged",
                        MAX_SUMMARY_READ >> 20
                    ));
                }
                let buf = reader.insert(n);
                let read = file.read(buf).map_err(|e| e.to_string())?;
                reader.notify_read(read);
            }
            SummaryReadEvent::SeekRequest(to) => {
                let pos = file.seek(to).map_err(|e| e.to_string())?;
                reader.notify_seeked(pos);
            }
        }
    }
    Ok(reader.finish())
}

/// The data of the attachment record at `offset` (`length` bytes long in the index), checked to
/// be an attachment named `name` that lies within the file.
fn read_attachment(
    file: &mut File,
    size: u64,
    offset: u64,
    length: u64,
    name: &str,
) -> Result<Vec<u8>, String> {
    offset
        .checked_add(length)
        .filter(|e| *e <= size)
        .ok_or("the index points past the end of the file")?;
    let length = usize::try_from(length)
        .ok()
        .filter(|l| *l <= MAX_RECORD)
        .ok_or("an attachment larger than a netlist can be")?;
    let mut rec = vec![0u8; length];
    file.seek(SeekFrom::Start(offset))
        .and_then(|_| file.read_exact(&mut rec))
        .map_err(|e| e.to_string())?;
    let mut at = 0usize;
    let mut take = |n: usize| -> Result<&[u8], String> {
        let stop = at
            .checked_add(n)
            .filter(|s| *s <= rec.len())
            .ok_or("a truncated attachment record")?;
        let slice = &rec[at..stop];
        at = stop;
        Ok(slice)
    };
    let le = |b: &[u8]| -> u64 {
        b.iter()
            .rev()
            .fold(0u64, |acc, x| (acc << 8) | u64::from(*x))
    };
    if take(1)? != [ATTACHMENT_OP] {
        return Err("the index points at something other than an attachment".into());
    }
    let record_len = le(take(8)?);
    if record_len != length as u64 - 9 {
        return Err("the attachment's length disagrees with the index".into());
    }
    take(16)?; // log time, create time
    let name_len = le(take(4)?) as usize;
    if take(name_len)? != name.as_bytes() {
        return Err("the attachment's name disagrees with the index".into());
    }
    let media_len = le(take(4)?) as usize;
    take(media_len)?;
    let data_len = usize::try_from(le(take(8)?)).map_err(|e| e.to_string())?;
    Ok(take(data_len)?.to_vec())
}

/// One file of a session, from its summary.
pub(crate) fn file_entry(path: &Path, netlists: &mut BTreeMap<u64, RecordedNetlist>) -> FileEntry {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let mut entry = FileEntry {
        name: name.clone(),
        bytes: 0,
        dnm: None,
        complete: false,
        messages: 0,
        start_unix_ns: None,
        end_unix_ns: None,
        revisions: Vec::new(),
        channels: BTreeMap::new(),
        error: None,
    };
    let mut file = match File::open(path) {
        Ok(f) => f,
        Err(e) => {
            entry.error = Some(e.to_string());
            return entry;
        }
    };
    entry.bytes = file.metadata().map_or(0, |m| m.len());
    let summary = match read_summary(&mut file, entry.bytes) {
        Ok(Some(s)) => s,
        Ok(None) => {
            entry.error = Some(
                "no summary: still being written, or its recorder stopped before closing it".into(),
            );
            return entry;
        }
        Err(e) => {
            entry.error = Some(format!(
                "no readable summary (still being written, cut short, or damaged): {e}"
            ));
            return entry;
        }
    };
    entry.complete = true;
    if let Some(stats) = &summary.stats {
        entry.messages = stats.message_count;
        if stats.message_count > 0 {
            entry.start_unix_ns = Some(stats.message_start_time);
            entry.end_unix_ns = Some(stats.message_end_time);
        }
        for (id, n) in &stats.channel_message_counts {
            if let Some(c) = summary.channels.get(id) {
                entry.channels.insert(c.topic.clone(), *n);
            }
        }
    }
    entry.dnm = summary
        .channels
        .values()
        .find_map(|c| c.metadata.get("dnm").cloned())
        .or_else(|| {
            summary.channels.values().find_map(|c| {
                c.topic
                    .strip_prefix('/')
                    .and_then(|t| t.split('/').next())
                    .map(str::to_string)
            })
        });
    let mut read = 0usize;
    for a in &summary.attachment_indexes {
        let Some(revision) = a
            .name
            .strip_prefix("netlist-r")
            .and_then(|r| r.strip_suffix(".toml"))
            .and_then(|r| r.parse::<u64>().ok())
        else {
            continue;
        };
        if entry.revisions.contains(&revision) {
            continue;
        }
        if entry.revisions.len() >= MAX_NETLISTS {
            entry.error = Some(format!(
                "more than {MAX_NETLISTS} netlists: the rest not read"
            ));
            break;
        }
        entry.revisions.push(revision);
        if netlists.contains_key(&revision) {
            continue;
        }
        if read.saturating_add(a.length as usize) > MAX_NETLIST_BYTES {
            entry.error = Some("its netlists are larger than netlists can be: not read".into());
            break;
        }
        read = read.saturating_add(a.length as usize);
        match read_attachment(&mut file, entry.bytes, a.offset, a.length, &a.name) {
            Ok(data) => {
                netlists.insert(
                    revision,
                    RecordedNetlist {
                        revision,
                        file: name.clone(),
                        text: String::from_utf8_lossy(&data).into_owned(),
                    },
                );
            }
            Err(e) => entry.error = Some(format!("netlist of revision {revision}: {e}")),
        }
    }
    entry.revisions.sort_unstable();
    entry.revisions.dedup();
    entry
}

/// A DNM's files are `<stem>-<dnm>.mcap`, then `<stem>-<dnm>.1.mcap`, `.2`, ... (names never
/// contain a dot): the order they were written in.
fn order_key(p: &Path) -> (String, u64) {
    let stem = p
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    match stem.rsplit_once('.') {
        Some((head, n)) => match n.parse::<u64>() {
            Ok(n) => (head.to_string(), n),
            Err(_) => (stem, 0),
        },
        None => (stem, 0),
    }
}

/// The MCAP files of a folder (regular files only: a link to elsewhere is not the session's),
/// each DNM's in the order written.
pub fn files(dir: &Path) -> Result<Vec<PathBuf>, SessionError> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|source| SessionError::ListFolder {
            dir: dir.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok())
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    out.sort_by_cached_key(|p| order_key(p));
    Ok(out)
}

/// A session's files in order, each with its entry: a closed file's taken from the manifest on
/// disk when it lists that file at its size (a closed file does not change), every other read
/// from the file. The manifest on disk is read as a stream and its entries are handed on one at
/// a time, so a session's files cost memory only for their names while it is walked, whatever
/// the session's length; `netlists` gets the netlists of every revision the entries name.
fn walk(
    dir: &Path,
    netlists: &mut BTreeMap<u64, RecordedNetlist>,
    mut emit: impl FnMut(FileEntry),
) -> Result<(), SessionError> {
    // The first file naming each revision: where its netlist is said to be found.
    let mut first: BTreeMap<u64, String> = BTreeMap::new();
    let mut emit = |e: FileEntry| {
        for r in &e.revisions {
            first.entry(*r).or_insert_with(|| e.name.clone());
        }
        emit(e);
    };
    let on_disk = files(dir)?;
    let mut disk = on_disk.iter().peekable();
    // Revisions of reused entries, and a file each was found in, for a netlist the manifest
    // on disk does not hold.
    let mut named: BTreeMap<u64, PathBuf> = BTreeMap::new();
    let mut listed: Vec<RecordedNetlist> = Vec::new();
    if let Ok(file) = File::open(dir.join(MANIFEST)) {
        let mut on_entry = |e: FileEntry| {
            let key = order_key(Path::new(&e.name));
            while let Some(p) = disk.next_if(|p| order_key(p) < key) {
                emit(file_entry(p, netlists));
            }
            let Some(p) = disk.next_if(|p| p.file_name().is_some_and(|n| *n == *e.name)) else {
                return; // no longer in the folder, or listed out of order: read when reached
            };
            let size = std::fs::metadata(p).map_or(0, |m| m.len());
            if e.complete && e.error.is_none() && e.bytes == size {
                for r in &e.revisions {
                    named.entry(*r).or_insert_with(|| p.clone());
                }
                emit(e);
            } else {
                emit(file_entry(p, netlists));
            }
        };
        let seed = Previous {
            on_entry: &mut on_entry,
            netlists: &mut listed,
        };
        let mut reader = serde_json::Deserializer::from_reader(std::io::BufReader::new(file));
        if let Err(e) = serde::de::DeserializeSeed::deserialize(seed, &mut reader) {
            tracing::debug!(
                "{}: {e}: the rest read from the files",
                dir.join(MANIFEST).display()
            );
        }
    }
    for p in disk {
        emit(file_entry(p, netlists));
    }
    // A reused entry's netlist: from the manifest on disk, else read again from its file.
    for n in listed {
        if named.contains_key(&n.revision) {
            netlists.entry(n.revision).or_insert(n);
        }
    }
    for (revision, p) in named {
        if !netlists.contains_key(&revision) {
            file_entry(&p, netlists);
        }
    }
    for (revision, n) in netlists.iter_mut() {
        if let Some(f) = first.get(revision) {
            n.file.clone_from(f);
        }
    }
    Ok(())
}

/// Reads a manifest's entries one at a time, and its netlists.
struct Previous<'a, F> {
    on_entry: &'a mut F,
    netlists: &'a mut Vec<RecordedNetlist>,
}

impl<'de, F: FnMut(FileEntry)> serde::de::DeserializeSeed<'de> for Previous<'_, F> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de, F: FnMut(FileEntry)> serde::de::Visitor<'de> for Previous<'_, F> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a session's manifest")
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(key) = map.next_key::<String>()? {
            match key.as_str() {
                "files" => map.next_value_seed(Entries(&mut *self.on_entry))?,
                "netlists" => *self.netlists = map.next_value()?,
                _ => {
                    map.next_value::<serde::de::IgnoredAny>()?;
                }
            }
        }
        Ok(())
    }
}

/// A manifest's `files`, each handed on as it is read.
struct Entries<'a, F>(&'a mut F);

impl<'de, F: FnMut(FileEntry)> serde::de::DeserializeSeed<'de> for Entries<'_, F> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_seq(self)
    }
}

impl<'de, F: FnMut(FileEntry)> serde::de::Visitor<'de> for Entries<'_, F> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("a list of files")
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        while let Some(e) = seq.next_element::<FileEntry>()? {
            (self.0)(e);
        }
        Ok(())
    }
}

/// What a manifest says of all its files together, gathered one file at a time.
#[derive(Default)]
struct Totals {
    dnms: BTreeSet<String>,
    revisions: BTreeSet<u64>,
    start_unix_ns: Option<u64>,
    end_unix_ns: Option<u64>,
    messages: u64,
    bytes: u64,
    files: usize,
}

impl Totals {
    fn add(&mut self, f: &FileEntry) {
        self.dnms.extend(f.dnm.clone());
        self.revisions.extend(f.revisions.iter().copied());
        self.start_unix_ns = self.start_unix_ns.into_iter().chain(f.start_unix_ns).min();
        self.end_unix_ns = self.end_unix_ns.into_iter().chain(f.end_unix_ns).max();
        self.messages += f.messages;
        self.bytes += f.bytes;
        self.files += 1;
    }
}

fn session_name_of(dir: &Path) -> String {
    dir.file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default()
}

/// The manifest of a session folder, built from its files.
pub fn index(dir: &Path) -> Result<Manifest, SessionError> {
    let mut netlists = BTreeMap::new();
    let mut totals = Totals::default();
    let mut files = Vec::new();
    walk(dir, &mut netlists, |e| {
        totals.add(&e);
        files.push(e);
    })?;
    Ok(Manifest {
        format: 1,
        session: session_name_of(dir),
        start_unix_ns: totals.start_unix_ns,
        end_unix_ns: totals.end_unix_ns,
        messages: totals.messages,
        bytes: totals.bytes,
        dnms: totals.dnms.into_iter().collect(),
        revisions: totals.revisions.into_iter().collect(),
        netlists: netlists.into_values().collect(),
        files,
    })
}

/// Each file of a session with its entry, in order, as [`index`] lists them, without holding
/// them all (a reader that needs only a few of each entry's figures).
pub fn for_each_entry(dir: &Path, emit: impl FnMut(FileEntry)) -> Result<(), SessionError> {
    walk(dir, &mut BTreeMap::new(), emit)
}

/// What a manifest written says of its session (its files are in the file).
#[derive(Debug, Clone, PartialEq)]
pub struct Written {
    pub files: usize,
    pub messages: u64,
    pub bytes: u64,
}

/// Manifests are written one at a time in a process.
static WRITING: Mutex<()> = Mutex::new(());

/// Builds the manifest of `dir` and writes it there (atomically: a reader never sees half).
///
/// It is written as it is built: one line per file, the totals and netlists after the files.
/// What it holds in memory at once is one entry, the netlists and the folder's file names, so
/// a session of weeks of files costs a rotation no more memory than a session of one; its time
/// grows with the files (a stream of their entries through, each file's size looked up).
pub fn write_manifest(dir: &Path) -> Result<Written, SessionError> {
    let _one = WRITING.lock().unwrap_or_else(|e| e.into_inner());
    let path = dir.join(MANIFEST);
    let tmp = dir.join(format!(".{MANIFEST}.{}", std::process::id()));
    let written = write_to(dir, &tmp, &path).and_then(|w| {
        std::fs::rename(&tmp, &path)
            .map(|_| w)
            .map_err(|source| SessionError::WriteManifest {
                path: path.clone(),
                source,
            })
    });
    if written.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    written
}

/// Writes the manifest of `dir` to `tmp` (errors named after `path`, the manifest's own): its
/// head, each file's entry as the walk hands it on, then the totals and the netlists.
fn write_to(dir: &Path, tmp: &Path, path: &Path) -> Result<Written, SessionError> {
    let mut out = ManifestWriter::create(tmp, path)?;
    out.head(&session_name_of(dir))?;
    let mut netlists = BTreeMap::new();
    let mut totals = Totals::default();
    let mut failed: Option<SessionError> = None;
    walk(dir, &mut netlists, |e| {
        if failed.is_none() {
            failed = out.entry(&e).err();
        }
        totals.add(&e);
    })?;
    if let Some(e) = failed {
        return Err(e);
    }
    out.tail(&totals, netlists.values())?;
    out.finish()?;
    Ok(Written {
        files: totals.files,
        messages: totals.messages,
        bytes: totals.bytes,
    })
}

/// A manifest written as a stream: one line per file, compact JSON each.
struct ManifestWriter<'p> {
    out: std::io::BufWriter<File>,
    /// The manifest's own path, for errors.
    path: &'p Path,
    /// Entries written so far.
    entries: usize,
}

impl<'p> ManifestWriter<'p> {
    fn create(tmp: &Path, path: &'p Path) -> Result<Self, SessionError> {
        let file = File::create(tmp).map_err(|e| Self::failed(path, e))?;
        Ok(Self {
            out: std::io::BufWriter::new(file),
            path,
            entries: 0,
        })
    }

    fn failed(path: &Path, source: std::io::Error) -> SessionError {
        SessionError::WriteManifest {
            path: path.to_path_buf(),
            source,
        }
    }

    fn raw(&mut self, text: &str) -> Result<(), SessionError> {
        use std::io::Write;
        self.out
            .write_all(text.as_bytes())
            .map_err(|e| Self::failed(self.path, e))
    }

    /// `lead`, then `value` as compact JSON.
    fn value(&mut self, lead: &str, value: &impl Serialize) -> Result<(), SessionError> {
        self.raw(lead)?;
        serde_json::to_writer(&mut self.out, value).map_err(|e| match e.io_error_kind() {
            Some(kind) => Self::failed(self.path, std::io::Error::new(kind, e)),
            None => SessionError::Serialize(e),
        })
    }

    fn head(&mut self, session: &str) -> Result<(), SessionError> {
        self.raw("{")?;
        self.value("\n\"format\": ", &1)?;
        self.value(",\n\"session\": ", &session)?;
        self.raw(",\n\"files\": [")
    }

    fn entry(&mut self, e: &FileEntry) -> Result<(), SessionError> {
        let lead = if self.entries == 0 { "\n" } else { ",\n" };
        self.entries += 1;
        self.value(lead, e)
    }

    fn tail<'n>(
        &mut self,
        totals: &Totals,
        netlists: impl Iterator<Item = &'n RecordedNetlist>,
    ) -> Result<(), SessionError> {
        self.value("\n],\n\"dnms\": ", &totals.dnms)?;
        self.value(",\n\"revisions\": ", &totals.revisions)?;
        self.value(",\n\"start_unix_ns\": ", &totals.start_unix_ns)?;
        self.value(",\n\"end_unix_ns\": ", &totals.end_unix_ns)?;
        self.value(",\n\"messages\": ", &totals.messages)?;
        self.value(",\n\"bytes\": ", &totals.bytes)?;
        self.raw(",\n\"netlists\": [")?;
        for (i, n) in netlists.enumerate() {
            self.value(if i == 0 { "\n" } else { ",\n" }, n)?;
        }
        self.raw("\n]\n}\n")
    }

    /// Flushes the manifest and syncs it to the disk.
    fn finish(self) -> Result<(), SessionError> {
        let path = self.path;
        self.out
            .into_inner()
            .map_err(|e| Self::failed(path, e.into_error()))?
            .sync_data()
            .map_err(|e| Self::failed(path, e))
    }
}

/// Session folders whose manifest is to be written again, and whether a write is under way.
struct Pending {
    dirs: BTreeSet<PathBuf>,
    busy: bool,
    thread: bool,
}

static PENDING: Mutex<Pending> = Mutex::new(Pending {
    dirs: BTreeSet::new(),
    busy: false,
    thread: false,
});
static PENDING_CHANGED: std::sync::Condvar = std::sync::Condvar::new();

/// Asks for `dir`'s manifest to be written again, on a thread of its own (a recorder's writer
/// never waits for it); requests for one folder made meanwhile are written once.
pub fn request_manifest(dir: &Path) {
    let Ok(mut p) = PENDING.lock() else { return };
    p.dirs.insert(dir.to_path_buf());
    if !p.thread {
        let spawned = std::thread::Builder::new()
            .name("record-manifest".into())
            .spawn(manifest_loop);
        match spawned {
            Ok(_) => p.thread = true,
            Err(e) => tracing::warn!("no thread for the sessions' manifests: {e}"),
        }
    }
    PENDING_CHANGED.notify_all();
}

/// Waits until every manifest asked for is written (before a process ends).
pub fn settle() {
    let Ok(mut p) = PENDING.lock() else { return };
    while p.thread && (p.busy || !p.dirs.is_empty()) {
        p = match PENDING_CHANGED.wait(p) {
            Ok(p) => p,
            Err(_) => return,
        };
    }
}

fn manifest_loop() {
    loop {
        let dir = {
            let Ok(mut p) = PENDING.lock() else { return };
            loop {
                if let Some(d) = p.dirs.pop_first() {
                    p.busy = true;
                    break d;
                }
                p.busy = false;
                PENDING_CHANGED.notify_all();
                p = match PENDING_CHANGED.wait(p) {
                    Ok(p) => p,
                    Err(_) => return,
                };
            }
        };
        if let Err(e) = write_manifest(&dir) {
            tracing::warn!("the session's manifest: {e}");
        }
        give_back_freed_memory();
    }
}

/// Returns the heap's free pages to the system. A manifest is built on this thread alone, and
/// what it frees (the files' summaries read, the entries passed through) is given back at once
/// rather than kept by the allocator among pages other threads still use.
fn give_back_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only releases free memory of the allocator's own arenas.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The manifest of a session folder: the one written there if it is current (it lists exactly
/// the folder's files), else built again.
pub fn manifest(dir: &Path) -> Result<Manifest, SessionError> {
    let on_disk: Vec<(String, u64)> = files(dir)?
        .iter()
        .filter_map(|p| {
            Some((
                p.file_name()?.to_string_lossy().into_owned(),
                std::fs::metadata(p).ok()?.len(),
            ))
        })
        .collect();
    if let Ok(text) = std::fs::read(dir.join(MANIFEST))
        && let Ok(m) = serde_json::from_slice::<Manifest>(&text)
        && m.files
            .iter()
            .map(|f| (f.name.clone(), f.bytes))
            .eq(on_disk.iter().cloned())
        && m.files.iter().all(|f| f.complete)
    {
        return Ok(m);
    }
    index(dir)
}

/// The sessions under `root`: its folders holding MCAP files, oldest first.
pub fn sessions(root: &Path) -> Result<Vec<Manifest>, SessionError> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
        .map_err(|source| SessionError::ListFolder {
            dir: root.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    let mut out = Vec::new();
    for d in dirs {
        if files(&d).is_ok_and(|f| !f.is_empty()) {
            match manifest(&d) {
                Ok(m) => out.push(m),
                Err(e) => tracing::warn!("{}: {e}", d.display()),
            }
        }
    }
    // Oldest first; sessions without a message last.
    out.sort_by_key(|m| {
        (
            m.start_unix_ns.is_none(),
            m.start_unix_ns,
            m.session.clone(),
        )
    });
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn a_dnms_files_are_listed_in_the_order_written_and_links_are_not_followed() {
        let dir = std::env::temp_dir().join(format!("dnm-session-order-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        for n in [
            "rec-a.10.mcap",
            "rec-a.2.mcap",
            "rec-a.mcap",
            "rec-a.1.mcap",
            "rec-cam-2.mcap",
        ] {
            std::fs::write(dir.join(n), b"").unwrap();
        }
        std::os::unix::fs::symlink("/etc/hostname", dir.join("rec-b.mcap")).unwrap();
        let names: Vec<String> = files(&dir)
            .unwrap()
            .iter()
            .map(|p| p.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(
            names,
            [
                "rec-a.mcap",
                "rec-a.1.mcap",
                "rec-a.2.mcap",
                "rec-a.10.mcap",
                "rec-cam-2.mcap"
            ]
        );
        // Empty files: listed, not closed, no panic.
        let m = index(&dir).unwrap();
        assert!(m.files.iter().all(|f| !f.complete && f.error.is_some()));
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn a_run_started_within_the_second_of_another_takes_a_folder_of_its_own() {
        let root = std::env::temp_dir().join(format!("dnm-claim-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let name = session_name("b", 1_795_000_000);
        let first = claim_folder(&root, &name);
        let second = claim_folder(&root, &name);
        let third = claim_folder(&root, &name);
        assert_eq!(first, root.join("b-20261118T110640Z"));
        assert_eq!(second, root.join("b-20261118T110640Z-2"));
        assert_eq!(third, root.join("b-20261118T110640Z-3"));
        assert!(first.is_dir() && second.is_dir() && third.is_dir());
        let _ = std::fs::remove_dir_all(&root);
    }

    #[test]
    fn session_folders_are_told_by_system_time_and_run() {
        let t = "20261118T110640Z";
        assert_eq!(session_of("b", &format!("b-{t}")), Some((t.into(), 1)));
        assert_eq!(session_of("b", &format!("b-{t}-2")), Some((t.into(), 2)));
        assert_eq!(session_of("b", &format!("b-{t}-12")), Some((t.into(), 12)));
        // Another system whose name extends this one's, and names that are not sessions.
        assert_eq!(session_of("b", &format!("b-x-{t}")), None);
        assert_eq!(session_of("b", &format!("b-{t}-1")), None);
        assert_eq!(session_of("b", &format!("b-{t}-x")), None);
        assert_eq!(session_of("b", "b-2026111xT110640Z"), None);
        assert_eq!(session_of("b", &format!("bb-{t}")), None);
    }

    #[test]
    fn session_names_carry_the_utc_time() {
        assert_eq!(session_name("beetle", 0), "beetle-19700101T000000Z");
        assert_eq!(session_name("b", 1_795_000_000), "b-20261118T110640Z");
        assert_eq!(session_name("b", 951_782_400), "b-20000229T000000Z");
    }
}
