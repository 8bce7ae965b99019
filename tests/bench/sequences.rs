//! Onboard sequences: from the sample that satisfies a `wait_until` condition to the next
//! step's switch in force on every DNM of the rover, for a condition on an output of the
//! authority's own computer (`src_a` on `rover`) and of another (`src_b` on `drive`, its own
//! process, reached over Zenoh). Each rover computer runs in its own process; twenty runs per
//! case, each a sequence uploaded through a ground station: `wait_until = "SRC.out.seq >= N"`
//! (N a second ahead of the source's count), then a switch.
//!
//! The sample's time is its send stamp as the authority reports it (`sample_unix_ns` of the
//! `condition_met` event); the moment a DNM is switched is its own stamp of the store of its
//! task word, read from its shared memory (CLOCK_MONOTONIC, turned into wall-clock time by
//! this process's offset between the two: one machine, one clock).
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench sequences`
//! (results to stdout as a Markdown table; `DNM_BENCH_RUNS` sets the runs per case).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

#[path = "../support/mod.rs"]
mod support;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use dnm_ground::CommandState;
use dnm_module::TaskWatch;
use dnm_module::protocol::monotonic_ns;
use dnm_proto::station::{Fate, Order, SequenceAction, SequenceState};
use support::ground::{Api, ROVER, Rig, slot, wait_in_step};
use support::{eventually, zenoh_client};
use zenoh::Wait;

fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

/// Submits `order` and waits until the rover took it.
fn done(api: &Api, order: &Order) {
    let e = api.submit(order);
    let e = eventually("the command's fate", || {
        Some(api.entry(e.seq, 5)).filter(|e| e.state.is_final())
    });
    assert!(
        e.state == CommandState::Applied && matches!(e.fate, Some(Fate::Done { .. })),
        "{e:?}"
    );
}

/// The newest count of ticker `module` (on `dnm`), from its last-value key.
fn count(session: &zenoh::Session, system: &str, dnm: &str, module: &str) -> u64 {
    eventually("the source's last value", || {
        let replies = session
            .get(dnm::keys::port(system, dnm, module, "out"))
            .timeout(Duration::from_secs(2))
            .wait()
            .ok()?;
        let reply = replies.recv().ok()?;
        let bytes = reply.result().ok()?.payload().to_bytes().to_vec();
        // `Tick`: origin, then seq (u64 each).
        Some(u64::from_le_bytes(bytes.get(8..16)?.try_into().ok()?))
    })
}

/// Per run: (sample → condition met by the authority, sample → switch in force on every DNM),
/// ms.
fn run(module: &str, dnm: &str, runs: usize) -> Vec<(f64, f64)> {
    let rig = Rig::new(&format!("bq{module}"), "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&[]);
    let (_station, api) = rig.station();
    let _procs: Vec<_> = ROVER.iter().map(|d| rig.up(&[d], false)).collect();
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let mut out = Vec::new();
    for i in 0..runs {
        let target = if i % 2 == 0 { "b" } else { "a" };
        let n = count(&session, &rig.system, dnm, module) + 20;
        let text = format!(
            "[sequence]\nname = \"bench\"\n\n[[step]]\nwait_until = \"{module}.out.seq >= {n}\"\n\
             timeout = \"1m\"\non_timeout = \"abort\"\n\n[[step]]\nswitch = \"{target}\"\n"
        );
        done(
            &api,
            &Order::Sequence {
                name: "bench".into(),
                action: SequenceAction::Upload {
                    file: "bench.toml".into(),
                    text,
                    netlists: BTreeMap::new(),
                },
            },
        );
        let watches: Vec<TaskWatch> = ROVER
            .iter()
            .map(|d| TaskWatch::open(&rig.system, d).unwrap())
            .collect();
        done(
            &api,
            &Order::Sequence {
                name: "bench".into(),
                action: SequenceAction::Start,
            },
        );
        let deadline = Instant::now() + Duration::from_secs(60);
        let stamps: Vec<u64> = loop {
            let words: Vec<(u64, u16, u64)> = watches.iter().map(TaskWatch::read).collect();
            if words.iter().all(|w| w.1 == slot(target)) {
                break words.iter().map(|w| w.2).collect();
            }
            assert!(Instant::now() < deadline, "never switched: {words:?}");
            std::thread::sleep(Duration::from_millis(1));
        };
        // This process's wall clock minus its monotonic one.
        let offset = dnm_ground::now_unix_ns() as i128 - monotonic_ns() as i128;
        let in_force = *stamps.iter().max().unwrap() as i128 + offset;
        let q = eventually("the sequence finished", || {
            api.link()
                .rover?
                .sequences
                .into_iter()
                .find(|q| q.name == "bench" && q.state == SequenceState::Finished)
        });
        let run = q.history.iter().map(|e| e.run).max().unwrap();
        let met = q
            .history
            .iter()
            .find(|e| e.run == run && e.what == "condition_met")
            .unwrap();
        let sample = met.sample_unix_ns.unwrap() as i128;
        let r = (
            (met.at_unix_ns as i128 - sample) as f64 / 1e6,
            (in_force - sample) as f64 / 1e6,
        );
        eprintln!(
            "{module} run {i}: condition met {:.1} ms, switch in force {:.1} ms after the sample",
            r.0, r.1
        );
        out.push(r);
    }
    out
}

fn main() {
    let runs: usize = std::env::var("DNM_BENCH_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20);
    let cases = [
        (
            "`src_a` on `rover` (the authority's computer)",
            run("src_a", "rover", runs),
        ),
        (
            "`src_b` on `drive` (another computer)",
            run("src_b", "drive", runs),
        ),
    ];
    println!("# From the sample that satisfies a condition to the next step's switch\n");
    println!(
        "| condition on | runs | met p50 (ms) | met p99 (ms) | in force p50 (ms) | in force p99 (ms) |"
    );
    println!("|---|---|---|---|---|---|");
    for (name, r) in &cases {
        let met: Vec<f64> = r.iter().map(|x| x.0).collect();
        let in_force: Vec<f64> = r.iter().map(|x| x.1).collect();
        println!(
            "| {name} | {} | {:.1} | {:.1} | {:.1} | {:.1} |",
            r.len(),
            quantile(&met, 0.5),
            quantile(&met, 0.99),
            quantile(&in_force, 0.5),
            quantile(&in_force, 0.99)
        );
    }
}
