//! Processes of a rover and a ground station, the station's API, and a poller that watches
//! every rover DNM's task word in shared memory.
#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: failing loudly is right

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_ground::{CommandState, Entry, LinkStatus};
use dnm_module::TaskWatch;
use dnm_module::protocol::monotonic_ns;
use dnm_proto::station::Order;

use super::{endpoint, eventually};

/// A process of the test, with its output in a log file; SIGTERM when dropped.
pub struct Proc {
    pub child: Child,
    pub log: PathBuf,
}

impl Proc {
    /// `dnm ARGS`, output to `dir/NAME.log`.
    pub fn dnm(dir: &Path, name: &str, args: &[String]) -> Self {
        Self::dnm_env(dir, name, args, &[])
    }

    /// [`Proc::dnm`] with more environment variables.
    pub fn dnm_env(dir: &Path, name: &str, args: &[String], env: &[(&str, &str)]) -> Self {
        let log = dir.join(format!("{name}.log"));
        let out = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&log)
            .unwrap();
        use std::os::unix::process::CommandExt;
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_dnm"));
        // SAFETY: prctl(2) between fork and exec, async-signal-safe: the process dies with the
        // test, even if the test is killed.
        unsafe {
            cmd.pre_exec(|| {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL);
                Ok(())
            });
        }
        let child = cmd
            .args(args)
            .env("DNM_MODULE_HOST", super::system::module_host())
            .env(
                "RUST_LOG",
                "info,dnm_ground=debug,dnm_authority=debug,dnm_downlink=debug",
            )
            .envs(env.iter().copied())
            .stdin(Stdio::null())
            .stdout(out.try_clone().unwrap())
            .stderr(out)
            .spawn()
            .unwrap();
        Self { child, log }
    }

    /// Whether the process is still running.
    pub fn alive(&mut self) -> bool {
        matches!(self.child.try_wait(), Ok(None))
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// Kills it the hard way (as a power cut or a crash would).
    pub fn kill(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// How many lines of a process's log a failed test prints.
const LOG_TAIL: usize = 40;

impl Drop for Proc {
    fn drop(&mut self) {
        if std::thread::panicking() {
            // A failed test shows what its processes said last (their logs live in a temporary
            // folder that is gone by the time anyone reads the failure).
            let log =
                String::from_utf8_lossy(&std::fs::read(&self.log).unwrap_or_default()).into_owned();
            let lines: Vec<&str> = log.lines().collect();
            let tail = &lines[lines.len().saturating_sub(LOG_TAIL)..];
            eprintln!(
                "--- the last {} lines of {} ---\n{}",
                tail.len(),
                self.log.display(),
                tail.join("\n")
            );
        }
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let deadline = Instant::now() + Duration::from_secs(15);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Global Zenoh options of a process reaching `port` on loopback.
pub fn zenoh_args(mode: &str, port: u16) -> Vec<String> {
    vec![
        "--no-multicast".into(),
        "--zenoh-mode".into(),
        mode.into(),
        "--connect".into(),
        endpoint(port),
    ]
}

/// The station's HTTP/JSON API.
pub struct Api(pub String);

impl Api {
    fn agent() -> ureq::Agent {
        ureq::Agent::new_with_config(
            ureq::Agent::config_builder()
                .http_status_as_error(false)
                .timeout_global(Some(Duration::from_secs(60)))
                .build(),
        )
    }

    /// (status, body).
    pub fn post_raw(&self, body: &[u8]) -> (u16, serde_json::Value) {
        let mut r = Self::agent()
            .post(format!("{}/commands", self.0))
            .content_type("application/json")
            .send(body)
            .unwrap();
        let status = r.status().as_u16();
        let text = r.body_mut().read_to_string().unwrap();
        (status, serde_json::from_str(&text).unwrap())
    }

    pub fn submit(&self, order: &Order) -> Entry {
        let (status, body) = self.post_raw(&serde_json::to_vec(order).unwrap());
        assert_eq!(status, 201, "{body}");
        serde_json::from_value(body).unwrap()
    }

    fn get<T: serde::de::DeserializeOwned>(&self, path: &str) -> Option<T> {
        let mut r = Self::agent().get(format!("{}{path}", self.0)).call().ok()?;
        if r.status().as_u16() != 200 {
            return None;
        }
        serde_json::from_str(&r.body_mut().read_to_string().ok()?).ok()
    }

    /// The status `GET path` answers with (0: no answer).
    /// `GET path` as JSON (waiting for the station's API if it is not answering yet).
    pub fn get_json(&self, path: &str) -> serde_json::Value {
        super::eventually(path, || self.get(path))
    }

    pub fn status(&self, path: &str) -> u16 {
        Self::agent()
            .get(format!("{}{path}", self.0))
            .call()
            .map_or(0, |r| r.status().as_u16())
    }

    pub fn entries(&self) -> Vec<Entry> {
        self.get("/commands").unwrap_or_default()
    }

    pub fn entry(&self, seq: u64, wait_s: u64) -> Entry {
        self.get(&format!("/commands/{seq}?wait={wait_s}")).unwrap()
    }

    pub fn link(&self) -> LinkStatus {
        self.get("/link").unwrap()
    }

    pub fn up(&self) -> bool {
        self.get::<LinkStatus>("/link").is_some()
    }

    /// Waits until every command of the outbox is final.
    pub fn all_final(&self) -> Vec<Entry> {
        let deadline = Instant::now() + Duration::from_secs(600);
        loop {
            let e = self.entries();
            if !e.is_empty() && e.iter().all(|e| e.state.is_final()) {
                return e;
            }
            let pending: Vec<(u64, CommandState)> = e
                .iter()
                .filter(|e| !e.state.is_final())
                .map(|e| (e.seq, e.state))
                .take(5)
                .collect();
            assert!(
                Instant::now() < deadline,
                "commands never finished: {pending:?}"
            );
            std::thread::sleep(Duration::from_millis(500));
        }
    }
}

/// What one DNM went through, as its task word showed it.
#[derive(Debug, Default, Clone)]
pub struct Seen {
    /// Distinct (revision, slot) in the order seen, with the stamp of the store.
    pub states: Vec<(u64, u16, u64)>,
}

/// Reads the task word of every rover DNM about every millisecond, and records what each
/// went through and every moment they disagreed.
pub struct Poller {
    stop: Arc<AtomicBool>,
    down: Arc<Mutex<BTreeMap<String, bool>>>,
    thread: Option<std::thread::JoinHandle<Watched>>,
}

/// What the poller saw: per DNM, and every sample on which they disagreed.
pub type Watched = (BTreeMap<String, Seen>, Vec<Split>);

/// A sample on which DNMs disagreed.
#[derive(Debug, Clone)]
pub struct Split {
    /// Since the newest store among the DNMs, at the sample (CLOCK_MONOTONIC), ns.
    pub since_switch_ns: u64,
    /// (DNM, revision, slot, stamp of its last store).
    pub words: Vec<(String, u64, u16, u64)>,
}

impl Poller {
    pub fn start(system: &str, dnms: &[&str]) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let down: Arc<Mutex<BTreeMap<String, bool>>> = Arc::default();
        let (system, dnms): (String, Vec<String>) = (
            system.to_string(),
            dnms.iter().map(|d| d.to_string()).collect(),
        );
        let thread = {
            let (stop, down) = (stop.clone(), down.clone());
            std::thread::spawn(move || {
                let mut watches: BTreeMap<String, Option<TaskWatch>> =
                    dnms.iter().map(|d| (d.clone(), None)).collect();
                let mut seen: BTreeMap<String, Seen> = BTreeMap::new();
                let mut splits = Vec::new();
                while !stop.load(Ordering::Relaxed) {
                    let down_now = down.lock().unwrap().clone();
                    for (d, w) in watches.iter_mut() {
                        if down_now.get(d).copied().unwrap_or(false) {
                            *w = None;
                        } else if w.is_none() {
                            *w = TaskWatch::open(&system, d).ok();
                        }
                    }
                    let mut words = Vec::new();
                    for (d, w) in &watches {
                        if let Some(w) = w {
                            let (rev, slot, at) = w.read();
                            // Revision 0: a DNM that has not adopted anything yet runs nothing.
                            if rev > 0 {
                                words.push((d.clone(), rev, slot, at));
                            }
                        }
                    }
                    let now = monotonic_ns();
                    for (d, rev, slot, at) in &words {
                        let s = seen.entry(d.clone()).or_default();
                        if s.states.last().is_none_or(|l| (l.0, l.1) != (*rev, *slot)) {
                            s.states.push((*rev, *slot, *at));
                        }
                    }
                    if words
                        .windows(2)
                        .any(|p| (p[0].1, p[0].2) != (p[1].1, p[1].2))
                    {
                        let newest = words.iter().map(|w| w.3).max().unwrap_or(0);
                        splits.push(Split {
                            since_switch_ns: now.saturating_sub(newest),
                            words: words.clone(),
                        });
                    }
                    std::thread::sleep(Duration::from_millis(1));
                }
                (seen, splits)
            })
        };
        Self {
            stop,
            down,
            thread: Some(thread),
        }
    }

    /// Stops watching `dnm` (its process is about to die) or watches it again.
    pub fn set_down(&self, dnm: &str, down: bool) {
        self.down.lock().unwrap().insert(dnm.to_string(), down);
        // Let the poller drop or reopen it.
        std::thread::sleep(Duration::from_millis(20));
    }

    pub fn finish(mut self) -> Watched {
        self.stop.store(true, Ordering::Relaxed);
        self.thread.take().unwrap().join().unwrap()
    }
}

/// A DNM's report over Zenoh.
pub fn report(session: &zenoh::Session, system: &str, dnm: &str) -> Option<dnm::DnmReport> {
    use zenoh::Wait;
    let replies = session
        .get(format!("{system}/dnm/{dnm}"))
        .timeout(Duration::from_secs(3))
        .wait()
        .ok()?;
    let r = replies.recv().ok()?;
    serde_json::from_slice(&r.result().ok()?.payload().to_bytes()).ok()
}

/// Waits until every DNM named reports `revision` (any if 0) and `task` with all its modules
/// running.
pub fn wait_in_step(session: &zenoh::Session, system: &str, dnms: &[&str], task: &str) -> u64 {
    eventually(&format!("DNMs {dnms:?} on task {task}"), || {
        let reports: Vec<dnm::DnmReport> = dnms
            .iter()
            .map(|d| report(session, system, d))
            .collect::<Option<_>>()?;
        let rev = reports[0].revision;
        reports
            .iter()
            .all(|r| {
                r.revision == rev
                    && rev > 0
                    && r.active_task.as_deref() == Some(task)
                    && r.modules
                        .iter()
                        .all(|m| m.state == dnm::ModuleRunState::Running)
            })
            .then_some(rev)
    })
}

/// The test system: a rover of three DNMs (`rover` the authority, `drive`, `vision`) and one
/// across the radio (`ground`), with ticker sources, a relay and a pair reader.
const NETLIST: &str = r#"
[system]
name = "SYSTEM"
default_task = "a"
authority = "rover"
LOSS

[[dnm]]
name = "rover"

[[dnm]]
name = "drive"
parent = "rover"

[[dnm]]
name = "vision"
parent = "rover"

[[dnm]]
name = "ground"
parent = "rover"
link = "radio"

[[module]]
name = "src_a"
kind = "ticker"
dnm = "rover"
rate_hz = 20
params = { origin = 1 }

[[module]]
name = "src_b"
kind = "ticker"
dnm = "drive"
rate_hz = 20
params = { origin = ORIGIN }

[[module]]
name = "relay"
kind = "relay"
dnm = "vision"

[[module]]
name = "pair"
kind = "pair"
dnm = "drive"

[[module]]
name = "watch"
kind = "relay"
dnm = "ground"

[task.a]
links = ["src_a.out -> relay.in", "src_a.out -> pair.a", "src_b.out -> pair.b", "relay.out -> watch.in"]

[task.b]
links = ["src_b.out -> relay.in", "src_b.out -> pair.a", "src_a.out -> pair.b", "relay.out -> watch.in"]

[task.c]
links = ["src_a.out -> pair.a", "src_b.out -> pair.b"]
"#;

pub const TASKS: [&str; 3] = ["a", "b", "c"];
pub const ROVER: [&str; 3] = ["rover", "drive", "vision"];

pub struct Rig {
    pub system: String,
    pub dir: PathBuf,
    pub netlist: PathBuf,
    pub rover_port: u16,
    pub radio_port: u16,
    pub ground_port: u16,
    pub http: String,
}

impl Drop for Rig {
    fn drop(&mut self) {
        // (A test's processes are its locals, declared after the rig: gone by now.)
        super::remove_unless_failed(&self.dir);
    }
}

impl Rig {
    pub fn new(tag: &str, loss_line: &str) -> Self {
        let system = format!("g{tag}{}", std::process::id());
        let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let netlist = dir.join("netlist.toml");
        std::fs::write(&netlist, text(&system, loss_line, 2)).unwrap();
        Self {
            system,
            dir,
            netlist,
            rover_port: super::free_port(),
            radio_port: super::free_port(),
            ground_port: super::free_port(),
            http: format!("127.0.0.1:{}", super::free_port()),
        }
    }

    /// The rover's router, and the ground's, which reaches it across the radio.
    pub fn routers(&self) -> (Proc, Proc) {
        let config = |side: &str| {
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join(format!("../configs/zenoh/{side}-router.json5"))
                .display()
                .to_string()
        };
        let rover = vec![
            "--zenoh-config".into(),
            config("rover"),
            "--listen".into(),
            super::endpoint(self.rover_port),
            "router".into(),
        ];
        let ground = vec![
            "--zenoh-config".into(),
            config("ground"),
            "--listen".into(),
            super::endpoint(self.ground_port),
            "--connect".into(),
            super::endpoint(self.radio_port),
            "router".into(),
        ];
        let routers = (
            Proc::dnm(&self.dir, "rover-router", &rover),
            Proc::dnm(&self.dir, "ground-router", &ground),
        );
        for port in [self.rover_port, self.ground_port] {
            eventually("a router listening", || {
                std::net::TcpStream::connect(("127.0.0.1", port)).ok()
            });
        }
        routers
    }

    /// `dnm up` of some DNMs: rover side as peers of the rover's router, ground side as a
    /// client of the ground's router.
    pub fn up(&self, dnms: &[&str], ground_side: bool) -> Proc {
        self.up_env(dnms, ground_side, &[])
    }

    /// [`Rig::up`] with more environment variables.
    pub fn up_env(&self, dnms: &[&str], ground_side: bool, env: &[(&str, &str)]) -> Proc {
        self.up_from(&self.netlist, dnms, ground_side, env)
    }

    /// `dnm up NETLIST` of some DNMs (a computer that joins with a netlist of its own).
    pub fn up_from(
        &self,
        netlist: &Path,
        dnms: &[&str],
        ground_side: bool,
        env: &[(&str, &str)],
    ) -> Proc {
        let mut args = if ground_side {
            zenoh_args("client", self.ground_port)
        } else {
            zenoh_args("peer", self.rover_port)
        };
        args.push("up".into());
        args.push(netlist.display().to_string());
        for d in dnms {
            args.push("--dnm".into());
            args.push(d.to_string());
        }
        args.extend([
            "--no-record".into(),
            "--state-dir".into(),
            self.dir.join("state").display().to_string(),
        ]);
        Proc::dnm_env(&self.dir, &dnms.join("-"), &args, env)
    }

    /// `dnm up` of some rover DNMs recording into `record_dir` (their sessions there), with
    /// more arguments of `dnm up`.
    pub fn up_recording(&self, dnms: &[&str], record_dir: &Path, extra: &[&str]) -> Proc {
        let mut args = zenoh_args("peer", self.rover_port);
        args.extend(["up".into(), self.netlist.display().to_string()]);
        for d in dnms {
            args.extend(["--dnm".into(), d.to_string()]);
        }
        args.extend(extra.iter().map(|s| s.to_string()));
        args.extend([
            "--record-dir".into(),
            record_dir.display().to_string(),
            "--state-dir".into(),
            self.dir.join("state").display().to_string(),
        ]);
        Proc::dnm(&self.dir, &dnms.join("-"), &args)
    }

    pub fn linksim(&self, extra: &[&str]) -> Proc {
        self.linksim_to(self.rover_port, extra)
    }

    /// The radio to `port` (a proxy in front of the rover's router) instead of the router.
    pub fn linksim_to(&self, port: u16, extra: &[&str]) -> Proc {
        let mut args: Vec<String> = vec![
            "linksim".into(),
            "--bind".into(),
            format!("127.0.0.1:{}", self.radio_port),
            "--to".into(),
            format!("127.0.0.1:{port}"),
        ];
        args.extend(extra.iter().map(|s| s.to_string()));
        Proc::dnm(&self.dir, "linksim", &args)
    }

    pub fn station(&self) -> (Proc, Api) {
        self.station_named("ground-1", &self.http)
    }

    /// The station `ground-1` with more arguments of `dnm ground serve`.
    pub fn station_with(&self, extra: &[&str]) -> (Proc, Api) {
        self.station_full("ground-1", &self.http, extra)
    }

    /// A station of its own name, outbox and API address.
    pub fn station_named(&self, name: &str, http: &str) -> (Proc, Api) {
        self.station_full(name, http, &[])
    }

    fn station_full(&self, name: &str, http: &str, extra: &[&str]) -> (Proc, Api) {
        let mut args = zenoh_args("client", self.ground_port);
        args.extend([
            "ground".into(),
            "serve".into(),
            "--system".into(),
            self.system.clone(),
            "--station".into(),
            name.into(),
            "--db".into(),
            self.dir.join(format!("{name}.redb")).display().to_string(),
            "--http".into(),
            http.into(),
        ]);
        args.extend(extra.iter().map(|s| s.to_string()));
        let log = if name == "ground-1" {
            "station".to_string()
        } else {
            format!("station-{name}")
        };
        let p = Proc::dnm(&self.dir, &log, &args);
        let api = Api(format!("http://{http}"));
        eventually("the station's API", || api.up().then_some(()));
        (p, api)
    }
}

pub fn text(system: &str, loss_line: &str, origin: u32) -> String {
    NETLIST
        .replace("SYSTEM", system)
        .replace("LOSS", loss_line)
        .replace("ORIGIN", &origin.to_string())
}

pub fn slot(task: &str) -> u16 {
    TASKS.iter().position(|t| *t == task).unwrap() as u16
}
