//! Commanding the rover through the ground station: from an operator's command to the switch
//! in force on every DNM of the rover, on a clean link and through the emulated radio, against
//! the link's round trip measured in the same run; and the spread of the switch instants
//! across the rover's DNMs (one machine, one clock).
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench ground`
//! (results to stdout as a Markdown table).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

#[path = "../support/mod.rs"]
mod support;

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

fn run(name: &'static str, radio: &[&str], commands: usize) -> Run {
    let rig = Rig::new(name, "");
    let _routers = rig.routers();
    let _rover = rig.up(&["rover"], false);
    let _others = rig.up(&["drive", "vision"], false);
    let _radio = rig.linksim(radio);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let (_station, api) = rig.station();
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
    let runs = [
        run("clean", &[], 60),
        run(
            "radio",
            &[
                "--delay", "300ms", "--rate", "256kbit", "--loss", "0.2", "--seed", "3",
            ],
            40,
        ),
    ];
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
}
