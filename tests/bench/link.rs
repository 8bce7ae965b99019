//! Links between DNMs over Zenoh, all in one run so ratios are against baselines measured on
//! the same machine at the same time:
//!
//! 1. a link crossing two DNM processes on loopback (module -> DNM egress -> Zenoh -> DNM
//!    mirror -> module) against raw Zenoh publish/subscribe between two processes with the same
//!    payload, rate and publisher settings;
//! 2. the same two modules on one DNM (a shared-memory link), which reproduces the paper's
//!    comparison of virtual (local) and real (middleware) connections.
//!
//! Run: `cargo bench -p dnm --bench link` (results go to stdout as a Markdown table).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use common::{free_port, human, latencies, latencies_after, percentiles, unique, up};
use dnm_module::protocol::monotonic_ns;
use iceoryx2::prelude::{LogLevel, set_log_level};
use zenoh::Wait;

const SIZES: [usize; 4] = [64, 4096, 320 * 240 * 3, 1 << 20];
const SAMPLES: usize = 2000;
const RATE_HZ: f64 = 500.0;
const SKIP: usize = 100;

fn main() {
    set_log_level(LogLevel::Error);
    let args: Vec<String> = std::env::args().collect();
    match args.get(1).map(String::as_str) {
        Some("zpub") => return zenoh_pub(args[2].parse().unwrap(), args[3].parse().unwrap()),
        Some("zsub") => return zenoh_sub(args[2].parse().unwrap()),
        _ => {}
    }
    // With `DNM_BASELINE=/path/to/other/dnm`, that build's crossing is measured too, right
    // after this tree's, so a change is compared with what it replaces in the same run.
    let baseline = std::env::var_os("DNM_BASELINE").map(std::path::PathBuf::from);
    println!(
        "# DNM link benchmark ({SAMPLES} samples per size at {RATE_HZ} Hz, loopback, two processes)\n"
    );
    println!(
        "| payload | raw Zenoh p50 / p99 (µs) | crossing DNMs p50 / p99 (µs) | ratio p50 | ratio p99 | local (shm) p50 / p99 (µs) | crossing / local p50 | CPU per message, raw Zenoh / crossing (µs) |{}",
        if baseline.is_some() {
            " baseline build: crossing p50 / p99 (µs) | ratio p50 | ratio p99 | CPU per message (µs) |"
        } else {
            ""
        }
    );
    println!(
        "|---|---|---|---|---|---|---|---|{}",
        if baseline.is_some() {
            "---|---|---|"
        } else {
            ""
        }
    );
    for size in SIZES {
        let raw = raw_zenoh(size);
        let crossing = crossing(size);
        let local = local(size);
        let before = baseline.as_ref().map(|b| {
            common::use_dnm(Some(b.clone()));
            let c = self::crossing(size);
            common::use_dnm(None);
            format!(
                " {:.1} / {:.1} | {:.2} | {:.2} | {:.1} |",
                c.0,
                c.1,
                c.0 / raw.0,
                c.1 / raw.1,
                c.2
            )
        });
        println!(
            "| {} | {:.1} / {:.1} | {:.1} / {:.1} | {:.2} | {:.2} | {:.1} / {:.1} | {:.1}x | {:.1} / {:.1} |{}",
            human(size),
            raw.0,
            raw.1,
            crossing.0,
            crossing.1,
            crossing.0 / raw.0,
            crossing.1 / raw.1,
            local.0,
            local.1,
            crossing.0 / local.0,
            raw.2,
            crossing.2,
            before.unwrap_or_default(),
        );
    }
}

fn session(listen: Option<u16>, connect: Option<u16>) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"peer\"").unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    if let Some(p) = listen {
        c.insert_json5("listen/endpoints", &format!("[\"tcp/127.0.0.1:{p}\"]"))
            .unwrap();
    }
    if let Some(p) = connect {
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{p}\"]"))
            .unwrap();
    }
    zenoh::open(c).wait().unwrap()
}

// ------------------------------------------------------------------------------------------
// Raw Zenoh: a publisher process and a subscriber process, no DNM. The publisher is declared
// like a DNM's egress publisher (express); the send time travels in the first 8 bytes.

fn zenoh_pub(port: u16, size: usize) {
    let s = session(None, Some(port));
    let publisher = s
        .declare_publisher("bench/raw")
        .express(true)
        .wait()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let period = Duration::from_secs_f64(1.0 / RATE_HZ);
    let mut buf = vec![0u8; size];
    let sent = (SAMPLES + SKIP + 200) as u64;
    let cpu = own_cpu();
    for seq in 0..sent {
        buf[8..16].copy_from_slice(&seq.to_le_bytes());
        buf[0..8].copy_from_slice(&monotonic_ns().to_le_bytes());
        // Copies the payload into Zenoh, as the DNM's egress did from shared memory.
        publisher.put(buf.clone()).wait().unwrap();
        std::thread::sleep(period);
    }
    println!("{}", (own_cpu() - cpu) / sent as f64);
}

/// CPU seconds (user and system) this process used so far.
fn own_cpu() -> f64 {
    // SAFETY: getrusage fills the struct it is given.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: as above; RUSAGE_SELF is always valid.
    unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) };
    let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
    t(u.ru_utime) + t(u.ru_stime)
}

/// CPU seconds (user and system) used so far by `pids` and every process they started.
fn tree_cpu(pids: &[u32]) -> f64 {
    let mut stack = pids.to_vec();
    let mut total = 0.0;
    while let Some(pid) = stack.pop() {
        total += dnm_core::procfs::cpu_seconds(pid).unwrap_or(0.0);
        // Children are listed per thread (the DNM starts modules from its own thread).
        for task in std::fs::read_dir(format!("/proc/{pid}/task"))
            .into_iter()
            .flatten()
            .flatten()
        {
            let children =
                std::fs::read_to_string(task.path().join("children")).unwrap_or_default();
            stack.extend(
                children
                    .split_whitespace()
                    .filter_map(|c| c.parse::<u32>().ok()),
            );
        }
    }
    total
}

fn zenoh_sub(port: u16) {
    let s = session(Some(port), None);
    let (tx, rx) = std::sync::mpsc::channel();
    let _sub = s
        .declare_subscriber("bench/raw")
        .callback(move |sample| {
            let now = monotonic_ns();
            let b = sample.payload().to_bytes();
            let stamp = u64::from_le_bytes(b[0..8].try_into().unwrap());
            let _ = tx.send(now.saturating_sub(stamp));
        })
        .wait()
        .unwrap();
    println!("ready");
    let mut rx = rx.iter();
    let _: Vec<u64> = rx.by_ref().take(SKIP).collect();
    let cpu = own_cpu();
    let lat: Vec<u64> = rx.take(SAMPLES).collect();
    println!("{}", serde_json::to_string(&lat).unwrap());
    println!("{}", (own_cpu() - cpu) / SAMPLES as f64);
}

/// p50 and p99 latency (µs), and the CPU per message (µs) of the publisher and the subscriber.
fn raw_zenoh(size: usize) -> (f64, f64, f64) {
    let exe = std::env::current_exe().unwrap();
    let port = free_port();
    let sub = Command::new(&exe)
        .args(["zsub", &port.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let publ = Command::new(&exe)
        .args(["zpub", &port.to_string(), &size.to_string()])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let out = sub.wait_with_output().unwrap();
    let pub_out = publ.wait_with_output().unwrap();
    let text = String::from_utf8(out.stdout).unwrap();
    let mut lines = text.lines().rev();
    let sub_cpu: f64 = lines.next().unwrap().parse().unwrap();
    let lat: Vec<u64> = serde_json::from_str(lines.next().unwrap()).unwrap();
    let pub_cpu: f64 = String::from_utf8(pub_out.stdout)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    let (p50, p99) = percentiles(lat);
    (p50, p99, (pub_cpu + sub_cpu) * 1e6)
}

// ------------------------------------------------------------------------------------------
// Through DNMs: blob_source -> latency, on two DNM processes or on one DNM.

fn netlist(system: &str, size: usize, lat_dnm: &str) -> String {
    format!(
        r#"[system]
name = "{system}"
[[dnm]]
name = "x"
[[dnm]]
name = "y"
[[module]]
name = "src"
kind = "blob_source"
dnm = "x"
rate_hz = {RATE_HZ}
params = {{ bytes = {size} }}
[[module]]
name = "lat"
kind = "latency"
dnm = "{lat_dnm}"
[task.run]
links = ["src.out -> lat.in"]
"#
    )
}

/// p50 and p99 latency (µs), and the CPU per message (µs) of both DNM processes and their
/// modules.
fn crossing(size: usize) -> (f64, f64, f64) {
    let system = unique(&format!("x{size}"));
    let text = netlist(&system, size, "y");
    let port = free_port();
    let zx = [
        "--no-multicast".to_string(),
        "--listen".into(),
        format!("tcp/127.0.0.1:{port}"),
    ];
    let zy = [
        "--no-multicast".to_string(),
        "--connect".into(),
        format!("tcp/127.0.0.1:{port}"),
    ];
    let x = up(&system, &text, &zx, Some("x"), 1);
    let y = up(&system, &text, &zy, Some("y"), 2);
    let pids = [x.pid(), y.pid()];
    let mut from = None;
    let lat = latencies_after(&system, "y", "lat", SAMPLES, SKIP, || {
        from = Some((tree_cpu(&pids), Instant::now()));
    });
    let (cpu, t0) = from.unwrap();
    let messages = t0.elapsed().as_secs_f64() * RATE_HZ;
    let (p50, p99) = percentiles(lat);
    (p50, p99, (tree_cpu(&pids) - cpu) / messages * 1e6)
}

fn local(size: usize) -> (f64, f64) {
    let system = unique(&format!("l{size}"));
    let text = netlist(&system, size, "x");
    let z = ["--no-multicast".to_string()];
    let _x = up(&system, &text, &z, Some("x"), 1);
    percentiles(latencies(&system, "x", "lat", SAMPLES, SKIP))
}
