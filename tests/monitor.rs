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
}

fn read(path: &Path) -> Rrd {
    let file = std::fs::File::open(path).unwrap();
    let mut rrd = Rrd {
        entities: BTreeSet::new(),
        rows: BTreeMap::new(),
        edges: Vec::new(),
        blueprint_messages: 0,
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
    let has = |e: &str| rrd.entities.contains(e);
    // The pose: the simulator's truth and the odometry estimate, their paths, the scene.
    for e in [
        "/world/world",
        "/world/odometry",
        "/world/paths/world/0",
        "/world/paths/odometry/0",
        "/world/rocks",
        "/world/waypoints/autopilot",
    ] {
        assert!(has(e), "no {e} in {:?}", rrd.entities);
    }
    // The camera, as JPEG frames that crossed Zenoh.
    assert!(
        rrd.rows.get("/camera/camera/image").copied().unwrap_or(0) >= 3,
        "camera frames: {:?}",
        rrd.rows.get("/camera/camera/image")
    );
    // Time series: wheel speeds and motor currents, battery, IMU, range, the commanded twist,
    // and the JSON telemetry, every numeric field, with no code for those kinds.
    for e in [
        "/series/motor_left/state/omega",
        "/series/motor_left/state/current",
        "/series/battery/state/voltage",
        "/series/imu/imu/gyro/2",
        "/series/range/range/range",
        "/series/mixer/left/omega",
        "/series/watchdog/twist/linear",
        "/series/odometry/odom/x",
    ] {
        assert!(
            rrd.rows.get(e).copied().unwrap_or(0) >= 10,
            "{e}: {:?} rows; entities: {:?}",
            rrd.rows.get(e),
            rrd.entities
        );
    }
    assert!(
        rrd.entities
            .iter()
            .any(|e| e.starts_with("/series/telemetry/")),
        "telemetry (JSON) fields: {:?}",
        rrd.entities
    );
    assert!(has("/graph") && has("/log"));
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
    let _ = std::fs::remove_dir_all(&dir);
}
