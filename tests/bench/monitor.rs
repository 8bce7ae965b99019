//! What watching costs. Beetle-One (`dnm up`, its four DNMs in one process) runs three
//! phases of equal length, in one run:
//! 1. nobody watches (the baseline);
//! 2. every output of every module watched at its full rate (a Zenoh subscriber on
//!    `<system>/watch/**/full`);
//! 3. `dnm-monitor`'s default view (numbers at 10 Hz, camera at 1 Hz as JPEG, the wiring and
//!    the DNMs' reports every second), through a TCP proxy standing for the radio link.
//!
//! Reported: the DNM process's CPU against the baseline, the bytes per second the watcher
//! receives and (phase 3) the bytes per second through the link in both directions (counted by
//! the proxy), and every module's step rate against the
//! baseline: watching must never slow a module.
//!
//! Run: `cargo build --release --workspace && cargo bench --workspace --bench monitor`

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

#[path = "common.rs"]
mod common;

use std::collections::BTreeMap;
use std::process::{Child, Command};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use common::{counting_proxy, cpu_seconds, free_port, unique, up};
use dnm::admin::{Request, request};
use zenoh::Wait;

const BEETLE: &str = include_str!("../../configs/beetle.toml");
/// Seconds each phase is measured.
const PHASE_S: u64 = 20;
/// Seconds each phase settles first.
const SETTLE_S: u64 = 3;

struct Phase {
    name: &'static str,
    dnm_cpu_percent: f64,
    received_bytes_per_s: f64,
    radio_bytes_per_s: Option<f64>,
    rates: BTreeMap<String, f64>,
}

/// Steps per module over the phase, from the DNMs' own counters.
fn steps(system: &str) -> BTreeMap<String, u64> {
    let r = request(system, &Request::Status).unwrap();
    r.dnms
        .iter()
        .flat_map(|d| d.modules.iter().map(|m| (m.name.clone(), m.steps)))
        .collect()
}

fn measure(
    name: &'static str,
    system: &str,
    dnm_pid: u32,
    received: &AtomicU64,
    radio: Option<&AtomicU64>,
) -> Phase {
    // Let whatever started settle first.
    std::thread::sleep(Duration::from_secs(SETTLE_S));
    let (cpu0, steps0, got0) = (
        cpu_seconds(dnm_pid),
        steps(system),
        received.load(Ordering::Relaxed),
    );
    let radio0 = radio.map(|r| r.load(Ordering::Relaxed));
    let t0 = Instant::now();
    std::thread::sleep(Duration::from_secs(PHASE_S));
    let dt = t0.elapsed().as_secs_f64();
    let (cpu1, steps1, got1) = (
        cpu_seconds(dnm_pid),
        steps(system),
        received.load(Ordering::Relaxed),
    );
    let radio1 = radio.map(|r| r.load(Ordering::Relaxed));
    Phase {
        name,
        dnm_cpu_percent: (cpu1 - cpu0) / dt * 100.0,
        received_bytes_per_s: (got1 - got0) as f64 / dt,
        radio_bytes_per_s: radio0.zip(radio1).map(|(a, b)| (b - a) as f64 / dt),
        rates: steps1
            .iter()
            .map(|(m, s)| {
                (
                    m.clone(),
                    (s - steps0.get(m).copied().unwrap_or(0)) as f64 / dt,
                )
            })
            .collect(),
    }
}

struct Kill(Child);

impl Drop for Kill {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.0.id() as i32, libc::SIGTERM) };
        let _ = self.0.wait();
    }
}

fn main() {
    let system = unique("mon");
    let port = free_port();
    // No ground station in this run: the rover must not go safe for the lack of one.
    let netlist = BEETLE
        .replace("name = \"beetle\"", &format!("name = \"{system}\""))
        .replace("after = \"5s\"", "after = \"1h\"");
    let args: Vec<String> = vec![
        "--no-multicast".into(),
        "--listen".into(),
        format!("tcp/127.0.0.1:{port}"),
    ];
    let sys = up(&system, &netlist, &args, None, 4);
    let exe = std::path::PathBuf::from(env!("CARGO_BIN_EXE_dnm"));
    let monitor_exe = exe.with_file_name("dnm-monitor");
    assert!(
        monitor_exe.exists(),
        "no dnm-monitor beside {}: build it with `cargo build --release --workspace`",
        exe.display()
    );

    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"client\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
        .unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    let session = zenoh::open(c).wait().unwrap();
    let received = Arc::new(AtomicU64::new(0));

    let mut phases = vec![measure(
        "nobody watches",
        &system,
        sys.pid(),
        &received,
        None,
    )];

    let all = {
        let received = received.clone();
        session
            .declare_subscriber(format!("{system}/watch/**/full"))
            .callback(move |s| {
                received.fetch_add(s.payload().len() as u64, Ordering::Relaxed);
            })
            .wait()
            .unwrap()
    };
    phases.push(measure(
        "every output watched, full rate",
        &system,
        sys.pid(),
        &received,
        None,
    ));
    drop(all);

    // The link between the ground and the rover: a proxy that counts every byte both ways.
    let radio_bytes = Arc::new(AtomicU64::new(0));
    let radio_port = counting_proxy(port, radio_bytes.clone(), radio_bytes.clone());
    let rrd = std::env::temp_dir().join(format!("{system}.rrd"));
    let mut rrd_bytes = 0;
    for (name, extra) in [
        ("dnm-monitor default view, across the link", &[][..]),
        (
            "dnm-monitor thin view (--rate 1hz --status-every 5)",
            &["--rate", "1hz", "--status-every", "5"][..],
        ),
    ] {
        let monitor = Kill(
            Command::new(&monitor_exe)
                .args([
                    "--system",
                    &system,
                    "--connect",
                    &format!("tcp/127.0.0.1:{radio_port}"),
                    "--no-multicast",
                    "--save",
                ])
                .arg(&rrd)
                .args(extra)
                .env("RUST_LOG", "warn")
                .spawn()
                .unwrap(),
        );
        phases.push(measure(
            name,
            &system,
            sys.pid(),
            &received,
            Some(&radio_bytes),
        ));
        drop(monitor);
        if rrd_bytes == 0 {
            rrd_bytes = std::fs::metadata(&rrd).map_or(0, |m| m.len());
        }
        let _ = std::fs::remove_file(&rrd);
    }

    let base = &phases[0];
    println!(
        "Beetle-One, {} s per phase; DNM CPU is the `dnm up` process hosting all four DNMs (100% = one core).\n",
        PHASE_S
    );
    println!(
        "| phase | DNM CPU | vs nobody watching | watcher receives | radio link (both ways) | slowest module rate vs nobody watching |"
    );
    println!("|---|---|---|---|---|---|");
    for p in &phases {
        let slowest = p
            .rates
            .iter()
            .filter_map(|(m, r)| {
                let b = base.rates.get(m).copied().unwrap_or(0.0);
                (b > 0.5).then(|| (r / b, m))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0));
        println!(
            "| {} | {:.1}% | {:.2}x | {} | {} | {} |",
            p.name,
            p.dnm_cpu_percent,
            p.dnm_cpu_percent / base.dnm_cpu_percent,
            // The monitor counts what it receives itself (the radio column says it in bytes).
            if p.radio_bytes_per_s.is_some() {
                "-".to_string()
            } else {
                format!("{:.1} KiB/s", p.received_bytes_per_s / 1024.0)
            },
            p.radio_bytes_per_s.map_or("-".into(), |b| format!(
                "{:.1} KiB/s ({:.0} kbit/s)",
                b / 1024.0,
                b * 8.0 / 1000.0
            )),
            slowest.map_or("-".into(), |(r, m)| format!("{r:.3}x ({m})")),
        );
    }
    println!(
        "\nThe default view's .rrd after {} s (settling and the phase): {:.1} MiB",
        SETTLE_S + PHASE_S,
        rrd_bytes as f64 / (1 << 20) as f64
    );
    println!(
        "\nModule step rates (steps/s), nobody watching → every output watched → default view → thin view:"
    );
    for (m, r) in &base.rates {
        let at = |i: usize| phases[i].rates.get(m).copied().unwrap_or(0.0);
        println!("- {m}: {r:.1} → {:.1} → {:.1} → {:.1}", at(1), at(2), at(3));
    }
}
