//! Beetle-One end to end: the demo mission headless, and the safety watchdog when the
//! operator's joystick process dies. Every process is real; the rover's state is read over
//! Zenoh from the port keys, as an operator's tool would.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use dnm_rover::msgs::{MotorState, WatchdogState};
use serde_json::Value;
use zenoh::Wait;

#[path = "support/mod.rs"]
mod support;

use support::{eventually, free_port, zenoh_client};

const DNM: &str = env!("CARGO_BIN_EXE_dnm");
const BEETLE: &str = include_str!("../configs/beetle.toml");

/// configs/beetle.toml under a system name of its own, in a folder of its own.
fn netlist(tag: &str) -> (String, PathBuf) {
    let system = format!("beetle{}{tag}", std::process::id());
    let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("beetle.toml");
    // No ground station takes part here: the rover must not go safe for the lack of one.
    std::fs::write(
        &path,
        BEETLE
            .replace("name = \"beetle\"", &format!("name = \"{system}\""))
            .replace("after = \"5s\"", "after = \"1h\""),
    )
    .unwrap();
    (system, path)
}

#[test]
fn demo_mission_runs_headless_and_odometry_matches_ground_truth() {
    let (system, path) = netlist("demo");
    let out = Command::new(DNM)
        .args([
            "--no-multicast",
            "demo",
            "--json",
            "--teleop-seconds",
            "4",
            "--netlist",
        ])
        .arg(&path)
        .env("DNM_RUN_DIR", path.parent().unwrap())
        .env("DNM_RECORD_DIR", path.parent().unwrap().join("recordings"))
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "demo failed: {stdout}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let s: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(s["ok"], true, "{s:#}");
    // Waypoints reached under the autopilot.
    assert_eq!(s["waypoints_total"], 3);
    assert_eq!(s["waypoints_reached"], 3);
    // Final odometry agrees with the simulator's ground truth within the stated tolerance
    // (0.1 m + 1 % of the distance driven), moving and at rest.
    let distance = s["distance_m"].as_f64().unwrap();
    assert!(distance > 8.0, "the rover hardly moved: {distance} m");
    let tolerance = 0.1 + 0.01 * distance;
    assert!(
        s["final_position_error_m"].as_f64().unwrap() <= tolerance,
        "{s:#}"
    );
    assert!(
        s["at_rest_position_error_m"].as_f64().unwrap() <= tolerance,
        "{s:#}"
    );
    assert!(
        s["final_heading_error_deg"].as_f64().unwrap() < 5.0,
        "{s:#}"
    );
    // teleop -> auto -> teleop through the ground station, on the rover's three DNMs at one
    // instant (the ground's DNM, across the radio, follows); a module replaced in between.
    let switches = s["switches"].as_array().unwrap();
    let tos: Vec<&str> = switches.iter().map(|w| w["to"].as_str().unwrap()).collect();
    assert_eq!(tos, ["auto", "teleop"]);
    for w in switches {
        assert_eq!(w["per_dnm_ns"].as_array().unwrap().len(), 3, "{w}");
        assert!(w["command_to_switch_ms"].as_f64().unwrap() > 0.0, "{w}");
        // A loaded test machine: the benchmark measures the spread on a quiet one.
        assert!(w["spread_us"].as_f64().unwrap() < 20_000.0, "{w}");
    }
    assert!(s["replaced"].as_str().unwrap().starts_with("camera"));
    assert!(s["zenoh_messages"].as_u64().unwrap() > 1000);
    assert_eq!(s["watchdog_trips"], 0);

    // The mission is one session folder: every DNM's files and a manifest listing exactly
    // them, whose counts are what the files hold (read back with the mcap crate).
    let root = path.parent().unwrap().join("recordings");
    let sessions: Vec<PathBuf> = std::fs::read_dir(&root)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.is_dir())
        .collect();
    assert_eq!(sessions.len(), 1, "{sessions:?}");
    let session = &sessions[0];
    let name = session.file_name().unwrap().to_string_lossy().into_owned();
    assert!(name.starts_with(&format!("{system}-")), "{name}");
    let manifest: Value = serde_json::from_slice(
        &std::fs::read(session.join("manifest.json")).expect("a manifest in the session"),
    )
    .unwrap();
    let mut on_disk: Vec<String> = std::fs::read_dir(session)
        .unwrap()
        .flatten()
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".mcap"))
        .collect();
    on_disk.sort();
    let mut listed: Vec<String> = manifest["files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["name"].as_str().unwrap().to_string())
        .collect();
    listed.sort();
    assert_eq!(
        listed, on_disk,
        "the manifest lists exactly the session's files"
    );
    assert_eq!(
        manifest["dnms"],
        serde_json::json!(["drive", "ground", "rover", "vision"])
    );
    assert_eq!(
        manifest["revisions"],
        serde_json::json!([1, 2]),
        "the camera replaced"
    );
    let mut total = 0u64;
    for f in manifest["files"].as_array().unwrap() {
        assert_eq!(f["complete"], true, "{f}");
        let bytes = std::fs::read(session.join(f["name"].as_str().unwrap())).unwrap();
        let n = mcap::MessageStream::new(&bytes).unwrap().count() as u64;
        assert_eq!(f["messages"].as_u64().unwrap(), n, "{f}");
        total += n;
    }
    assert_eq!(manifest["messages"].as_u64().unwrap(), total);
    // Per channel and in time: odometry on the rover's files, over the mission's span.
    let odom: u64 = manifest["files"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|f| f["channels"]["/rover/odometry/odom"].as_u64())
        .sum();
    assert!(odom > 100, "{manifest:#}");
    let span_s = (manifest["end_unix_ns"].as_u64().unwrap()
        - manifest["start_unix_ns"].as_u64().unwrap()) as f64
        / 1e9;
    assert!(span_s > 10.0, "the session spans the mission: {span_s} s");
    let netlists = manifest["netlists"].as_array().unwrap();
    assert_eq!(netlists.len(), 2);
    assert!(
        netlists
            .iter()
            .all(|n| n["text"].as_str().unwrap().contains("[task.auto]"))
    );
    // `dnm recordings` lists it; `dnm stats` reads the folder.
    let listed = Command::new(DNM)
        .args(["recordings", "--json"])
        .arg(&root)
        .output()
        .unwrap();
    assert!(listed.status.success());
    let listed: Value = serde_json::from_slice(&listed.stdout).unwrap();
    assert_eq!(listed[0]["session"], name.as_str());
    let stats = Command::new(DNM)
        .args(["stats", "--json"])
        .arg(session)
        .output()
        .unwrap();
    assert!(
        stats.status.success(),
        "{}",
        String::from_utf8_lossy(&stats.stderr)
    );
    let stats: Value = serde_json::from_slice(&stats.stdout).unwrap();
    assert_eq!(stats.as_array().unwrap().len(), on_disk.len());
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}

/// A module's entry in a DNM report.
fn module(report: &Value, name: &str) -> Value {
    report["modules"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == name)
        .unwrap()
        .clone()
}

struct Up(Child);

impl Drop for Up {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.0.id() as i32, libc::SIGTERM) };
        let _ = self.0.wait();
    }
}

fn last<T: bytemuck::Pod>(
    session: &zenoh::Session,
    key: &str,
) -> Option<(T, dnm::keys::SampleHeader)> {
    let replies = session
        .get(key)
        .timeout(Duration::from_secs(5))
        .wait()
        .unwrap();
    let reply = replies.recv().ok()?;
    let s = reply.result().ok()?;
    let bytes = s.payload().to_bytes();
    let header = dnm::keys::decode_header(&s.attachment()?.to_bytes())?;
    (bytes.len() == size_of::<T>()).then(|| (bytemuck::pod_read_unaligned(&bytes), header))
}

#[test]
fn watchdog_stops_the_motors_when_the_joystick_dies() {
    let (system, path) = netlist("wd");
    let port = free_port();
    let _up = Up(Command::new(DNM)
        .args([
            "--no-multicast",
            "--listen",
            &format!("tcp/127.0.0.1:{port}"),
            "up",
        ])
        .arg(&path)
        .arg("--state-dir")
        .arg(path.parent().unwrap().join("state"))
        .env("DNM_RUN_DIR", path.parent().unwrap())
        .env("DNM_RECORD_DIR", path.parent().unwrap().join("recordings"))
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap());
    let session = zenoh_client(port);
    let key = |dnm: &str, module: &str, port: &str| format!("{system}/port/{dnm}/{module}/{port}");

    // The joystick drives: the wheels turn.
    eventually("the joystick drives the wheels", || {
        let (m, _) = last::<MotorState>(&session, &key("drive", "motor_left", "state"))?;
        (m.omega > 1.0).then_some(())
    });
    let report = |dnm: &str| -> Value {
        let replies = session
            .get(format!("{system}/dnm/{dnm}"))
            .timeout(Duration::from_secs(5))
            .wait()
            .unwrap();
        let r = replies.recv().unwrap();
        serde_json::from_slice(&r.result().unwrap().payload().to_bytes()).unwrap()
    };
    let joystick = module(&report("ground"), "joystick");
    let pid = joystick["pid"].as_u64().unwrap() as i32;

    // The operator's joystick process dies.
    // SAFETY: kill(2) with the pid the DNM reported for its module process.
    assert_eq!(unsafe { libc::kill(pid, libc::SIGKILL) }, 0);

    // The watchdog trips: it commands a stop within its timeout of the last command
    // (measured by the watchdog's own clock, not by this test's).
    let (wd, _) = eventually("the watchdog trips", || {
        last::<WatchdogState>(&session, &key("drive", "watchdog", "state"))
            .filter(|(w, _)| w.tripped == 1)
    });
    assert_eq!(wd.trips, 1);
    let period_ns = 1_000_000_000 / 50; // the watchdog steps at 50 Hz
    let reaction = wd.tripped_at_ns - wd.last_command_ns;
    assert!(
        reaction >= wd.timeout_ns && reaction <= wd.timeout_ns + 2 * period_ns,
        "tripped {reaction} ns after the last command; timeout {} ns",
        wd.timeout_ns
    );
    // Both motors are commanded to stop and do.
    for motor in ["motor_left", "motor_right"] {
        let (m, h) = eventually(&format!("{motor} stops"), || {
            last::<MotorState>(&session, &key("drive", motor, "state"))
                .filter(|(m, _)| m.command == 0.0 && m.omega.abs() < 0.01)
        });
        assert!(h.stamp_ns > wd.tripped_at_ns, "{m:?}");
    }
    // The joystick stays down (`restart = "never"`), and the watchdog keeps the stop.
    let joystick = module(&report("ground"), "joystick");
    assert_eq!(joystick["state"], "stopped", "{joystick}");
    let (wd, _) = last::<WatchdogState>(&session, &key("drive", "watchdog", "state")).unwrap();
    assert_eq!((wd.tripped, wd.trips), (1, 1));
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}
