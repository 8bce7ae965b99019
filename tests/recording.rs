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
    // Rates as sent: ~100 Hz and ~50 Hz over ~3 s.
    let a = channels["/main/src_a/out"].1.len();
    let b = channels["/main/src_b/out"].1.len();
    assert!(a > 150 && b > 75 && a > b, "{a} {b}");
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
    std::thread::sleep(Duration::from_secs(3));
    child.kill().unwrap();
    child.wait().unwrap();
    let bytes = std::fs::read(&file).unwrap();
    let (channels, read) = read(&bytes, true);
    // Chunks are finished every second: at least the first seconds are there.
    assert!(read > 100, "only {read} messages readable");
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
