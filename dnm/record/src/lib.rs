//! Recordings: every output port of a DNM written to MCAP by the [`record::Recorder`] (a DNM
//! plugin, off the modules' path), one folder and manifest per session ([`session`]),
//! recordings replayed into a running system ([`replay`]) or read back for a viewer
//! ([`playback`]), and their statistics ([`stats`]).
//! How a sample is stored and read back is [`codec`] (and [`standard`] for standard messages).
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
pub mod codec;
pub mod playback;
pub mod record;
pub mod replay;
pub mod session;
pub mod standard;
pub mod stats;
pub mod tap;

/// Suffix of the channel that keeps a port's own bytes beside its standard message
/// (`/<dnm>/<module>/<port>/raw`).
pub const RAW_SUFFIX: &str = "/raw";

/// Whether `topic` is the companion of a standard channel, holding the port's own bytes.
pub fn is_raw(topic: &str) -> bool {
    topic.ends_with(RAW_SUFFIX) && topic.trim_start_matches('/').split('/').count() == 4
}

/// Parses and validates a netlist stored in a recording (`file` names it in errors); the
/// caller decides what it may describe (nothing is run for a recording).
pub use dnm_netlist::ParseNetlist;

/// Largest record or decompressed chunk a recording may declare (a corrupt length would
/// otherwise be allocated as given).
const MAX_RECORD: u64 = 1 << 30;

/// Why [`check_layout`] refused a file: it is not a recording, or a length it declares cannot
/// be trusted (the file is damaged).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum LayoutError {
    #[error("not an MCAP file (no MCAP magic at its start)")]
    NotMcap,
    /// A record longer than any a recording holds, and than what is left of the file.
    #[error("corrupt recording: the record at byte {at} claims {len} bytes")]
    RecordTooLong { at: usize, len: u64 },
    #[error(
        "corrupt recording: the chunk at byte {at} claims {uncompressed} bytes \
         uncompressed from {compressed} compressed"
    )]
    ChunkTooLarge {
        at: usize,
        uncompressed: u64,
        compressed: u64,
    },
}

/// Checks the lengths an MCAP file declares before a reader trusts them: every record lies
/// within the file (the last may be cut short, as in a file still being written) and no chunk
/// claims more uncompressed bytes than its compressed data can plausibly hold.
pub fn check_layout(bytes: &[u8]) -> Result<(), LayoutError> {
    const MAGIC: &[u8] = b"\x89MCAP0\r\n";
    const CHUNK: u8 = 0x06;
    if bytes.len() < MAGIC.len() || &bytes[..MAGIC.len()] != MAGIC {
        return Err(LayoutError::NotMcap);
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
        // A chunk still being written declares no length yet: the readers stop there.
        if len == u64::MAX {
            break;
        }
        if len > left {
            if len > MAX_RECORD {
                return Err(LayoutError::RecordTooLong { at, len });
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
                return Err(LayoutError::ChunkTooLarge {
                    at,
                    uncompressed,
                    compressed,
                });
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
    type Item = Result<mcap::Message<'static>, mcap::McapError>;

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
                Err(e) => return Some(Err(e)),
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_go_across_threads_and_into_other_errors() {
        fn ok<E: std::error::Error + Send + Sync + 'static>() {}
        ok::<LayoutError>();
        ok::<codec::DecodeError>();
        ok::<codec::ReadError>();
        ok::<standard::StandardMappingError>();
        ok::<stats::ExportError>();
        ok::<session::SessionError>();
        ok::<record::RecorderStartError>();
        ok::<replay::RecordingFilesError>();
        ok::<replay::OpenError>();
        ok::<replay::ReplayError>();
        ok::<check::ParamError>();
        ok::<check::CheckError>();
    }

    #[test]
    fn lengths_a_file_cannot_hold_are_refused() {
        assert_eq!(check_layout(b"PK\x03\x04"), Err(LayoutError::NotMcap));
        let mut file = b"\x89MCAP0\r\n".to_vec();
        file.push(0x01);
        file.extend_from_slice(&(2 * MAX_RECORD).to_le_bytes());
        assert_eq!(
            check_layout(&file),
            Err(LayoutError::RecordTooLong {
                at: 8,
                len: 2 * MAX_RECORD
            })
        );
        assert_eq!(
            check_layout(&file).unwrap_err().to_string(),
            format!(
                "corrupt recording: the record at byte 8 claims {} bytes",
                2 * MAX_RECORD
            )
        );
        // A chunk the writer has not finished (its length still the placeholder): the end.
        file.truncate(9);
        file.extend_from_slice(&u64::MAX.to_le_bytes());
        file.extend_from_slice(&[0; 64]);
        assert_eq!(check_layout(&file), Ok(()));
        // Cut short, but by a length a record may have: read up to there.
        file.truncate(9);
        file.extend_from_slice(&100u64.to_le_bytes());
        assert_eq!(check_layout(&file), Ok(()));
    }
}
