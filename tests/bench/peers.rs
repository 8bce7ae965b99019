//! Side by side with dora-rs, in one run on this machine:
//!
//! 1. the same two-module pipeline (a source at 500 Hz, a sink measuring each payload's delivery
//!    time; 64 B, 4 KiB, 1 MiB): ours is `blob_source → latency` on one DNM, dora's a
//!    `dora-source → dora-sink` dataflow started on its daemon (`peers/dora/src/bin/`), both
//!    stamping CLOCK_MONOTONIC as the payload leaves. Latency p50/p99, CPU per message (every
//!    process of the system, from `/proc`, over the measured window) and memory (PSS, so shared
//!    memory counts once);
//! 2. the same ten-link task change: two sources and five two-input readers, every link moved
//!    to the other source. Ours is a task switch, timed inside the DNM, as the operator's
//!    request and until every reader has read its new sources; dora has none, so its fastest
//!    way is to stop the dataflow and start the other one (its daemon and coordinator stay up),
//!    timed until every reader has data again. Both sides' readers are polled every
//!    millisecond.
//!
//! Run: `peers/dora/run`, which builds dora 1.1.0 (pinned, outside the workspace) and its nodes,
//! then this benchmark with `DORA` (the `dora` command) and `DORA_NODES` (the nodes' folder).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{crossed_pairs, human, latencies, percentiles, raw_node, unique, up};
use dnm::admin::{Request, request};
use dnm_module::msg::PairReading;
use dnm_module::port_service;
use dnm_module::protocol::{dnm_prefix, output_service};
use dnm_netlist::Payload;
use iceoryx2::prelude::{LogLevel, set_log_level};

const SIZES: [usize; 3] = [64, 4096, 1 << 20];
const RATE_HZ: f64 = 500.0;
const SAMPLES: usize = 2000;
const SKIP: usize = 250;
const SWITCHES: usize = 100;
const DORA_CHANGES: usize = 10;

fn main() {
    set_log_level(LogLevel::Error);
    let (Some(dora), Some(nodes)) = (std::env::var_os("DORA"), std::env::var_os("DORA_NODES"))
    else {
        eprintln!(
            "this benchmark needs dora-rs: run `peers/dora/run`, which builds dora 1.1.0 and its \
             nodes and then runs it"
        );
        std::process::exit(2);
    };
    let dora = Dora {
        exe: PathBuf::from(dora),
        nodes: PathBuf::from(nodes),
        dir: std::env::temp_dir().join(unique("dora")),
    };
    std::fs::create_dir_all(&dora.dir).unwrap();
    dora.cli(&["up"]);
    println!("# side by side with dora-rs 1.1.0 ({SAMPLES} samples per size at {RATE_HZ} Hz)\n");
    println!(
        "| payload | ours p50 / p99 (µs) | dora p50 / p99 (µs) | ours CPU per message (µs) | dora CPU per message (µs) | ours memory, PSS (MiB) | dora memory, PSS (MiB) | processes counted, ours / dora |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for size in SIZES {
        let ours = ours_pipeline(size);
        let theirs = dora.pipeline(size);
        println!(
            "| {} | {:.1} / {:.1} | {:.1} / {:.1} | {:.1} | {:.1} | {:.1} | {:.1} | {} / {} |",
            human(size),
            ours.p50,
            ours.p99,
            theirs.p50,
            theirs.p99,
            ours.cpu_us,
            theirs.cpu_us,
            ours.pss_mib,
            theirs.pss_mib,
            ours.processes,
            theirs.processes
        );
    }
    let ours = ours_change();
    let theirs = dora.change();
    println!("\n| ten-link task change | median | max |");
    println!("|---|---|---|");
    let row = |what: &str, v: &[u64]| {
        println!(
            "| {what} | {:.3} | {:.3} |",
            median(v) / 1000.0,
            *v.iter().max().unwrap() as f64 / 1000.0
        );
    };
    row("ours: task switch inside the DNM (µs)", &ours.inside);
    row(
        "ours: the operator's switch request, round trip (µs)",
        &ours.round_trip,
    );
    row(
        "ours: from the request until every reader has read its new sources (µs)",
        &ours.until_data,
    );
    row(
        "dora: stop the dataflow, start the other, until every reader has data (µs)",
        &theirs,
    );
    println!(
        "\nratio dora change / ours until every reader has read its new sources, medians: {:.0}x",
        median(&theirs) / median(&ours.until_data)
    );
    dora.cli(&["down"]);
    let _ = std::fs::remove_dir_all(&dora.dir);
}

struct Measured {
    p50: f64,
    p99: f64,
    cpu_us: f64,
    pss_mib: f64,
    /// Processes counted for CPU and memory.
    processes: usize,
}

/// Processes whose command line satisfies `pred`.
fn processes(pred: impl Fn(&str) -> bool) -> Vec<u32> {
    let mut pids = Vec::new();
    for e in std::fs::read_dir("/proc").unwrap().flatten() {
        let Some(pid) = e.file_name().to_str().and_then(|s| s.parse::<u32>().ok()) else {
            continue;
        };
        let Ok(cmd) = std::fs::read(format!("/proc/{pid}/cmdline")) else {
            continue;
        };
        let cmd = String::from_utf8_lossy(&cmd).replace('\0', " ");
        if pred(&cmd) {
            pids.push(pid);
        }
    }
    pids
}

/// CPU time of `pids` so far, in seconds: every thread's time on a CPU in nanoseconds
/// (`/proc/PID/task/TID/schedstat`), finer than the 10 ms ticks of `/proc/PID/stat`.
fn cpu(pids: &[u32]) -> f64 {
    let mut ns = 0u64;
    for pid in pids {
        let Ok(tasks) = std::fs::read_dir(format!("/proc/{pid}/task")) else {
            continue;
        };
        for t in tasks.flatten() {
            if let Some(v) = std::fs::read_to_string(t.path().join("schedstat"))
                .ok()
                .and_then(|s| s.split_whitespace().next()?.parse::<u64>().ok())
            {
                ns += v;
            }
        }
    }
    ns as f64 / 1e9
}

/// Proportional set size of `pids`, MiB: shared pages count once across them.
fn pss_mib(pids: &[u32]) -> f64 {
    let kib: u64 = pids
        .iter()
        .filter_map(|p| std::fs::read_to_string(format!("/proc/{p}/smaps_rollup")).ok())
        .filter_map(|s| {
            s.lines()
                .find(|l| l.starts_with("Pss:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<u64>().ok())
        })
        .sum();
    kib as f64 / 1024.0
}

// ------------------------------------------------------------------------------------------
// Ours.

fn ours_pipeline(size: usize) -> Measured {
    let system = unique(&format!("p{size}"));
    let netlist = format!(
        "[system]\nname = \"{system}\"\n\
         [[module]]\nname = \"src\"\nkind = \"blob_source\"\nrate_hz = {RATE_HZ}\nparams = {{ bytes = {size} }}\n\
         [[module]]\nname = \"lat\"\nkind = \"latency\"\n\
         [task.run]\nlinks = [\"src.out -> lat.in\"]\n"
    );
    let up = up(&system, &netlist, &[], None, 1);
    let dnm = up.pid();
    let pids = processes(|cmd| cmd.contains(&format!("\"system\":\"{system}\"")));
    let pids: Vec<u32> = pids.into_iter().chain([dnm]).collect();
    // Warm up, then measure over a window of SAMPLES messages.
    let _ = latencies(&system, "local", "lat", SKIP, 0);
    let (t, c) = (Instant::now(), cpu(&pids));
    let lat = latencies(&system, "local", "lat", SAMPLES, 0);
    let (c, messages) = (cpu(&pids) - c, t.elapsed().as_secs_f64() * RATE_HZ);
    let pss = pss_mib(&pids);
    let (p50, p99) = percentiles(lat);
    Measured {
        p50,
        p99,
        cpu_us: c * 1e6 / messages,
        pss_mib: pss,
        processes: pids.len(),
    }
}

fn median(v: &[u64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_unstable();
    v[v.len() / 2] as f64
}

/// Our ten-link change, in ns: inside the DNM, the operator's round trip, and until every
/// reader has read its new sources.
struct Change {
    inside: Vec<u64>,
    round_trip: Vec<u64>,
    until_data: Vec<u64>,
}

fn ours_change() -> Change {
    let system = unique("chg");
    let netlist = crossed_pairs(&system, "");
    let _up = up(&system, &netlist, &[], None, 1);
    // The readers' outputs: which source each of their inputs read.
    let node = raw_node(&dnm_prefix(&system, "local"));
    let payload = Payload::Fixed {
        size_bytes: size_of::<PairReading>(),
    };
    let readers: Vec<_> = (0..5)
        .map(|i| {
            port_service(&node, &output_service(&format!("p{i}"), "out"), &payload)
                .unwrap()
                .subscriber_builder()
                .create()
                .unwrap()
        })
        .collect();
    let mut change = Change {
        inside: Vec::new(),
        round_trip: Vec::new(),
        until_data: Vec::new(),
    };
    for i in 0..SWITCHES {
        let (task, a_origin) = if i % 2 == 0 { ("b", 2) } else { ("a", 1) };
        for r in &readers {
            while let Ok(Some(_)) = r.receive() {}
        }
        let t = Instant::now();
        let r = request(&system, &Request::Switch { task: task.into() }).unwrap();
        change.round_trip.push(t.elapsed().as_nanos() as u64);
        assert!(r.ok, "{r:?}");
        change.inside.push(r.switches[0].duration_ns);
        // Polled every millisecond, as dora's readers' files are.
        let mut fed = [false; 5];
        while !fed.iter().all(|f| *f) {
            for (k, r) in readers.iter().enumerate() {
                while let Ok(Some(s)) = r.receive() {
                    let p: PairReading = bytemuck::pod_read_unaligned(s.payload());
                    if p.a_origin == a_origin && p.b_origin == 3 - a_origin {
                        fed[k] = true;
                    }
                }
            }
            if !fed.iter().all(|f| *f) {
                std::thread::sleep(Duration::from_millis(1));
            }
        }
        change.until_data.push(t.elapsed().as_nanos() as u64);
    }
    change
}

// ------------------------------------------------------------------------------------------
// dora.

struct Dora {
    exe: PathBuf,
    nodes: PathBuf,
    dir: PathBuf,
}

impl Dora {
    fn cli(&self, args: &[&str]) {
        let out = Command::new(&self.exe)
            .args(args)
            .current_dir(&self.dir)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "dora {}: {}{}",
            args.join(" "),
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
    }

    fn node(&self, name: &str) -> String {
        self.nodes.join(name).display().to_string()
    }

    /// Every process of dora's: its coordinator and daemon (the `dora` command) and its nodes.
    fn processes(&self) -> Vec<u32> {
        let exe = self.exe.display().to_string();
        let nodes = self.nodes.display().to_string();
        processes(|cmd| cmd.starts_with(&exe) || cmd.starts_with(&nodes))
    }

    fn start(&self, name: &str, yaml: &str) {
        let path = self.dir.join(format!("{name}.yml"));
        std::fs::write(&path, yaml).unwrap();
        self.cli(&["start", path.to_str().unwrap(), "--name", name, "--detach"]);
    }

    fn stop(&self, name: &str) {
        self.cli(&["stop", "--name", name]);
    }

    fn pipeline(&self, size: usize) -> Measured {
        let name = unique(&format!("d{size}"));
        let out = self.dir.join(format!("{name}.lat"));
        let period_ms = (1e3 / RATE_HZ) as u64;
        let yaml = format!(
            "nodes:\n\
             \x20 - id: src\n    path: {src}\n    env:\n      SIZE: \"{size}\"\n    inputs:\n      tick: dora/timer/millis/{period_ms}\n    outputs:\n      - out\n\
             \x20 - id: lat\n    path: {sink}\n    env:\n      OUT: \"{out}\"\n    inputs:\n      in: src/out\n",
            src = self.node("dora-source"),
            sink = self.node("dora-sink"),
            out = out.display(),
        );
        self.start(&name, &yaml);
        wait_for(&first(&out));
        let started = Instant::now();
        std::thread::sleep(Duration::from_secs_f64(SKIP as f64 / RATE_HZ));
        let pids = self.processes();
        let (t, c) = (Instant::now(), cpu(&pids));
        std::thread::sleep(Duration::from_secs_f64(SAMPLES as f64 / RATE_HZ));
        let (c, window) = (cpu(&pids) - c, t.elapsed().as_secs_f64());
        let pss = pss_mib(&pids);
        // A little more than the window, so that SAMPLES samples follow the warm-up even if
        // dora's timer runs a little slow.
        std::thread::sleep(Duration::from_millis(500));
        let running = started.elapsed().as_secs_f64();
        self.stop(&name);
        wait_for(&out);
        let bytes = std::fs::read(&out).unwrap();
        // Messages in the window at the rate the sink actually received them.
        let messages = window * (bytes.len() / 8) as f64 / running;
        // The samples of the measured window: those after the warm-up, not those sent while
        // the dataflow was being stopped.
        let lat: Vec<u64> = bytes
            .chunks_exact(8)
            .map(|c| u64::from_le_bytes(c.try_into().unwrap()))
            .skip(SKIP)
            .take(SAMPLES)
            .collect();
        assert_eq!(lat.len(), SAMPLES, "dora delivered too few samples");
        let (p50, p99) = percentiles(lat);
        Measured {
            p50,
            p99,
            cpu_us: c * 1e6 / messages,
            pss_mib: pss,
            processes: pids.len(),
        }
    }

    /// Dataflow `task` (a or b) of the ten-link change, its readers writing to `tag`'s files.
    fn change_yaml(&self, task: &str, tag: &str) -> String {
        let src = self.node("dora-source");
        let sink = self.node("dora-sink");
        let mut yaml = String::from("nodes:\n");
        for s in ["src_a", "src_b"] {
            yaml += &format!(
                "  - id: {s}\n    path: {src}\n    inputs:\n      tick: dora/timer/millis/10\n    outputs:\n      - out\n"
            );
        }
        let (x, y) = if task == "a" {
            ("src_a", "src_b")
        } else {
            ("src_b", "src_a")
        };
        for i in 0..5 {
            let out = self.dir.join(format!("{tag}-p{i}.lat"));
            yaml += &format!(
                "  - id: p{i}\n    path: {sink}\n    env:\n      OUT: \"{}\"\n    inputs:\n      a: {x}/out\n      b: {y}/out\n",
                out.display()
            );
        }
        yaml
    }

    /// Each change, ns.
    fn change(&self) -> Vec<u64> {
        let mut running = unique("chg0");
        self.start(&running, &self.change_yaml("a", &running));
        for i in 0..5 {
            wait_for(&first(&self.dir.join(format!("{running}-p{i}.lat"))));
        }
        let mut times = Vec::new();
        for n in 1..=DORA_CHANGES {
            let next = unique(&format!("chg{n}"));
            let task = if n % 2 == 1 { "b" } else { "a" };
            let yaml = self.change_yaml(task, &next);
            let t = Instant::now();
            self.stop(&running);
            self.start(&next, &yaml);
            for i in 0..5 {
                wait_for(&first(&self.dir.join(format!("{next}-p{i}.lat"))));
            }
            times.push(t.elapsed().as_nanos() as u64);
            running = next;
        }
        self.stop(&running);
        times
    }
}

fn first(out: &Path) -> PathBuf {
    PathBuf::from(format!("{}.first", out.display()))
}

/// Until `path` exists (the benchmark has no time limit: a dataflow that never delivers shows
/// as a run that does not end).
fn wait_for(path: &Path) {
    while !path.exists() {
        std::thread::sleep(Duration::from_millis(1));
    }
}
