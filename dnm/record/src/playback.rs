//! A recording read back for a viewer: a session folder's (or one file's) messages in log-time
//! order, each port's message as the port's own bytes with its message type, and the DNMs' task
//! switches, module events and onboard sequence events as they were recorded. Nothing is
//! published anywhere: `dnm monitor --session` draws a session from this.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let parse: &dnm_record::ParseNetlist = unimplemented!();
//! use dnm_record::playback::{Playback, Played};
//! let mut session = Playback::open("recordings/beetle-20261122T081135Z".as_ref(), parse)?;
//! while let Some(item) = session.next() {
//!     if let Played::Switch { record, .. } = item {
//!         println!("{} switched to {}", record.dnm, record.to);
//!     }
//! }
//! # Ok(()) }
//! ```

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use std::sync::Arc;

use dnm_netlist::{MessageType, Netlist};
use dnm_proto::station::SequenceEvent;
use dnm_proto::{ModuleEvent, SwitchRecord};

use crate::codec::{Reading, reading_of};
use crate::replay::{Merge, OpenError, PortTopic, RecordingFilesError, inputs};

/// One thing a recording holds, at its recorded time (ns since the Unix epoch).
#[derive(Debug, Clone)]
pub enum Played {
    /// A sample of an output port, as the port's own bytes.
    Sample {
        at_unix_ns: u64,
        dnm: String,
        module: String,
        port: String,
        /// The port's message type (shared by every sample of the port).
        message: Arc<MessageType>,
        bytes: Vec<u8>,
    },
    /// A DNM's task switch.
    Switch {
        at_unix_ns: u64,
        record: SwitchRecord,
    },
    /// A module's exit, hang, restart...
    Event { at_unix_ns: u64, event: ModuleEvent },
    /// An onboard sequence's event, as the authority told its DNM's recorder.
    Sequence {
        at_unix_ns: u64,
        event: SequenceEvent,
    },
}

/// Why a recording could not be read back.
#[derive(Debug, thiserror::Error)]
pub enum PlaybackError {
    #[error(transparent)]
    Files(#[from] RecordingFilesError),
    #[error("{}: no such session folder or file (`dnm recordings` lists the sessions)", path.display())]
    Missing { path: std::path::PathBuf },
    /// No netlist in any file: the files are not a DNM's recording.
    #[error("{}: the recording holds no netlist (is it a DNM's recording?)", path.display())]
    NoNetlist { path: std::path::PathBuf },
    /// Every file lacks its summary, where the netlists are: none was closed.
    #[error(
        "{}: none of its files was closed (a recorder still writing them, or stopped before \
         closing them), so no netlist can be read; `dnm recordings` shows each file's state",
        path.display()
    )]
    NotClosed { path: std::path::PathBuf },
    /// None of the recorded netlists parses (the newest one's error).
    #[error(transparent)]
    Netlist(dnm_netlist::NetlistError),
    #[error(transparent)]
    Open(#[from] OpenError),
}

/// How a recorded channel is read back.
#[derive(Clone)]
enum Channel {
    Port(Arc<PortChannel>),
    Switches,
    Events,
    Sequences,
    /// Not read back: a standard channel whose own bytes are kept beside it, or a channel
    /// no recorded netlist knows.
    Skip,
}

/// A port's channel: whose it is, its message type, how it is read.
struct PortChannel {
    dnm: String,
    module: String,
    port: String,
    message: Arc<MessageType>,
    reading: Reading,
}

/// A recording read back in log-time order (see the module's documentation).
pub struct Playback {
    merge: Merge,
    /// The netlists it recorded, by revision.
    netlists: BTreeMap<u64, Netlist>,
    /// Ports whose own bytes are recorded beside their standard message.
    raw_ports: BTreeSet<String>,
    channels: HashMap<(Arc<str>, Arc<str>), Channel>,
    /// Messages that could not be read back (damaged, or not their port's type).
    pub unreadable: u64,
}

impl std::fmt::Debug for Playback {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Playback")
            .field("files", &self.merge.names)
            .field("revisions", &self.netlists.keys().collect::<Vec<_>>())
            .field("unreadable", &self.unreadable)
            .finish_non_exhaustive()
    }
}

impl Playback {
    /// Opens the recording at `path` (a session folder or one MCAP file); `parse` reads its
    /// netlists (each revision's).
    pub fn open(path: &Path, parse: &crate::ParseNetlist) -> Result<Self, PlaybackError> {
        if !path.exists() {
            return Err(PlaybackError::Missing {
                path: path.to_path_buf(),
            });
        }
        let files = inputs(path)?;
        let mut recorded = BTreeMap::new();
        let mut closed = false;
        for f in &files {
            closed |= crate::session::file_entry(f, &mut recorded).complete;
        }
        let mut netlists = BTreeMap::new();
        let mut newest_error = None;
        for (revision, n) in recorded {
            let name = format!("{} (revision {revision})", n.file);
            match parse(Path::new(&name), &n.text) {
                Ok(netlist) => {
                    netlists.insert(revision, netlist);
                }
                Err(e) => {
                    tracing::warn!("{name}: not read: {e}");
                    newest_error = Some(e);
                }
            }
        }
        if netlists.is_empty() {
            let path = path.to_path_buf();
            return Err(match newest_error {
                Some(e) => PlaybackError::Netlist(e),
                None if !closed => PlaybackError::NotClosed { path },
                None => PlaybackError::NoNetlist { path },
            });
        }
        let (merge, summaries) = Merge::open(&files)?;
        let raw_ports = summaries
            .iter()
            .flatten()
            .flat_map(|s| s.channels.values())
            .filter(|c| crate::is_raw(&c.topic))
            .map(|c| c.topic.trim_end_matches(crate::RAW_SUFFIX).to_string())
            .collect();
        Ok(Self {
            merge,
            netlists,
            raw_ports,
            channels: HashMap::new(),
            unreadable: 0,
        })
    }

    /// The netlists the recording holds, by revision.
    pub fn netlists(&self) -> &BTreeMap<u64, Netlist> {
        &self.netlists
    }

    /// How the channel `topic` recorded as `schema` is read back.
    fn channel(&mut self, topic: &Arc<str>, schema: &Arc<str>) -> Channel {
        let key = (topic.clone(), schema.clone());
        if let Some(c) = self.channels.get(&key) {
            return c.clone();
        }
        let c = self.decide(topic, schema);
        self.channels.insert(key, c.clone());
        c
    }

    fn decide(&self, topic: &str, schema: &str) -> Channel {
        let Ok(t) = PortTopic::of(topic) else {
            // `/<dnm>/_switches` and the like have two parts.
            return match topic.rsplit('/').next() {
                Some("_switches") => Channel::Switches,
                Some("_events") => Channel::Events,
                Some("_sequences") => Channel::Sequences,
                _ => Channel::Skip,
            };
        };
        if t.module.starts_with('_') || t.port.starts_with('_') {
            return Channel::Skip;
        }
        if !t.raw && self.raw_ports.contains(t.port_topic) {
            return Channel::Skip; // the bytes beside it are read instead
        }
        // The newest netlist that has the port gives its type.
        let message = self.netlists.values().rev().find_map(|n| {
            n.kind_of(t.module)
                .and_then(|k| k.outputs.iter().find(|p| p.name == t.port))
                .map(|p| p.message.clone())
        });
        let Some(message) = message else {
            return Channel::Skip;
        };
        match reading_of(&message, schema, t.raw) {
            // A standard message that does not carry the port's bytes exactly always has them
            // beside it (`/raw`), which is read instead.
            Ok(Reading::Standard(mapping)) if !mapping.exact() => Channel::Skip,
            Ok(reading) => Channel::Port(Arc::new(PortChannel {
                dnm: t.dnm.to_string(),
                module: t.module.to_string(),
                port: t.port.to_string(),
                message: Arc::new(message),
                reading,
            })),
            Err(_) => Channel::Skip,
        }
    }
}

impl Iterator for Playback {
    type Item = Played;

    fn next(&mut self) -> Option<Played> {
        loop {
            let m = self.merge.next()?;
            let at_unix_ns = m.time;
            let played = match self.channel(&m.topic, &m.schema) {
                Channel::Skip => continue,
                Channel::Port(c) => match c.reading.read(&c.message, &m.data) {
                    Ok(bytes) => Some(Played::Sample {
                        at_unix_ns,
                        dnm: c.dnm.clone(),
                        module: c.module.clone(),
                        port: c.port.clone(),
                        message: c.message.clone(),
                        bytes,
                    }),
                    Err(_) => None,
                },
                Channel::Switches => serde_json::from_slice(&m.data)
                    .ok()
                    .map(|record| Played::Switch { at_unix_ns, record }),
                Channel::Events => serde_json::from_slice(&m.data)
                    .ok()
                    .map(|event| Played::Event { at_unix_ns, event }),
                Channel::Sequences => serde_json::from_slice(&m.data)
                    .ok()
                    .map(|event| Played::Sequence { at_unix_ns, event }),
            };
            match played {
                Some(p) => return Some(p),
                None => self.unreadable += 1,
            }
        }
    }
}
