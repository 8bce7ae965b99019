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

/// One simulated rover at a time. Each test runs the whole of Beetle-One (four DNMs, about
/// twenty module processes, the simulator at 100 Hz) and is sized for a two-core machine; two at
/// once starve each other for hundreds of milliseconds, and then the simulation's dead reckoning,
/// the watchdog and the recorders see an overload no rover computer would run.
static ONE_ROVER: std::sync::Mutex<()> = std::sync::Mutex::new(());

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
    let _one = ONE_ROVER.lock().unwrap_or_else(|e| e.into_inner());
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
    // Nothing went wrong, so nothing warns: not even its DNMs stopping in order at the end.
    let stderr = String::from_utf8_lossy(&out.stderr);
    let warnings: Vec<&str> = stderr
        .lines()
        .filter(|l| l.contains("WARN") || l.contains("ERROR"))
        .collect();
    assert!(warnings.is_empty(), "{}", warnings.join("\n"));
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
    // teleop -> auto -> teleop by the exploration sequence, run on board by the authority, on
    // the rover's three DNMs at one instant (the ground's DNM, across the radio, follows); the
    // camera replaced in between.
    let switches = s["switches"].as_array().unwrap();
    let tos: Vec<&str> = switches.iter().map(|w| w["to"].as_str().unwrap()).collect();
    assert_eq!(tos, ["auto", "teleop"]);
    assert!(switches.iter().all(|w| w["by"] == "sequence"), "{s:#}");
    assert_eq!(s["sequence"]["name"], "explore", "{s:#}");
    assert_eq!(s["sequence"]["state"], "finished", "{s:#}");
    let events: Vec<&str> = s["sequence"]["events"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| e.as_str().unwrap())
        .collect();
    assert!(
        events
            .iter()
            .any(|e| e.starts_with("condition_met step 2: autopilot.progress.reached >= 3 held")),
        "{events:#?}"
    );
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
    // The sequence's events are in the authority DNM's files, read back with the mcap crate.
    let mut said: Vec<String> = Vec::new();
    for f in manifest["files"].as_array().unwrap() {
        let bytes = std::fs::read(session.join(f["name"].as_str().unwrap())).unwrap();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == "/rover/_sequences" {
                let e: Value = serde_json::from_slice(&m.data).unwrap();
                assert_eq!(e["sequence"], "explore", "{e}");
                said.push(e["what"].as_str().unwrap().to_string());
            }
        }
    }
    for what in [
        "started",
        "step_started",
        "condition_met",
        "step_done",
        "finished",
    ] {
        assert!(
            said.iter().any(|w| w == what),
            "{what} not recorded: {said:?}"
        );
    }
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

    standard_messages_read_with_a_cdr_reader(session);
    replaying_the_session_reproduces_the_path(&system, session);
    odometry_is_deterministic_on_its_recorded_inputs(session);
    let _ = std::fs::remove_dir_all(path.parent().unwrap());
}

/// ROS 2 messages as robotics tools declare them, read with Rerun's CDR reader (`re_cdr`).
mod ros {
    #![allow(dead_code)] // every field is read (the layout); not every one is checked
    use serde::Deserialize;
    #[derive(Debug, Deserialize)]
    pub struct Time {
        pub sec: i32,
        pub nanosec: u32,
    }
    #[derive(Debug, Deserialize)]
    pub struct Header {
        pub stamp: Time,
        pub frame_id: String,
    }
    #[derive(Debug, Deserialize)]
    pub struct Vector3 {
        pub x: f64,
        pub y: f64,
        pub z: f64,
    }
    #[derive(Debug, Deserialize)]
    pub struct Quaternion {
        pub x: f64,
        pub y: f64,
        pub z: f64,
        pub w: f64,
    }
    #[derive(Debug, Deserialize)]
    pub struct Pose {
        pub position: Vector3,
        pub orientation: Quaternion,
    }
    #[derive(Debug, Deserialize)]
    pub struct Twist {
        pub linear: Vector3,
        pub angular: Vector3,
    }
    #[derive(Debug, Deserialize)]
    pub struct PoseWithCovariance {
        pub pose: Pose,
        pub covariance: [[f64; 6]; 6],
    }
    #[derive(Debug, Deserialize)]
    pub struct TwistWithCovariance {
        pub twist: Twist,
        pub covariance: [[f64; 6]; 6],
    }
    #[derive(Debug, Deserialize)]
    pub struct Odometry {
        pub header: Header,
        pub child_frame_id: String,
        pub pose: PoseWithCovariance,
        pub twist: TwistWithCovariance,
    }
    #[derive(Debug, Deserialize)]
    pub struct Imu {
        pub header: Header,
        pub orientation: Quaternion,
        pub orientation_covariance: [f64; 9],
        pub angular_velocity: Vector3,
        pub angular_velocity_covariance: [f64; 9],
        pub linear_acceleration: Vector3,
        pub linear_acceleration_covariance: [f64; 9],
    }
    #[derive(Debug, Deserialize)]
    pub struct BatteryState {
        pub header: Header,
        pub voltage: f32,
        pub temperature: f32,
        pub current: f32,
        pub charge: f32,
        pub capacity: f32,
        pub design_capacity: f32,
        pub percentage: f32,
        pub power_supply_status: u8,
        pub power_supply_health: u8,
        pub power_supply_technology: u8,
        pub present: bool,
        pub cell_voltage: Vec<f32>,
        pub cell_temperature: Vec<f32>,
        pub location: String,
        pub serial_number: String,
    }
    #[derive(Debug, Deserialize)]
    pub struct Range {
        pub header: Header,
        pub radiation_type: u8,
        pub field_of_view: f32,
        pub min_range: f32,
        pub max_range: f32,
        pub range: f32,
    }
    #[derive(Debug, Deserialize)]
    pub struct JointState {
        pub header: Header,
        pub name: Vec<String>,
        pub position: Vec<f64>,
        pub velocity: Vec<f64>,
        pub effort: Vec<f64>,
    }
    #[derive(Debug, Deserialize)]
    pub struct Transform {
        pub translation: Vector3,
        pub rotation: Quaternion,
    }
    #[derive(Debug, Deserialize)]
    pub struct TransformStamped {
        pub header: Header,
        pub child_frame_id: String,
        pub transform: Transform,
    }
    #[derive(Debug, Deserialize)]
    pub struct TfMessage {
        pub transforms: Vec<TransformStamped>,
    }
    #[derive(Debug, Deserialize)]
    pub struct TwistStamped {
        pub header: Header,
        pub twist: Twist,
    }
    #[derive(Debug, Deserialize)]
    pub struct Image {
        pub header: Header,
        pub height: u32,
        pub width: u32,
        pub encoding: String,
        pub is_bigendian: u8,
        pub step: u32,
        pub data: Vec<u8>,
    }

    pub fn read<'a, T: Deserialize<'a>>(data: &'a [u8]) -> T {
        assert_eq!(&data[..2], &[0, 1], "little-endian CDR");
        let (v, used) = re_cdr::from_bytes::<T, re_cdr::LittleEndian>(&data[4..]).unwrap();
        assert_eq!(used, data.len() - 4, "the whole message is read");
        v
    }
}

/// Every message of a session, by topic: (sequence, log time, data), and each channel's
/// (schema name, schema encoding, message encoding).
type Channels =
    std::collections::BTreeMap<String, ((String, String, String), Vec<(u32, u64, Vec<u8>)>)>;

fn read_session(session: &std::path::Path) -> Channels {
    let mut out = Channels::new();
    for f in support::mcap_files(session) {
        let bytes = std::fs::read(&f).unwrap();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            let schema = m.channel.schema.as_ref().unwrap();
            let e = out.entry(m.channel.topic.clone()).or_insert_with(|| {
                (
                    (
                        schema.name.clone(),
                        schema.encoding.clone(),
                        m.channel.message_encoding.clone(),
                    ),
                    Vec::new(),
                )
            });
            e.1.push((m.sequence, m.log_time, m.data.into_owned()));
        }
    }
    // A DNM's files in the order written: in time.
    for (_, m) in out.values_mut() {
        m.sort_by_key(|(_, t, _)| *t);
    }
    out
}

fn pod<T: bytemuck::Pod>(cdr: &[u8]) -> T {
    bytemuck::pod_read_unaligned(&cdr[4..])
}

/// The session's ports in standard messages: schema names, fields read with a CDR reader, and
/// values equal to the ports' own bytes kept beside them.
fn standard_messages_read_with_a_cdr_reader(session: &std::path::Path) {
    use dnm_rover::msgs as b;
    let ch = read_session(session);
    let expect = [
        ("/drive/world/state", "tf2_msgs/msg/TFMessage", true),
        ("/rover/odometry/odom", "nav_msgs/msg/Odometry", true),
        ("/rover/imu/imu", "sensor_msgs/msg/Imu", false),
        ("/rover/battery/state", "sensor_msgs/msg/BatteryState", true),
        ("/rover/range/range", "sensor_msgs/msg/Range", true),
        (
            "/drive/watchdog/twist",
            "geometry_msgs/msg/TwistStamped",
            false,
        ),
        (
            "/drive/motor_left/state",
            "sensor_msgs/msg/JointState",
            true,
        ),
        (
            "/drive/motor_right/state",
            "sensor_msgs/msg/JointState",
            true,
        ),
        ("/vision/camera/image", "sensor_msgs/msg/Image", false),
    ];
    for (topic, name, raw) in expect {
        let ((schema, enc, msg_enc), msgs) = ch.get(topic).unwrap_or_else(|| panic!("no {topic}"));
        assert_eq!(
            (schema.as_str(), enc.as_str(), msg_enc.as_str()),
            (name, "ros2msg", "cdr"),
            "{topic}"
        );
        assert!(msgs.len() > 10, "{topic}: {} messages", msgs.len());
        assert_eq!(
            ch.contains_key(&format!("{topic}/raw")),
            raw,
            "{topic}: own bytes kept beside it exactly when the standard message cannot hold them"
        );
    }
    // The rover's body beside its pose, as tools that draw URDF look for it: once per file of
    // the DNM that records the pose, its root link the pose's frame.
    let ((schema, enc, msg_enc), bodies) = ch
        .get("/drive/_robot_description/world")
        .expect("the rover's body beside its pose");
    assert_eq!(
        (schema.as_str(), enc.as_str(), msg_enc.as_str()),
        ("std_msgs/msg/String", "ros2msg", "cdr")
    );
    let drive_files = support::mcap_files(session)
        .iter()
        .filter(|f| f.file_name().unwrap().to_string_lossy().contains("-drive"))
        .count();
    assert_eq!(
        bodies.len(),
        drive_files,
        "one body per file of the drive DNM"
    );
    for (_, _, data) in bodies {
        let urdf: String = ros::read(data);
        assert!(
            urdf.contains("<robot name=\"beetle_one\">")
                && urdf.contains("<link name=\"base_link\">"),
            "{urdf}"
        );
    }
    // The pairs of (standard, own) messages of a port, matched by sequence number.
    let pairs = |topic: &str| -> Vec<(&[u8], &[u8])> {
        let own: std::collections::HashMap<u32, &[u8]> = ch[&format!("{topic}/raw")]
            .1
            .iter()
            .map(|(s, _, d)| (*s, d.as_slice()))
            .collect();
        let v: Vec<(&[u8], &[u8])> = ch[topic]
            .1
            .iter()
            .filter_map(|(s, _, d)| Some((d.as_slice(), *own.get(s)?)))
            .collect();
        assert!(v.len() > 10, "{topic}");
        v
    };
    let close = |a: f64, b: f64, tol: f64| (a - b).abs() <= tol;
    for (std, own) in pairs("/drive/world/state") {
        let tf: ros::TfMessage = ros::read(std);
        let w: b::WorldState = pod(own);
        assert_eq!(tf.transforms.len(), 1);
        let t = &tf.transforms[0];
        assert_eq!(
            (t.header.frame_id.as_str(), t.child_frame_id.as_str()),
            ("world", "base_link")
        );
        assert!(t.header.stamp.sec > 1_700_000_000);
        let tr = &t.transform.translation;
        assert_eq!((tr.x, tr.y, tr.z), (w.x, w.y, w.z));
        let q = &t.transform.rotation;
        let yaw = (2.0 * (q.w * q.z + q.x * q.y)).atan2(1.0 - 2.0 * (q.y * q.y + q.z * q.z));
        let d = (yaw - w.yaw).rem_euclid(std::f64::consts::TAU);
        assert!(
            !(1e-9..=std::f64::consts::TAU - 1e-9).contains(&d),
            "{yaw} vs {}",
            w.yaw
        );
        assert!(close(
            q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w,
            1.0,
            1e-12
        ));
    }
    for (std, own) in pairs("/rover/odometry/odom") {
        let o: ros::Odometry = ros::read(std);
        let n: b::Odometry = pod(own);
        assert_eq!(
            (o.header.frame_id.as_str(), o.child_frame_id.as_str()),
            ("odom", "base_link")
        );
        assert_eq!((o.pose.pose.position.x, o.pose.pose.position.y), (n.x, n.y));
        assert!(
            close(
                2.0 * o.pose.pose.orientation.z.atan2(o.pose.pose.orientation.w),
                n.yaw,
                1e-9
            ) || close(
                (2.0 * o.pose.pose.orientation.z.atan2(o.pose.pose.orientation.w) - n.yaw).abs(),
                std::f64::consts::TAU,
                1e-9
            )
        );
        assert_eq!(
            (o.twist.twist.linear.x, o.twist.twist.angular.z),
            (n.linear, n.angular)
        );
        assert_eq!(o.pose.covariance, [[0.0; 6]; 6]);
    }
    for (std, own) in pairs("/rover/battery/state") {
        let s: ros::BatteryState = ros::read(std);
        let n: b::BatteryState = pod(own);
        assert_eq!(
            (s.voltage, s.current, s.percentage),
            (n.voltage as f32, n.current as f32, n.charge as f32)
        );
        assert!(s.present && s.location == "battery" && s.power_supply_status == 2);
        assert!(s.cell_voltage.is_empty() && s.serial_number.is_empty());
    }
    for (std, own) in pairs("/rover/range/range") {
        let s: ros::Range = ros::read(std);
        let n: b::Range = pod(own);
        assert_eq!(
            (s.range, s.max_range, s.radiation_type),
            (n.range as f32, n.max as f32, 1)
        );
    }
    for (std, own) in pairs("/drive/motor_left/state") {
        let s: ros::JointState = ros::read(std);
        let n: b::MotorState = pod(own);
        assert_eq!(s.name, ["motor_left"]);
        assert_eq!(
            (s.velocity.as_slice(), s.effort.as_slice()),
            (&[n.omega][..], &[n.current][..])
        );
        assert!(s.position.is_empty());
    }
    // Exact standard messages: no bytes beside them; every field there.
    for (_, _, d) in &ch["/rover/imu/imu"].1 {
        let s: ros::Imu = ros::read(d);
        assert_eq!(s.orientation_covariance[0], -1.0, "no orientation estimate");
        assert!(
            s.linear_acceleration.z.abs() > 5.0,
            "gravity: {:?}",
            s.linear_acceleration
        );
        assert!(s.angular_velocity.x.is_finite() && s.angular_velocity.y.is_finite());
    }
    let mut turning = 0;
    for (_, _, d) in &ch["/drive/watchdog/twist"].1 {
        let s: ros::TwistStamped = ros::read(d);
        assert_eq!(s.header.frame_id, "base_link");
        assert_eq!((s.twist.linear.y, s.twist.linear.z), (0.0, 0.0));
        turning += usize::from(s.twist.angular.z != 0.0);
    }
    assert!(turning > 0, "the rover turned at some point");
    for (_, _, d) in &ch["/vision/camera/image"].1 {
        let s: ros::Image = ros::read(d);
        assert_eq!((s.width, s.height, s.encoding.as_str()), (320, 240, "rgb8"));
        assert_eq!((s.step, s.data.len()), (960, 960 * 240));
        assert_eq!(s.is_bigendian, 0);
        assert!(!s.header.frame_id.is_empty());
    }
}

/// `dnm replay --check odometry`: its code, on its recorded inputs, writes what it wrote on the
/// rover; with a parameter changed, the check reports where it first diverges.
fn odometry_is_deterministic_on_its_recorded_inputs(session: &std::path::Path) {
    let check = |extra: &[&str]| {
        let out = Command::new(DNM)
            .args(["replay", "--json", "--check", "odometry"])
            .args(extra)
            .arg(session)
            .output()
            .unwrap();
        let report: Value = serde_json::from_slice(&out.stdout)
            .unwrap_or_else(|_| panic!("{}", String::from_utf8_lossy(&out.stderr)));
        (out.status.code(), report)
    };
    let (code, r) = check(&[]);
    assert_eq!(code, Some(0), "{r:#}");
    assert_eq!(r["ok"], true, "{r:#}");
    let odom = &r["outputs"]["odom"];
    let recorded = odom["recorded"].as_u64().unwrap();
    assert!(recorded > 500, "{r:#}");
    assert_eq!(
        odom["identical"].as_u64().unwrap() + odom["within_tolerance"].as_u64().unwrap(),
        recorded,
        "{r:#}"
    );
    // Positions come from encoder counts alone: bit for bit, not just within tolerance.
    assert!(odom["identical"].as_u64().unwrap() > 0, "{r:#}");
    assert_eq!(r["unrecorded_inputs"], 0, "{r:#}");
    eprintln!("determinism check: {odom}");

    // A recording that lost encoder counts says so, and a divergence after them is marked as
    // perhaps the recording's.
    let lossy = with_lost_ticks(session, 200..204);
    let out = Command::new(DNM)
        .args(["replay", "--json", "--check", "odometry"])
        .arg(&lossy)
        .output()
        .unwrap();
    let r: Value = serde_json::from_slice(&out.stdout)
        .unwrap_or_else(|_| panic!("{}", String::from_utf8_lossy(&out.stderr)));
    assert_eq!(r["unrecorded_inputs"], 4, "{r:#}");
    let gap = &r["first_unrecorded_input"];
    assert_eq!(gap["source"], "/encoders/ticks", "{r:#}");
    assert_eq!(
        (gap["from_seq"].as_u64(), gap["to_seq"].as_u64()),
        (Some(200), Some(203))
    );
    assert!(
        gap["after_unix_ns"].as_u64() < gap["before_unix_ns"].as_u64(),
        "{r:#}"
    );
    if !r["divergence"].is_null() {
        assert_eq!(r["divergence"]["after_unrecorded_inputs"], true, "{r:#}");
    }
    let _ = std::fs::remove_dir_all(&lossy);

    let (code, r) = check(&["--set", "wheel_radius=0.16"]);
    assert_eq!(code, Some(1), "{r:#}");
    assert_eq!(r["ok"], false);
    assert_eq!(r["params"]["wheel_radius"], 0.16);
    let d = &r["divergence"];
    assert_eq!(d["output"], "odometry.odom", "{r:#}");
    let fields: Vec<&str> = d["fields"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_str().unwrap())
        .collect();
    assert!(
        fields.contains(&"distance") && fields.contains(&"x"),
        "{r:#}"
    );
    assert!(d["recorded"]["x"] != d["replayed"]["x"], "{r:#}");
}

/// A copy of `session` (its recordings only) whose drive DNM's files lost the encoder counts
/// numbered `lost`.
fn with_lost_ticks(session: &std::path::Path, lost: std::ops::Range<u32>) -> PathBuf {
    let copy = session.with_extension("lossy");
    std::fs::create_dir_all(&copy).unwrap();
    for e in std::fs::read_dir(session).unwrap().flatten() {
        let (path, name) = (e.path(), e.file_name());
        if path.extension().is_none_or(|x| x != "mcap") {
            continue;
        }
        if !name.to_string_lossy().starts_with("rec-drive") {
            std::fs::copy(&path, copy.join(&name)).unwrap();
            continue;
        }
        let bytes = std::fs::read(&path).unwrap();
        let file = std::fs::File::create(copy.join(&name)).unwrap();
        let mut w = mcap::Writer::new(std::io::BufWriter::new(file)).unwrap();
        for m in mcap::MessageStream::new(&bytes).unwrap() {
            let m = m.unwrap();
            if m.channel.topic == "/drive/encoders/ticks" && lost.contains(&m.sequence) {
                continue;
            }
            w.write(&m).unwrap();
        }
        w.finish().unwrap();
    }
    copy
}

const MIRROR: &str = r#"
[system]
name = "SYSTEM"
default_task = "drive"

[[dnm]]
name = "drive"

# Its world is not linked: the encoder counts come from the replay.
[[module]]
name = "encoders"
kind = "wheel_encoders"

[[module]]
name = "odometry"
kind = "odometry"

[task.drive]
links = ["encoders.ticks -> odometry.ticks"]
"#;

/// A whole session replayed into a running system whose odometry is fed by the replayed
/// encoder counts: the path it computes is the rover's recorded path (its pose in the world),
/// within the tolerance the demo holds odometry to.
fn replaying_the_session_reproduces_the_path(system: &str, session: &std::path::Path) {
    use dnm_rover::msgs as b;
    // The rover's path as recorded: its pose in the world (the simulator's truth).
    let recorded: Vec<(f64, f64, f64)> = read_session(session)["/drive/world/state/raw"]
        .1
        .iter()
        .map(|(_, _, d)| pod::<b::WorldState>(d))
        .map(|w| (w.x, w.y, w.distance))
        .collect();
    let mirror = format!("{system}m");
    let dir = session.parent().unwrap().parent().unwrap().join("mirror");
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("mirror.toml");
    std::fs::write(&file, MIRROR.replace("SYSTEM", &mirror)).unwrap();
    let up = Up(Command::new(DNM)
        .args(["--no-multicast", "up"])
        .arg(&file)
        .arg("--record-dir")
        .arg(dir.join("recordings"))
        .env("DNM_RUN_DIR", &dir)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap());
    eventually("the mirror's odometry running", || {
        let out = Command::new(DNM)
            .args(["status", "--json", "--system", &mirror])
            .env("DNM_RUN_DIR", &dir)
            .output()
            .ok()?;
        let v: Value = serde_json::from_slice(&out.stdout).ok()?;
        let running = v.to_string().matches("\"running\"").count();
        (running >= 2).then_some(())
    });
    let out = Command::new(DNM)
        .args(["replay", "--json", "--rate", "3", "--system", &mirror])
        .arg(session)
        .env("RUST_LOG", "warn")
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(report["files"].as_array().unwrap().len() >= 4, "{report:#}");
    assert_eq!(report["unreadable"], 0, "{report:#}");
    let channels = report["channels"].to_string();
    assert!(
        channels.contains("/vision/camera/image") && channels.contains("/drive/world/state"),
        "{report:#}"
    );
    std::thread::sleep(Duration::from_millis(500));
    drop(up);
    let mirrored: Vec<b::Odometry> = read_session(&dir.join("recordings"))
        .get("/drive/odometry/odom/raw")
        .map(|(_, m)| m.iter().map(|(_, _, d)| pod(d)).collect())
        .unwrap_or_default();
    assert!(
        mirrored.len() > 50,
        "{} odometry samples from the replay",
        mirrored.len()
    );
    // Stated tolerance: the demo's own for odometry against the truth, 0.1 m + 1 % of the
    // distance driven, everywhere along the path and at its end.
    let driven = recorded.last().unwrap().2;
    let tol = 0.1 + 0.01 * driven;
    let (a, b) = (recorded.last().unwrap(), mirrored.last().unwrap());
    let end = ((a.0 - b.x).powi(2) + (a.1 - b.y).powi(2)).sqrt();
    assert!(
        end < tol,
        "end of path: recorded ({}, {}), replayed odometry ({}, {}); tolerance {tol} m",
        a.0,
        a.1,
        b.x,
        b.y
    );
    let worst = mirrored
        .iter()
        .map(|m| {
            recorded
                .iter()
                .map(|r| ((r.0 - m.x).powi(2) + (r.1 - m.y).powi(2)).sqrt())
                .fold(f64::INFINITY, f64::min)
        })
        .fold(0.0, f64::max);
    assert!(
        worst < tol,
        "a replayed pose {worst} m off the recorded path (tolerance {tol} m)"
    );
    eprintln!(
        "replayed path: {} poses, end {end:.4} m off, worst {worst:.4} m",
        mirrored.len()
    );
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
    let _one = ONE_ROVER.lock().unwrap_or_else(|e| e.into_inner());
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

/// The rover's body (its URDF) is for the DNM's recorder: the wiring and the kind catalog that
/// tools fetch over the radio leave it out.
#[test]
fn the_body_stays_on_the_rover() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/beetle.toml");
    let netlist = dnm::parse_netlist(&path, &std::fs::read_to_string(&path).unwrap()).unwrap();
    let has_body = |p: &dnm_netlist::PortSpec| {
        p.message
            .standard
            .as_ref()
            .is_some_and(|s| s.body.is_some())
    };
    let world = netlist.kind_of("world").unwrap();
    assert!(
        world.outputs.iter().any(has_body),
        "the pose declares its body on the DNM"
    );
    let wiring = dnm_netlist::Wiring::of(&netlist, "drive", 1, None);
    assert!(
        wiring
            .modules
            .iter()
            .flat_map(|m| m.inputs.iter().chain(&m.outputs))
            .all(|p| !has_body(p))
    );
    let catalog = netlist.catalog.without_bodies();
    assert!(
        catalog
            .iter()
            .flat_map(|e| e.spec.inputs.iter().chain(&e.spec.outputs))
            .all(|p| !has_body(p))
    );
    assert!(
        netlist
            .catalog
            .iter()
            .flat_map(|e| e.spec.outputs.iter())
            .any(has_body)
    );
}
