//! A module killed under traffic, and how soon it works again: a source stepping at 500 Hz is
//! SIGKILLed [`KILLS`] times, each time once it has run long enough to count as healthy again,
//! and the time from the kill to its first output after it is measured (the first sample a
//! `latency` sink reads that was sent after the kill). The DNM's own events split it: the kill
//! to the exit seen, the exit to the new process started, that to the first output. Beside it,
//! another pair on the same DNM runs untouched: its latency while the kills go on against a
//! quiet stretch before them, and the samples its sink missed.
//!
//! Run: `cargo build --release --workspace`, then `cargo bench -p dnm --bench restart`. With
//! `DNM_BASELINE=/path/to/other/dnm` (another build's `dnm`, its `dnm-module-host` beside it),
//! the same is measured with that build too, in the same run.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use common::{percentiles, stamped_latencies, unique, up, use_dnm};
use dnm::admin::{Request, request};
use dnm_module::protocol::monotonic_ns;

const KILLS: usize = 20;
const RATE_HZ: f64 = 500.0;
/// Time between kills: longer than the longest back-off of the builds compared, so every kill
/// finds a module that has run long enough to count as healthy.
const BETWEEN: Duration = Duration::from_secs(6);
/// The quiet stretch the untouched pair is measured over before the kills.
const QUIET: Duration = Duration::from_secs(10);

/// What one kill took, ns: to the exit seen, to the new process started, to its first output.
struct Kill {
    seen: Option<u64>,
    started: Option<u64>,
    output: u64,
}

/// The DNM's report of module `name`: (pid, its events as (what, at_ns)).
fn report(system: &str, name: &str) -> (Option<u32>, Vec<(String, u64)>) {
    let r = request(system, &Request::Status).unwrap();
    let d = &r.dnms[0];
    let pid = d
        .modules
        .iter()
        .find(|m| m.name == name)
        .and_then(|m| m.pid);
    let events = d
        .events
        .iter()
        .filter(|e| e.module == name)
        .map(|e| (e.what.clone(), e.at_ns))
        .collect();
    (pid, events)
}

fn netlist(system: &str) -> String {
    format!(
        r#"[system]
name = "{system}"
[[module]]
name = "src"
kind = "blob_source"
rate_hz = {RATE_HZ}
max_restarts = 100
params = {{ bytes = 64 }}
[[module]]
name = "lat"
kind = "latency"
[[module]]
name = "other"
kind = "blob_source"
rate_hz = {RATE_HZ}
params = {{ bytes = 64 }}
[[module]]
name = "olat"
kind = "latency"
[task.run]
links = ["src.out -> lat.in", "other.out -> olat.in"]
"#
    )
}

/// Kills `src` [`KILLS`] times; what each kill took, and the untouched pair's readings.
fn run(label: &str) -> (Vec<Kill>, Vec<(u64, u64, u64)>, u64) {
    let system = unique(&format!("restart{label}"));
    let _up = up(&system, &netlist(&system), &[], None, 1);
    let stop = Arc::new(AtomicBool::new(false));
    let reader = |module: &'static str| {
        let (system, stop) = (system.clone(), stop.clone());
        std::thread::spawn(move || stamped_latencies(&system, "local", module, &stop))
    };
    let (lat, olat) = (reader("lat"), reader("olat"));
    std::thread::sleep(QUIET);
    let kills_from = monotonic_ns();
    let mut killed = Vec::new();
    for _ in 0..KILLS {
        let (pid, _) = report(&system, "src");
        let pid = pid.expect("src runs");
        let at = monotonic_ns();
        // SAFETY: kill(2) on a module process of the system this benchmark started.
        unsafe { libc::kill(pid as i32, libc::SIGKILL) };
        killed.push((pid, at));
        std::thread::sleep(BETWEEN);
    }
    let (_, events) = report(&system, "src");
    stop.store(true, Ordering::Relaxed);
    let (lat, olat) = (lat.join().unwrap(), olat.join().unwrap());
    let kills = killed
        .iter()
        .map(|&(_, at)| {
            let after = |what: &str| {
                events
                    .iter()
                    .find(|(w, t)| w == what && *t >= at)
                    .map(|(_, t)| t - at)
            };
            let output = lat
                .iter()
                .map(|&(read, _, latency)| read.saturating_sub(latency))
                .find(|&sent| sent > at)
                .expect("src sent again after its kill")
                - at;
            Kill {
                seen: after("exited"),
                started: after("restarting"),
                output,
            }
        })
        .collect();
    (kills, olat, kills_from)
}

fn ms(ns: u64) -> f64 {
    ns as f64 / 1e6
}

fn main() {
    let mut builds: Vec<(&str, Option<std::path::PathBuf>)> = vec![("this tree", None)];
    if let Some(b) = std::env::var_os("DNM_BASELINE") {
        builds.push(("baseline", Some(b.into())));
    }
    println!(
        "# A module SIGKILLed under traffic ({KILLS} kills, {} s apart, of a 64 B source at \
         {RATE_HZ} Hz)\n",
        BETWEEN.as_secs()
    );
    println!(
        "| DNM build | kill → first output p50 / max (ms) | kill → exit seen p50 (ms) | kill → started p50 (ms) | untouched pair p50 / p99 quiet (µs) | … during the kills (µs) | its samples missed |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (label, exe) in &builds {
        use_dnm(exe.clone());
        let (kills, olat, kills_from) = run(&label.replace(' ', ""));
        let p50 = |v: Vec<u64>| percentiles(v).0;
        let outputs: Vec<u64> = kills.iter().map(|k| k.output).collect();
        let max = outputs.iter().copied().max().unwrap_or(0);
        let seen: Vec<u64> = kills.iter().filter_map(|k| k.seen).collect();
        let started: Vec<u64> = kills.iter().filter_map(|k| k.started).collect();
        let (quiet, during): (Vec<_>, Vec<_>) = olat
            .iter()
            .skip(100)
            .partition(|&&(read, _, _)| read < kills_from);
        let lat = |v: &[&(u64, u64, u64)]| percentiles(v.iter().map(|x| x.2).collect());
        let (q50, q99) = lat(&quiet);
        let (d50, d99) = lat(&during);
        let missed: u64 = olat
            .windows(2)
            .map(|w| w[1].1.saturating_sub(w[0].1 + 1))
            .sum();
        println!(
            "| {label} | {:.1} / {:.1} | {:.1} ({} of {KILLS}) | {:.1} ({} of {KILLS}) | {:.1} / {:.1} | {:.1} / {:.1} | {missed} of {} |",
            p50(outputs) / 1e3,
            ms(max),
            p50(seen.clone()) / 1e3,
            seen.len(),
            p50(started.clone()) / 1e3,
            started.len(),
            q50,
            q99,
            d50,
            d99,
            olat.len(),
        );
    }
}
