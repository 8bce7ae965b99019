//! Connection-layer benchmark, all in one run so ratios are against a baseline measured on the
//! same machine at the same time:
//!
//! 1. one-hop latency, module to module through a DNM, against raw iceoryx2 publish-subscribe
//!    between two processes with the same payload, service settings and event wake-up;
//! 2. a task switch of 10 links against really destroying and creating 10 iceoryx2 subscribers;
//! 3. resident memory of a DNM hosting 15 modules and of its module processes.
//!
//! Run: `cargo bench -p dnm --bench connection` (results go to stdout as a Markdown table).
//! With `DNM_BASELINE=/path/to/other/dnm` (another build's `dnm`, with its `dnm-module-host`
//! beside it), every DNM measurement is also taken with that build, interleaved in the same run,
//! so a change is compared against what it replaces on the same machine at the same time.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::process::{Command, Stdio};
use std::time::Duration;

use common::{
    crossed_pairs, human, latencies, percentiles, raw_node, real_rewiring, unique, up, use_dnm,
};

use dnm::admin::{Request, request};
use dnm_module::event_service;
use dnm_module::port_service;
use dnm_module::protocol::{PortHeader, monotonic_ns};
use dnm_netlist::Payload;
use iceoryx2::prelude::*;

const SIZES: [usize; 3] = [64, 4096, 1 << 20];
const SAMPLES: usize = 2000;
const RATE_HZ: f64 = 500.0;

fn main() {
    set_log_level(LogLevel::Error);
    let args: Vec<String> = std::env::args().collect();
    match args.get(1).map(String::as_str) {
        Some("raw-pub") => return raw_pub(&args[2], args[3].parse().unwrap()),
        Some("raw-sub") => return raw_sub(&args[2], args[3].parse().unwrap()),
        _ => {}
    }
    let mut builds: Vec<(&str, Option<std::path::PathBuf>)> = vec![("this tree", None)];
    if let Some(b) = std::env::var_os("DNM_BASELINE") {
        builds.push(("baseline", Some(b.into())));
    }
    println!("# connection-layer benchmark ({SAMPLES} samples per size at {RATE_HZ} Hz)\n");
    println!(
        "| payload | DNM build | raw iceoryx2 p50 / p99 (µs) | through DNM p50 / p99 (µs) | ratio p50 | ratio p99 |"
    );
    println!("|---|---|---|---|---|---|");
    for size in SIZES {
        for (label, exe) in &builds {
            let raw = raw_latency(size);
            use_dnm(exe.clone());
            let dnm = dnm_latency(size);
            println!(
                "| {} | {label} | {:.1} / {:.1} | {:.1} / {:.1} | {:.2} | {:.2} |",
                human(size),
                raw.0,
                raw.1,
                dnm.0,
                dnm.1,
                dnm.0 / raw.0,
                dnm.1 / raw.1
            );
        }
    }
    println!();
    for (label, exe) in &builds {
        println!("## {label}\n");
        use_dnm(exe.clone());
        switch_and_memory();
    }
}

// ------------------------------------------------------------------------------------------
// Raw iceoryx2: a publisher process and a subscriber process, no DNM.

fn raw_pub(prefix: &str, size: usize) {
    let node = raw_node(prefix);
    let payload = Payload::Bytes { max_bytes: 1 << 20 };
    let publisher = port_service(&node, "raw/out", &payload)
        .unwrap()
        .publisher_builder()
        .initial_max_slice_len(1 << 20)
        .allocation_strategy(AllocationStrategy::PowerOfTwo)
        .create()
        .unwrap();
    let notifier = event_service(&node, "raw/out/ev")
        .unwrap()
        .notifier_builder()
        .create()
        .unwrap();
    let period = Duration::from_secs_f64(1.0 / RATE_HZ);
    // Same work per sample as a module: loan, write the 16-byte tag, header, send, notify.
    for seq in 0..(SAMPLES as u64 + 200) {
        let s = publisher.loan_slice_uninit(size).unwrap();
        let mut s = s.write_from_fn(|_| 0u8);
        s.payload_mut()[8..16].copy_from_slice(&seq.to_le_bytes());
        *s.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq,
            task_word: 0,
        };
        s.send().unwrap();
        notifier.notify().unwrap();
        std::thread::sleep(period);
    }
}

fn raw_sub(prefix: &str, size: usize) {
    let node = raw_node(prefix);
    let payload = Payload::Bytes { max_bytes: 1 << 20 };
    let _ = size;
    let sub = port_service(&node, "raw/out", &payload)
        .unwrap()
        .subscriber_builder()
        .create()
        .unwrap();
    let listener = event_service(&node, "raw/out/ev")
        .unwrap()
        .listener_builder()
        .create()
        .unwrap();
    let waitset = WaitSetBuilder::new().create::<ipc::Service>().unwrap();
    let _g = waitset.attach_notification(&listener).unwrap();
    let mut lat = Vec::with_capacity(SAMPLES);
    println!("ready");
    while lat.len() < SAMPLES {
        waitset
            .wait_and_process_once(|_| CallbackProgression::Continue)
            .unwrap();
        listener.try_wait(|_| ()).unwrap();
        while let Some(s) = sub.receive().unwrap() {
            lat.push(monotonic_ns().saturating_sub(s.user_header().stamp_ns));
        }
    }
    println!("{}", serde_json::to_string(&lat).unwrap());
}

fn raw_latency(size: usize) -> (f64, f64) {
    let prefix = format!("{}_", unique(&format!("raw{size}")));
    let exe = std::env::current_exe().unwrap();
    let sub = Command::new(&exe)
        .args(["raw-sub", &prefix, &size.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let mut publ = Command::new(&exe)
        .args(["raw-pub", &prefix, &size.to_string()])
        .spawn()
        .unwrap();
    let out = sub.wait_with_output().unwrap();
    let _ = publ.kill();
    let _ = publ.wait();
    let text = String::from_utf8(out.stdout).unwrap();
    let lat: Vec<u64> = serde_json::from_str(text.lines().last().unwrap()).unwrap();
    percentiles(lat)
}

// ------------------------------------------------------------------------------------------
// Through a DNM: blob_source module -> latency module, hosted by `dnm up`.

fn dnm_latency(size: usize) -> (f64, f64) {
    let system = unique(&format!("lat{size}"));
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
    let lat = latencies(&system, "local", "lat", SAMPLES, 50);
    percentiles(lat)
}

// ------------------------------------------------------------------------------------------
// Task switch vs real rewiring, and memory.

fn switch_and_memory() {
    let system = unique("sw");
    let idle: String = (0..8)
        .map(|i| format!("[[module]]\nname = \"idle{i}\"\nkind = \"ticker\"\nrate_hz = 10\n"))
        .collect();
    let netlist = crossed_pairs(&system, &idle);
    let _up = up(&system, &netlist, &[], None, 1);

    let mut virt = Vec::new();
    for i in 0..400 {
        let task = if i % 2 == 0 { "b" } else { "a" };
        let r = request(&system, &Request::Switch { task: task.into() }).unwrap();
        assert!(r.ok, "{r:?}");
        virt.push(r.switches[0].duration_ns);
    }
    // Let the rate and CPU meters settle before reading memory.
    std::thread::sleep(Duration::from_millis(1500));
    let status = request(&system, &Request::Status).unwrap().dnms.remove(0);

    // Real rewiring: 10 subscribers destroyed and created again on live services.
    let real = real_rewiring(10, 50);
    let (v50, v99) = percentiles(virt);
    let (r50, r99) = percentiles(real);
    println!("| task switch, 10 links | p50 (µs) | p99 (µs) |");
    println!("|---|---|---|");
    println!("| virtual (one store of the task word, inside the DNM) | {v50:.3} | {v99:.3} |");
    println!("| real rewiring (destroy + create 10 iceoryx2 subscribers) | {r50:.1} | {r99:.1} |");
    println!(
        "| ratio real / virtual | {:.0}x | {:.0}x |\n",
        r50 / v50,
        r99 / v99
    );

    let mem = status.memory.unwrap_or_default();
    println!("| resident memory (KiB), 15 modules | private (anon + file) | shared memory |");
    println!("|---|---|---|");
    println!(
        "| DNM process | {} | {} |",
        mem.private_kib(),
        mem.shmem_kib
    );
    let mut private: Vec<u64> = status
        .modules
        .iter()
        .filter_map(|m| m.memory.map(|m| m.private_kib()))
        .collect();
    private.sort_unstable();
    let shm_max = status
        .modules
        .iter()
        .filter_map(|m| m.memory.map(|m| m.shmem_kib))
        .max()
        .unwrap_or(0);
    println!(
        "| module process (min / median / max) | {} / {} / {} | up to {shm_max} |",
        private[0],
        private[private.len() / 2],
        private[private.len() - 1]
    );
    println!(
        "\nDNM CPU {:.1}% of one core with 15 modules; module CPU: {}",
        status.cpu_percent,
        status
            .modules
            .iter()
            .map(|m| format!("{} {:.1}%", m.name, m.cpu_percent))
            .collect::<Vec<_>>()
            .join(", ")
    );
}
