//! Commanding the rover through the ground station: from an operator's command to the switch
//! in force on every DNM of the rover, on a clean link and through the emulated radio, against
//! the link's round trip measured in the same run; and the spread of the switch instants
//! across the rover's DNMs (one machine, one clock). A third run commands through the same
//! radio while the ground's record of the rover drains a backlog (the station came up after a
//! minute of the rover's recording, its downlink held to a budget): the downlink's bytes are
//! counted on the link, rover to ground, by a proxy in front of the rover's router.
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench ground` (results
//! to stdout as a Markdown table; `-- clean` for the clean link alone).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

#[path = "../support/mod.rs"]
mod support;

mod common;

use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use dnm_module::TaskWatch;
use dnm_module::protocol::monotonic_ns;
use dnm_proto::station::{Fate, Order};
use support::ground::{ROVER, Rig, TASKS, slot, wait_in_step};
use support::zenoh_client;

/// Quantiles of a sample, in its unit.
fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

struct Run {
    name: &'static str,
    rtt_ms: Vec<f64>,
    latency_ms: Vec<f64>,
    spread_us: Vec<f64>,
}

/// The radio profile: 300 ms each way, 256 kbit/s, a fifth of the packets lost each way.
const RADIO: [&str; 8] = [
    "--delay", "300ms", "--rate", "256kbit", "--loss", "0.2", "--seed", "3",
];
/// The downlink's budget while a backlog drains (a quarter of the radio).
const BUDGET: &str = "64kbit";
const BUDGET_BYTES_PER_S: f64 = 8000.0;
/// How long the rover records before the station comes up: the backlog.
const BACKLOG: Duration = Duration::from_secs(60);
/// The downlink plan of the backlog run: a 2 KB payload at 2 Hz (about half the budget live),
/// and the tickers.
const PLAN: &str = r#"
[[module]]
name = "blob"
kind = "blob_source"
dnm = "rover"
rate_hz = 10
params = { bytes = 2000 }

[[downlink]]
output = "blob.out"
rate_hz = 2
priority = 1

[[downlink]]
output = "src_a.out"
rate_hz = 5
priority = 2
"#;

fn run(name: &'static str, radio: &[&str], commands: usize) -> Run {
    let rig = Rig::new(name, "");
    let _routers = rig.routers();
    let _rover = rig.up(&["rover"], false);
    let _others = rig.up(&["drive", "vision"], false);
    let _radio = rig.linksim(radio);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let (_station, api) = rig.station();
    command(name, &rig, &api, commands)
}

/// What the backlog run measured besides the commands: the downlink's bytes a second on the
/// link while the commands ran, and the backlog left (bytes) when they were done.
struct Drain {
    downlink_bytes_per_s: f64,
    backlog_before: u64,
    backlog_after: u64,
}

fn run_draining(name: &'static str, commands: usize) -> (Run, Drain) {
    let rig = Rig::new("drain", "");
    let text = std::fs::read_to_string(&rig.netlist).unwrap() + PLAN;
    std::fs::write(&rig.netlist, text).unwrap();
    let _routers = rig.routers();
    let rec = rig.dir.join("rover-rec");
    let _rover = rig.up_recording(&["rover"], &rec, &[]);
    let _others = rig.up_recording(&["drive", "vision"], &rec, &[]);
    let (toward, back) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let proxy = common::counting_proxy(rig.rover_port, toward, back.clone());
    let _radio = rig.linksim_to(proxy, &RADIO);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    std::thread::sleep(BACKLOG);
    let (_station, api) = rig.station_with(&["--downlink-budget", BUDGET]);
    // The backlog is known once the station heard of the channels and asked the recording.
    let backlog = |api: &support::ground::Api| {
        api.get_json("/downlink")["backlog_bytes"]
            .as_u64()
            .unwrap_or(0)
    };
    let backlog_before =
        support::eventually("a backlog", || Some(backlog(&api)).filter(|b| *b > 0));
    let (b0, t0) = (back.load(Ordering::Relaxed), Instant::now());
    let run = command(name, &rig, &api, commands);
    let down = (back.load(Ordering::Relaxed) - b0) as f64 / t0.elapsed().as_secs_f64();
    let drain = Drain {
        downlink_bytes_per_s: down,
        backlog_before,
        backlog_after: backlog(&api),
    };
    (run, drain)
}

/// Times `commands` switches given through the station `api` of `rig`.
fn command(name: &'static str, rig: &Rig, api: &support::ground::Api, commands: usize) -> Run {
    let watches: Vec<TaskWatch> = ROVER
        .iter()
        .map(|d| TaskWatch::open(&rig.system, d).unwrap())
        .collect();
    // The link's round trip, from the station's own pings (one a second).
    let mut rtt_ms = Vec::new();
    let mut last = 0;
    while rtt_ms.len() < 10 {
        let l = api.link();
        if l.answered > last {
            last = l.answered;
            rtt_ms.extend(l.rtt_ms);
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    let mut latency_ms = Vec::new();
    let mut spread_us = Vec::new();
    for i in 0..commands {
        let task = TASKS[(i + 1) % 3];
        // Between pings, as an operator would: not timed to the link's rhythm.
        std::thread::sleep(Duration::from_millis(300 + (i as u64 * 137) % 700));
        let t0 = monotonic_ns();
        let e = api.submit(&Order::Switch {
            task: task.into(),
            at_unix_ns: None,
            late_by_ms: None,
        });
        let done = api.entry(e.seq, 120);
        let Some(Fate::Applied { revision, .. }) = done.fate else {
            panic!("{done:?}");
        };
        // Every DNM in force: the latest of their stores.
        let deadline = Instant::now() + Duration::from_secs(30);
        let stamps: Vec<u64> = loop {
            let words: Vec<(u64, u16, u64)> = watches.iter().map(TaskWatch::read).collect();
            if words.iter().all(|w| (w.0, w.1) == (revision, slot(task))) {
                break words.iter().map(|w| w.2).collect();
            }
            assert!(Instant::now() < deadline, "not in force: {words:?}");
            std::thread::sleep(Duration::from_millis(1));
        };
        let (first, last) = (*stamps.iter().min().unwrap(), *stamps.iter().max().unwrap());
        latency_ms.push(last.saturating_sub(t0) as f64 / 1e6);
        spread_us.push((last - first) as f64 / 1e3);
    }
    Run {
        name,
        rtt_ms,
        latency_ms,
        spread_us,
    }
}

fn main() {
    // `-- clean`: the clean link alone (a minute instead of twelve).
    if std::env::args().skip(1).any(|a| a == "clean") {
        let r = run("clean", &[], 60);
        let rtt = quantile(&r.rtt_ms, 0.5);
        let p50 = quantile(&r.latency_ms, 0.5);
        println!(
            "clean: RTT p50 {rtt:.1} ms; command → in force p50 / p99 {p50:.1} / {:.1} ms \
             (1.5 RTT + 50 ms = {:.1} ms); spread of switch instants p50 / p99 / max \
             {:.0} / {:.0} / {:.0} µs",
            quantile(&r.latency_ms, 0.99),
            1.5 * rtt + 50.0,
            quantile(&r.spread_us, 0.5),
            quantile(&r.spread_us, 0.99),
            quantile(&r.spread_us, 1.0),
        );
        return;
    }
    let (draining, drain) = run_draining("radio, backlog draining", 40);
    let runs = [run("clean", &[], 60), run("radio", &RADIO, 40), draining];
    println!("# Ground station to every DNM of the rover (switches, one machine)\n");
    println!(
        "| link | commands | link RTT p50 (ms) | command → in force on every DNM p50 / p99 (ms) | p50 / RTT p50 | spread of switch instants p50 / p99 / max (µs) |"
    );
    println!("|---|---|---|---|---|---|");
    for r in &runs {
        let rtt = quantile(&r.rtt_ms, 0.5);
        let (p50, p99) = (quantile(&r.latency_ms, 0.5), quantile(&r.latency_ms, 0.99));
        println!(
            "| {} | {} | {:.1} | {:.1} / {:.1} | {:.2} | {:.0} / {:.0} / {:.0} |",
            r.name,
            r.latency_ms.len(),
            rtt,
            p50,
            p99,
            p50 / rtt,
            quantile(&r.spread_us, 0.5),
            quantile(&r.spread_us, 0.99),
            quantile(&r.spread_us, 1.0),
        );
    }
    let p50 = |i: usize| quantile(&runs[i].latency_ms, 0.5);
    println!(
        "\nWhile the backlog drained: command p50 {:.2}x the radio's without one; the downlink \
         {:.1} kbit/s on the link, rover to ground (budget {BUDGET}: {:.2}x, Zenoh's framing and \
         the station's pings' answers included); backlog {:.0} KiB when the commands began, \
         {:.0} KiB when they ended.",
        p50(2) / p50(1),
        drain.downlink_bytes_per_s * 8.0 / 1000.0,
        drain.downlink_bytes_per_s / BUDGET_BYTES_PER_S,
        drain.backlog_before as f64 / 1024.0,
        drain.backlog_after as f64 / 1024.0,
    );
}
