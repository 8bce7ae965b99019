//! `dnm monitor`: a ground-side Zenoh client that watches a running system and streams it to
//! Rerun. It never runs inside a DNM or a module: it reads what any operator's tool can read.
//!
//! - **What it asks for.** A glance at every DNM (`<system>/dnm/*?glance`: modules' states,
//!   the last events and switches, peers) every `status_every`, and the wiring in force
//!   (`<system>/dnm/<dnm>/wiring`) when a glance shows a new revision or task; every output through the DNMs' on-demand watch keys
//!   (`<system>/watch/...`), numeric ones at `numeric_rate` and camera frames (JPEG) at
//!   `camera_rate`. Nothing else crosses the radio for it.
//! - **What it draws** (entity paths):
//!   - `world/<module>`: the pose of any output with numeric `x`, `y` and `yaw` (the
//!     simulator's truth, the odometry estimate), its path under `world/paths/<module>`, the
//!     waypoints and the rocks of Beetle-One's world;
//!   - `camera/<module>/<port>`: the frames;
//!   - `series/<module>/<port>/<field>`: every numeric field of every message (arrays by index,
//!     JSON by path), whatever the kind;
//!   - `graph`: the live connection graph: modules as nodes placed in a column per DNM,
//!     coloured by state, the active task's links as edges, redrawn on every switch, apply and
//!     module state change;
//!   - `log`: switches, applies, module faults and restarts, DNMs and links lost and found;
//!   - what a ground station filled in of its record after an outage
//!     (`<system>/ground_filled/...`, see `dnm-downlink`): its time series and poses at their
//!     send times, in the past of the timeline where the outage left them empty, and the
//!     filled-in stretches of a path in blue under `world/paths/<module>/filled`.
//! - **Layout.** A blueprint for a rover operator: world and camera on the left; the connection
//!   graph, time series (a tab per module) and the log on the right.

use dnm_proto::clock::now_unix_ns;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::mpsc::{self, Receiver, RecvTimeoutError, SyncSender};
use std::time::{Duration, Instant};

use dnm_netlist::{MessageType, Wiring};
use dnm_proto::keys::{self, JPEG_ENCODING, WatchRate};
use dnm_proto::{DnmGlance, ModuleRunState};
use rerun::RecordingStream;
use rerun::blueprint::components::PanelState;
use rerun::blueprint::{
    Blueprint, BlueprintActivation, BlueprintPanel, ContainerLike, GraphView, Horizontal,
    SelectionPanel, Spatial2DView, Spatial3DView, Tabs, TextLogView, TimePanel, TimeSeriesView,
    Vertical,
};
use serde_json::Value;
use zenoh::Wait;

mod playback;
pub use playback::play;

/// The timeline every sample is put on: the producer's wall-clock send time.
pub const TIMELINE: &str = "time";

/// What to watch and how often.
#[derive(Debug, Clone)]
pub struct MonitorOptions {
    pub system: String,
    /// Rate of numeric outputs.
    pub numeric_rate: WatchRate,
    /// Rate of camera frames.
    pub camera_rate: WatchRate,
    /// How often the wiring and the DNMs' reports are asked for.
    pub status_every: Duration,
    /// Stop after this long (else until the process is stopped).
    pub duration: Option<Duration>,
}

impl MonitorOptions {
    pub fn new(system: &str) -> Self {
        Self {
            system: system.to_string(),
            numeric_rate: WatchRate::Hz10,
            camera_rate: WatchRate::Hz1,
            status_every: Duration::from_secs(1),
            duration: None,
        }
    }
}

/// What a monitor run received.
#[derive(Debug, Clone, Default)]
pub struct MonitorStats {
    pub samples: u64,
    pub bytes: u64,
    /// Samples dropped because the monitor fell behind.
    pub dropped: u64,
    pub revisions: u64,
    pub switches: u64,
    /// Messages a station filled in of its record, drawn where they belong in time.
    pub filled: u64,
}

enum Event {
    Sample {
        module: String,
        port: String,
        encoding: String,
        bytes: Vec<u8>,
        unix_ns: u64,
    },
    Status {
        wiring: Option<Wiring>,
        reports: Vec<DnmGlance>,
    },
    /// An onboard sequence's event, as the authority published it.
    Sequence(dnm_proto::station::SequenceEvent),
    /// A message a ground station filled in of its record (from the rover's recording, after
    /// a gap), decoded, at its send time.
    Filled {
        module: String,
        port: String,
        value: Value,
        unix_ns: u64,
    },
}

/// Samples waiting for the logging thread at most; beyond, they are dropped and counted.
const QUEUE: usize = 1024;

/// Watches `options.system` on `session` and logs it to `rec` until `options.duration` passes
/// or `stop` is set.
pub fn run(
    session: &zenoh::Session,
    rec: &RecordingStream,
    options: &MonitorOptions,
    stop_when: &std::sync::atomic::AtomicBool,
) -> anyhow::Result<MonitorStats> {
    let (tx, rx) = mpsc::sync_channel::<Event>(QUEUE);
    let dropped = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let poller = {
        let (session, tx, stop) = (session.clone(), tx.clone(), stop.clone());
        let (system, every) = (options.system.clone(), options.status_every);
        std::thread::Builder::new()
            .name("monitor-status".into())
            .spawn(move || status_loop(&session, &system, every, &tx, &stop))?
    };
    // The authority's sequence events, each as it happens.
    let _sequences = {
        let tx = tx.clone();
        session
            .declare_subscriber(keys::authority_sequences(&options.system))
            .callback(move |sample| {
                if let Ok(e) = serde_json::from_slice(&sample.payload().to_bytes()) {
                    let _ = tx.try_send(Event::Sequence(e));
                }
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("watching sequence events: {e}"))?
    };
    // What stations fill in of their record of the rover after an outage.
    let _filled = {
        let tx = tx.clone();
        let system = options.system.clone();
        session
            .declare_subscriber(keys::ground_filled_all(&options.system))
            .callback(move |sample| {
                let Some((_, module, port)) =
                    keys::ground_filled_port(&system, sample.key_expr().as_str())
                else {
                    return;
                };
                let Some((unix_ns, _)) = sample
                    .attachment()
                    .and_then(|a| keys::decode_downlink(&a.to_bytes()))
                else {
                    return;
                };
                if let Ok(value) = serde_json::from_slice(&sample.payload().to_bytes()) {
                    let _ = tx.try_send(Event::Filled {
                        module,
                        port,
                        value,
                        unix_ns,
                    });
                }
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("watching what stations fill in: {e}"))?
    };
    let mut view = View::new(rec.clone(), options.clone());
    let result = view.run(session, &rx, &tx, &dropped, stop_when);
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    drop(rx);
    let _ = poller.join();
    let mut stats = result?;
    stats.dropped = dropped.load(std::sync::atomic::Ordering::Relaxed);
    rec.flush_blocking()?;
    Ok(stats)
}

fn status_loop(
    session: &zenoh::Session,
    system: &str,
    every: Duration,
    tx: &SyncSender<Event>,
    stop: &std::sync::atomic::AtomicBool,
) {
    // The (revision, task) whose wiring was fetched last: the wiring (tens of KiB) is asked
    // for again only when the DNMs' glances show another.
    let mut fetched: Option<(u64, String)> = None;
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        let started = Instant::now();
        let timeout = Duration::from_secs(5);
        let reports = collect::<DnmGlance>(
            session,
            &format!("{}?glance", keys::all_dnms(system)),
            timeout,
        );
        let wiring = match in_force(&reports) {
            Some((dnm, now)) if fetched.as_ref() != Some(&now) => {
                let w = newest_wiring(collect::<Wiring>(
                    session,
                    &keys::wiring(system, &dnm),
                    timeout,
                ));
                if w.is_some() {
                    fetched = Some(now);
                }
                w
            }
            _ => None,
        };
        if tx.send(Event::Status { wiring, reports }).is_err() {
            return;
        }
        let rest = every.saturating_sub(started.elapsed());
        let until = Instant::now() + rest;
        while Instant::now() < until && !stop.load(std::sync::atomic::Ordering::Relaxed) {
            std::thread::sleep(rest.min(Duration::from_millis(100)));
        }
    }
}

/// What the DNMs say is in force: the newest revision, and the task most of the DNMs on it
/// run (a DNM across the radio may lag), with one DNM that says so.
fn in_force(glances: &[DnmGlance]) -> Option<(String, (u64, String))> {
    let newest = glances
        .iter()
        .filter(|g| g.active_task.is_some())
        .map(|g| g.revision)
        .max()?;
    let mut votes: BTreeMap<&str, Vec<&str>> = BTreeMap::new();
    for g in glances.iter().filter(|g| g.revision == newest) {
        if let Some(t) = &g.active_task {
            votes.entry(t.as_str()).or_default().push(&g.dnm);
        }
    }
    let (task, dnms) = votes
        .into_iter()
        .max_by_key(|(t, d)| (d.len(), std::cmp::Reverse(*t)))?;
    Some((dnms.first()?.to_string(), (newest, task.to_string())))
}

/// The wiring in force: the newest revision with a task, as the rover's DNMs tell it (a DNM
/// across the radio may lag), the same DNM's answer each time.
fn newest_wiring(all: Vec<Wiring>) -> Option<Wiring> {
    all.into_iter()
        .filter(|w| w.active_task.is_some())
        .max_by(|a, b| {
            let radio = |w: &Wiring| w.dnms.iter().any(|d| d.name == w.dnm && d.radio);
            (a.revision, !radio(a), std::cmp::Reverse(&a.dnm)).cmp(&(
                b.revision,
                !radio(b),
                std::cmp::Reverse(&b.dnm),
            ))
        })
}

/// Every JSON reply to `key`, decoded; replies that do not decode are skipped.
fn collect<T: serde::de::DeserializeOwned>(
    session: &zenoh::Session,
    key: &str,
    timeout: Duration,
) -> Vec<T> {
    let Ok(replies) = session
        .get(key)
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(timeout)
        .wait()
    else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result()
            && let Ok(v) = serde_json::from_slice(&s.payload().to_bytes())
        {
            out.push(v);
        }
    }
    out
}

/// A pose path keeps a point per this much movement, m.
const PATH_STEP: f64 = 0.05;
/// Points in one segment of a path: a path is logged as segments (`world/paths/<module>/<n>`),
/// and only the growing one is logged again, so what is sent stays small on a long drive.
const SEGMENT_POINTS: usize = 200;
/// A path is logged at most this often, ns (it is a whole strip each time).
const PATH_EVERY_NS: u64 = 500_000_000;
/// Filled-in poses further apart in time than this are stretches of their own.
const FILLED_APART_NS: u64 = 5_000_000_000;
/// Numeric fields of one sample drawn at most (a huge JSON array must not flood the viewer).
const MAX_FIELDS: usize = 256;

#[derive(Default)]
struct Path {
    /// The growing segment's number and points.
    segment: usize,
    points: Vec<[f32; 3]>,
    /// When it was last logged, by the view's clock (ns).
    logged_at_ns: Option<u64>,
    dirty: bool,
}

/// What has been drawn, to log only what changed.
struct View {
    rec: RecordingStream,
    options: MonitorOptions,
    wiring: Option<Wiring>,
    /// Declared once the first wiring is drawn: tells `dnm demo` (and anyone) the monitor
    /// is watching.
    ready: Option<zenoh::liveliness::LivelinessToken>,
    /// The watch subscriptions, by key.
    subscribers: BTreeMap<String, zenoh::pubsub::Subscriber<()>>,
    /// Message types of the outputs, by (module, port).
    messages: BTreeMap<(String, String), MessageType>,
    /// Each module's state as last reported.
    states: BTreeMap<String, ModuleRunState>,
    dnms_seen: BTreeSet<String>,
    peers: BTreeMap<(String, String), String>,
    events_seen: BTreeSet<(String, String, String, u64)>,
    switches_seen: BTreeSet<(String, u64, String, u64)>,
    paths: BTreeMap<String, Path>,
    /// Poses filled in by stations, by module: send time → position.
    filled: BTreeMap<String, BTreeMap<u64, [f32; 3]>>,
    filled_dirty: BTreeSet<String>,
    stats: MonitorStats,
    blueprint_modules: Vec<String>,
    /// The time drawn at: a recording's, while one is played back; else the wall clock.
    clock: Option<u64>,
}

impl View {
    fn new(rec: RecordingStream, options: MonitorOptions) -> Self {
        Self {
            rec,
            options,
            wiring: None,
            ready: None,
            subscribers: BTreeMap::new(),
            messages: BTreeMap::new(),
            states: BTreeMap::new(),
            dnms_seen: BTreeSet::new(),
            peers: BTreeMap::new(),
            events_seen: BTreeSet::new(),
            switches_seen: BTreeSet::new(),
            paths: BTreeMap::new(),
            filled: BTreeMap::new(),
            filled_dirty: BTreeSet::new(),
            stats: MonitorStats::default(),
            blueprint_modules: Vec::new(),
            clock: None,
        }
    }

    fn run(
        &mut self,
        session: &zenoh::Session,
        rx: &Receiver<Event>,
        tx: &SyncSender<Event>,
        dropped: &std::sync::Arc<std::sync::atomic::AtomicU64>,
        stop_when: &std::sync::atomic::AtomicBool,
    ) -> anyhow::Result<MonitorStats> {
        let until = self.options.duration.map(|d| Instant::now() + d);
        self.send_blueprint()?;
        self.say(
            rerun::TextLogLevel::INFO,
            &format!(
                "monitoring `{}`: graph nodes green running, yellow starting, orange hung, red failed, grey stopped",
                self.options.system
            ),
        )?;
        while !stop_when.load(std::sync::atomic::Ordering::Relaxed) {
            let wait = match until {
                Some(u) => match u.checked_duration_since(Instant::now()) {
                    Some(d) => d.min(Duration::from_millis(200)),
                    None => break,
                },
                None => Duration::from_millis(200),
            };
            match rx.recv_timeout(wait) {
                Ok(Event::Sample {
                    module,
                    port,
                    encoding,
                    bytes,
                    unix_ns,
                }) => {
                    self.stats.samples += 1;
                    self.stats.bytes += bytes.len() as u64;
                    self.sample(&module, &port, &encoding, &bytes, unix_ns)?;
                }
                Ok(Event::Status { wiring, reports }) => {
                    if let Some(w) = wiring {
                        self.wiring_changed(session, w, tx, dropped)?;
                    }
                    self.reports(&reports)?;
                }
                Ok(Event::Sequence(e)) => self.sequence(&e)?,
                Ok(Event::Filled {
                    module,
                    port,
                    value,
                    unix_ns,
                }) => {
                    self.stats.filled += 1;
                    self.rec
                        .set_timestamp_nanos_since_epoch(TIMELINE, unix_ns as i64);
                    if let Some((x, y, z)) = self.draw(&module, &port, &value)? {
                        self.filled
                            .entry(module.clone())
                            .or_default()
                            .insert(unix_ns, [x as f32, y as f32, z as f32]);
                        self.filled_dirty.insert(module);
                    }
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            self.flush_paths(false)?;
        }
        self.flush_paths(true)?;
        self.subscribers.clear();
        Ok(self.stats.clone())
    }

    /// The time things happen at: the recording's while one is played back, else now.
    fn now_ns(&self) -> u64 {
        self.clock.unwrap_or_else(now_unix_ns)
    }

    fn at_now(&self) {
        self.rec
            .set_timestamp_nanos_since_epoch(TIMELINE, self.now_ns() as i64);
    }

    fn say(&self, level: &str, text: &str) -> anyhow::Result<()> {
        self.at_now();
        self.rec
            .log("log", &rerun::TextLog::new(text).with_level(level))?;
        Ok(())
    }

    /// An onboard sequence's event, in the log.
    fn sequence(&self, e: &dnm_proto::station::SequenceEvent) -> anyhow::Result<()> {
        let level = match e.what.as_str() {
            "guard_fired" | "aborted" | "timed_out" => rerun::TextLogLevel::WARN,
            _ => rerun::TextLogLevel::INFO,
        };
        let step = e.step.map_or(String::new(), |s| format!(" step {}", s + 1));
        self.say(
            level,
            &format!("sequence `{}`{step}: {} {}", e.sequence, e.what, e.detail),
        )
    }

    /// A module event (exit, hang, restart...), in the log.
    fn module_event(&self, e: &dnm_proto::ModuleEvent) -> anyhow::Result<()> {
        let level = match e.what.as_str() {
            "exited" | "hung" | "gave_up" => rerun::TextLogLevel::ERROR,
            "restarting" | "stopped" => rerun::TextLogLevel::WARN,
            _ => rerun::TextLogLevel::INFO,
        };
        self.say(
            level,
            &format!("`{}` on `{}`: {} {}", e.module, e.dnm, e.what, e.detail),
        )
    }

    /// A DNM's task switch, in the log.
    fn switched(&self, dnm: &str, s: &dnm_proto::SwitchRecord) -> anyhow::Result<()> {
        self.say(
            rerun::TextLogLevel::INFO,
            &format!(
                "`{dnm}` switched {} → `{}` (revision {}, {:.2} µs)",
                s.from
                    .as_deref()
                    .map_or("(none)".into(), |f| format!("`{f}`")),
                s.to,
                s.revision,
                s.duration_ns as f64 / 1000.0
            ),
        )
    }

    /// A new revision or task: subscriptions follow the outputs, the graph its links.
    fn wiring_changed(
        &mut self,
        session: &zenoh::Session,
        w: Wiring,
        tx: &SyncSender<Event>,
        dropped: &std::sync::Arc<std::sync::atomic::AtomicU64>,
    ) -> anyhow::Result<()> {
        if self.show_wiring(w)?
            && let Some(w) = self.wiring.clone()
        {
            self.subscribe(session, &w, tx, dropped);
        }
        if self.wiring.is_some() && self.ready.is_none() {
            let key = format!("{}/monitor/{}", self.options.system, std::process::id());
            match session.liveliness().declare_token(key).wait() {
                Ok(t) => self.ready = Some(t),
                Err(e) => tracing::debug!("monitor token: {e}"),
            }
        }
        Ok(())
    }

    /// Draws a new revision or task in force: the log, the scene, the graph, the layout.
    /// `true` when the revision changed (the outputs may have).
    fn show_wiring(&mut self, w: Wiring) -> anyhow::Result<bool> {
        let (rev_changed, task_changed) = match &self.wiring {
            None => (true, true),
            Some(old) => (old.revision != w.revision, old.active_task != w.active_task),
        };
        if !rev_changed && !task_changed {
            return Ok(false);
        }
        if rev_changed {
            self.stats.revisions += 1;
            self.say(
                rerun::TextLogLevel::INFO,
                &format!(
                    "revision {} in force: {} modules on {} DNMs, tasks {}",
                    w.revision,
                    w.modules.len(),
                    w.dnms.len(),
                    w.tasks.keys().cloned().collect::<Vec<_>>().join(", ")
                ),
            )?;
            self.messages = w
                .modules
                .iter()
                .flat_map(|m| {
                    m.outputs
                        .iter()
                        .map(|p| ((m.name.clone(), p.name.clone()), p.message.clone()))
                })
                .collect();
            self.scene(&w)?;
        }
        if task_changed && !rev_changed {
            self.stats.switches += 1;
        }
        self.say(
            rerun::TextLogLevel::INFO,
            &format!(
                "task `{}` active",
                w.active_task.as_deref().unwrap_or("(none)")
            ),
        )?;
        self.wiring = Some(w);
        self.draw_graph()?;
        self.send_blueprint()?;
        Ok(rev_changed)
    }

    fn subscribe(
        &mut self,
        session: &zenoh::Session,
        w: &Wiring,
        tx: &SyncSender<Event>,
        dropped: &std::sync::Arc<std::sync::atomic::AtomicU64>,
    ) {
        let mut wanted: BTreeMap<String, (String, String)> = BTreeMap::new();
        for m in &w.modules {
            for p in &m.outputs {
                let rate = if p.message.encoding == "dnm-image-rgb8" {
                    self.options.camera_rate
                } else {
                    self.options.numeric_rate
                };
                let key = keys::watch(&self.options.system, &m.dnm, &m.name, &p.name, rate);
                wanted.insert(key, (m.name.clone(), p.name.clone()));
            }
        }
        self.subscribers.retain(|k, _| wanted.contains_key(k));
        for (key, (module, port)) in wanted {
            if self.subscribers.contains_key(&key) {
                continue;
            }
            let (tx, dropped) = (tx.clone(), dropped.clone());
            let sub = session
                .declare_subscriber(key.clone())
                .callback(move |s| {
                    let unix_ns = s
                        .attachment()
                        .and_then(|a| keys::decode_header(&a.to_bytes()))
                        .map(|h| h.unix_ns)
                        .filter(|t| *t > 0)
                        .unwrap_or_else(now_unix_ns);
                    let event = Event::Sample {
                        module: module.clone(),
                        port: port.clone(),
                        encoding: s.encoding().to_string(),
                        bytes: s.payload().to_bytes().to_vec(),
                        unix_ns,
                    };
                    if tx.try_send(event).is_err() {
                        dropped.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    }
                })
                .wait();
            match sub {
                Ok(s) => {
                    self.subscribers.insert(key, s);
                }
                Err(e) => tracing::warn!(key = %key, "cannot watch: {e}"),
            }
        }
    }

    /// Beetle-One's waypoints and rocks, from the parameters of its modules.
    fn scene(&self, w: &Wiring) -> anyhow::Result<()> {
        for m in &w.modules {
            let param = |name: &str| match m.params.get(name) {
                Some(dnm_netlist::ParamValue::String(s)) => Some(s.clone()),
                _ => None,
            };
            if let Some(text) = param("waypoints")
                && let Ok(points) = dnm_rover::control::parse_waypoints(&text)
            {
                let pts: Vec<[f32; 3]> = points
                    .iter()
                    .map(|(x, y)| [*x as f32, *y as f32, 0.0])
                    .collect();
                let labels: Vec<String> =
                    (1..=pts.len()).map(|i| format!("waypoint {i}")).collect();
                self.rec.log_static(
                    format!("world/waypoints/{}", m.name),
                    &rerun::Points3D::new(pts)
                        .with_radii([0.15])
                        .with_colors([rerun::Color::from_rgb(80, 160, 255)])
                        .with_labels(labels),
                )?;
            }
            if m.kind == "rover_world" {
                let name = param("terrain").unwrap_or_else(|| "mars-yard".into());
                if let Some(t) = dnm_rover::world::Terrain::named(&name) {
                    let centers: Vec<[f32; 3]> = t
                        .rocks
                        .iter()
                        .map(|r| {
                            [
                                r.center.x as f32,
                                r.center.y as f32,
                                (r.height / 2.0) as f32,
                            ]
                        })
                        .collect();
                    let halves: Vec<[f32; 3]> = t
                        .rocks
                        .iter()
                        .map(|r| [r.radius as f32, r.radius as f32, (r.height / 2.0) as f32])
                        .collect();
                    self.rec.log_static(
                        "world/rocks",
                        &rerun::Ellipsoids3D::from_centers_and_half_sizes(centers, halves)
                            .with_colors([rerun::Color::from_rgb(150, 110, 80)])
                            .with_fill_mode(rerun::FillMode::Solid),
                    )?;
                }
            }
        }
        Ok(())
    }

    fn reports(&mut self, reports: &[DnmGlance]) -> anyhow::Result<()> {
        let mut changed = false;
        let answering: BTreeSet<String> = reports.iter().map(|r| r.dnm.clone()).collect();
        for d in answering.difference(&self.dnms_seen.clone()) {
            self.say(rerun::TextLogLevel::INFO, &format!("DNM `{d}` answers"))?;
        }
        for d in self.dnms_seen.clone().difference(&answering) {
            self.say(
                rerun::TextLogLevel::WARN,
                &format!("DNM `{d}` does not answer"),
            )?;
        }
        self.dnms_seen = answering;
        for r in reports {
            for m in &r.modules {
                let before = self.states.insert(m.name.clone(), m.state);
                if before != Some(m.state) {
                    changed = true;
                    if before.is_some() {
                        let level = match m.state {
                            ModuleRunState::Failed | ModuleRunState::Hung => {
                                rerun::TextLogLevel::ERROR
                            }
                            ModuleRunState::Stopped => rerun::TextLogLevel::WARN,
                            _ => rerun::TextLogLevel::INFO,
                        };
                        self.say(
                            level,
                            &format!(
                                "module `{}` on `{}` is {}",
                                m.name,
                                r.dnm,
                                state_name(m.state)
                            ),
                        )?;
                    }
                }
            }
            for e in &r.events {
                let id = (e.dnm.clone(), e.module.clone(), e.what.clone(), e.at_ns);
                if self.events_seen.insert(id) {
                    self.module_event(e)?;
                }
            }
            for s in &r.switches {
                let id = (s.dnm.clone(), s.revision, s.to.clone(), s.at_ns);
                if self.switches_seen.insert(id) {
                    self.switched(&r.dnm, s)?;
                }
            }
            for p in &r.peers {
                let key = (r.dnm.clone(), p.dnm.clone());
                let before = self.peers.insert(key, p.state.clone());
                if before.as_ref().is_some_and(|b| *b != p.state) {
                    let level = if p.state == "alive" {
                        rerun::TextLogLevel::INFO
                    } else {
                        rerun::TextLogLevel::WARN
                    };
                    self.say(
                        level,
                        &format!("link `{}` → `{}`: {}", r.dnm, p.dnm, p.state),
                    )?;
                }
            }
        }
        // Forget what the DNMs no longer report (their lists are bounded): the sets stay small
        // on a long mission.
        let reported: BTreeSet<_> = reports
            .iter()
            .flat_map(|r| {
                r.events
                    .iter()
                    .map(|e| (e.dnm.clone(), e.module.clone(), e.what.clone(), e.at_ns))
            })
            .collect();
        self.events_seen
            .retain(|e| !self.dnms_seen.contains(&e.0) || reported.contains(e));
        let reported: BTreeSet<_> = reports
            .iter()
            .flat_map(|r| {
                r.switches
                    .iter()
                    .map(|s| (s.dnm.clone(), s.revision, s.to.clone(), s.at_ns))
            })
            .collect();
        self.switches_seen
            .retain(|s| !self.dnms_seen.contains(&s.0) || reported.contains(s));
        if changed {
            self.draw_graph()?;
        }
        Ok(())
    }

    /// The connection graph: a column of modules per DNM, coloured by state, and the active
    /// task's links.
    fn draw_graph(&self) -> anyhow::Result<()> {
        let Some(w) = &self.wiring else {
            return Ok(());
        };
        let mut ids = Vec::new();
        let mut labels = Vec::new();
        let mut colors = Vec::new();
        let mut positions = Vec::new();
        for (col, d) in w.dnms.iter().enumerate() {
            for (row, m) in w.modules.iter().filter(|m| m.dnm == d.name).enumerate() {
                let state = self.states.get(&m.name).copied();
                ids.push(m.name.clone());
                labels.push(format!("{} · {}", m.name, d.name));
                colors.push(state_color(state));
                positions.push([col as f32 * 260.0, row as f32 * 70.0]);
            }
        }
        self.at_now();
        self.rec.log(
            "graph",
            &rerun::GraphNodes::new(ids)
                .with_labels(labels)
                .with_colors(colors)
                .with_positions(positions),
        )?;
        let edges: Vec<(String, String)> = w
            .active_links()
            .iter()
            .map(|l| (l.from.module.clone(), l.to.module.clone()))
            .collect();
        self.rec.log(
            "graph",
            &rerun::GraphEdges::new(edges).with_directed_edges(),
        )?;
        Ok(())
    }

    fn sample(
        &mut self,
        module: &str,
        port: &str,
        encoding: &str,
        bytes: &[u8],
        unix_ns: u64,
    ) -> anyhow::Result<()> {
        self.rec
            .set_timestamp_nanos_since_epoch(TIMELINE, unix_ns as i64);
        if encoding == JPEG_ENCODING {
            self.rec.log(
                format!("camera/{module}/{port}"),
                &rerun::EncodedImage::from_file_contents(bytes.to_vec())
                    .with_media_type(rerun::MediaType::JPEG),
            )?;
            return Ok(());
        }
        let Some(message) = self.messages.get(&(module.to_string(), port.to_string())) else {
            return Ok(());
        };
        let value = dnm_netlist::values::decode(message, bytes);
        if let Some((x, y, z)) = self.draw(module, port, &value)? {
            let path = self.paths.entry(module.to_string()).or_default();
            let p = [x as f32, y as f32, z as f32];
            let far = path.points.last().is_none_or(|q| {
                let (dx, dy) = (q[0] - p[0], q[1] - p[1]);
                f64::from(dx * dx + dy * dy).sqrt() >= PATH_STEP
            });
            if far {
                path.points.push(p);
                path.dirty = true;
            }
        }
        Ok(())
    }

    /// A camera frame as its port carries it (`dnm-image-rgb8`: width, height and row step,
    /// then the rows); a frame shorter than its header says is left out.
    fn image(
        &mut self,
        module: &str,
        port: &str,
        bytes: &[u8],
        unix_ns: u64,
    ) -> anyhow::Result<()> {
        let Some(dnm_rover::msgs::ImageLayout {
            width,
            height,
            step,
        }) = dnm_rover::msgs::ImageLayout::of(bytes)
        else {
            return Ok(());
        };
        let pixels = &bytes[dnm_rover::msgs::IMAGE_HEADER..];
        let row = width * 3;
        if width == 0 {
            return Ok(());
        }
        let rgb: Vec<u8> = if step == row {
            pixels[..row * height].to_vec()
        } else {
            pixels
                .chunks(step)
                .take(height)
                .flat_map(|r| &r[..row])
                .copied()
                .collect()
        };
        self.rec
            .set_timestamp_nanos_since_epoch(TIMELINE, unix_ns as i64);
        self.rec.log(
            format!("camera/{module}/{port}"),
            &rerun::Image::from_rgb24(rgb, [width as u32, height as u32]),
        )?;
        Ok(())
    }

    /// Draws a message's fields at the time set: every numeric field as a time series, and a
    /// pose (`x`, `y`, `yaw`) as the module's body in the world; the pose's position, if any.
    fn draw(
        &mut self,
        module: &str,
        port: &str,
        value: &Value,
    ) -> anyhow::Result<Option<(f64, f64, f64)>> {
        let mut fields = Vec::new();
        numeric_fields("", value, &mut fields);
        fields.truncate(MAX_FIELDS);
        for (field, v) in &fields {
            self.rec.log(
                format!("series/{module}/{port}/{field}"),
                &rerun::Scalars::single(*v),
            )?;
        }
        let get = |k: &str| fields.iter().find(|(f, _)| f == k).map(|(_, v)| *v);
        if let (Some(x), Some(y), Some(yaw)) = (get("x"), get("y"), get("yaw")) {
            let z = get("z").unwrap_or(0.0);
            let truth = self
                .wiring
                .as_ref()
                .and_then(|w| w.module(module))
                .is_some_and(|m| m.kind == "rover_world");
            let color = if truth {
                rerun::Color::from_rgb(230, 230, 230)
            } else {
                rerun::Color::from_rgb(255, 170, 0)
            };
            self.rec.log(
                format!("world/{module}"),
                &rerun::Transform3D::from_translation_rotation(
                    [x as f32, y as f32, z as f32],
                    rerun::RotationAxisAngle::new(
                        [0.0, 0.0, 1.0],
                        rerun::Angle::from_radians(yaw as f32),
                    ),
                ),
            )?;
            self.rec.log(
                format!("world/{module}/body"),
                &rerun::Boxes3D::from_half_sizes([[0.3, 0.22, 0.1]])
                    .with_centers([[0.0, 0.0, 0.1]])
                    .with_colors([color])
                    .with_labels([if truth { "truth" } else { module }]),
            )?;
            return Ok(Some((x, y, z)));
        }
        Ok(None)
    }

    /// The stretches of a module's path that stations filled in, in blue (as the station's
    /// page draws them), a strip per stretch.
    fn flush_filled(&mut self) -> anyhow::Result<()> {
        for m in std::mem::take(&mut self.filled_dirty) {
            let Some(points) = self.filled.get(&m) else {
                continue;
            };
            let mut strips: Vec<Vec<[f32; 3]>> = Vec::new();
            let mut last: Option<u64> = None;
            for (t, p) in points {
                let apart = last.is_none_or(|l| t.saturating_sub(l) > FILLED_APART_NS);
                match strips.last_mut() {
                    Some(s) if !apart => s.push(*p),
                    _ => strips.push(vec![*p]),
                }
                last = Some(*t);
            }
            self.at_now();
            self.rec.log(
                format!("world/paths/{m}/filled"),
                &rerun::LineStrips3D::new(strips)
                    .with_colors([rerun::Color::from_rgb(70, 130, 230)])
                    .with_radii([0.03]),
            )?;
        }
        Ok(())
    }

    /// Paths are logged at most twice a second (they are whole strips).
    fn flush_paths(&mut self, all: bool) -> anyhow::Result<()> {
        self.flush_filled()?;
        let now = self.now_ns();
        let due: Vec<String> = self
            .paths
            .iter()
            .filter(|(_, p)| {
                p.dirty
                    && (all
                        // Either way: a wall clock stepped back must not stop the paths.
                        || p.logged_at_ns
                            .is_none_or(|t| now.abs_diff(t) >= PATH_EVERY_NS))
            })
            .map(|(m, _)| m.clone())
            .collect();
        for m in due {
            let truth = self
                .wiring
                .as_ref()
                .and_then(|w| w.module(&m))
                .is_some_and(|w| w.kind == "rover_world");
            let Some(p) = self.paths.get_mut(&m) else {
                continue;
            };
            self.rec
                .set_timestamp_nanos_since_epoch(TIMELINE, now as i64);
            self.rec.log(
                format!("world/paths/{m}/{}", p.segment),
                &rerun::LineStrips3D::new([p.points.clone()])
                    .with_colors([if truth {
                        rerun::Color::from_rgb(230, 230, 230)
                    } else {
                        rerun::Color::from_rgb(255, 170, 0)
                    }])
                    .with_radii([0.03]),
            )?;
            p.dirty = false;
            p.logged_at_ns = Some(now);
            if p.points.len() >= SEGMENT_POINTS {
                // That segment is whole: the next starts where it ends.
                p.segment += 1;
                p.points = p.points.last().copied().into_iter().collect();
            }
        }
        Ok(())
    }

    /// The operator's layout; the time series get a tab per module once the wiring is known.
    fn send_blueprint(&mut self) -> anyhow::Result<()> {
        let modules: Vec<String> = self
            .wiring
            .as_ref()
            .map(|w| {
                w.modules
                    .iter()
                    .filter(|m| {
                        m.outputs
                            .iter()
                            .any(|p| p.message.encoding != "dnm-image-rgb8")
                    })
                    .map(|m| m.name.clone())
                    .collect()
            })
            .unwrap_or_default();
        if !self.blueprint_modules.is_empty() && modules == self.blueprint_modules {
            return Ok(());
        }
        self.blueprint_modules = modules.clone();
        let series: ContainerLike = if modules.is_empty() {
            TimeSeriesView::new("Time series")
                .with_origin("series")
                .into()
        } else {
            Tabs::new(modules.iter().map(|m| {
                TimeSeriesView::new(m.as_str())
                    .with_origin(format!("series/{m}"))
                    .into()
            }))
            .into()
        };
        let blueprint = Blueprint::new(Horizontal::new([
            Vertical::new([
                Spatial3DView::new("World").with_origin("world").into(),
                Spatial2DView::new("Camera").with_origin("camera").into(),
            ])
            .with_row_shares([0.6, 0.4])
            .into(),
            Vertical::new([
                GraphView::new("Connection layer")
                    .with_origin("graph")
                    .into(),
                series,
                TextLogView::new("Events").with_origin("log").into(),
            ])
            .with_row_shares([0.4, 0.35, 0.25])
            .into(),
        ]))
        // The operator's views take the screen; the panels stay a click away.
        .with_blueprint_panel(BlueprintPanel::from_state(PanelState::Collapsed))
        .with_selection_panel(SelectionPanel::from_state(PanelState::Collapsed))
        .with_time_panel(TimePanel::new().with_state(PanelState::Collapsed));
        blueprint.send(&self.rec, BlueprintActivation::default())?;
        Ok(())
    }
}

fn state_name(s: ModuleRunState) -> &'static str {
    match s {
        ModuleRunState::Starting => "starting",
        ModuleRunState::Running => "running",
        ModuleRunState::Hung => "hung",
        ModuleRunState::Failed => "failed",
        ModuleRunState::Stopped => "stopped",
    }
}

fn state_color(s: Option<ModuleRunState>) -> rerun::Color {
    match s {
        Some(ModuleRunState::Running) => rerun::Color::from_rgb(60, 180, 75),
        Some(ModuleRunState::Starting) => rerun::Color::from_rgb(230, 200, 40),
        Some(ModuleRunState::Hung) => rerun::Color::from_rgb(245, 130, 48),
        Some(ModuleRunState::Failed) => rerun::Color::from_rgb(220, 40, 40),
        Some(ModuleRunState::Stopped) | None => rerun::Color::from_rgb(140, 140, 140),
    }
}

/// Every number in `v` (booleans as 0/1), by path: `field`, `field/0`, `a/b`.
pub fn numeric_fields(prefix: &str, v: &Value, out: &mut Vec<(String, f64)>) {
    let join = |k: &str| {
        if prefix.is_empty() {
            k.to_string()
        } else {
            format!("{prefix}/{k}")
        }
    };
    match v {
        Value::Number(n) => {
            if let Some(f) = n.as_f64().filter(|f| f.is_finite()) {
                out.push((prefix.to_string(), f));
            }
        }
        Value::Bool(b) => out.push((prefix.to_string(), f64::from(u8::from(*b)))),
        Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                numeric_fields(&join(&i.to_string()), x, out);
            }
        }
        Value::Object(o) => {
            for (k, x) in o {
                // Keys become entity path parts: keep them to safe characters.
                let k: String = k
                    .chars()
                    .map(|c| {
                        if c.is_ascii_alphanumeric() || c == '_' || c == '-' {
                            c
                        } else {
                            '_'
                        }
                    })
                    .collect();
                numeric_fields(&join(&k), x, out);
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_number_becomes_a_series() {
        let v =
            serde_json::json!({"x": 1.5, "gyro": [1, 2], "ok": true, "name": "a", "a b": {"c": 3}});
        let mut out = Vec::new();
        numeric_fields("", &v, &mut out);
        out.sort_by(|a, b| a.0.cmp(&b.0));
        assert_eq!(
            out,
            vec![
                ("a_b/c".to_string(), 3.0),
                ("gyro/0".to_string(), 1.0),
                ("gyro/1".to_string(), 2.0),
                ("ok".to_string(), 1.0),
                ("x".to_string(), 1.5),
            ]
        );
    }
}
