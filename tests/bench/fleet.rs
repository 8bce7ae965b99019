//! A fleet on one Zenoh router: ten systems (rovers of three DNMs each) and two ground stations,
//! against one rover and one station on the same router measured first in the same run. Per
//! phase: the operator's command round trip (a switch submitted to the station's API until the
//! station reports it applied on the rover) and the router's CPU.
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench fleet`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;
#[path = "../support/mod.rs"]
mod support;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::cpu_seconds;
use dnm_proto::station::{Fate, Order};
use support::ground::{Api, Proc, ROVER, TASKS, text, wait_in_step, zenoh_args};
use support::{endpoint, eventually, free_port, zenoh_client};

const ROVERS: usize = 10;
const COMMANDS: usize = 30;

fn quantile(v: &[f64], q: f64) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s[((s.len() - 1) as f64 * q).round() as usize]
}

struct Fleet {
    dir: PathBuf,
    port: u16,
}

impl Fleet {
    fn system(&self, i: usize) -> String {
        format!("fleet{i}x{}", std::process::id())
    }

    /// Rover `i`: its three DNMs in one `dnm up`, a peer of the router.
    fn rover(&self, i: usize) -> Proc {
        let system = self.system(i);
        let netlist = self.dir.join(format!("{system}.toml"));
        std::fs::write(&netlist, text(&system, "", 2)).unwrap();
        let mut args = zenoh_args("peer", self.port);
        args.extend(["up".into(), netlist.display().to_string()]);
        for d in ROVER {
            args.extend(["--dnm".into(), d.into()]);
        }
        args.extend([
            "--no-record".into(),
            "--state-dir".into(),
            self.dir.join(format!("state-{i}")).display().to_string(),
        ]);
        Proc::dnm(&self.dir, &system, &args)
    }

    /// A station commanding rover `i`, a client of the router.
    fn station(&self, i: usize) -> (Proc, Api) {
        let http = format!("127.0.0.1:{}", free_port());
        let mut args = zenoh_args("client", self.port);
        args.extend([
            "ground".into(),
            "serve".into(),
            "--system".into(),
            self.system(i),
            "--db".into(),
            self.dir
                .join(format!("station-{i}.redb"))
                .display()
                .to_string(),
            "--http".into(),
            http.clone(),
        ]);
        let p = Proc::dnm(&self.dir, &format!("station-{i}"), &args);
        let api = Api(format!("http://{http}"));
        eventually("the station's API", || api.up().then_some(()));
        (p, api)
    }

    fn in_step(&self, i: usize) {
        let session = zenoh_client(self.port);
        wait_in_step(&session, &self.system(i), &ROVER, "a");
    }
}

/// `COMMANDS` switches through `api`, one after the other: ms from submit to applied.
fn command_round_trips(api: &Api) -> Vec<f64> {
    let mut ms = Vec::new();
    for i in 0..COMMANDS {
        let task = TASKS[(i + 1) % TASKS.len()];
        std::thread::sleep(Duration::from_millis(200 + (i as u64 * 137) % 300));
        let t = Instant::now();
        let e = api.submit(&Order::Switch {
            task: task.into(),
            at_unix_ns: None,
            late_by_ms: None,
        });
        let done = api.entry(e.seq, 120);
        assert!(matches!(done.fate, Some(Fate::Applied { .. })), "{done:?}");
        ms.push(t.elapsed().as_secs_f64() * 1000.0);
    }
    ms
}

fn router(dir: &Path, port: u16) -> Proc {
    let r = Proc::dnm(
        dir,
        "router",
        &["--listen".into(), endpoint(port), "router".into()],
    );
    eventually("the router listening", || {
        std::net::TcpStream::connect(("127.0.0.1", port)).ok()
    });
    r
}

fn main() {
    let dir = std::env::temp_dir().join(format!("dnm-bench-fleet-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let port = free_port();
    let router = router(&dir, port);
    let fleet = Fleet {
        dir: dir.clone(),
        port,
    };
    println!("# a fleet on one router ({COMMANDS} switches per station and phase)\n");
    println!(
        "| on the router | station | command round trip p50 / p90 / max (ms) | router CPU (% of a core) |"
    );
    println!("|---|---|---|---|");

    // One rover, one station.
    let mut rovers = vec![fleet.rover(0)];
    fleet.in_step(0);
    let (s0, api0) = fleet.station(0);
    let c = cpu_seconds(router.pid());
    let t = Instant::now();
    let one = command_round_trips(&api0);
    let cpu = (cpu_seconds(router.pid()) - c) / t.elapsed().as_secs_f64() * 100.0;
    println!(
        "| 1 rover, 1 station | 1 | {:.1} / {:.1} / {:.1} | {cpu:.1} |",
        quantile(&one, 0.5),
        quantile(&one, 0.9),
        quantile(&one, 1.0)
    );

    // Ten rovers, two stations commanding at once.
    for i in 1..ROVERS {
        rovers.push(fleet.rover(i));
    }
    for i in 1..ROVERS {
        fleet.in_step(i);
    }
    let (s1, api1) = fleet.station(1);
    let c = cpu_seconds(router.pid());
    let t = Instant::now();
    let (a, b) = std::thread::scope(|s| {
        let a = s.spawn(|| command_round_trips(&api0));
        let b = s.spawn(|| command_round_trips(&api1));
        (a.join().unwrap(), b.join().unwrap())
    });
    let cpu = (cpu_seconds(router.pid()) - c) / t.elapsed().as_secs_f64() * 100.0;
    for (n, v) in [(1, &a), (2, &b)] {
        println!(
            "| {ROVERS} rovers, 2 stations | {n} | {:.1} / {:.1} / {:.1} | {cpu:.1} |",
            quantile(v, 0.5),
            quantile(v, 0.9),
            quantile(v, 1.0)
        );
    }
    let all: Vec<f64> = a.iter().chain(&b).copied().collect();
    println!(
        "\nratio of the p50 round trip, {ROVERS} rovers and 2 stations against 1 and 1: {:.2}",
        quantile(&all, 0.5) / quantile(&one, 0.5)
    );
    drop((s0, s1));
    drop(rovers);
    drop(router);
    let _ = std::fs::remove_dir_all(&dir);
}
