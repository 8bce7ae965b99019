//! Analysing a recording: per-channel counts, rates, gaps and bytes; task switches in time
//! order; latency from each link's source to the next output of the module it feeds; and
//! channels exported to CSV for plotting.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::LayoutError;

/// One channel of a recording.
#[derive(Debug, Clone, Serialize)]
pub struct ChannelStats {
    pub topic: String,
    pub schema: String,
    pub encoding: String,
    pub messages: u64,
    pub bytes: u64,
    /// Messages per second between the first and the last.
    pub rate_hz: f64,
    /// Longest time between two messages, ms.
    pub max_gap_ms: f64,
    /// Messages missing by sequence number (not recorded).
    pub missing: u64,
}

/// Time from a link's source sample to the next output of the module it feeds.
#[derive(Debug, Clone, Serialize)]
pub struct LinkLatency {
    pub link: String,
    pub samples: usize,
    pub p50_ms: f64,
    pub p99_ms: f64,
}

#[derive(Debug, Clone, Serialize)]
pub struct Stats {
    pub duration_s: f64,
    pub messages: u64,
    pub channels: Vec<ChannelStats>,
    pub switches: Vec<serde_json::Value>,
    pub netlist_revisions: Vec<String>,
    pub links: Vec<LinkLatency>,
}

struct Seen {
    schema: String,
    encoding: String,
    times: Vec<u64>,
    seqs: Vec<u32>,
    bytes: u64,
}

/// Why [`export_csv`] wrote no CSV files, or not all of them.
#[derive(Debug, thiserror::Error)]
pub enum ExportError {
    /// The recording is not one, or is damaged.
    #[error(transparent)]
    Layout(#[from] LayoutError),
    /// The output folder could not be made.
    #[error("{}: {source}", dir.display())]
    Folder {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// A CSV file could not be created in the output folder.
    #[error("{}: {source}", path.display())]
    Create {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// Writing a CSV file failed (a full disk).
    #[error("{0}")]
    Write(#[source] std::io::Error),
}

/// Reads a recording, tolerating a missing end (a DNM that was killed); an error says why it
/// is not a readable recording.
pub fn stats(bytes: &[u8], parse: &crate::ParseNetlist) -> Result<Stats, LayoutError> {
    crate::check_layout(bytes)?;
    let mut channels: BTreeMap<String, Seen> = BTreeMap::new();
    let mut switches = Vec::new();
    for m in crate::messages(bytes) {
        let Ok(m) = m else { break };
        if crate::is_raw(&m.channel.topic) {
            // The same samples as its standard channel.
            continue;
        }
        if m.channel.topic.ends_with("/_switches") {
            if let Ok(v) = serde_json::from_slice(&m.data) {
                switches.push(v);
            }
            continue;
        }
        let e = channels
            .entry(m.channel.topic.clone())
            .or_insert_with(|| Seen {
                schema: m
                    .channel
                    .schema
                    .as_ref()
                    .map(|s| s.name.clone())
                    .unwrap_or_default(),
                encoding: m.channel.message_encoding.clone(),
                times: Vec::new(),
                seqs: Vec::new(),
                bytes: 0,
            });
        e.times.push(m.log_time);
        e.seqs.push(m.sequence);
        e.bytes += m.data.len() as u64;
    }
    let mut revisions = Vec::new();
    let mut netlist_text = None;
    if let Ok(Some(summary)) = mcap::Summary::read(bytes) {
        for idx in &summary.metadata_indexes {
            if crate::within(bytes, idx)
                && let Ok(meta) = mcap::read::metadata(bytes, idx)
                && meta.name == "dnm.netlist"
            {
                revisions.extend(meta.metadata.get("revision").cloned());
                netlist_text = meta.metadata.get("text").cloned();
            }
        }
    }
    let (mut first, mut last) = (u64::MAX, 0u64);
    let mut out = Vec::new();
    for (topic, s) in &channels {
        let n = s.times.len();
        // A damaged file may hold times out of order.
        let t0 = s.times.iter().copied().min().unwrap_or(0);
        let t1 = s.times.iter().copied().max().unwrap_or(0);
        first = first.min(t0);
        last = last.max(t1);
        let span = (t1 - t0) as f64 / 1e9;
        let max_gap = s
            .times
            .windows(2)
            .map(|w| w[1].saturating_sub(w[0]))
            .max()
            .unwrap_or(0);
        let missing = s
            .seqs
            .windows(2)
            .map(|w| u64::from(w[1].saturating_sub(w[0]).saturating_sub(1)))
            .sum();
        out.push(ChannelStats {
            topic: topic.clone(),
            schema: s.schema.clone(),
            encoding: s.encoding.clone(),
            messages: n as u64,
            bytes: s.bytes,
            rate_hz: if span > 0.0 {
                (n - 1) as f64 / span
            } else {
                0.0
            },
            max_gap_ms: max_gap as f64 / 1e6,
            missing,
        });
    }
    let links = netlist_text
        .and_then(|t| parse(Path::new("recorded.toml"), &t).ok())
        .map(|n| link_latencies(&n, &channels))
        .unwrap_or_default();
    Ok(Stats {
        duration_s: if last > first {
            (last - first) as f64 / 1e9
        } else {
            0.0
        },
        messages: out.iter().map(|c| c.messages).sum(),
        channels: out,
        switches,
        netlist_revisions: revisions,
        links,
    })
}

fn link_latencies(
    netlist: &dnm_netlist::Netlist,
    channels: &BTreeMap<String, Seen>,
) -> Vec<LinkLatency> {
    let topic = |module: &str, port: &str| {
        netlist
            .module(module)
            .map(|m| format!("/{}/{module}/{port}", m.dnm))
    };
    let mut out = Vec::new();
    for l in netlist.all_links() {
        let Some(src) = topic(&l.from.module, &l.from.port).and_then(|t| channels.get(&t)) else {
            continue;
        };
        // The consumer's outputs, merged in time order.
        let Some(kind) = netlist.kind_of(&l.to.module) else {
            continue;
        };
        let mut outs: Vec<u64> = kind
            .outputs
            .iter()
            .filter_map(|p| topic(&l.to.module, &p.name).and_then(|t| channels.get(&t)))
            .flat_map(|s| s.times.iter().copied())
            .collect();
        outs.sort_unstable();
        let mut lat = Vec::new();
        let mut j = 0;
        for &t_in in &src.times {
            while j < outs.len() && outs[j] < t_in {
                j += 1;
            }
            if let Some(&t_out) = outs.get(j) {
                lat.push(t_out - t_in);
            }
        }
        if lat.is_empty() {
            continue;
        }
        lat.sort_unstable();
        let p = |q: f64| lat[((lat.len() - 1) as f64 * q) as usize] as f64 / 1e6;
        out.push(LinkLatency {
            link: l.to_string(),
            samples: lat.len(),
            p50_ms: p(0.5),
            p99_ms: p(0.99),
        });
    }
    out
}

/// Writes each of `topics` to `<dir>/<topic with / as _>.csv`: log time, sequence, then the
/// decoded fields (fixed-size messages and JSON) or the byte count. Returns the files written.
pub fn export_csv(bytes: &[u8], topics: &[String], dir: &Path) -> Result<Vec<String>, ExportError> {
    use std::io::Write;
    crate::check_layout(bytes)?;
    std::fs::create_dir_all(dir).map_err(|source| ExportError::Folder {
        dir: dir.to_path_buf(),
        source,
    })?;
    let mut files: BTreeMap<String, (std::io::BufWriter<std::fs::File>, Vec<String>)> =
        BTreeMap::new();
    for m in crate::messages(bytes) {
        let Ok(m) = m else { break };
        if !topics.iter().any(|t| *t == m.channel.topic) {
            continue;
        }
        let schema = m.channel.schema.as_ref();
        let value = match (m.channel.message_encoding.as_str(), schema) {
            ("cdr", Some(s)) if s.encoding == "ros2msg" && m.data.len() >= 4 => {
                dnm_netlist::values::decode_pod(&String::from_utf8_lossy(&s.data), &m.data[4..])
            }
            ("json", _) => serde_json::from_slice(&m.data).ok(),
            _ => None,
        }
        .unwrap_or_else(|| serde_json::json!({ "bytes": m.data.len() }));
        let mut fields: Vec<(String, String)> = Vec::new();
        flatten("", &value, &mut fields);
        let entry = match files.entry(m.channel.topic.clone()) {
            std::collections::btree_map::Entry::Occupied(e) => e.into_mut(),
            std::collections::btree_map::Entry::Vacant(v) => {
                let name = format!(
                    "{}.csv",
                    m.channel.topic.trim_start_matches('/').replace('/', "_")
                );
                let path = dir.join(name);
                let file = match std::fs::File::create(&path) {
                    Ok(file) => file,
                    Err(source) => return Err(ExportError::Create { path, source }),
                };
                let mut w = std::io::BufWriter::new(file);
                let columns: Vec<String> = fields.iter().map(|(k, _)| k.clone()).collect();
                writeln!(w, "log_time_ns,sequence,{}", columns.join(","))
                    .map_err(ExportError::Write)?;
                v.insert((w, columns))
            }
        };
        let row: Vec<String> = entry
            .1
            .iter()
            .map(|c| {
                fields
                    .iter()
                    .find(|(k, _)| k == c)
                    .map(|(_, v)| v.clone())
                    .unwrap_or_default()
            })
            .collect();
        writeln!(entry.0, "{},{},{}", m.log_time, m.sequence, row.join(","))
            .map_err(ExportError::Write)?;
    }
    let mut written = Vec::new();
    for (topic, (mut w, _)) in files {
        w.flush().map_err(ExportError::Write)?;
        written.push(topic);
    }
    Ok(written)
}

fn flatten(prefix: &str, v: &serde_json::Value, out: &mut Vec<(String, String)>) {
    match v {
        serde_json::Value::Object(map) => {
            for (k, v) in map {
                let key = if prefix.is_empty() {
                    k.clone()
                } else {
                    format!("{prefix}.{k}")
                };
                flatten(&key, v, out);
            }
        }
        serde_json::Value::Array(items) => {
            for (i, v) in items.iter().enumerate() {
                flatten(&format!("{prefix}[{i}]"), v, out);
            }
        }
        serde_json::Value::String(s) => out.push((
            prefix.to_string(),
            format!("\"{}\"", s.replace('"', "\"\"")),
        )),
        other => out.push((prefix.to_string(), other.to_string())),
    }
}
