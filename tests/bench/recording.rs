//! Recording to MCAP, all in one run:
//!
//! 1. writer capacity: how fast the writer path (encode + MCAP + zstd chunks + file) takes
//!    small messages and camera frames, fed directly;
//! 2. a live system recording at a sustained load (small messages and camera frames): what was
//!    recorded, what was dropped, and the DNM's CPU;
//! 3. one-hop latency between two modules with recording off and on, same payloads, the two
//!    alternating; what the recorder recorded and dropped meanwhile.
//!
//! Run: `cargo bench -p dnm --bench recording`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use common::{cpu_seconds, human, latencies, percentiles, unique, up, up_recording};
use dnm::admin::{Request, request};
use dnm_netlist::{MessageType, Payload};
use iceoryx2::prelude::{LogLevel, set_log_level};

const SAMPLES: usize = 1500;
/// Latency runs per payload and mode (off, on, off, on, ...).
const ROUNDS: usize = 5;
const RATE_HZ: f64 = 500.0;

fn main() {
    set_log_level(LogLevel::Error);
    println!("# recording benchmark\n");
    writer_capacity();
    live_load();
    latency();
}

fn writer_capacity() {
    let dir = std::env::temp_dir().join(unique("wcap"));
    std::fs::create_dir_all(&dir).unwrap();
    println!("| writer fed directly | messages/s | MB/s (port bytes) |");
    println!("|---|---|---|");
    for (name, size, count) in [
        ("16 B ticks", 16usize, 400_000usize),
        ("225 KiB frames", 320 * 240 * 3, 600),
    ] {
        let message = MessageType {
            schema_name: "bench/Blob".into(),
            encoding: "application/octet-stream".into(),
            schema: "uint8[] data\n".into(),
            payload: Payload::Bytes { max_bytes: size },
            standard: None,
        };
        let file = std::fs::File::create(dir.join(format!("{size}.mcap"))).unwrap();
        let mut w = mcap::WriteOptions::new()
            .compression(Some(mcap::Compression::Zstd))
            .chunk_size(Some(1 << 20))
            .create(std::io::BufWriter::new(file))
            .unwrap();
        let schema = w
            .add_schema("bench/Blob", "ros2msg", b"uint8[] data\n")
            .unwrap();
        let channel = w
            .add_channel(schema, "/x", "cdr", &BTreeMap::new())
            .unwrap();
        // Frames of a rendered scene compress; random bytes would not: use a gradient.
        let payload: Vec<u8> = (0..size).map(|i| (i / 3 % 251) as u8).collect();
        let t = Instant::now();
        for seq in 0..count {
            let data = dnm::record::encode(&message, "x", seq as u64, &payload);
            w.write_to_known_channel(
                &mcap::records::MessageHeader {
                    channel_id: channel,
                    sequence: seq as u32,
                    log_time: seq as u64,
                    publish_time: seq as u64,
                },
                &data,
            )
            .unwrap();
        }
        w.finish().unwrap();
        let s = t.elapsed().as_secs_f64();
        println!(
            "| {name} | {:.0} | {:.1} |",
            count as f64 / s,
            (count * size) as f64 / s / 1e6
        );
    }
    println!();
    let _ = std::fs::remove_dir_all(&dir);
}

fn live_load() {
    let system = unique("live");
    let netlist = format!(
        r#"[system]
name = "{system}"
[[module]]
name = "t1"
kind = "ticker"
rate_hz = 1000
[[module]]
name = "t2"
kind = "ticker"
rate_hz = 1000
[[module]]
name = "cam1"
kind = "blob_source"
rate_hz = 30
params = {{ bytes = 230400 }}
[[module]]
name = "cam2"
kind = "blob_source"
rate_hz = 30
params = {{ bytes = 230400 }}
[[module]]
name = "r1"
kind = "relay"
[task.run]
links = ["t1.out -> r1.in"]
"#
    );
    let dir = std::env::temp_dir().join(unique("liverec"));
    let up = up_recording(&system, &netlist, &[], None, 1, Some(&dir));
    std::thread::sleep(Duration::from_secs(2));
    let read = || request(&system, &Request::Status).unwrap().dnms.remove(0);
    let (a, t0) = (read(), Instant::now());
    let cpu0 = cpu_seconds(up.pid());
    std::thread::sleep(Duration::from_secs(10));
    let (b, dt) = (read(), t0.elapsed().as_secs_f64());
    let cpu1 = cpu_seconds(up.pid());
    let (ra, rb) = (a.recording.unwrap(), b.recording.unwrap());
    println!("| live system: 2 × 1 kHz ticks, 1 relay, 2 × 30 Hz 225 KiB frames | value |");
    println!("|---|---|");
    println!(
        "| recorded messages/s | {:.0} |",
        (rb.messages - ra.messages) as f64 / dt
    );
    println!(
        "| recorded MB/s (encoded, before compression) | {:.2} |",
        (rb.bytes - ra.bytes) as f64 / dt / 1e6
    );
    println!("| dropped in the window | {} |", rb.dropped - ra.dropped);
    println!(
        "| DNM process CPU (recorder included), % of one core | {:.1} |\n",
        (cpu1 - cpu0) / dt * 100.0
    );
    drop(up);
    let _ = std::fs::remove_dir_all(&dir);
}

fn latency() {
    println!(
        "| payload | recording off p50 / p99 (µs), median of runs | recording on p50 / p99 (µs), median of runs | added p50 | added p99 | recorded / dropped while measuring |"
    );
    println!("|---|---|---|---|---|---|");
    for size in [64usize, 4096, 320 * 240 * 3] {
        let run = |record: bool| {
            let system = unique(&format!("l{size}{}", u8::from(record)));
            let netlist = format!(
                r#"[system]
name = "{system}"
[[module]]
name = "src"
kind = "blob_source"
rate_hz = {RATE_HZ}
params = {{ bytes = {size} }}
[[module]]
name = "lat"
kind = "latency"
[task.run]
links = ["src.out -> lat.in"]
"#
            );
            let dir = std::env::temp_dir().join(unique(&format!("lr{size}")));
            let _up = if record {
                up_recording(&system, &netlist, &[], None, 1, Some(&dir))
            } else {
                up(&system, &netlist, &[], None, 1)
            };
            let recording = || {
                request(&system, &Request::Status)
                    .ok()
                    .and_then(|mut r| r.dnms.remove(0).recording)
            };
            let before = recording();
            let lat = latencies(&system, "local", "lat", SAMPLES, 100);
            let after = recording();
            let _ = std::fs::remove_dir_all(&dir);
            // Of the source's samples while measuring: recorded, and dropped by the recorder.
            let counts = match (before, after) {
                (Some(a), Some(b)) => (b.messages - a.messages, b.dropped - a.dropped),
                _ => (0, 0),
            };
            (lat, counts)
        };
        // Off and on alternate, each run a system of its own; the medians of the runs' p50 and
        // p99 are compared (one run's start can land this VM's cores in a better or a worse
        // state than the next).
        let (mut off, mut on) = (Vec::new(), Vec::new());
        let (mut recorded, mut dropped) = (0, 0);
        for _ in 0..ROUNDS {
            off.push(percentiles(run(false).0));
            let (lat, (r, d)) = run(true);
            on.push(percentiles(lat));
            recorded += r;
            dropped += d;
        }
        let median = |v: &[(f64, f64)], p99: bool| {
            let mut x: Vec<f64> = v.iter().map(|(a, b)| if p99 { *b } else { *a }).collect();
            x.sort_by(f64::total_cmp);
            x[x.len() / 2]
        };
        let (off, on) = (
            (median(&off, false), median(&off, true)),
            (median(&on, false), median(&on, true)),
        );
        println!(
            "| {} | {:.1} / {:.1} | {:.1} / {:.1} | {:+.0} % | {:+.0} % | {recorded} / {dropped} |",
            human(size),
            off.0,
            off.1,
            on.0,
            on.1,
            (on.0 / off.0 - 1.0) * 100.0,
            (on.1 / off.1 - 1.0) * 100.0
        );
    }
}
