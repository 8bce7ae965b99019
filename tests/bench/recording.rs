//! Recording to MCAP, all in one run:
//!
//! 1. writer capacity: how fast the writer path (encode + MCAP + zstd chunks + file) takes
//!    small messages and camera frames, fed directly;
//! 2. a live system recording at a sustained load (small messages and camera frames): what was
//!    recorded, what was dropped, and the DNM's CPU;
//! 3. one-hop latency between two modules in one system, the DNM's recorder started and stopped
//!    every half second, same payloads; what the recorder recorded and dropped meanwhile.
//!
//! Run: `cargo bench -p dnm --bench recording` (or `-- writer`, `-- live`, `-- latency` for
//! one part; `DNM_BENCH_SIZES=230400` for the latency of camera frames alone, about 13 minutes;
//! `DNM_BENCH_RECORDER_WORKERS=0,1` to compare recorders with 0 and 1 zstd workers in one run).
//! The latency part takes about 40 minutes.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use common::{cpu_seconds, human, percentiles, timed_latencies, unique, up, up_recording};
use dnm::admin::{Request, request};
use dnm::record::{RecordOptions, Recorder};
use dnm_module::protocol::dnm_prefix;
use dnm_netlist::{MessageType, Payload};
use iceoryx2::prelude::{LogLevel, set_log_level};
use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};

/// Latency windows per payload, recording off and on alternating: with 480 each way the added
/// p99's 90 % interval was about ±3 % for 225 KiB frames, ±7 % for 4 KiB (it halves with four
/// times the windows; `DNM_BENCH_WINDOWS` sets another number)...
const WINDOWS: usize = 960;
/// ...each this long...
const WINDOW: Duration = Duration::from_millis(500);
/// ...of which the start is left out.
const SETTLE: Duration = Duration::from_millis(100);
const RATE_HZ: f64 = 500.0;

fn main() {
    // The recorder runs here as in a `dnm` process: with the allocator bounded the same way
    // (`GLIBC_TUNABLES=glibc.malloc.arena_max=8` measures glibc's defaults instead).
    let bounded = dnm::allocator::bound_for_long_runs();
    set_log_level(LogLevel::Error);
    println!("# recording benchmark\n");
    println!("allocator bounded as in `dnm`: {bounded}\n");
    // `cargo bench --bench recording -- latency` runs one part; no name runs them all.
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let wanted = |part: &str| only.is_empty() || only.iter().any(|o| o == part);
    if wanted("writer") {
        writer_capacity();
    }
    if wanted("live") {
        live_load();
    }
    if wanted("latency") {
        latency();
    }
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
        "| payload | zstd workers | recording off p50 / p99 (µs) | recording on p50 / p99 (µs) | added p50 | added p99 | added p99, 90 % interval | noise floor p50 / p99 (off against off) | recorded / dropped while on |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    // `DNM_BENCH_RECORDER_WORKERS=0,1` compares recorders in one system: the on windows take
    // turns between the worker counts, each off window between two on windows.
    let workers = env_or("DNM_BENCH_RECORDER_WORKERS", vec![0]);
    let window_count = env_or("DNM_BENCH_WINDOWS", vec![WINDOWS])[0].max(2 * workers.len());
    // `DNM_BENCH_SIZES=230400` measures camera frames only.
    for size in env_or("DNM_BENCH_SIZES", vec![64usize, 4096, 320 * 240 * 3]) {
        let system = unique(&format!("l{size}"));
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
        let _up = up(&system, &netlist, &[], None, 1);
        let parsed = dnm::parse_netlist(Path::new("latency.toml"), &netlist).unwrap();
        let prefix = dnm_prefix(&system, "local");
        let dir = std::env::temp_dir().join(unique(&format!("lr{size}")));
        let stop = AtomicBool::new(false);
        // One system throughout; the DNM's own recorder (the same code) is started and stopped
        // in windows, so off and on share the system's start and alternate every window.
        let (samples, windows, recorded, dropped) = std::thread::scope(|s| {
            let reader = s.spawn(|| timed_latencies(&system, "local", "lat", &stop));
            std::thread::sleep(SETTLE);
            // (from, to, the recorder's mode if it was on): a recorder's start and stop fall
            // between windows.
            let mut windows: Vec<(Instant, Instant, Option<usize>)> = Vec::new();
            let (mut recorded, mut dropped) = (vec![0; workers.len()], vec![0; workers.len()]);
            let mut toggling = Duration::ZERO;
            for w in 0..window_count {
                if w % 2 == 1 {
                    let mode = (w / 2) % workers.len();
                    let t = Instant::now();
                    let mut options = RecordOptions::timestamped(&dir);
                    options.stem = format!("w{w}");
                    options.compression_workers = workers[mode] as u32;
                    let mut recorder = Recorder::start("local", &prefix, options).unwrap();
                    recorder.commit(&parsed, "local", 1);
                    let from = Instant::now();
                    toggling += from - t;
                    std::thread::sleep(WINDOW);
                    let to = Instant::now();
                    let report = recorder.report();
                    drop(recorder);
                    toggling += to.elapsed();
                    recorded[mode] += report.messages;
                    dropped[mode] += report.dropped;
                    windows.push((from, to, Some(mode)));
                } else {
                    let from = Instant::now();
                    std::thread::sleep(WINDOW);
                    windows.push((from, Instant::now(), None));
                }
            }
            stop.store(true, Ordering::Relaxed);
            eprintln!(
                "{}: starting and stopping the recorder took {:?} on average",
                human(size),
                toggling / (window_count as u32 / 2)
            );
            (reader.join().unwrap(), windows, recorded, dropped)
        });
        let _ = std::fs::remove_dir_all(&dir);
        // Each sample goes to the window it arrived in, unless it came in that window's first
        // SETTLE or between windows (a recorder starting, or finishing its file).
        let mut per_window: Vec<Vec<u64>> = vec![Vec::new(); windows.len()];
        for (at, ns) in samples {
            if let Some(i) = windows
                .iter()
                .position(|(from, to, _)| *from + SETTLE <= at && at < *to)
            {
                per_window[i].push(ns);
            }
        }
        let off_w: Vec<&Vec<u64>> = (0..windows.len())
            .filter(|&i| windows[i].2.is_none())
            .map(|i| &per_window[i])
            .collect();
        // Off windows alternate between two halves: their difference is what the measurement
        // itself moves by.
        let off_a: Vec<&Vec<u64>> = off_w.iter().copied().step_by(2).collect();
        let off_b: Vec<&Vec<u64>> = off_w.iter().copied().skip(1).step_by(2).collect();
        let pool = |w: &[&Vec<u64>]| w.iter().flat_map(|v| v.iter().copied()).collect::<Vec<_>>();
        let off_n = pool(&off_w).len();
        let off = percentiles(pool(&off_w));
        let (a, b) = (percentiles(pool(&off_a)), percentiles(pool(&off_b)));
        for (mode, n_workers) in workers.iter().enumerate() {
            let on_w: Vec<&Vec<u64>> = (0..windows.len())
                .filter(|&i| windows[i].2 == Some(mode))
                .map(|i| &per_window[i])
                .collect();
            let on_n = pool(&on_w).len();
            let on = percentiles(pool(&on_w));
            let (lo, hi) = bootstrap_p99_ratio(&off_w, &on_w);
            println!(
                "| {} | {n_workers} | {:.1} / {:.1} | {:.1} / {:.1} | {:+.1} % | {:+.1} % | {:+.1} % … {:+.1} % | {:+.1} % / {:+.1} % | {} / {} |",
                human(size),
                off.0,
                off.1,
                on.0,
                on.1,
                (on.0 / off.0 - 1.0) * 100.0,
                (on.1 / off.1 - 1.0) * 100.0,
                (lo - 1.0) * 100.0,
                (hi - 1.0) * 100.0,
                (b.0 / a.0 - 1.0) * 100.0,
                (b.1 / a.1 - 1.0) * 100.0,
                recorded[mode],
                dropped[mode],
            );
            eprintln!(
                "{}, {n_workers} zstd workers: {off_n} samples off, {on_n} on",
                human(size)
            );
        }
        // Two recorders against each other, when there are two: the second's p99 over the
        // first's, resampled the same way.
        if let [first, second] = workers[..] {
            let mode_w = |m: usize| -> Vec<&Vec<u64>> {
                (0..windows.len())
                    .filter(|&i| windows[i].2 == Some(m))
                    .map(|i| &per_window[i])
                    .collect()
            };
            let (w0, w1) = (mode_w(0), mode_w(1));
            let (p0, p1) = (percentiles(pool(&w0)), percentiles(pool(&w1)));
            let (lo, hi) = bootstrap_p99_ratio(&w0, &w1);
            println!(
                "\n{}: {second} zstd workers against {first}: p50 {:+.1} %, p99 {:+.1} % (90 % interval {:+.1} % … {:+.1} %)\n",
                human(size),
                (p1.0 / p0.0 - 1.0) * 100.0,
                (p1.1 / p0.1 - 1.0) * 100.0,
                (lo - 1.0) * 100.0,
                (hi - 1.0) * 100.0,
            );
        }
    }
}

/// The comma-separated numbers in environment variable `name`, or `default` if it is unset.
fn env_or(name: &str, default: Vec<usize>) -> Vec<usize> {
    match std::env::var(name) {
        Err(_) => default,
        Ok(v) => v
            .split(',')
            .map(|x| {
                x.trim()
                    .parse()
                    .unwrap_or_else(|e| panic!("{name}={v}: {x:?} is not a number ({e})"))
            })
            .collect(),
    }
}

/// 90 % interval of p99(on) / p99(off), by resampling whole windows (a block bootstrap: samples
/// in one window are not independent, a slow phase of the machine spans a window).
fn bootstrap_p99_ratio(off: &[&Vec<u64>], on: &[&Vec<u64>]) -> (f64, f64) {
    const RESAMPLES: usize = 1000;
    // xorshift64*: resampling needs no more than a fixed, repeatable stream.
    let mut state = 0x9E37_79B9_7F4A_7C15u64;
    let mut next = move |n: usize| {
        state ^= state >> 12;
        state ^= state << 25;
        state ^= state >> 27;
        (state.wrapping_mul(0x2545_F491_4F6C_DD1D) >> 33) as usize % n
    };
    let mut p99 = |windows: &[&Vec<u64>], buf: &mut Vec<u64>| {
        buf.clear();
        for _ in 0..windows.len() {
            buf.extend_from_slice(windows[next(windows.len())]);
        }
        let k = (buf.len() - 1) * 99 / 100;
        *buf.select_nth_unstable(k).1 as f64
    };
    let mut buf = Vec::new();
    let mut ratios: Vec<f64> = (0..RESAMPLES)
        .map(|_| {
            let off = p99(off, &mut buf);
            p99(on, &mut buf) / off
        })
        .collect();
    ratios.sort_by(f64::total_cmp);
    (
        ratios[RESAMPLES / 20],
        ratios[RESAMPLES - 1 - RESAMPLES / 20],
    )
}
