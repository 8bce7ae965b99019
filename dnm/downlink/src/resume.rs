//! A station's session taken up again: what its files hold (the copy's messages, each
//! channel's plan as written beside it), and a file a killed station left unfinished made
//! whole.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use dnm_record::tap::ChannelDesc;

use crate::copy::Copies;
use crate::ground::STEM;
use crate::protocol::Announce;

/// Channel metadata keys holding a channel's plan in the ground's files, for a restarted
/// station to know it before the rover announces it again.
const PLAN_DNM: &str = "dnm.downlink.dnm";
const PLAN_PERIOD: &str = "dnm.downlink.period_ns";
const PLAN_PRIORITY: &str = "dnm.downlink.priority";
const PLAN_ORDER: &str = "dnm.downlink.order";

/// A channel's metadata in the ground's files: the rover's, and its plan.
pub(crate) fn plan_metadata(a: &Announce) -> std::collections::BTreeMap<String, String> {
    let mut m = a.desc.metadata.clone();
    m.insert(PLAN_DNM.into(), a.dnm.clone());
    if let Some(p) = a.period_ns {
        m.insert(PLAN_PERIOD.into(), p.to_string());
    }
    m.insert(PLAN_PRIORITY.into(), a.priority.to_string());
    let order = if a.newest_first {
        "newest_first"
    } else {
        "oldest_first"
    };
    m.insert(PLAN_ORDER.into(), order.into());
    m
}

/// The announcement a channel of the ground's files was written with.
fn announce_of(channel: &mcap::Channel<'_>) -> Option<Announce> {
    let mut metadata = channel.metadata.clone();
    let dnm = metadata.remove(PLAN_DNM)?;
    let period_ns = metadata.remove(PLAN_PERIOD).and_then(|p| p.parse().ok());
    let priority = metadata.remove(PLAN_PRIORITY)?.parse().ok()?;
    let newest_first = metadata.remove(PLAN_ORDER)? == "newest_first";
    let schema = channel.schema.as_ref()?;
    Some(Announce {
        dnm,
        desc: ChannelDesc {
            topic: channel.topic.clone(),
            schema_name: schema.name.clone(),
            schema_encoding: schema.encoding.clone(),
            schema: String::from_utf8_lossy(&schema.data).into_owned(),
            message_encoding: channel.message_encoding.clone(),
            metadata,
        },
        period_ns,
        priority,
        newest_first,
    })
}

/// What the session's files already hold, by channel; the index of the next file; the
/// channels' announcements as written.
pub(crate) fn held(dir: &Path) -> (Copies, u64, HashMap<String, Announce>) {
    let mut copies = Copies::new();
    let mut announces = HashMap::new();
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
        let Ok(mut bytes) = std::fs::read(&path) else {
            continue;
        };
        if dnm_record::check_layout(&bytes).is_err() {
            tracing::warn!(file = %path.display(), "not read: its layout is not MCAP's");
            continue;
        }
        // A file of a killed station ends with its last whole chunk: it is finished now,
        // for every reader (its summary, the session's manifest).
        if !finished(&bytes) {
            match finish_killed(&path, &bytes) {
                Ok(()) => bytes = std::fs::read(&path).unwrap_or_default(),
                Err(e) => tracing::warn!(file = %path.display(), "left unfinished: {e}"),
            }
        }
        for m in dnm_record::messages(&bytes).map_while(Result::ok) {
            if !announces.contains_key(&m.channel.topic)
                && let Some(a) = announce_of(&m.channel)
            {
                announces.insert(m.channel.topic.clone(), a.clone());
                copies.entry(m.channel.topic.clone()).or_default().announce = Some(a);
            }
            copies.entry(m.channel.topic.clone()).or_default().take(
                m.log_time,
                m.sequence,
                m.data.len(),
                false,
            );
        }
    }
    (copies, next, announces)
}

/// Whether a file ends with MCAP's footer and magic (its writer finished it).
fn finished(bytes: &[u8]) -> bool {
    bytes.ends_with(mcap::MAGIC)
}

/// Rewrites a file a killed station left unfinished: its messages up to the last whole
/// chunk and its netlists, with a summary, in place of it.
fn finish_killed(path: &Path, bytes: &[u8]) -> Result<(), String> {
    let part = path.with_extension("mcap.part");
    let file = File::create(&part).map_err(|e| format!("{}: {e}", part.display()))?;
    let mut w = mcap::WriteOptions::new()
        .compression(Some(mcap::Compression::Zstd))
        .compression_level(1)
        .profile("ros2")
        .library("dnm ground")
        .create(BufWriter::new(file))
        .map_err(|e| e.to_string())?;
    // The netlists: top-level attachments, outside the chunks.
    let options = mcap::read::Options::IgnoreEndMagic.into();
    if let Ok(records) = mcap::read::LinearReader::new_with_options(bytes, options) {
        for r in records.map_while(Result::ok) {
            if let mcap::records::Record::Attachment { header, data, .. } = r {
                w.attach(&mcap::Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name,
                    media_type: header.media_type,
                    data,
                })
                .map_err(|e| e.to_string())?;
            }
        }
    }
    let mut ids: HashMap<u16, u16> = HashMap::new();
    let mut n = 0u64;
    for m in dnm_record::messages(bytes).map_while(Result::ok) {
        let id = match ids.get(&m.channel.id) {
            Some(id) => *id,
            None => {
                let schema = match &m.channel.schema {
                    Some(s) => w
                        .add_schema(&s.name, &s.encoding, &s.data)
                        .map_err(|e| e.to_string())?,
                    None => 0,
                };
                let id = w
                    .add_channel(
                        schema,
                        &m.channel.topic,
                        &m.channel.message_encoding,
                        &m.channel.metadata,
                    )
                    .map_err(|e| e.to_string())?;
                ids.insert(m.channel.id, id);
                id
            }
        };
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: m.sequence,
            log_time: m.log_time,
            publish_time: m.publish_time,
        };
        w.write_to_known_channel(&header, &m.data)
            .map_err(|e| e.to_string())?;
        n += 1;
    }
    w.finish().map_err(|e| e.to_string())?;
    w.into_inner().flush().map_err(|e| e.to_string())?;
    std::fs::rename(&part, path).map_err(|e| format!("{}: {e}", path.display()))?;
    tracing::info!(file = %path.display(), messages = n, "finished a file a killed station left");
    Ok(())
}
