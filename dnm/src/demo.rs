//! `dnm demo`: the whole simulated Beetle-One on this machine, and its mission driven the way
//! operators would drive it: through a ground station (its outbox, the rover's authority,
//! every DNM switching at one instant) and over Zenoh. Joystick driving, then the exploration
//! sequence (`configs/sequences/explore.toml`), uploaded through the station and carried out on
//! board by the authority with no command from the ground: a switch to the autopilot until it
//! reports every waypoint reached, the camera narrowed while the rover runs, a switch back to
//! the joystick. Then a summary.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use bytemuck::Pod;
use dnm::admin::{Request, Response};
use dnm::host::Host;
use dnm::{HostOptions, SwitchRecord};
use dnm_netlist::Netlist;
use dnm_rover::msgs::{BatteryState, Odometry, Progress, Range, WatchdogState, WorldState};
use serde::Serialize;
use zenoh::Wait;

/// The Beetle-One netlist, built in so the demo runs from any folder.
const BEETLE: &str = include_str!("../../configs/beetle.toml");
/// Its exploration sequence, likewise.
const EXPLORE: &str = include_str!("../../configs/sequences/explore.toml");
const EXPLORE_FILE: &str = "configs/sequences/explore.toml";

/// How far odometry may be from the simulator's ground truth at the end: 0.1 m plus 1 % of
/// the distance driven (encoder quantisation, sampling, and the lag between the two readings).
fn tolerance(distance: f64) -> f64 {
    0.1 + 0.01 * distance
}

#[derive(Debug, Clone)]
pub struct DemoArgs {
    pub netlist: Option<PathBuf>,
    /// The sequence the rover runs on board (default: the built-in exploration).
    pub sequence: Option<PathBuf>,
    pub keep_running: bool,
    pub json: bool,
    /// Seconds of joystick driving before and after the autopilot.
    pub teleop_s: f64,
    /// Record every port to MCAP.
    pub record: Option<dnm::record::RecordOptions>,
    /// Watch the mission in Rerun.
    pub rerun: Option<RerunOut>,
    /// Serve the station's web interface here while the demo runs.
    pub web: Option<std::net::SocketAddr>,
}

/// Where `dnm demo --rerun` shows the mission.
#[derive(Debug, Clone)]
pub enum RerunOut {
    /// A viewer started from the PATH, else an .rrd under `recordings/`.
    Auto,
    Save(PathBuf),
}

/// Waits (a minute at most) until the monitor announces it is watching (a liveliness token
/// under `<system>/monitor/`), so the mission it shows starts at the beginning.
fn wait_for_monitor(
    session: &zenoh::Session,
    system: &str,
    monitor: &mut std::process::Child,
    quiet: bool,
) {
    let deadline = Instant::now() + Duration::from_secs(60);
    while Instant::now() < deadline {
        if let Ok(Some(status)) = monitor.try_wait() {
            if !quiet {
                println!("Rerun: the monitor stopped ({status}); the mission goes on without it");
            }
            return;
        }
        let found = session
            .liveliness()
            .get(format!("{system}/monitor/*"))
            .timeout(Duration::from_secs(1))
            .wait()
            .is_ok_and(|r| r.recv().is_ok_and(|r| r.result().is_ok()));
        if found {
            return;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    if !quiet {
        println!("Rerun: the monitor is not watching yet; the mission starts without waiting");
    }
}

/// Starts `dnm-monitor` on the demo's Zenoh network (reached at `endpoint`).
fn start_monitor(
    out: &RerunOut,
    system: &str,
    endpoint: &str,
    quiet: bool,
) -> anyhow::Result<std::process::Child> {
    let mut args: Vec<String> = vec![
        "--system".into(),
        system.into(),
        "--connect".into(),
        endpoint.into(),
        "--no-multicast".into(),
    ];
    let save = match out {
        RerunOut::Auto if crate::monitor_cmd::viewer_available() => None,
        RerunOut::Auto => {
            let stamp = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            std::fs::create_dir_all("recordings").context("creating recordings/")?;
            Some(PathBuf::from(format!("recordings/demo-{stamp}.rrd")))
        }
        RerunOut::Save(p) => Some(p.clone()),
    };
    match &save {
        Some(p) => {
            if !quiet {
                println!(
                    "Rerun: saving to {} (open it with `rerun {}`)",
                    p.display(),
                    p.display()
                );
            }
            args.extend(["--save".into(), p.display().to_string()]);
        }
        None => {
            if !quiet {
                println!("Rerun: starting a viewer");
            }
            args.push("--spawn".into());
        }
    }
    crate::monitor_cmd::start(&args)
}

/// Reads last values of ports over Zenoh, as any operator tool would.
struct Probe<'a> {
    session: &'a zenoh::Session,
    netlist: &'a Netlist,
}

impl Probe<'_> {
    fn get<T: Pod>(&self, module: &str, port: &str) -> Option<T> {
        let dnm = &self.netlist.module(module)?.dnm;
        let key = dnm::keys::port(&self.netlist.system, dnm, module, port);
        let replies = self
            .session
            .get(key)
            .timeout(Duration::from_secs(2))
            .wait()
            .ok()?;
        let reply = replies.recv().ok()?;
        let sample = reply.result().ok()?;
        let bytes = sample.payload().to_bytes();
        (bytes.len() == size_of::<T>()).then(|| bytemuck::pod_read_unaligned(&bytes))
    }

    fn request(&self, req: &Request) -> anyhow::Result<Response> {
        let r = dnm::remote::request(
            self.session,
            &self.netlist.system,
            req,
            Duration::from_secs(10),
        )
        .map_err(anyhow::Error::msg)?;
        if !r.ok {
            bail!("{}", r.error.unwrap_or_default());
        }
        Ok(r)
    }
}

/// What the status line shows.
#[derive(Debug, Default, Clone, Copy)]
struct Snapshot {
    truth: WorldState,
    odom: Odometry,
    battery: BatteryState,
    progress: Progress,
    range: Range,
    watchdog: WatchdogState,
}

impl Snapshot {
    fn read(p: &Probe<'_>) -> Option<Snapshot> {
        Some(Snapshot {
            truth: p.get("world", "state")?,
            odom: p.get("odometry", "odom")?,
            battery: p.get("battery", "state").unwrap_or_default(),
            progress: p.get("autopilot", "progress").unwrap_or_default(),
            range: p.get("range", "range").unwrap_or_default(),
            watchdog: p.get("watchdog", "state").unwrap_or_default(),
        })
    }

    fn pose_error(&self) -> (f64, f64) {
        let d = (self.truth.x - self.odom.x).hypot(self.truth.y - self.odom.y);
        let yaw = dnm_rover::kinematics::wrap(self.truth.yaw - self.odom.yaw);
        (d, yaw.to_degrees().abs())
    }
}

/// A switch as the mission saw it: the slowest DNM's switch time and every DNM's.
#[derive(Debug, Serialize)]
struct SwitchSummary {
    from: Option<String>,
    to: String,
    at_s: f64,
    revision: u64,
    slowest_ns: u64,
    per_dnm_ns: Vec<(String, u64)>,
    /// What asked for it: `station` (an operator's command) or `sequence` (a step on board).
    by: String,
    /// From the operator's command (or the sequence reaching the step) to the decided
    /// instant, ms.
    command_to_switch_ms: f64,
    /// Between the first and the last DNM of the rover to switch, µs.
    spread_us: f64,
}

/// What the exploration sequence did, as the mission saw it.
struct Explored {
    /// Odometry against the truth at rest on the last waypoint, m.
    at_rest_error: f64,
    replaced: String,
    revision: u64,
    summary: SequenceSummary,
}

/// The sequence as the rover reported it.
#[derive(Debug, Serialize)]
struct SequenceSummary {
    name: String,
    /// `finished`, `aborted`...
    state: String,
    steps: usize,
    duration_s: f64,
    /// Why it stopped, if it was aborted.
    why: String,
    /// Its events, in words.
    events: Vec<String>,
}

#[derive(Debug, Serialize)]
struct Summary {
    ok: bool,
    duration_s: f64,
    distance_m: f64,
    odometry_distance_m: f64,
    waypoints_reached: u64,
    waypoints_total: u64,
    final_pose_truth: [f64; 3],
    final_pose_odometry: [f64; 3],
    final_position_error_m: f64,
    final_heading_error_deg: f64,
    position_tolerance_m: f64,
    at_rest_position_error_m: f64,
    switches: Vec<SwitchSummary>,
    /// The exploration sequence as the rover carried it out.
    sequence: Option<SequenceSummary>,
    replaced: String,
    revision: u64,
    module_messages: u64,
    zenoh_messages: u64,
    zenoh_bytes: u64,
    watchdog_trips: u64,
    battery_charge: f64,
    problems: Vec<String>,
}

struct Mission<'a> {
    probe: Probe<'a>,
    station: &'a dnm_ground::Station,
    start: Instant,
    json: bool,
    tty: bool,
    task: String,
    last_line: Instant,
    switches: Vec<SwitchSummary>,
}

impl Mission<'_> {
    fn t(&self) -> f64 {
        self.start.elapsed().as_secs_f64()
    }

    fn say(&mut self, msg: &str) {
        if !self.json {
            if self.tty {
                print!("\r\x1b[2K");
            }
            println!("[{:6.1} s] {msg}", self.t());
        }
    }

    /// The live one-line status.
    fn status(&mut self, s: &Snapshot) {
        if self.json {
            return;
        }
        let every = if self.tty {
            Duration::from_millis(250)
        } else {
            Duration::from_secs(2)
        };
        if self.last_line.elapsed() < every {
            return;
        }
        self.last_line = Instant::now();
        let (err, _) = s.pose_error();
        let line = format!(
            "[{:6.1} s] {:<6} x {:6.2} y {:6.2} yaw {:5.0}° v {:4.2} m/s | odometry error {:4.2} m | battery {:4.1} V {:3.0}% | waypoints {}/{} | range {:3.1} m{}",
            self.t(),
            self.task,
            s.truth.x,
            s.truth.y,
            s.truth.yaw.to_degrees(),
            s.truth.linear,
            err,
            s.battery.voltage,
            s.battery.charge * 100.0,
            s.progress.reached,
            s.progress.total,
            s.range.range,
            if s.watchdog.tripped == 1 {
                " | WATCHDOG STOP"
            } else {
                ""
            }
        );
        if self.tty {
            print!("\r\x1b[2K{line}");
            let _ = std::io::stdout().flush();
        } else {
            println!("{line}");
        }
    }

    /// Watches the rover for `seconds`, or until `done` says so; returns the last snapshot.
    fn watch(&mut self, seconds: f64, mut done: impl FnMut(&Snapshot) -> bool) -> Option<Snapshot> {
        let until = Instant::now() + Duration::from_secs_f64(seconds);
        let mut last = None;
        while Instant::now() < until {
            if let Some(s) = Snapshot::read(&self.probe) {
                self.status(&s);
                last = Some(s);
                if done(&s) {
                    break;
                }
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        last
    }

    /// Gives the ground station `order` and waits until the rover applied it.
    fn command(&mut self, order: dnm_proto::station::Order) -> anyhow::Result<(u64, u64)> {
        use dnm_proto::station::Fate;
        let entry = self.station.submit(order)?;
        let done = self
            .station
            .wait(entry.seq, Duration::from_secs(60))
            .context("the command vanished from the outbox")?;
        match done.fate {
            Some(Fate::Applied {
                revision,
                at_unix_ns,
                ..
            }) => {
                // Decided for an instant that may still be a few milliseconds ahead.
                let ahead = at_unix_ns.saturating_sub(dnm_ground::now_unix_ns());
                std::thread::sleep(Duration::from_nanos(ahead) + Duration::from_millis(20));
                Ok((revision, at_unix_ns))
            }
            Some(Fate::Refused { reason }) => {
                bail!("the rover refused command {}: {reason}", entry.seq)
            }
            other => bail!("command {} not applied within 60 s: {other:?}", entry.seq),
        }
    }

    /// Gives the ground station `order` (one that changes nothing the DNMs run) and waits until
    /// the rover took it; returns what the rover says it did.
    fn order(&mut self, order: dnm_proto::station::Order) -> anyhow::Result<String> {
        use dnm_proto::station::Fate;
        let entry = self.station.submit(order)?;
        let done = self
            .station
            .wait(entry.seq, Duration::from_secs(60))
            .context("the command vanished from the outbox")?;
        match done.fate {
            Some(Fate::Done { detail, .. }) => Ok(detail),
            Some(Fate::Refused { reason }) => {
                bail!("the rover refused command {}: {reason}", entry.seq)
            }
            other => bail!("command {} not done within 60 s: {other:?}", entry.seq),
        }
    }

    /// Uploads the exploration sequence, starts it, and follows it until the rover says it
    /// ended: its events as they come, the rover's state, its switches.
    fn explore(&mut self, netlist: &Netlist, args: &DemoArgs) -> anyhow::Result<Explored> {
        use dnm_proto::station::{Order, SequenceAction, SequenceState};
        let (file, text) = match &args.sequence {
            Some(p) => (
                p.display().to_string(),
                std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?,
            ),
            None => (EXPLORE_FILE.to_string(), EXPLORE.to_string()),
        };
        let sequence = dnm_netlist::Sequence::parse(Path::new(&file), &text, netlist)?;
        let name = sequence.name.clone();
        let said = self.order(Order::Sequence {
            name: name.clone(),
            action: SequenceAction::Upload {
                file,
                text,
                netlists: Default::default(),
            },
        })?;
        self.say(&format!("uploaded through the ground station: {said}"));
        let started = dnm_ground::now_unix_ns();
        let said = self.order(Order::Sequence {
            name: name.clone(),
            action: SequenceAction::Start,
        })?;
        self.say(&format!("{said}; from here the rover runs on its own"));
        let reached_all =
            |s: &Snapshot| s.progress.total > 0 && s.progress.reached == s.progress.total;
        let mut at_rest_error = f64::NAN;
        let mut told = 0usize;
        let until = Instant::now() + Duration::from_secs(300);
        let q = loop {
            if let Some(s) = Snapshot::read(&self.probe) {
                self.status(&s);
                // At rest on the last waypoint: the pose estimates compared.
                if at_rest_error.is_nan()
                    && reached_all(&s)
                    && s.truth.linear.abs() < 1e-3
                    && s.odom.linear.abs() < 1e-3
                {
                    at_rest_error = s.pose_error().0;
                }
            }
            let q = self
                .station
                .link()
                .rover
                .and_then(|r| r.sequences.into_iter().find(|q| q.name == name));
            if let Some(q) = &q {
                let events: Vec<_> = q
                    .history
                    .iter()
                    .filter(|e| e.at_unix_ns >= started)
                    .cloned()
                    .collect();
                for e in events.iter().skip(told) {
                    self.said_on_board(e)?;
                }
                told = told.max(events.len());
                if matches!(q.state, SequenceState::Finished | SequenceState::Aborted)
                    && q.history.iter().any(|e| e.at_unix_ns >= started)
                {
                    break q.clone();
                }
            }
            if Instant::now() > until {
                bail!("the sequence `{name}` did not end within 300 s: {q:?}");
            }
            std::thread::sleep(Duration::from_millis(100));
        };
        let events: Vec<_> = q
            .history
            .iter()
            .filter(|e| e.at_unix_ns >= started)
            .collect();
        let edit = events
            .iter()
            .zip(events.iter().skip(1))
            .find(|(a, b)| {
                a.what == "step_started" && a.detail.starts_with("replace") && b.in_force.is_some()
            })
            .map(|(a, b)| {
                (
                    a.detail.clone(),
                    b.in_force.clone().unwrap_or_else(|| unreachable!()),
                )
            });
        let state = serde_json::to_value(q.state)?
            .as_str()
            .unwrap_or_default()
            .to_string();
        Ok(Explored {
            at_rest_error,
            // "replace module `camera` fov_deg=40" -> "camera: fov_deg=40 (revision 2)..."
            replaced: edit
                .as_ref()
                .map(|(what, f)| {
                    let what = what
                        .trim_start_matches("replace module ")
                        .replacen('`', "", 2);
                    let what = what.replacen(' ', ": ", 1);
                    format!("{what} (revision {}), by the sequence on board", f.revision)
                })
                .unwrap_or_default(),
            revision: edit.map_or(0, |(_, f)| f.revision),
            summary: SequenceSummary {
                name,
                state,
                steps: q.steps,
                duration_s: events
                    .last()
                    .map_or(0.0, |e| e.at_unix_ns.saturating_sub(started) as f64 / 1e9),
                why: q.why.clone(),
                events: events
                    .iter()
                    .map(|e| {
                        let step = e.step.map_or(String::new(), |s| format!(" step {}", s + 1));
                        format!("{}{step}: {}", e.what, e.detail)
                    })
                    .collect(),
            },
        })
    }

    /// Says what the sequence did on board; a switch it made is measured like an operator's.
    fn said_on_board(&mut self, e: &dnm_proto::station::SequenceEvent) -> anyhow::Result<()> {
        let step = e.step.map_or(String::new(), |s| format!(" step {}", s + 1));
        self.say(&format!("on board: {}{step}: {}", e.what, e.detail));
        if let Some(f) = &e.in_force
            && let Some(task) = f.task.as_ref().filter(|t| **t != self.task)
        {
            let task = task.clone();
            // Decided for an instant that may still be a few milliseconds ahead.
            let ahead = f.at_unix_ns.saturating_sub(dnm_ground::now_unix_ns());
            std::thread::sleep(Duration::from_nanos(ahead) + Duration::from_millis(20));
            let step_started = e.at_unix_ns.min(f.at_unix_ns);
            self.switched(&task, f.revision, step_started, f.at_unix_ns, "sequence")?;
        }
        Ok(())
    }

    fn switch(&mut self, task: &str) -> anyhow::Result<()> {
        let asked = dnm_ground::now_unix_ns();
        let (revision, at) = self.command(dnm_proto::station::Order::Switch {
            task: task.into(),
            at_unix_ns: None,
            late_by_ms: None,
        })?;
        self.switched(task, revision, asked, at, "station")
    }

    /// Reads what the rover's DNMs recorded of the switch to `task` in `revision`, decided
    /// for `at` after it was asked for at `asked`, and says so.
    fn switched(
        &mut self,
        task: &str,
        revision: u64,
        asked: u64,
        at: u64,
        by: &str,
    ) -> anyhow::Result<()> {
        // Each DNM of the rover recorded its switch; those across the radio follow later.
        let status = self.probe.request(&Request::Status)?;
        let records: Vec<SwitchRecord> = status
            .dnms
            .iter()
            .filter(|d| self.probe.netlist.dnm(&d.dnm).is_some_and(|n| !n.radio))
            .filter_map(|d| {
                d.switches
                    .iter()
                    .rev()
                    .find(|s| s.to == task && s.revision == revision)
                    .cloned()
            })
            .collect();
        let slowest = records.iter().map(|s| s.duration_ns).max().unwrap_or(0);
        let stamps = records.iter().map(|s| s.at_ns);
        let spread = stamps.clone().max().unwrap_or(0) - stamps.min().unwrap_or(0);
        let summary = SwitchSummary {
            from: records.first().and_then(|s| s.from.clone()),
            to: task.to_string(),
            at_s: self.t(),
            revision,
            slowest_ns: slowest,
            per_dnm_ns: records
                .iter()
                .map(|s| (s.dnm.clone(), s.duration_ns))
                .collect(),
            by: by.to_string(),
            command_to_switch_ms: at.saturating_sub(asked) as f64 / 1e6,
            spread_us: spread as f64 / 1e3,
        };
        let how = if by == "station" {
            "through the ground station: {} ms from command to the instant"
        } else {
            "by the sequence on board: {} ms from the step to the instant"
        };
        self.say(&format!(
            "switched {} -> {task} {}, {} rover DNMs within {:.0} µs of each other; slowest switch inside a DNM {:.2} µs",
            summary.from.as_deref().unwrap_or("?"),
            how.replace("{}", &format!("{:.0}", summary.command_to_switch_ms)),
            records.len(),
            summary.spread_us,
            slowest as f64 / 1000.0
        ));
        self.switches.push(summary);
        self.task = task.to_string();
        Ok(())
    }
}

fn load(args: &DemoArgs) -> anyhow::Result<Netlist> {
    let loaded = match &args.netlist {
        Some(p) => dnm::load_netlist(p),
        None if Path::new("configs/beetle.toml").exists() => {
            dnm::load_netlist(Path::new("configs/beetle.toml"))
        }
        None => dnm::parse_netlist(Path::new("configs/beetle.toml"), BEETLE),
    };
    let netlist = loaded.map_err(|e| anyhow::anyhow!("{e}"))?;
    for needed in ["world", "odometry", "autopilot", "camera", "joystick"] {
        if netlist.module(needed).is_none() {
            bail!(
                "{}: the demo drives Beetle-One and needs a module `{needed}`; start from configs/beetle.toml",
                netlist.file.display()
            );
        }
    }
    for task in ["teleop", "auto"] {
        if !netlist.tasks.contains_key(task) {
            bail!("{}: the demo needs task `{task}`", netlist.file.display());
        }
    }
    if !dnm::commanded_by_authority(&netlist) {
        bail!(
            "{}: the demo commands the rover through a ground station and needs `authority` in [system]",
            netlist.file.display()
        );
    }
    Ok(netlist)
}

pub fn run(zenoh: &dnm::ZenohOptions, args: &DemoArgs) -> anyhow::Result<ExitCode> {
    let netlist = load(args)?;
    let dnms: Vec<String> = netlist.dnms.iter().map(|d| d.name.clone()).collect();
    let mut options = HostOptions::standard().context("locating the module host")?;
    options.record = args.record.clone().map(|o| o.into_session(&netlist.system));
    let tty = std::io::stdout().is_terminal() && !args.json;
    if !args.json {
        println!(
            "Beetle-One (system `{}`): DNMs {} on this machine, {} modules; Zenoh peer embedded",
            netlist.system,
            dnms.join(", "),
            netlist.modules.len()
        );
        if let Some(r) = &options.record {
            println!(
                "recording the session to {}/ (every DNM's files and manifest.json)",
                r.dir.display()
            );
        }
    }
    // A fresh rover and ground station each run: the authority's and the outbox's databases
    // live in a folder of their own.
    let state = std::env::temp_dir().join(format!("dnm-demo-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&state);
    options.state_dir = Some(state.clone());
    // With Rerun, the monitor (a process of its own, as on a real ground station) joins the
    // demo's Zenoh network on a known loopback port.
    let mut zenoh = zenoh.clone();
    let monitor_endpoint = match &args.rerun {
        Some(_) if zenoh.config.is_none() && zenoh.listen.is_empty() => {
            let port = std::net::TcpListener::bind("127.0.0.1:0")?
                .local_addr()?
                .port();
            let e = format!("tcp/127.0.0.1:{port}");
            zenoh.listen = vec![e.clone()];
            Some(e)
        }
        Some(_) => Some(
            zenoh
                .listen
                .first()
                .map(|e| e.replace("0.0.0.0", "127.0.0.1"))
                .context("--rerun with a Zenoh configuration file: also give --listen")?,
        ),
        None => None,
    };
    let host = Host::start(netlist.clone(), &dnms, options, zenoh.config()?)?;
    let mut monitor = match (&args.rerun, &monitor_endpoint) {
        (Some(out), Some(endpoint)) => {
            match start_monitor(out, &netlist.system, endpoint, args.json) {
                Ok(m) => Some(m),
                Err(e) => {
                    host.stop();
                    return Err(e);
                }
            }
        }
        _ => None,
    };
    if let Some(m) = &mut monitor {
        wait_for_monitor(host.session(), &netlist.system, m, args.json);
    }
    let station = match dnm_ground::Station::start(
        host.session().clone(),
        dnm_ground::StationOptions::new(&netlist.system, "demo-station", state.join("ground.redb")),
    ) {
        Ok(s) => s,
        Err(e) => {
            if let Some(m) = monitor {
                crate::monitor_cmd::stop(m);
            }
            host.stop();
            return Err(e.into());
        }
    };
    let station = std::sync::Arc::new(station);
    let web = match args.web {
        None => None,
        Some(addr) => match dnm_ground::http::Api::serve(station.clone(), addr) {
            Ok(api) => {
                eprintln!("the ground station's web interface: http://{}/", api.addr());
                Some(api)
            }
            Err(e) => {
                if let Some(m) = monitor {
                    crate::monitor_cmd::stop(m);
                }
                drop(station);
                host.stop();
                return Err(anyhow::anyhow!(e));
            }
        },
    };
    let result = mission(&host, &station, &netlist, args, tty);
    let summary = match result {
        Ok(s) => s,
        Err(e) => {
            if let Some(m) = monitor {
                crate::monitor_cmd::stop(m);
            }
            drop(web);
            drop(station);
            host.stop();
            let _ = std::fs::remove_dir_all(&state);
            return Err(e);
        }
    };
    if args.json {
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        print_summary(&summary);
    }
    if args.keep_running {
        if !args.json {
            println!(
                "still running (task `teleop`); try `dnm status --system {}` or the Zenoh keys in README.md; Ctrl-C to stop",
                netlist.system
            );
        }
        host.wait();
    } else {
        host.stop();
    }
    if let Some(m) = monitor {
        crate::monitor_cmd::stop(m);
    }
    drop(web);
    drop(station);
    let _ = std::fs::remove_dir_all(&state);
    Ok(if summary.ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn mission(
    host: &Host,
    station: &dnm_ground::Station,
    netlist: &Netlist,
    args: &DemoArgs,
    tty: bool,
) -> anyhow::Result<Summary> {
    let mut m = Mission {
        probe: Probe {
            session: host.session(),
            netlist,
        },
        station,
        start: Instant::now(),
        json: args.json,
        tty,
        task: netlist.initial_task().unwrap_or("teleop").to_string(),
        last_line: Instant::now() - Duration::from_secs(10),
        switches: Vec::new(),
    };
    let mut problems = Vec::new();

    // Everything runs and the simulator answers.
    let deadline = Instant::now() + Duration::from_secs(30);
    while Snapshot::read(&m.probe).is_none() {
        if Instant::now() > deadline {
            bail!("the rover's modules did not come up within 30 s; see `RUST_LOG=info`");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    if m.task != "teleop" {
        m.switch("teleop")?;
    }
    m.say("driving by joystick (task `teleop`)");
    m.watch(args.teleop_s, |_| false);

    // The rest of the mission is a plan the rover carries out on its own: the exploration
    // sequence, uploaded through the ground station and run on board by the authority.
    let explored = m.explore(netlist, args)?;
    let at_rest_error = explored.at_rest_error;
    let replaced = explored.replaced.clone();
    let revision = explored.revision;
    let sequence = explored.summary;
    if sequence.state != "finished" {
        problems.push(format!(
            "the sequence `{}` did not finish: {} ({})",
            sequence.name, sequence.state, sequence.why
        ));
    }
    m.say("back to the joystick (task `teleop`)");
    let last = m
        .watch(args.teleop_s, |_| false)
        .context("lost the rover's state")?;
    if tty {
        println!();
    }

    let status = m.probe.request(&Request::Status)?;
    let module_messages = status
        .dnms
        .iter()
        .flat_map(|d| d.modules.iter().map(|m| m.sent))
        .sum();
    let zenoh_messages = status
        .dnms
        .iter()
        .flat_map(|d| d.routes.published.iter().map(|r| r.messages))
        .sum();
    let zenoh_bytes = status
        .dnms
        .iter()
        .flat_map(|d| d.routes.published.iter().map(|r| r.bytes))
        .sum();
    let (err, yaw_err) = last.pose_error();
    let distance = last.truth.distance;
    let tol = tolerance(distance);
    if err > tol {
        problems.push(format!(
            "odometry is {err:.2} m from the ground truth, more than the {tol:.2} m allowed"
        ));
    }
    if at_rest_error.is_nan() || at_rest_error > tolerance(distance) {
        problems.push(format!(
            "at rest on the last waypoint odometry was {at_rest_error:.2} m from the ground truth"
        ));
    }
    Ok(Summary {
        ok: problems.is_empty(),
        duration_s: m.t(),
        distance_m: distance,
        odometry_distance_m: last.odom.distance,
        waypoints_reached: last.progress.reached,
        waypoints_total: last.progress.total,
        final_pose_truth: [last.truth.x, last.truth.y, last.truth.yaw.to_degrees()],
        final_pose_odometry: [last.odom.x, last.odom.y, last.odom.yaw.to_degrees()],
        final_position_error_m: err,
        final_heading_error_deg: yaw_err,
        position_tolerance_m: tol,
        at_rest_position_error_m: at_rest_error,
        switches: m.switches,
        sequence: Some(sequence),
        replaced,
        revision: status.revision.unwrap_or(revision),
        module_messages,
        zenoh_messages,
        zenoh_bytes,
        watchdog_trips: last.watchdog.trips,
        battery_charge: last.battery.charge,
        problems,
    })
}

fn print_summary(s: &Summary) {
    println!(
        "\nBeetle-One mission {} in {:.1} s",
        if s.ok { "completed" } else { "FAILED" },
        s.duration_s
    );
    println!(
        "  distance driven   {:.2} m (ground truth); odometry says {:.2} m",
        s.distance_m, s.odometry_distance_m
    );
    println!(
        "  waypoints         {} of {} reached in `auto`",
        s.waypoints_reached, s.waypoints_total
    );
    println!(
        "  final pose        truth ({:.2}, {:.2}, {:.0}°), odometry ({:.2}, {:.2}, {:.0}°): {:.3} m, {:.1}° apart (allowed {:.2} m); at rest on the last waypoint {:.3} m",
        s.final_pose_truth[0],
        s.final_pose_truth[1],
        s.final_pose_truth[2],
        s.final_pose_odometry[0],
        s.final_pose_odometry[1],
        s.final_pose_odometry[2],
        s.final_position_error_m,
        s.final_heading_error_deg,
        s.position_tolerance_m,
        s.at_rest_position_error_m,
    );
    for sw in &s.switches {
        println!(
            "  switch            {} -> {} at {:.1} s by the {}: {:.0} ms from {} to instant; {} rover DNMs within {:.0} µs; slowest {:.2} µs inside a DNM",
            sw.from.as_deref().unwrap_or("?"),
            sw.to,
            sw.at_s,
            if sw.by == "station" {
                "ground station"
            } else {
                "sequence on board"
            },
            sw.command_to_switch_ms,
            if sw.by == "station" {
                "command"
            } else {
                "step"
            },
            sw.per_dnm_ns.len(),
            sw.spread_us,
            sw.slowest_ns as f64 / 1000.0
        );
    }
    if let Some(q) = &s.sequence {
        println!(
            "  sequence          `{}` run on board by the authority, no command from the ground: {}, {} steps in {:.1} s{}",
            q.name,
            q.state,
            q.steps,
            q.duration_s,
            if q.why.is_empty() {
                String::new()
            } else {
                format!(" ({})", q.why)
            }
        );
    }
    if !s.replaced.is_empty() {
        println!("  replaced live     {}", s.replaced);
    }
    println!(
        "  messages          {} sent by modules; {} ({:.1} MB) crossed DNMs over Zenoh",
        s.module_messages,
        s.zenoh_messages,
        s.zenoh_bytes as f64 / 1e6
    );
    println!(
        "  battery           {:.1} % left; watchdog stops: {}",
        s.battery_charge * 100.0,
        s.watchdog_trips
    );
    for p in &s.problems {
        println!("  problem: {p}");
    }
}
