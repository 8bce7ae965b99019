//! A recorded session drawn as a running one is (`dnm monitor --session DIR`): the `dnm`
//! command reads the session and writes it, frame by frame ([`PlaybackFrame`]), on this
//! process's standard input. Everything is drawn at its recorded time: the poses and paths,
//! the camera (raw RGB frames, at `camera_rate`), every numeric field (at `numeric_rate`), the
//! connection graph changing at the recorded switches, the events and the operator's layout.

use std::collections::BTreeMap;
use std::io::Read;

use anyhow::Context;
use dnm_netlist::Wiring;
use dnm_proto::playback::{MAX_HEADER, PlaybackFrame};
use rerun::RecordingStream;

use crate::{MonitorOptions, MonitorStats, View};

/// The largest sample taken from the pipe (a port holds at most a few MiB).
const MAX_SAMPLE: u64 = 1 << 30;

/// Reads one frame: its header, and a sample's bytes into `payload`. `None` at the end.
fn read_frame(
    input: &mut impl Read,
    payload: &mut Vec<u8>,
) -> anyhow::Result<Option<PlaybackFrame<Wiring>>> {
    let mut len = [0u8; 4];
    match input.read_exact(&mut len) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => return Ok(None),
        Err(e) => return Err(e).context("reading the session"),
    }
    let len = u32::from_le_bytes(len) as usize;
    anyhow::ensure!(
        len <= MAX_HEADER,
        "a frame header of {len} bytes: not a session stream"
    );
    let mut head = vec![0u8; len];
    input.read_exact(&mut head).context("reading the session")?;
    let frame: PlaybackFrame<Wiring> =
        serde_json::from_slice(&head).context("a frame of the session stream")?;
    payload.clear();
    if let PlaybackFrame::Sample { bytes, .. } = &frame {
        anyhow::ensure!(*bytes <= MAX_SAMPLE, "a sample of {bytes} bytes");
        input
            .take(*bytes)
            .read_to_end(payload)
            .context("reading the session")?;
        anyhow::ensure!(
            payload.len() as u64 == *bytes,
            "the session stream ends mid-sample"
        );
    }
    Ok(Some(frame))
}

/// Draws the session read from `input` into `rec`, with `options`' rates.
pub fn play(
    input: &mut impl Read,
    rec: &RecordingStream,
    options: &MonitorOptions,
) -> anyhow::Result<MonitorStats> {
    let mut view = View::new(rec.clone(), options.clone());
    view.send_blueprint()?;
    // Per output, the time of the sample drawn last: the rates hold as they do live.
    let mut last: BTreeMap<(String, String), u64> = BTreeMap::new();
    let mut payload = Vec::new();
    while let Some(frame) = read_frame(input, &mut payload)? {
        match frame {
            PlaybackFrame::Wiring { at_unix_ns, wiring } => {
                view.clock = Some(at_unix_ns);
                view.show_wiring(wiring)?;
            }
            PlaybackFrame::Sample {
                at_unix_ns,
                module,
                port,
                ..
            } => {
                let key = (module, port);
                let image = view
                    .messages
                    .get(&key)
                    .is_some_and(|m| m.encoding == "dnm-image-rgb8");
                let rate = if image {
                    options.camera_rate
                } else {
                    options.numeric_rate
                };
                let due = last
                    .get(&key)
                    .is_none_or(|t| at_unix_ns.saturating_sub(*t) >= rate.period_ns());
                if !due {
                    continue;
                }
                last.insert(key.clone(), at_unix_ns);
                view.clock = Some(at_unix_ns);
                view.stats.samples += 1;
                view.stats.bytes += payload.len() as u64;
                let (module, port) = key;
                if image {
                    view.image(&module, &port, &payload, at_unix_ns)?;
                } else {
                    view.sample(&module, &port, "", &payload, at_unix_ns)?;
                }
            }
            PlaybackFrame::Switch { at_unix_ns, record } => {
                view.clock = Some(at_unix_ns);
                view.switched(&record.dnm, &record)?;
            }
            PlaybackFrame::Event { at_unix_ns, event } => {
                view.clock = Some(at_unix_ns);
                view.module_event(&event)?;
            }
            PlaybackFrame::Sequence { at_unix_ns, event } => {
                view.clock = Some(at_unix_ns);
                view.sequence(&event)?;
            }
        }
        view.flush_paths(false)?;
    }
    view.flush_paths(true)?;
    rec.flush_blocking()?;
    Ok(view.stats.clone())
}
