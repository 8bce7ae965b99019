//! Fault protection: from a failure to every surviving DNM of the rover on its safe task, for
//! the station dying with one rover computer (`vision`: the authority safes the others) and
//! with the authority's computer (`rover`: the others safe themselves by their leases), twenty
//! times each in one rover, with `on_link_loss = { after = "2s", task = "c" }`. The moment a
//! DNM is safe is its own stamp of the store of its task word, read from its shared memory.
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench safing`
//! (results to stdout as a Markdown table; `DNM_BENCH_RUNS` sets the runs per case).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

#[path = "../support/mod.rs"]
mod support;

use std::time::{Duration, Instant};

use dnm_ground::CommandState;
use dnm_module::TaskWatch;
use dnm_module::protocol::monotonic_ns;
use dnm_proto::station::Order;
use support::ground::{Proc, ROVER, Rig, slot, wait_in_step};
use support::{eventually, zenoh_client};

const LOSS_MS: u64 = 2000;

fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// Which computer dies with the station.
#[derive(Clone, Copy)]
enum Case {
    Vision,
    Authority,
}

/// Milliseconds from the failure to the last survivor's store of the safe task, per run.
fn run(case: Case, runs: usize) -> Vec<f64> {
    let name = match case {
        Case::Vision => "bsv",
        Case::Authority => "bsa",
    };
    let rig = Rig::new(name, r#"on_link_loss = { after = "2s", task = "c" }"#);
    let _routers = rig.routers();
    let _radio = rig.linksim(&[]);
    let (mut station, mut api) = rig.station();
    // Each rover computer in its own process.
    let mut procs: Vec<(&str, Option<Proc>)> = ROVER
        .iter()
        .map(|d| (*d, Some(rig.up(&[d], false))))
        .collect();
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let victim = match case {
        Case::Vision => "vision",
        Case::Authority => "rover",
    };
    let survivors: Vec<&str> = ROVER.iter().copied().filter(|d| *d != victim).collect();
    let mut took = Vec::new();
    for i in 0..runs {
        // The rover in `b`, commanded by a station that has seen every safing so far.
        eventually("the station up to date", || {
            let l = api.link();
            (l.up && l.rover.is_some_and(|r| i == 0 || r.safe)).then_some(())
        });
        let e = api.submit(&Order::Switch {
            task: "b".into(),
            at_unix_ns: None,
            late_by_ms: None,
        });
        assert_eq!(api.entry(e.seq, 120).state, CommandState::Applied, "{e:?}");
        wait_in_step(&session, &rig.system, &ROVER, "b");
        let watches: Vec<TaskWatch> = survivors
            .iter()
            .map(|d| TaskWatch::open(&rig.system, d).unwrap())
            .collect();

        let t0 = monotonic_ns();
        station.kill();
        let slot_of = procs.iter_mut().find(|(d, _)| *d == victim).unwrap();
        slot_of.1.take().unwrap().kill();
        let deadline = Instant::now() + Duration::from_secs(60);
        let stamps: Vec<u64> = loop {
            let words: Vec<(u64, u16, u64)> = watches.iter().map(TaskWatch::read).collect();
            if words.iter().all(|w| w.1 == slot("c")) {
                break words.iter().map(|w| w.2).collect();
            }
            assert!(Instant::now() < deadline, "never safe: {words:?}");
            std::thread::sleep(Duration::from_millis(1));
        };
        let last = *stamps.iter().max().unwrap();
        took.push(last.saturating_sub(t0) as f64 / 1e6);
        eprintln!("run {i}: safe after {:.0} ms", took.last().unwrap());

        // The computer and the station come back; the rover stays safe until commanded.
        drop(watches);
        slot_of.1 = Some(rig.up(&[victim], false));
        wait_in_step(&session, &rig.system, &ROVER, "c");
        (station, api) = rig.station();
    }
    took
}

fn main() {
    let runs: usize = std::env::var("DNM_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20);
    let cases = [
        (
            "the station and `vision` (a rover computer)",
            run(Case::Vision, runs),
        ),
        (
            "the station and `rover` (the authority's computer)",
            run(Case::Authority, runs),
        ),
    ];
    println!(
        "# From a failure to every surviving rover DNM safe (loss of signal after {LOSS_MS} ms)\n"
    );
    println!("| killed together | runs | p50 (ms) | max (ms) | max − loss-of-signal time (ms) |");
    println!("|---|---|---|---|---|");
    for (name, took) in &cases {
        let max = quantile(took, 1.0);
        println!(
            "| {name} | {} | {:.0} | {:.0} | {:.0} |",
            took.len(),
            quantile(took, 0.5),
            max,
            max - LOSS_MS as f64
        );
    }
}
