//! Replaying a recording into the ports of a running system: each recorded channel
//! `/<dnm>/<module>/<port>` is published again on that port in that DNM's shared memory, with its
//! event, so downstream modules run on the recorded data as if the producer were live.

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use dnm_module::protocol::{PortHeader, dnm_config, dnm_prefix, monotonic_ns, output_event};
use dnm_module::{event_service, port_service};
use dnm_netlist::MessageType;
use iceoryx2::prelude::*;

type Svc = ipc::Service;

/// How fast to replay.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Pace {
    /// At `factor` times the recorded speed (1.0: as recorded).
    Rate(f64),
    /// As fast as possible.
    Fast,
}

/// What a replay did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ReplayReport {
    pub messages: u64,
    pub channels: Vec<String>,
    pub seconds: f64,
}

/// The port bytes a recorded message came from (the inverse of [`crate::record::encode`]).
pub fn decode(message: &MessageType, data: &[u8]) -> Result<Vec<u8>, String> {
    if message.encoding == dnm_module::msg::POD_ENCODING {
        data.get(4..)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| "message shorter than its CDR header".into())
    } else if message.encoding == "application/json" {
        Ok(data.to_vec())
    } else if message.encoding == "dnm-image-rgb8" {
        Err("replaying camera frames is not supported yet".into())
    } else {
        let len = data
            .get(4..8)
            .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
            .ok_or("message shorter than its CDR header")?;
        data.get(8..8 + len)
            .map(<[u8]>::to_vec)
            .ok_or_else(|| "CDR byte sequence runs past the message".into())
    }
}

struct Target {
    publisher: iceoryx2::port::publisher::Publisher<Svc, [u8], PortHeader>,
    notifier: iceoryx2::port::notifier::Notifier<Svc>,
    message: MessageType,
}

/// Replays `bytes` (an MCAP recording) into system `system` on this machine. `only` selects
/// channels by topic (all when empty); the recorded netlist gives each port's message type.
pub fn replay(
    bytes: &[u8],
    system: Option<&str>,
    only: &[String],
    pace: Pace,
    parse: &crate::ParseNetlist<'_>,
) -> Result<ReplayReport, String> {
    crate::check_layout(bytes)?;
    // The recorded netlist: system name and port types.
    let summary = mcap::Summary::read(bytes).ok().flatten().ok_or(
        "the recording has no summary (was its DNM killed?); replay needs a finished file",
    )?;
    let text = summary
        .metadata_indexes
        .iter()
        .filter(|i| i.name == "dnm.netlist")
        .filter(|i| crate::within(bytes, i))
        .filter_map(|i| mcap::read::metadata(bytes, i).ok())
        .filter_map(|m| m.metadata.get("text").cloned())
        .next_back()
        .ok_or("the recording holds no netlist")?;
    let netlist = parse(Path::new("recorded.toml"), &text)?;
    let system = system.unwrap_or(&netlist.system).to_string();

    let mut nodes: BTreeMap<String, Node<Svc>> = BTreeMap::new();
    let mut targets: BTreeMap<String, Target> = BTreeMap::new();
    let mut messages = Vec::new();
    let mut skipped: Vec<String> = Vec::new();
    for m in crate::messages(bytes) {
        let Ok(m) = m else { break };
        let topic = m.channel.topic.clone();
        if topic.ends_with("/_switches")
            || skipped.contains(&topic)
            || (!only.is_empty() && !only.contains(&topic))
        {
            continue;
        }
        if !targets.contains_key(&topic) {
            let mut parts = topic.trim_start_matches('/').splitn(3, '/');
            let (Some(dnm), Some(module), Some(port)) = (parts.next(), parts.next(), parts.next())
            else {
                return Err(format!("channel `{topic}` is not /<dnm>/<module>/<port>"));
            };
            let message = netlist
                .kind_of(module)
                .and_then(|k| k.outputs.iter().find(|p| p.name == port))
                .map(|p| p.message.clone())
                .ok_or_else(|| format!("the recorded netlist has no output {module}.{port}"))?;
            // Checked before anything is published, so a replay never stops half-way.
            if message.encoding == "dnm-image-rgb8" {
                if only.contains(&topic) {
                    return Err(format!(
                        "{topic}: replaying camera frames is not supported yet"
                    ));
                }
                tracing::warn!(%topic, "camera frames are not replayed");
                skipped.push(topic);
                continue;
            }
            if !nodes.contains_key(dnm) {
                let config = dnm_config(&dnm_prefix(&system, dnm))?;
                let node = NodeBuilder::new()
                    .config(&config)
                    .create::<Svc>()
                    .map_err(|e| format!("node: {e:?}"))?;
                nodes.insert(dnm.to_string(), node);
            }
            let node = &nodes[dnm];
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
            targets.insert(
                topic.clone(),
                Target {
                    publisher,
                    notifier,
                    message,
                },
            );
        }
        messages.push((topic, m.log_time, m.sequence, m.data.into_owned()));
    }
    if messages.is_empty() {
        return Err(if only.is_empty() {
            "the recording holds no messages".into()
        } else {
            format!("no messages on {}", only.join(", "))
        });
    }
    messages.sort_by_key(|(_, t, _, _)| *t);
    // Subscribers connect to the new publishers before the first sample.
    std::thread::sleep(Duration::from_millis(200));
    let t0 = messages[0].1;
    let start = Instant::now();
    for (topic, time, seq, data) in &messages {
        if let Pace::Rate(factor) = pace {
            let due = Duration::from_nanos(((time - t0) as f64 / factor.max(1e-6)) as u64);
            if let Some(wait) = due.checked_sub(start.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        let target = &targets[topic];
        let payload = decode(&target.message, data).map_err(|e| format!("{topic}: {e}"))?;
        let sample = target
            .publisher
            .loan_slice_uninit(payload.len())
            .map_err(|e| format!("{topic}: {e:?}"))?;
        let mut sample = sample.write_from_slice(&payload);
        *sample.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq: u64::from(*seq),
            task_word: 0,
        };
        sample.send().map_err(|e| format!("{topic}: {e:?}"))?;
        let _ = target.notifier.notify();
        if pace == Pace::Fast {
            // Let on-input consumers keep up (their buffers hold a few samples).
            std::thread::sleep(Duration::from_micros(200));
        }
    }
    Ok(ReplayReport {
        messages: messages.len() as u64,
        channels: targets.keys().cloned().collect(),
        seconds: start.elapsed().as_secs_f64(),
    })
}
