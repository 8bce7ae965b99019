//! A recording session is one folder, `recordings/<system>-<UTC time>/`: every DNM's MCAP files
//! of one run and a manifest (`manifest.json`, in the spirit of rosbag2's `metadata.yaml`):
//! the files, the DNMs, the revisions, the time range, message counts per file and channel, and
//! the netlists. The manifest is built from the files' own MCAP summaries (read with seeks, so
//! a file of any size costs a few reads), written when a recorder closes its files, and can be
//! built again at any time (`dnm recordings DIR`).

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
    /// The file it was found in first.
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
fn read_summary(file: &mut File, size: u64) -> Result<Option<mcap::Summary>, String> {
    let mut reader = SummaryReader::new_with_options(
        SummaryReaderOptions::default()
            .with_file_size(size)
            .with_record_length_limit(MAX_RECORD),
    );
    while let Some(event) = reader.next_event() {
        match event.map_err(|e| e.to_string())? {
            SummaryReadEvent::ReadRequest(n) => {
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

/// The data of the attachment record at `offset` (`length` bytes long), if it is one.
fn read_attachment(file: &mut File, offset: u64, length: u64) -> Result<(String, Vec<u8>), String> {
    let length = usize::try_from(length)
        .ok()
        .filter(|l| *l <= MAX_RECORD)
        .ok_or("an attachment larger than a netlist can be")?;
    let mut rec = vec![0u8; length];
    file.seek(SeekFrom::Start(offset))
        .and_then(|_| file.read_exact(&mut rec))
        .map_err(|e| e.to_string())?;
    let mut at = 1 + 8 + 8 + 8; // opcode, record length, log time, create time
    let mut take = |n: usize| -> Result<&[u8], String> {
        let s = rec.get(at..at + n).ok_or("a truncated attachment record")?;
        at += n;
        Ok(s)
    };
    let u32_at = |b: &[u8]| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize;
    let name_len = u32_at(take(4)?);
    let name = String::from_utf8_lossy(take(name_len)?).into_owned();
    let media_len = u32_at(take(4)?);
    take(media_len)?;
    let data_len = take(8)?;
    let data_len = u64::from_le_bytes(data_len.try_into().map_err(|_| "bad length")?);
    let data = take(usize::try_from(data_len).map_err(|e| e.to_string())?)?.to_vec();
    Ok((name, data))
}

/// One file of a session, from its summary.
fn file_entry(path: &Path, netlists: &mut BTreeMap<u64, RecordedNetlist>) -> FileEntry {
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
            entry.error = Some("not closed (no summary): the recorder stopped before it".into());
            return entry;
        }
        Err(e) => {
            entry.error = Some(format!("not closed, or damaged: {e}"));
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
    for a in &summary.attachment_indexes {
        let Some(revision) = a
            .name
            .strip_prefix("netlist-r")
            .and_then(|r| r.strip_suffix(".toml"))
            .and_then(|r| r.parse::<u64>().ok())
        else {
            continue;
        };
        entry.revisions.push(revision);
        if netlists.contains_key(&revision) {
            continue;
        }
        match read_attachment(&mut file, a.offset, a.length) {
            Ok((_, data)) => {
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

/// The MCAP files of a folder, by name.
pub fn files(dir: &Path) -> Result<Vec<PathBuf>, String> {
    let mut out: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| format!("{}: {e}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e == "mcap"))
        .collect();
    // `rec-drive.mcap`, `rec-drive-1.mcap`, ..., `rec-drive-10.mcap`: a DNM's files in order.
    out.sort_by_key(|p| {
        let stem = p
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        match stem.rsplit_once('-') {
            Some((head, n)) if n.parse::<u64>().is_ok() => {
                (head.to_string(), n.parse::<u64>().unwrap_or(0))
            }
            _ => (stem, 0),
        }
    });
    Ok(out)
}

/// The manifest of a session folder, built from its files.
pub fn index(dir: &Path) -> Result<Manifest, String> {
    let mut netlists = BTreeMap::new();
    let files: Vec<FileEntry> = files(dir)?
        .iter()
        .map(|p| file_entry(p, &mut netlists))
        .collect();
    let dnms: BTreeSet<String> = files.iter().filter_map(|f| f.dnm.clone()).collect();
    let revisions: BTreeSet<u64> = files.iter().flat_map(|f| f.revisions.clone()).collect();
    Ok(Manifest {
        format: 1,
        session: dir
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default(),
        start_unix_ns: files.iter().filter_map(|f| f.start_unix_ns).min(),
        end_unix_ns: files.iter().filter_map(|f| f.end_unix_ns).max(),
        messages: files.iter().map(|f| f.messages).sum(),
        bytes: files.iter().map(|f| f.bytes).sum(),
        dnms: dnms.into_iter().collect(),
        revisions: revisions.into_iter().collect(),
        netlists: netlists.into_values().collect(),
        files,
    })
}

/// Recorders of one process write the manifest one at a time, each after closing its file, so
/// the last one written lists every file closed.
static WRITING: Mutex<()> = Mutex::new(());

/// Builds the manifest of `dir` and writes it there (atomically: a reader never sees half).
pub fn write_manifest(dir: &Path) -> Result<Manifest, String> {
    let _one = WRITING.lock().unwrap_or_else(|e| e.into_inner());
    let m = index(dir)?;
    let tmp = dir.join(format!(".{MANIFEST}.{}", std::process::id()));
    let json = serde_json::to_vec_pretty(&m).map_err(|e| e.to_string())?;
    std::fs::write(&tmp, json)
        .and_then(|_| std::fs::rename(&tmp, dir.join(MANIFEST)))
        .map_err(|e| format!("{}: {e}", dir.join(MANIFEST).display()))?;
    Ok(m)
}

/// The manifest of a session folder: the one written there if it is current (it lists exactly
/// the folder's files), else built again.
pub fn manifest(dir: &Path) -> Result<Manifest, String> {
    let names: Vec<String> = files(dir)?
        .iter()
        .filter_map(|p| p.file_name().map(|n| n.to_string_lossy().into_owned()))
        .collect();
    if let Ok(text) = std::fs::read(dir.join(MANIFEST))
        && let Ok(m) = serde_json::from_slice::<Manifest>(&text)
        && m.files.iter().map(|f| &f.name).eq(names.iter())
        && m.files.iter().all(|f| f.complete)
    {
        return Ok(m);
    }
    index(dir)
}

/// The sessions under `root`: its folders holding MCAP files, oldest first.
pub fn sessions(root: &Path) -> Result<Vec<Manifest>, String> {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
        .map_err(|e| format!("{}: {e}", root.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    dirs.sort();
    let mut out = Vec::new();
    for d in dirs {
        if files(&d).is_ok_and(|f| !f.is_empty()) {
            out.push(manifest(&d)?);
        }
    }
    out.sort_by_key(|m| (m.start_unix_ns, m.session.clone()));
    Ok(out)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn session_names_carry_the_utc_time() {
        assert_eq!(session_name("beetle", 0), "beetle-19700101T000000Z");
        assert_eq!(session_name("b", 1_795_000_000), "b-20261118T110640Z");
        assert_eq!(session_name("b", 951_782_400), "b-20000229T000000Z");
    }
}
