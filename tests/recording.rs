//! Recording every port to MCAP, read back with the `mcap` crate alone: schemas, counts,
//! monotonic times, the netlist; and a file from a DNM killed with SIGKILL still reads.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

#[path = "support/mod.rs"]
mod support;

use support::eventually;

const NETLIST: &str = r#"
[system]
name = "SYSTEM"
default_task = "a"

[[dnm]]
name = "main"

[[module]]
name = "src_a"
kind = "ticker"
rate_hz = 100
params = { origin = 1 }

[[module]]
name = "src_b"
kind = "ticker"
rate_hz = 50
params = { origin = 2 }

[[module]]
name = "relay"
kind = "relay"

[[module]]
name = "pair"
kind = "pair"

[task.a]
links = ["src_a.out -> relay.in", "relay.out -> pair.a", "src_b.out -> pair.b"]
"#;

/// `dnm up` of `netlist` (with `SYSTEM` replaced by a name of its own), recording into its
/// folder's `recordings/`.
fn start(tag: &str, netlist: &str) -> (Child, PathBuf, String) {
    let system = format!("rec{}{tag}", std::process::id());
    let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("netlist.toml");
    std::fs::write(&path, netlist.replace("SYSTEM", &system)).unwrap();
    // Waited for below with wait4(2), which also gives its peak memory.
    #[allow(clippy::zombie_processes)]
    let child = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(["--no-multicast", "up"])
        .arg(&path)
        .arg("--record-dir")
        .arg(dir.join("recordings"))
        .env("DNM_RUN_DIR", &dir)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    (child, dir, system)
}

fn recording(dir: &Path) -> PathBuf {
    eventually("a recording file", || {
        support::mcap_files(&dir.join("recordings"))
            .into_iter()
            .next()
    })
}

/// Per topic: (schema name, sequences, log times).
type Channels = BTreeMap<String, (String, Vec<u32>, Vec<u64>)>;

fn read(bytes: &[u8], lenient: bool) -> (Channels, usize) {
    let options = if lenient {
        enumset::enum_set!(mcap::read::Options::IgnoreEndMagic)
    } else {
        enumset::EnumSet::empty()
    };
    let mut out: Channels = BTreeMap::new();
    let mut read = 0;
    for m in mcap::MessageStream::new_with_options(bytes, options).unwrap() {
        let Ok(m) = m else {
            assert!(lenient, "a finished file reads to the end: {m:?}");
            break; // a truncated tail
        };
        read += 1;
        let schema = m
            .channel
            .schema
            .as_ref()
            .map(|s| s.name.clone())
            .unwrap_or_default();
        let e = out
            .entry(m.channel.topic.clone())
            .or_insert_with(|| (schema, Vec::new(), Vec::new()));
        e.1.push(m.sequence);
        e.2.push(m.log_time);
    }
    (out, read)
}

/// How many messages of a file still being written read before its unfinished tail.
fn readable(bytes: &[u8]) -> usize {
    let options = enumset::enum_set!(mcap::read::Options::IgnoreEndMagic);
    let Ok(stream) = mcap::MessageStream::new_with_options(bytes, options) else {
        return 0;
    };
    stream.take_while(Result::is_ok).count()
}

#[test]
fn every_port_is_recorded_with_schemas_counts_and_times() {
    let (mut child, dir, _) = start("all", NETLIST);
    let file = recording(&dir);
    std::thread::sleep(Duration::from_secs(3));
    // SAFETY: kill(2) on our own child; SIGTERM lets the DNM finish the file.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
    let bytes = std::fs::read(&file).unwrap();
    let (channels, _) = read(&bytes, false);
    let topics: Vec<&str> = channels.keys().map(String::as_str).collect();
    assert_eq!(
        topics,
        [
            "/main/pair/out",
            "/main/relay/out",
            "/main/src_a/out",
            "/main/src_b/out"
        ]
    );
    for (topic, (schema, seqs, times)) in &channels {
        assert!(!schema.is_empty(), "{topic} has no schema");
        // None lost: sequence numbers are consecutive from the first recorded one.
        for w in seqs.windows(2) {
            assert_eq!(w[1], w[0] + 1, "{topic} skipped a message");
        }
        for w in times.windows(2) {
            assert!(w[1] >= w[0], "{topic} log times go back");
        }
    }
    // Rates as sent, ~100 Hz and ~50 Hz, from the recorded times (how long the modules took
    // to start on a loaded machine is not the recorder's to answer for).
    let rate = |topic: &str| {
        let times = &channels[topic].2;
        assert!(times.len() > 20, "{topic}: {} messages", times.len());
        let span = (times[times.len() - 1] - times[0]) as f64 / 1e9;
        (times.len() - 1) as f64 / span
    };
    let (a, b) = (rate("/main/src_a/out"), rate("/main/src_b/out"));
    assert!(
        (70.0..=110.0).contains(&a) && (35.0..=55.0).contains(&b),
        "{a:.1} Hz, {b:.1} Hz"
    );
    // The netlist is in the file, and schemas decode without our code.
    let summary = mcap::Summary::read(&bytes).unwrap().unwrap();
    let schemas: Vec<&str> = summary
        .schemas
        .values()
        .map(|s| s.encoding.as_str())
        .collect();
    assert!(schemas.contains(&"ros2msg"));
    assert!(
        summary
            .metadata_indexes
            .iter()
            .any(|m| m.name == "dnm.netlist")
    );
    assert!(
        summary
            .attachment_indexes
            .iter()
            .any(|a| a.name.starts_with("netlist-r1"))
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_recording_from_a_killed_dnm_still_reads() {
    let (mut child, dir, _) = start("kill", NETLIST);
    let file = recording(&dir);
    // Chunks are finished every second: wait until finished chunks hold a few hundred
    // messages (however long a loaded machine takes to start the modules), then kill.
    let before = eventually("300 messages in finished chunks", || {
        let bytes = std::fs::read(&file).ok()?;
        let n = readable(&bytes);
        (n >= 300).then_some(n)
    });
    child.kill().unwrap();
    child.wait().unwrap();
    let bytes = std::fs::read(&file).unwrap();
    let (channels, read) = read(&bytes, true);
    // SIGKILL loses at most the chunk being written: everything finished before still reads.
    assert!(
        read >= before,
        "{read} messages readable after the kill, {before} before"
    );
    assert!(channels.contains_key("/main/src_a/out"));
    let _ = std::fs::remove_dir_all(&dir);
}

const CHAIN: &str = r#"
[system]
name = "SYSTEM"
default_task = "a"

[[dnm]]
name = "main"

[[module]]
name = "src"
kind = "ticker"
rate_hz = RATE
params = { origin = ORIGIN }

[[module]]
name = "relay"
kind = "relay"

[task.a]
links = ["src.out -> relay.in"]
"#;

fn start_chain(tag: &str, rate: &str, origin: u64) -> (Child, PathBuf, String) {
    let text = CHAIN
        .replace("RATE", rate)
        .replace("ORIGIN", &origin.to_string());
    start(tag, &text)
}

/// (origin, seq) of every Tick on `topic`, in order.
fn ticks(file: &Path, topic: &str) -> Vec<(u64, u64)> {
    let bytes = std::fs::read(file).unwrap();
    mcap::MessageStream::new(&bytes)
        .unwrap()
        .map(Result::unwrap)
        .filter(|m| m.channel.topic == topic)
        .map(|m| {
            let d = &m.data[4..]; // after the CDR header
            (
                u64::from_le_bytes(d[0..8].try_into().unwrap()),
                u64::from_le_bytes(d[8..16].try_into().unwrap()),
            )
        })
        .collect()
}

fn stop(mut child: Child) {
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGTERM) };
    assert!(child.wait().unwrap().success());
}

#[test]
fn replaying_a_recording_reproduces_downstream_outputs() {
    // Record a live source feeding a relay.
    let (live, live_dir, _) = start_chain("live", "50.0", 1);
    let recorded = recording(&live_dir);
    std::thread::sleep(Duration::from_secs(2));
    stop(live);
    let sources = ticks(&recorded, "/main/src/out");
    let relayed = ticks(&recorded, "/main/relay/out");
    assert!(sources.len() > 50 && relayed.len() > 50);

    // The same modules, with the source silenced, fed by the recording.
    let (fresh, fresh_dir, fresh_system) = start_chain("fresh", "0.01", 99);
    let replayed_file = recording(&fresh_dir);
    std::thread::sleep(Duration::from_millis(500));
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args([
            "replay",
            "--json",
            "--only",
            "/main/src/out",
            "--system",
            &fresh_system,
        ])
        .arg(&recorded)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["messages"].as_u64().unwrap(), sources.len() as u64);
    std::thread::sleep(Duration::from_millis(300));
    stop(fresh);

    // The relay forwarded exactly the replayed ticks, so its recorded outputs from the live run
    // reappear, in order.
    let again: Vec<(u64, u64)> = ticks(&replayed_file, "/main/relay/out")
        .into_iter()
        .filter(|(origin, _)| *origin == 1)
        .collect();
    assert_eq!(again, sources);
    let start = again.iter().position(|t| *t == relayed[0]).unwrap();
    assert_eq!(&again[start..start + relayed.len()], &relayed[..]);
    let _ = std::fs::remove_dir_all(&live_dir);
    let _ = std::fs::remove_dir_all(&fresh_dir);
}

const CAMERA_ONLY: &str = r#"
[system]
name = "SYSTEM"
default_task = "look"

[[dnm]]
name = "vision"

[[module]]
name = "camera"
kind = "camera"

[task.look]
links = []
"#;

/// A session of `bytes` of camera frames (320x240 RGB, uncompressed) in two files whose frames
/// alternate in time, as the recorder writes them.
fn camera_session(tag: &str, bytes: u64, system: &str) -> PathBuf {
    use dnm_module::msg::BytesMessage;
    let dir = std::env::temp_dir()
        .join(format!("dnm-test-recmem{}{tag}", std::process::id()))
        .join(format!("{system}-20261122T000000Z"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let message = dnm_rover::msgs::Image::message_type(320 * 240 * 3 + 12);
    let mut native = Vec::with_capacity(320 * 240 * 3 + 12);
    for v in [320u32, 240, 960] {
        native.extend_from_slice(&v.to_le_bytes());
    }
    native.extend((0..320 * 240 * 3).map(|i| (i % 251) as u8));
    let frame = dnm::record::encode(&message, "camera", 0, &native);
    let frames = bytes / frame.len() as u64;
    let text = CAMERA_ONLY.replace("SYSTEM", system);
    let t0 = 1_800_000_000_000_000_000u64;
    for (i, name) in ["rec-vision.mcap", "rec-vision.1.mcap"].iter().enumerate() {
        let file = std::fs::File::create(dir.join(name)).unwrap();
        let mut w = mcap::WriteOptions::new()
            .compression(None)
            .profile("ros2")
            .chunk_size(Some(1 << 20))
            .create(std::io::BufWriter::new(file))
            .unwrap();
        w.attach(&mcap::Attachment {
            log_time: t0,
            create_time: t0,
            name: "netlist-r1.toml".into(),
            media_type: "application/toml".into(),
            data: std::borrow::Cow::Borrowed(text.as_bytes()),
        })
        .unwrap();
        let (name, enc, schema, menc) = dnm::record::mcap_encoding(&message);
        let schema = w.add_schema(&name, enc, schema.as_bytes()).unwrap();
        let channel = w
            .add_channel(schema, "/vision/camera/image", menc, &BTreeMap::new())
            .unwrap();
        for n in (i as u64..frames).step_by(2) {
            let t = t0 + n * 10_000_000;
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: n as u32,
                    log_time: t,
                    publish_time: t,
                },
                &frame,
            )
            .unwrap();
        }
        w.finish().unwrap();
    }
    dir
}

/// Replays `session` as fast as it goes; returns the replay's report and its peak resident
/// memory (bytes).
fn replay_peak_rss(session: &Path, system: &str) -> (serde_json::Value, u64) {
    // Waited for below with wait4(2), which also gives its peak memory.
    #[allow(clippy::zombie_processes)]
    let child = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(["replay", "--json", "--fast", "--system", system])
        .arg(session)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let pid = child.id() as i32;
    let mut stdout = child.stdout.unwrap();
    let mut out = String::new();
    std::io::Read::read_to_string(&mut stdout, &mut out).unwrap();
    let mut status = 0;
    // SAFETY: rusage is plain data; all zeroes is a valid value.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: wait4(2) on our own child, with valid pointers.
    let r = unsafe { libc::wait4(pid, &mut status, 0, &mut usage) };
    assert_eq!(r, pid);
    assert!(
        libc::WIFEXITED(status) && libc::WEXITSTATUS(status) == 0,
        "{out}"
    );
    (
        serde_json::from_str(&out).unwrap(),
        usage.ru_maxrss as u64 * 1024,
    )
}

#[test]
fn replaying_a_2_gib_session_streams_it_with_memory_flat() {
    let system = format!("recmem{}", std::process::id());
    let small = camera_session("small", 64 << 20, &system);
    let (report, small_rss) = replay_peak_rss(&small, &system);
    let small_frames = report["messages"].as_u64().unwrap();
    assert!(small_frames > 200, "{report}");
    let _ = std::fs::remove_dir_all(small.parent().unwrap());
    let big = camera_session("big", 2 << 30, &system);
    // The lower of two replays: another test loading this machine meanwhile can raise one.
    let (report, first_rss) = replay_peak_rss(&big, &system);
    let (_, second_rss) = replay_peak_rss(&big, &system);
    let big_rss = first_rss.min(second_rss);
    let big_frames = report["messages"].as_u64().unwrap();
    let _ = std::fs::remove_dir_all(big.parent().unwrap());
    // Every frame of both files, none unreadable.
    assert!(big_frames > 9000, "{report}");
    assert_eq!(report["unreadable"], 0, "{report}");
    assert_eq!(report["files"].as_array().unwrap().len(), 2, "{report}");
    eprintln!(
        "peak memory replaying {small_frames} frames (64 MiB): {} MiB; {big_frames} frames (2 GiB): {} MiB",
        small_rss >> 20,
        big_rss >> 20
    );
    // 32 times the data, the same memory: what it holds does not grow with the session.
    assert!(
        big_rss < small_rss + (32 << 20),
        "peak memory {} MiB for 2 GiB against {} MiB for 64 MiB",
        big_rss >> 20,
        small_rss >> 20
    );
}
