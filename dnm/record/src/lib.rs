//! Recordings: every output port of a DNM written to MCAP by the [`record::Recorder`] (a DNM
//! plugin, off the modules' path), one folder and manifest per session ([`session`]),
//! recordings replayed into a running system ([`replay`]), and their statistics ([`stats`]).
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let mut node: dnm_core::Dnm = unimplemented!();
//! use dnm_record::record::{RecordOptions, Recorder};
//! let options = RecordOptions::timestamped("recordings".as_ref());
//! node.add_plugin(Box::new(Recorder::start(node.name(), node.prefix(), options)?));
//! # Ok(()) }
//! ```

pub mod check;
pub mod record;
pub mod replay;
pub mod session;
pub mod standard;
pub mod stats;

/// Suffix of the channel that keeps a port's own bytes beside its standard message
/// (`/<dnm>/<module>/<port>/raw`).
pub const RAW_SUFFIX: &str = "/raw";

/// Whether `topic` is the companion of a standard channel, holding the port's own bytes.
pub fn is_raw(topic: &str) -> bool {
    topic.ends_with(RAW_SUFFIX) && topic.trim_start_matches('/').split('/').count() == 4
}

/// Parses and validates a netlist stored in a recording (`file` names it in errors).
pub type ParseNetlist<'a> =
    dyn Fn(&std::path::Path, &str) -> Result<dnm_netlist::Netlist, String> + 'a;

/// Largest record or decompressed chunk a recording may declare (a corrupt length would
/// otherwise be allocated as given).
const MAX_RECORD: u64 = 1 << 30;

/// Checks the lengths an MCAP file declares before a reader trusts them: every record lies
/// within the file (the last may be cut short, as in a file still being written) and no chunk
/// claims more uncompressed bytes than its compressed data can plausibly hold.
pub fn check_layout(bytes: &[u8]) -> Result<(), String> {
    const MAGIC: &[u8] = b"\x89MCAP0\r\n";
    const CHUNK: u8 = 0x06;
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err("not an MCAP file (no MCAP magic at its start)".into());
    }
    let u64_at = |at: usize| -> Option<u64> {
        Some(u64::from_le_bytes(bytes.get(at..at + 8)?.try_into().ok()?))
    };
    let u32_at = |at: usize| -> Option<u32> {
        Some(u32::from_le_bytes(bytes.get(at..at + 4)?.try_into().ok()?))
    };
    let mut at = MAGIC.len();
    while at + 9 <= bytes.len() {
        let opcode = bytes[at];
        let Some(len) = u64_at(at + 1) else { break };
        let body = at + 9;
        let left = (bytes.len() - body) as u64;
        if len > left {
            if len > MAX_RECORD {
                return Err(format!(
                    "corrupt recording: the record at byte {at} claims {len} bytes"
                ));
            }
            // Cut short: the readers stop there.
            break;
        }
        if opcode == CHUNK {
            // start, end, uncompressed size, crc, compression (u32 length + name), records.
            let uncompressed = u64_at(body + 16).unwrap_or(0);
            let name_len = u64::from(u32_at(body + 28).unwrap_or(0));
            let compressed = len.saturating_sub(32 + name_len + 8);
            if uncompressed > MAX_RECORD || uncompressed > 64 * 1024 * 1024 + compressed * 1024 {
                return Err(format!(
                    "corrupt recording: the chunk at byte {at} claims {uncompressed} bytes \
                     uncompressed from {compressed} compressed"
                ));
            }
        }
        at = body + len as usize;
    }
    Ok(())
}

/// The messages of an MCAP recording in file order, up to its data end (a file cut short ends
/// with its last whole message). No length the file declares is allocated beyond 1 GiB.
pub fn messages(bytes: &[u8]) -> Messages<'_> {
    use mcap::sans_io::LinearReaderOptions;
    Messages {
        reader: mcap::sans_io::MessageReader::new_with_options(
            LinearReaderOptions::default()
                // A chunk's records may be larger than the (compressed) file; never larger
                // than any record `check_layout` lets through.
                .with_record_length_limit(MAX_RECORD as usize)
                .with_skip_end_magic(true),
        ),
        bytes,
        at: 0,
    }
}

/// See [`messages`].
pub struct Messages<'a> {
    reader: mcap::sans_io::MessageReader,
    bytes: &'a [u8],
    at: usize,
}

impl std::fmt::Debug for Messages<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Messages").field("at", &self.at).finish()
    }
}

impl Iterator for Messages<'_> {
    type Item = Result<mcap::Message<'static>, String>;

    fn next(&mut self) -> Option<Self::Item> {
        use mcap::sans_io::MessageReadEvent;
        loop {
            match self.reader.next_event()? {
                Ok(MessageReadEvent::ReadRequest(n)) => {
                    // A hint: never more than what is left.
                    let n = n.min(self.bytes.len() - self.at);
                    let buf = self.reader.insert(n);
                    let k = buf.len().min(n);
                    buf[..k].copy_from_slice(&self.bytes[self.at..self.at + k]);
                    self.reader.notify_read(k);
                    self.at += k;
                }
                Ok(MessageReadEvent::Message(m)) => return Some(Ok(m)),
                Err(e) => return Some(Err(e.to_string())),
            }
        }
    }
}

/// Whether a metadata index points inside the file (the reader would panic otherwise).
pub(crate) fn within(bytes: &[u8], idx: &mcap::records::MetadataIndex) -> bool {
    idx.offset
        .checked_add(idx.length)
        .is_some_and(|end| end <= bytes.len() as u64)
}
