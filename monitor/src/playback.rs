//! A recorded session drawn as a running one is (`dnm monitor --session DIR`): the `dnm`
//! command reads the session and writes it, frame by frame ([`PlaybackFrame`]), on this
//! process's standard input. Everything is drawn at its recorded time: the poses and paths,
//! the camera (raw RGB frames, at `camera_rate`), every numeric field (at `numeric_rate`), the
//! connection graph changing at the recorded switches, the events and the operator's layout.

use std::collections::BTreeMap;
use std::io::Read;

use anyhow::Context;
use dnm_netlist::Wiring;
use dnm_proto::ModuleRunState;
use dnm_proto::playback::{MAX_HEADER, PlaybackFrame};
use rerun::RecordingStream;

use crate::{MonitorOptions, MonitorStats, View};

/// The largest sample taken from the pipe (a port holds at most a few MiB).
const MAX_SAMPLE: u64 = 1 << 30;

/// What reading standard input as a session stream says when it is not one.
const NOT_A_SESSION: &str = "standard input is not a session stream (`dnm monitor --session DIR` writes one for --playback)";

/// Reads one frame: its header, and a sample's bytes into `payload`. `None` at the end.
fn read_frame(
    input: &mut impl Read,
    payload: &mut Vec<u8>,
) -> anyhow::Result<Option<PlaybackFrame<Wiring>>> {
    let mut len = [0u8; 4];
    let mut got = 0;
    while got < len.len() {
        match input.read(&mut len[got..]) {
            Ok(0) if got == 0 => return Ok(None),
            Ok(0) => anyhow::bail!("{NOT_A_SESSION}: it ends inside a frame's length"),
            Ok(n) => got += n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e).context("reading the session from standard input"),
        }
    }
    let len = u32::from_le_bytes(len) as u64;
    anyhow::ensure!(
        len <= MAX_HEADER as u64,
        "{NOT_A_SESSION}: a frame header of {len} bytes"
    );
    let mut head = Vec::new();
    input
        .take(len)
        .read_to_end(&mut head)
        .context("reading the session from standard input")?;
    anyhow::ensure!(
        head.len() as u64 == len,
        "{NOT_A_SESSION}: it ends inside a frame"
    );
    let frame: PlaybackFrame<Wiring> =
        serde_json::from_slice(&head).with_context(|| format!("{NOT_A_SESSION}: a bad frame"))?;
    payload.clear();
    if let PlaybackFrame::Sample { bytes, .. } = &frame {
        anyhow::ensure!(
            *bytes <= MAX_SAMPLE,
            "{NOT_A_SESSION}: a sample of {bytes} bytes"
        );
        input
            .take(*bytes)
            .read_to_end(payload)
            .context("reading the session from standard input")?;
        anyhow::ensure!(
            payload.len() as u64 == *bytes,
            "{NOT_A_SESSION}: it ends inside a sample"
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
                // A module is taken to run from the wiring that has it until an event says
                // otherwise (a recording holds no states, only what happened).
                for m in &wiring.modules {
                    view.states
                        .entry(m.name.clone())
                        .or_insert(ModuleRunState::Running);
                }
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
                let state = match event.what.as_str() {
                    "exited" | "gave_up" => Some(ModuleRunState::Failed),
                    "hung" => Some(ModuleRunState::Hung),
                    // A process started runs within milliseconds: no event says when.
                    "restarting" | "started" | "recovered" => Some(ModuleRunState::Running),
                    "stopped" => Some(ModuleRunState::Stopped),
                    _ => None,
                };
                if let Some(state) = state
                    && view.states.insert(event.module.clone(), state) != Some(state)
                {
                    view.draw_graph()?;
                }
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
