//! What securing the links costs, against plain TCP in the same run:
//!
//! 1. a link crossing two DNM processes (module -> DNM -> Zenoh -> DNM -> module), over plain
//!    TCP and over mutual TLS with the access control `dnm certs config` generates;
//! 2. an operator's command round trip (a task switch answered by both DNMs), the same two ways.
//!
//! Run: `cargo bench -p dnm --bench security` (results go to stdout as a Markdown table).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::path::PathBuf;
use std::process::Command;
use std::time::{Duration, Instant};

use common::{free_port, human, latencies, percentiles, unique, up};
use iceoryx2::prelude::{LogLevel, set_log_level};
use zenoh::Wait;

/// Payload, rate and samples measured: small messages fast, a camera image at camera rate.
const CASES: [(usize, f64, usize); 3] = [
    (64, 500.0, 2000),
    (4096, 500.0, 2000),
    (320 * 240 * 3, 30.0, 600),
];
const SKIP: usize = 100;
const COMMANDS: usize = 300;

fn dnm(args: &[&str]) {
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(args)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "dnm {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

fn netlist(system: &str, size: usize, rate_hz: f64) -> String {
    format!(
        r#"[system]
name = "{system}"
default_task = "run"
[[dnm]]
name = "x"
[[dnm]]
name = "y"
[[module]]
name = "src"
kind = "blob_source"
dnm = "x"
rate_hz = {rate_hz}
params = {{ bytes = {size} }}
[[module]]
name = "lat"
kind = "latency"
dnm = "y"
[task.run]
links = ["src.out -> lat.in"]
[task.also]
links = ["src.out -> lat.in"]
"#
    )
}

/// Certificates for a system and the Zenoh configurations of x (listens), y and an operator.
struct Pki {
    dir: PathBuf,
}

impl Pki {
    fn new(system: &str, text: &str, port: u16) -> Self {
        let dir = std::env::temp_dir().join(format!("dnm-bench-{system}-pki"));
        let _ = std::fs::remove_dir_all(&dir);
        let pki = dir.join("pki");
        let p = pki.to_str().unwrap();
        dnm(&["certs", "init", "--dir", p, "--system", system]);
        dnm(&[
            "certs", "issue", "--dir", p, "x", "--role", "rover", "--dnm", "x",
        ]);
        dnm(&[
            "certs", "issue", "--dir", p, "y", "--role", "rover", "--dnm", "y",
        ]);
        dnm(&["certs", "issue", "--dir", p, "op", "--role", "operator"]);
        dnm(&["certs", "issue", "--dir", p, "router", "--role", "router"]);
        let netlist = dir.join("netlist.toml");
        std::fs::write(&netlist, text).unwrap();
        let ep = format!("tls/127.0.0.1:{port}");
        for (name, side, mode) in [
            ("router", "--listen", "router"),
            ("x", "--connect", "client"),
            ("y", "--connect", "client"),
            ("op", "--connect", "client"),
        ] {
            let out = dir.join(format!("{name}.json5"));
            dnm(&[
                "certs",
                "config",
                "--dir",
                p,
                name,
                "--netlist",
                netlist.to_str().unwrap(),
                "--mode",
                mode,
                side,
                &ep,
                "--out",
                out.to_str().unwrap(),
            ]);
        }
        Self { dir }
    }

    fn config(&self, name: &str) -> PathBuf {
        self.dir.join(format!("{name}.json5"))
    }
}

struct Run {
    link: (f64, f64),
    command: (f64, f64),
    /// Switches not answered by both DNMs.
    incomplete: usize,
}

fn run((size, rate_hz, samples): (usize, f64, usize), tls: bool) -> Run {
    let system = unique(&format!("{}{size}", if tls { "s" } else { "p" }));
    let text = netlist(&system, size, rate_hz);
    let port = free_port();
    // As deployed: a router, each DNM computer and the operator its clients.
    let (zr, zx, zy, operator): (Vec<String>, Vec<String>, Vec<String>, zenoh::Config) = if tls {
        let pki = Pki::new(&system, &text, port);
        let arg = |n: &str| {
            vec![
                "--zenoh-config".to_string(),
                pki.config(n).display().to_string(),
            ]
        };
        (
            arg("router"),
            arg("x"),
            arg("y"),
            zenoh::Config::from_file(pki.config("op")).unwrap(),
        )
    } else {
        let client = vec![
            "--no-multicast".to_string(),
            "--zenoh-mode".into(),
            "client".into(),
            "--connect".into(),
            format!("tcp/127.0.0.1:{port}"),
        ];
        let mut c = zenoh::Config::default();
        c.insert_json5("mode", "\"client\"").unwrap();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        c.insert_json5("connect/endpoints", &format!("[\"tcp/127.0.0.1:{port}\"]"))
            .unwrap();
        (
            vec![
                "--no-multicast".into(),
                "--listen".into(),
                format!("tcp/127.0.0.1:{port}"),
            ],
            client.clone(),
            client,
            c,
        )
    };
    let router = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(&zr)
        .arg("router")
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let router = Kill(router);
    // The operator's session opens once the router listens.
    let session = loop {
        if let Ok(s) = zenoh::open(operator.clone()).wait() {
            break s;
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let _x = up(&system, &text, &zx, Some("x"), 1);
    let _y = up(&system, &text, &zy, Some("y"), 2);
    let link = percentiles(latencies(&system, "y", "lat", samples, SKIP));
    // The operator switches back and forth; both DNMs answer each switch.
    let mut rtt = Vec::new();
    let mut incomplete = 0;
    for i in 0..COMMANDS + 20 {
        let task = if i % 2 == 0 { "also" } else { "run" };
        let cmd = serde_json::json!({"client": "bench", "id": format!("s{i}"), "cmd": "switch", "task": task});
        let t = Instant::now();
        let replies = session
            .get(format!("{system}/dnm/*/cmd"))
            .payload(serde_json::to_vec(&cmd).unwrap())
            .target(zenoh::query::QueryTarget::All)
            .consolidation(zenoh::query::ConsolidationMode::None)
            .timeout(Duration::from_secs(5))
            .wait()
            .unwrap();
        let ok = replies.iter().filter(|r| r.result().is_ok()).count();
        if ok < 2 {
            // An answer lost with a link that closed and reopened (counted, not timed).
            incomplete += 1;
            continue;
        }
        if i >= 20 {
            rtt.push(t.elapsed().as_nanos() as u64);
        }
    }
    drop(router);
    Run {
        link,
        command: percentiles(rtt),
        incomplete,
    }
}

/// A child process killed when dropped.
struct Kill(std::process::Child);

impl Drop for Kill {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn main() {
    set_log_level(LogLevel::Error);
    if std::env::args().any(|a| a == "--list") {
        return;
    }
    println!(
        "# Secured links (mutual TLS + access control) against plain TCP, loopback, two DNM processes\n"
    );
    println!(
        "| payload at rate | link TCP p50 / p99 (µs) | link TLS p50 / p99 (µs) | TLS/TCP p50 | TLS/TCP p99 | command TCP p50 / p99 (µs) | command TLS p50 / p99 (µs) | TLS/TCP p50 | unanswered TCP / TLS |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for case in CASES {
        let plain = run(case, false);
        let tls = run(case, true);
        println!(
            "| {} at {} Hz | {:.1} / {:.1} | {:.1} / {:.1} | {:.2} | {:.2} | {:.0} / {:.0} | {:.0} / {:.0} | {:.2} | {} / {} of {COMMANDS} |",
            human(case.0),
            case.1,
            plain.link.0,
            plain.link.1,
            tls.link.0,
            tls.link.1,
            tls.link.0 / plain.link.0,
            tls.link.1 / plain.link.1,
            plain.command.0,
            plain.command.1,
            tls.command.0,
            tls.command.1,
            tls.command.0 / plain.command.0,
            plain.incomplete,
            tls.incomplete,
        );
    }
}
