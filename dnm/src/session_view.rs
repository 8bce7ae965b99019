//! `dnm monitor --session DIR`: a recorded session drawn the way the monitor draws a running
//! system (the operator's layout, the rover in `world`, the camera, every numeric field, the
//! connection graph changing at the recorded switches, the events), into a viewer or an `.rrd`.
//!
//! This command reads the session (MCAP, with the netlists it recorded) and hands it to
//! `dnm-monitor --playback` on a pipe, a frame per message ([`dnm::proto::playback`]): the
//! Rerun SDK stays in the monitor, the recording's reader here.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use dnm::playback::{Playback, Played};
use dnm::proto::playback::PlaybackFrame;
use dnm_netlist::{Netlist, Wiring};

/// What was handed to the monitor.
#[derive(Debug, Default)]
struct Fed {
    samples: u64,
    switches: u64,
    events: u64,
}

/// Turns what a recording holds into the monitor's frames: a wiring each time the revision or
/// the task in force changes, then what was recorded.
struct Feed {
    netlists: BTreeMap<u64, Netlist>,
    /// The (revision, task) whose wiring was sent last.
    current: Option<(u64, Option<String>)>,
    /// The task in force when the session began, as its first switch tells (where from).
    at_start: Option<String>,
    fed: Fed,
}

impl Feed {
    fn new(netlists: BTreeMap<u64, Netlist>, at_start: Option<String>) -> Self {
        Self {
            netlists,
            current: None,
            at_start,
            fed: Fed::default(),
        }
    }

    /// The netlist of `revision`: its own, else the newest recorded before it.
    fn netlist(&self, revision: u64) -> Option<&Netlist> {
        self.netlists
            .range(..=revision)
            .next_back()
            .or_else(|| self.netlists.iter().next())
            .map(|(_, n)| n)
    }

    /// Sends the wiring of `revision` with `task` in force, unless it is the one in force.
    fn wiring(
        &mut self,
        out: &mut impl Write,
        at_unix_ns: u64,
        dnm: &str,
        revision: u64,
        task: Option<&str>,
    ) -> std::io::Result<()> {
        let now = (revision, task.map(str::to_string));
        if self.current.as_ref() == Some(&now) {
            return Ok(());
        }
        let Some(netlist) = self.netlist(revision) else {
            return Ok(());
        };
        let wiring = Wiring::of(netlist, dnm, revision, task);
        self.current = Some(now);
        frame(out, &PlaybackFrame::Wiring { at_unix_ns, wiring }, &[])
    }

    fn item(&mut self, out: &mut impl Write, item: Played) -> std::io::Result<()> {
        if self.current.is_none() {
            // Before the first switch recorded: the first netlist, with the task that switch
            // left (a session begun mid-mission), else the netlist's initial one.
            if let Some((&revision, n)) = self.netlists.iter().next() {
                let task = self
                    .at_start
                    .clone()
                    .or_else(|| n.initial_task().map(str::to_string));
                let at = at_of(&item);
                self.wiring(out, at, "", revision, task.as_deref())?;
            }
        }
        match item {
            Played::Sample {
                at_unix_ns,
                dnm,
                module,
                port,
                bytes,
                ..
            } => {
                self.fed.samples += 1;
                let head = PlaybackFrame::<Wiring>::Sample {
                    at_unix_ns,
                    dnm,
                    module,
                    port,
                    bytes: bytes.len() as u64,
                };
                frame(out, &head, &bytes)
            }
            Played::Switch { at_unix_ns, record } => {
                self.fed.switches += 1;
                let (dnm, revision, to) = (record.dnm.clone(), record.revision, record.to.clone());
                self.wiring(out, at_unix_ns, &dnm, revision, Some(&to))?;
                frame(out, &PlaybackFrame::Switch { at_unix_ns, record }, &[])
            }
            Played::Event { at_unix_ns, event } => {
                self.fed.events += 1;
                frame(out, &PlaybackFrame::Event { at_unix_ns, event }, &[])
            }
            Played::Sequence { at_unix_ns, event } => {
                self.fed.events += 1;
                frame(out, &PlaybackFrame::Sequence { at_unix_ns, event }, &[])
            }
        }
    }
}

fn at_of(item: &Played) -> u64 {
    match item {
        Played::Sample { at_unix_ns, .. }
        | Played::Switch { at_unix_ns, .. }
        | Played::Event { at_unix_ns, .. }
        | Played::Sequence { at_unix_ns, .. } => *at_unix_ns,
    }
}

/// The task in force when the session at `dir` began: where its first switch switched from
/// (none when it started the session).
fn task_at_start(dir: &Path) -> Option<String> {
    let session = Playback::open(dir, &dnm::parse_recorded_netlist).ok()?;
    session
        .into_iter()
        .find_map(|item| match item {
            Played::Switch { record, .. } => Some(record.from),
            _ => None,
        })
        .flatten()
}

/// One frame: its header's length, the header, its payload.
fn frame(
    out: &mut impl Write,
    head: &PlaybackFrame<Wiring>,
    payload: &[u8],
) -> std::io::Result<()> {
    let head = serde_json::to_vec(head)?;
    if head.len() > dnm::proto::playback::MAX_HEADER {
        return Err(std::io::Error::other(format!(
            "a frame of {} bytes, more than the monitor takes (a netlist of that size?)",
            head.len()
        )));
    }
    out.write_all(&(head.len() as u32).to_le_bytes())?;
    out.write_all(&head)?;
    out.write_all(payload)
}

/// `--session DIR` (or `--session=DIR`) out of `args`: the folder, and the other arguments.
pub fn session_arg(args: &[String]) -> anyhow::Result<Option<(PathBuf, Vec<String>)>> {
    let mut rest = Vec::new();
    let mut session = None;
    let mut it = args.iter();
    while let Some(a) = it.next() {
        if a == "--session" {
            let dir = it.next().context(
                "--session needs a session folder (or an MCAP file): `dnm recordings` lists them",
            )?;
            session = Some(PathBuf::from(dir));
        } else if let Some(dir) = a.strip_prefix("--session=") {
            session = Some(PathBuf::from(dir));
        } else {
            rest.push(a.clone());
        }
    }
    Ok(session.map(|s| (s, rest)))
}

/// `dnm monitor --session DIR ARGS`: draws the session at `dir` with the monitor's `args`
/// (`--save FILE.rrd`, `--viewer URL`; else a viewer is started).
pub fn run(dir: &Path, args: &[String]) -> anyhow::Result<ExitCode> {
    let mut playback =
        Playback::open(dir, &dnm::parse_recorded_netlist).context("reading the session")?;
    let mut all = vec!["--playback".to_string()];
    all.extend(args.iter().cloned());
    let mut child = crate::monitor_cmd::start_piped(&all)?;
    let pipe = child.stdin.take().context("the monitor's standard input")?;
    let mut out = std::io::BufWriter::with_capacity(1 << 20, pipe);
    let mut feed = Feed::new(playback.netlists().clone(), task_at_start(dir));
    let mut fed = Ok(());
    for item in playback.by_ref() {
        fed = feed.item(&mut out, item);
        if fed.is_err() {
            break;
        }
    }
    let fed = fed.and_then(|()| out.flush());
    drop(out);
    let status = child.wait().context("waiting for the monitor")?;
    if !status.success() {
        anyhow::bail!("the monitor failed ({status}): see its message above");
    }
    // The monitor read everything unless it said otherwise: a pipe it closed early is its.
    fed.context("handing the session to the monitor")?;
    eprintln!(
        "session {}: {} samples, {} switches, {} events drawn{}",
        dir.display(),
        feed.fed.samples,
        feed.fed.switches,
        feed.fed.events,
        match playback.unreadable {
            0 => String::new(),
            n => format!(" ({n} messages unreadable, left out)"),
        }
    );
    Ok(ExitCode::SUCCESS)
}
