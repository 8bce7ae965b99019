//! Beetle-One watched in Rerun: `dnm demo --rerun-save` runs the mission (teleop, a switch to
//! the autopilot, a module replaced, a switch back) with `dnm-monitor` on the demo's Zenoh
//! network, and the `.rrd` it saved is read back with Rerun's own decoder: the pose, the
//! camera, the time series, the graph's nodes and edges are there, and after each switch the
//! graph's edges are the new task's links.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::collections::{BTreeMap, BTreeSet};
use std::io::BufReader;
use std::path::{Path, PathBuf};
use std::process::Command;

use re_log_encoding::rrd::DecoderApp;
use re_log_types::{LogMsg, StoreKind};
use rerun::components::GraphEdge;

const BEETLE: &str = include_str!("../configs/beetle.toml");

/// The `dnm` command, built next to this package's `dnm-monitor` by `cargo test --workspace`.
fn dnm() -> PathBuf {
    let dir = Path::new(env!("CARGO_BIN_EXE_dnm-monitor"))
        .parent()
        .unwrap();
    let p = dir.join("dnm");
    assert!(
        p.exists(),
        "{} is missing: run the tests with `cargo test --workspace`",
        p.display()
    );
    p
}

/// The module-level links of a task of configs/beetle.toml, as (from, to).
fn task_edges(task: &str) -> BTreeSet<(String, String)> {
    let v: toml::Value = toml::from_str(BEETLE).unwrap();
    v["task"][task]["links"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| {
            let (from, to) = l.as_str().unwrap().split_once(" -> ").unwrap();
            let module = |p: &str| p.split_once('.').unwrap().0.to_string();
            (module(from), module(to))
        })
        .collect()
}

/// What the recording holds: every entity path, and the graph's edge sets in time order.
struct Rrd {
    entities: BTreeSet<String>,
    /// Rows per entity.
    rows: BTreeMap<String, usize>,
    edges: Vec<(i64, BTreeSet<(String, String)>)>,
    blueprint_messages: usize,
    /// Times of the rows, per entity.
    times: BTreeMap<String, Vec<i64>>,
}

impl Rrd {
    /// Fails unless every one of `entities` was logged.
    fn assert_has(&self, entities: &[&str]) {
        for e in entities {
            assert!(self.entities.contains(*e), "no {e} in {:?}", self.entities);
        }
    }

    /// Fails unless every one of `entities` has at least `least` rows.
    fn assert_rows(&self, entities: &[&str], least: usize) {
        for e in entities {
            assert!(
                self.rows.get(*e).copied().unwrap_or(0) >= least,
                "{e}: {:?} rows, {least} at least; entities: {:?}",
                self.rows.get(*e),
                self.entities
            );
        }
    }
}

fn read(path: &Path) -> Rrd {
    let file = std::fs::File::open(path).unwrap();
    let mut rrd = Rrd {
        entities: BTreeSet::new(),
        rows: BTreeMap::new(),
        edges: Vec::new(),
        blueprint_messages: 0,
        times: BTreeMap::new(),
    };
    let edges_id = rerun::GraphEdges::descriptor_edges().component;
    for msg in DecoderApp::decode_eager(BufReader::new(file)).unwrap() {
        let LogMsg::ArrowMsg(store, arrow) = msg.unwrap() else {
            continue;
        };
        if store.kind() == StoreKind::Blueprint {
            rrd.blueprint_messages += 1;
            continue;
        }
        let chunk = re_chunk::Chunk::from_arrow_msg(&arrow).unwrap();
        let entity = chunk.entity_path().to_string();
        *rrd.rows.entry(entity.clone()).or_default() += chunk.num_rows();
        rrd.entities.insert(entity.clone());
        if let Some(t) = chunk.timelines().get(&"time".into()) {
            rrd.times
                .entry(entity.clone())
                .or_default()
                .extend(t.times_raw());
        }
        if entity == "/graph" {
            let times: Vec<i64> = chunk
                .iter_component_indices("time".into(), edges_id)
                .map(|(t, _)| t.as_i64())
                .collect();
            for (t, edges) in times
                .into_iter()
                .zip(chunk.iter_component::<GraphEdge>(edges_id))
            {
                let set = edges
                    .iter()
                    .map(|e| (e.0.first.to_string(), e.0.second.to_string()))
                    .collect();
                rrd.edges.push((t, set));
            }
        }
    }
    rrd.edges.sort_by_key(|(t, _)| *t);
    rrd
}

#[test]
fn the_demo_mission_saved_through_the_monitor_reads_back_in_rerun() {
    let dir = std::env::temp_dir().join(format!("dnm-test-monitor-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let system = format!("beetle{}mon", std::process::id());
    let netlist = dir.join("beetle.toml");
    std::fs::write(
        &netlist,
        BEETLE.replace("name = \"beetle\"", &format!("name = \"{system}\"")),
    )
    .unwrap();
    let rrd_path = dir.join("mission.rrd");
    let out = Command::new(dnm())
        .args(["--no-multicast", "demo", "--json", "--teleop-seconds", "4"])
        .arg("--netlist")
        .arg(&netlist)
        .arg("--rerun-save")
        .arg(&rrd_path)
        .env("DNM_RUN_DIR", &dir)
        .env("DNM_RECORD_DIR", dir.join("recordings"))
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "demo failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let summary: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(summary["ok"], true, "{summary:#}");

    let rrd = read(&rrd_path);
    // The pose: the simulator's truth and the odometry estimate, their paths, the scene.
    rrd.assert_has(&[
        "/world/world",
        "/world/odometry",
        "/world/paths/world/0",
        "/world/paths/odometry/0",
        "/world/rocks",
        "/world/waypoints/autopilot",
    ]);
    // The camera, as JPEG frames that crossed Zenoh.
    rrd.assert_rows(&["/camera/camera/image"], 3);
    // Time series: wheel speeds and motor currents, battery, IMU, range, the commanded twist,
    // and the JSON telemetry, every numeric field, with no code for those kinds.
    rrd.assert_rows(
        &[
            "/series/motor_left/state/omega",
            "/series/motor_left/state/current",
            "/series/battery/state/voltage",
            "/series/imu/imu/gyro/2",
            "/series/range/range/range",
            "/series/mixer/left/omega",
            "/series/watchdog/twist/linear",
            "/series/odometry/odom/x",
        ],
        10,
    );
    assert!(
        rrd.entities
            .iter()
            .any(|e| e.starts_with("/series/telemetry/")),
        "telemetry (JSON) fields: {:?}",
        rrd.entities
    );
    rrd.assert_has(&["/graph", "/log"]);
    assert!(rrd.blueprint_messages > 0, "no blueprint");

    // The connection graph followed the mission: teleop, auto, teleop.
    let teleop = task_edges("teleop");
    let auto = task_edges("auto");
    assert_ne!(teleop, auto);
    let mut seen: Vec<&BTreeSet<(String, String)>> = Vec::new();
    for (_, e) in &rrd.edges {
        if seen.last() != Some(&e) {
            seen.push(e);
        }
    }
    assert_eq!(
        seen,
        vec![&teleop, &auto, &teleop],
        "edge sets drawn in order: {seen:#?}"
    );
    the_recorded_session_reads_back_in_rerun(&dir, &teleop, &auto);
    let _ = std::fs::remove_dir_all(&dir);
}

/// What a session recorded: its task switches (log time, task switched to) in time order, and
/// the log times of odometry's poses.
fn recorded(session: &Path) -> (Vec<(i64, String)>, BTreeSet<i64>) {
    let mut out = Vec::new();
    let mut poses = BTreeSet::new();
    for f in std::fs::read_dir(session).unwrap().flatten() {
        if f.path().extension().is_none_or(|e| e != "mcap") {
            continue;
        }
        let bytes = std::fs::read(f.path()).unwrap();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic.ends_with("/_switches") {
                let v: serde_json::Value = serde_json::from_slice(&m.data).unwrap();
                out.push((m.log_time as i64, v["to"].as_str().unwrap().to_string()));
            }
            if m.channel.topic.ends_with("/odometry/odom") {
                poses.insert(m.log_time as i64);
            }
        }
    }
    out.sort();
    (out, poses)
}

/// `dnm monitor --session` turns the demo's recorded session into an `.rrd`: the operator's
/// layout, the rover in `world`, the camera, the time series, and the connection graph's
/// edges changing at the switches the session recorded, at their recorded times.
fn the_recorded_session_reads_back_in_rerun(
    dir: &Path,
    teleop: &BTreeSet<(String, String)>,
    auto: &BTreeSet<(String, String)>,
) {
    let session = std::fs::read_dir(dir.join("recordings"))
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.is_dir())
        .expect("the demo's session folder");
    let rrd_path = dir.join("session.rrd");
    let out = Command::new(dnm())
        .arg("monitor")
        .arg("--session")
        .arg(&session)
        .arg("--save")
        .arg(&rrd_path)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "dnm monitor --session: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let rrd = read(&rrd_path);
    assert!(rrd.blueprint_messages > 0, "no blueprint");
    rrd.assert_has(&[
        "/world/world",
        "/world/odometry",
        "/world/paths/world/0",
        "/world/rocks",
        "/world/waypoints/autopilot",
        "/graph",
        "/log",
    ]);
    rrd.assert_rows(&["/camera/camera/image"], 3);
    rrd.assert_rows(
        &[
            "/series/motor_left/state/omega",
            "/series/battery/state/voltage",
            "/series/odometry/odom/x",
        ],
        10,
    );
    // The poses are drawn at the times their messages were recorded.
    let (switches, recorded_poses) = recorded(&session);
    let poses = &rrd.times["/world/odometry"];
    assert!(poses.len() >= 10, "{} poses drawn", poses.len());
    let off: Vec<_> = poses
        .iter()
        .filter(|t| !recorded_poses.contains(t))
        .collect();
    assert!(off.is_empty(), "poses drawn at times not recorded: {off:?}");
    // The graph: teleop, auto, teleop, each change at the first DNM's recorded switch to it.
    let mut changes: Vec<(i64, &BTreeSet<(String, String)>)> = Vec::new();
    for (t, e) in &rrd.edges {
        if changes.last().map(|(_, s)| *s) != Some(e) {
            changes.push((*t, e));
        }
    }
    let sets: Vec<_> = changes.iter().map(|(_, s)| *s).collect();
    assert_eq!(sets, vec![teleop, auto, teleop], "edge sets in order");
    for (t, set) in &changes[1..] {
        let to = if *set == auto { "auto" } else { "teleop" };
        assert!(
            switches.iter().any(|(at, task)| at == t && task == to),
            "the edges of `{to}` drawn at {t}, not at a recorded switch: {switches:?}"
        );
        // At the first DNM's switch of that moment (the others follow within a millisecond).
        assert!(
            !switches
                .iter()
                .any(|(at, task)| task == to && at < t && t - at < 1_000_000_000),
            "the edges of `{to}` drawn after the first DNM switched: {switches:?}"
        );
    }
}

/// Two Zenoh peers on loopback: (the station's, the monitor's).
fn peers() -> (zenoh::Session, zenoh::Session) {
    use zenoh::Wait;
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let config = |key: &str| {
        let mut c = zenoh::Config::default();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5(key, &format!("[\"tcp/127.0.0.1:{port}\"]"))
            .unwrap();
        c
    };
    let station = zenoh::open(config("listen/endpoints")).wait().unwrap();
    let monitor = zenoh::open(config("connect/endpoints")).wait().unwrap();
    (station, monitor)
}

#[test]
fn what_a_station_fills_in_is_drawn_where_it_belongs_in_time() {
    use zenoh::Wait;
    let dir = std::env::temp_dir().join(format!("dnm-monitor-filled-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let rrd_path = dir.join("filled.rrd");
    let (station, monitor) = peers();
    let system = "filledsys";
    let rec = rerun::RecordingStreamBuilder::new("filled")
        .save(&rrd_path)
        .unwrap();
    let mut options = dnm_monitor::MonitorOptions::new(system);
    options.duration = Some(std::time::Duration::from_secs(6));
    let run = {
        let rec = rec.clone();
        std::thread::spawn(move || {
            let stop = std::sync::atomic::AtomicBool::new(false);
            dnm_monitor::run(&monitor, &rec, &options, &stop).unwrap()
        })
    };
    // Give the monitor's subscription time to reach the station's peer.
    std::thread::sleep(std::time::Duration::from_secs(2));
    // An outage ten minutes ago, filled in: forty poses, half a second apart, then a second
    // stretch a minute later.
    let t0 = dnm_proto::clock::now_unix_ns() - 600_000_000_000;
    let mut sent = Vec::new();
    for i in 0..40u64 {
        let t = t0 + i * 500_000_000 + if i >= 20 { 60_000_000_000 } else { 0 };
        let pose = serde_json::json!({"x": i as f64 * 0.1, "y": 1.0, "yaw": 0.0, "v": 0.2});
        station
            .put(
                dnm_proto::keys::ground_filled(system, "rover", "odometry", "odom"),
                serde_json::to_vec(&pose).unwrap(),
            )
            .attachment(dnm_proto::keys::encode_downlink(t, i as u32).to_vec())
            .wait()
            .unwrap();
        sent.push(t as i64);
    }
    let stats = run.join().unwrap();
    drop(rec);
    assert_eq!(stats.filled, 40, "{stats:?}");
    let rrd = read(&rrd_path);
    // Each field's series holds the filled-in values at their send times, in the past.
    let times = rrd.times.get("/series/odometry/odom/x").unwrap();
    for t in &sent {
        assert!(times.contains(t), "no x at {t}: {times:?}");
    }
    let poses = rrd.times.get("/world/odometry").unwrap();
    assert!(sent.iter().all(|t| poses.contains(t)), "{poses:?}");
    // The filled-in path, in two stretches.
    assert!(
        rrd.entities.contains("/world/paths/odometry/filled"),
        "{:?}",
        rrd.entities
    );
    let _ = std::fs::remove_dir_all(&dir);
}
