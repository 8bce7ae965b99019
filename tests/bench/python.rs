//! Modules in Python against modules in Rust, in one run: one hop through a DNM, a source
//! writing a payload at 500 Hz and a sink measuring, on reading it, how long ago it was sent
//! (CLOCK_MONOTONIC, one machine), at 64 B, 4 KiB and 1 MiB. Rust → Rust is `blob_source` →
//! `latency`; Python → Python is the same two written in Python with the `dnm` package (the
//! source loans its payload in shared memory and fills it in place; the sink reads it as a
//! numpy view of the sample). Both report on the same kind of output, read from the DNM's
//! shared memory by this process. Beside them, the same pair as dora Python nodes (dora-rs
//! 1.1.0, `dora run`): the source stamps CLOCK_MONOTONIC into the payload just before
//! `send_output`, the sink reads the arrow array without a copy. CPU per message is what every
//! process of the system (DNM and modules; dora's daemon and nodes) used over the measured
//! samples, divided by their number.
//!
//! Run: `scripts/test` once (it makes the Python environment in `target/py`), then
//! `target/py/bin/maturin develop --release -m modules/python/Cargo.toml` (with
//! `VIRTUAL_ENV=target/py`), `cargo build --release --workspace` and
//! `cargo bench -p dnm --bench python` (`DNM_PYTHON` names another Python with `dnm`). The
//! first run makes a Python environment with dora in `target/dora` (`DNM_DORA` names another
//! `dora` executable).
//!
//! Knobs for studying one cell: `DNM_PY_SIZES=64,4096` measures only those sizes,
//! `DNM_PY_NO_DORA=1` leaves dora out, `DNM_BENCH_PIN=1` pins each pair's source to CPU 0 and
//! its sink to CPU 1 (the default leaves placement to the kernel, as a deployment would).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::path::PathBuf;

use std::time::{Duration, Instant};

use common::{human, latencies_after, percentiles, tree_cpu_seconds, unique, up};

const SIZES: [usize; 3] = [64, 4096, 1 << 20];
/// Samples per round; each pair runs [`ROUNDS`] times, the pairs taking turns, and its samples
/// are pooled (the machine's noise then falls on every pair alike; each round's p50s go to
/// stderr).
const SAMPLES: usize = 700;
const ROUNDS: usize = 6;
const RATE_HZ: f64 = 500.0;
const SKIP: usize = 100;

const PY_MODULES: &str = r#"
import time
import dnm
from dnm.msg import Blob, Tick

MIB = 1 << 20

class Blobs(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_blobs", "a payload of `bytes` per step").output("out", Blob, max_bytes=MIB) \
            .param("bytes", 64).periodic(100)

    def __init__(self, setup):
        self.out = setup.output("out")
        self.size = setup.param("bytes")
        self.seq = 0

    def step(self, io):
        buf = io.loan(self.out, self.size)
        buf[8:16] = memoryview(self.seq.to_bytes(8, "little"))
        io.send(self.out)
        self.seq += 1

class Latency(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_latency", "how long ago each payload was sent, ns") \
            .input("in", Blob, max_bytes=MIB).output("latency_ns", Tick).on_input()

    def __init__(self, setup):
        self.inp = setup.input("in")
        self.out = setup.output("latency_ns")

    def step(self, io):
        data = io.read(self.inp)
        if data is None:
            return
        now = time.monotonic_ns()
        stamp, seq, _ = io.header(self.inp)
        io.write(self.out, Tick(origin=int(data[8]), seq=now - stamp))

if __name__ == "__main__":
    import sys
    kind = sys.argv[0].rsplit("/", 1)[-1].removesuffix(".py")
    raise SystemExit(dnm.host_main([{"py_blobs": Blobs, "py_latency": Latency}[kind]]))
"#;

fn python() -> PathBuf {
    let p: PathBuf = std::env::var_os("DNM_PYTHON").map_or_else(
        || PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/py/bin/python"),
        Into::into,
    );
    let ok = std::process::Command::new(&p)
        .args(["-c", "import dnm"])
        .status()
        .is_ok_and(|s| s.success());
    assert!(
        ok,
        "no Python with the `dnm` package at {}: run scripts/test once, then maturin develop \
         --release (see the top of tests/bench/python.rs), or set DNM_PYTHON",
        p.display()
    );
    p
}

/// What one pair measured.
struct Hop {
    p50_us: f64,
    p99_us: f64,
    /// CPU of the whole system per message, µs.
    cpu_us: f64,
}

/// One round of a pair: its latencies (ns) and the CPU its processes used meanwhile (s).
#[derive(Default)]
struct Round {
    lat: Vec<u64>,
    cpu_s: f64,
}

impl Round {
    fn add(&mut self, other: Round) {
        self.lat.extend(other.lat);
        self.cpu_s += other.cpu_s;
    }

    fn hop(self) -> Hop {
        let n = self.lat.len().max(1) as f64;
        let (p50_us, p99_us) = percentiles(self.lat);
        Hop {
            p50_us,
            p99_us,
            cpu_us: self.cpu_s * 1e6 / n,
        }
    }
}

impl Hop {
    fn cell(&self) -> String {
        format!(
            "{:.1} / {:.1} ({:.0})",
            self.p50_us, self.p99_us, self.cpu_us
        )
    }
}

/// One hop through a DNM.
fn hop(size: usize, exec: Option<&PathBuf>) -> Round {
    let system = unique(&format!("py{size}"));
    let (source, sink, kinds) = match exec {
        None => ("blob_source", "latency", String::new()),
        Some(e) => (
            "py_blobs",
            "py_latency",
            format!(
                "[kind.py_blobs]\nexec = \"{0}/py_blobs.py\"\n[kind.py_latency]\nexec = \"{0}/py_latency.py\"\n",
                e.display()
            ),
        ),
    };
    let netlist = format!(
        r#"[system]
name = "{system}"
{kinds}
[[module]]
name = "src"
kind = "{source}"
rate_hz = {RATE_HZ}
params = {{ bytes = {size} }}
[[module]]
name = "lat"
kind = "{sink}"
[task.run]
links = ["src.out -> lat.in"]
"#
    );
    let up = up(&system, &netlist, &[], None, 1);
    if std::env::var_os("DNM_BENCH_PIN").is_some() {
        pin(&system, "src", 0);
        pin(&system, "lat", 1);
    }
    let mut cpu0 = 0.0;
    let lat = latencies_after(&system, "local", "lat", SAMPLES, SKIP, || {
        cpu0 = tree_cpu_seconds(up.pid());
    });
    let cpu_s = tree_cpu_seconds(up.pid()) - cpu0;
    Round { lat, cpu_s }
}

/// Pins the process of `module` of `system` (found by its launch description) to `cpu`: its
/// main thread, the one that waits and steps.
fn pin(system: &str, module: &str, cpu: usize) {
    let needle = format!("\"module\":\"{module}\"");
    let since = Instant::now();
    loop {
        assert!(
            since.elapsed() < Duration::from_secs(30),
            "no process of module {module} of {system}"
        );
        for entry in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
            let cmd = std::fs::read(entry.path().join("cmdline")).unwrap_or_default();
            let cmd = String::from_utf8_lossy(&cmd);
            if cmd.contains(system) && cmd.contains(&needle) {
                let pid: i32 = entry.file_name().to_str().unwrap().parse().unwrap();
                // SAFETY: a zeroed cpu_set_t is an empty set; sched_setaffinity reads it only.
                let rc = unsafe {
                    let mut set: libc::cpu_set_t = std::mem::zeroed();
                    libc::CPU_SET(cpu, &mut set);
                    libc::sched_setaffinity(pid, std::mem::size_of::<libc::cpu_set_t>(), &set)
                };
                assert_eq!(rc, 0, "pinning {module} to CPU {cpu}");
                return;
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
}

const DORA_SOURCE: &str = r#"
import os, time
import numpy as np
import pyarrow as pa
from dora import Node

node = Node()
buf = np.zeros(int(os.environ["SIZE"]), dtype=np.uint8)
seq = 0
for event in node:
    if event["type"] == "INPUT":
        buf[8:16] = np.frombuffer(seq.to_bytes(8, "little"), dtype=np.uint8)
        # Stamped last, as the DNM stamps a sample when it is sent.
        buf[0:8] = np.frombuffer(time.monotonic_ns().to_bytes(8, "little"), dtype=np.uint8)
        node.send_output("out", pa.array(buf))
        seq += 1
    elif event["type"] == "STOP":
        break
"#;

const DORA_SINK: &str = r#"
import os, time
from dora import Node

skip, samples, out = int(os.environ["SKIP"]), int(os.environ["SAMPLES"]), os.environ["OUT"]
node = Node()
lat, n, first, last = [], 0, None, None
for event in node:
    if event["type"] == "INPUT":
        now = time.monotonic_ns()
        data = event["value"].to_numpy(zero_copy_only=True)
        stamp = int.from_bytes(data[0:8].tobytes(), "little")
        seq = int.from_bytes(data[8:16].tobytes(), "little")
        n += 1
        if n <= skip:
            if n == skip:
                open(out + ".warm", "w").close()
            continue
        first = seq if first is None else first
        last = seq
        lat.append(now - stamp)
        if len(lat) >= samples:
            break
    elif event["type"] == "STOP":
        break
with open(out + ".tmp", "w") as f:
    f.write(f"{last - first + 1 - len(lat)}\n" + "\n".join(map(str, lat)))
os.rename(out + ".tmp", out)
"#;

/// The `dora` command: `DNM_DORA`, else the one in `target/dora`, installed there from PyPI
/// on the first run.
fn dora() -> PathBuf {
    if let Some(p) = std::env::var_os("DNM_DORA") {
        return p.into();
    }
    let venv = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/dora");
    let dora = venv.join("bin/dora");
    if !dora.exists() {
        let run = |cmd: &mut std::process::Command| {
            assert!(cmd.status().is_ok_and(|s| s.success()), "{cmd:?} failed");
        };
        run(std::process::Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv));
        run(std::process::Command::new(venv.join("bin/pip")).args([
            "install",
            "-q",
            "dora-rs==1.1.0",
            "dora-rs-cli==1.1.0",
            "numpy",
            "pyarrow",
        ]));
    }
    dora
}

/// One hop between two dora Python nodes, and how many samples the sink missed.
fn dora_hop(dora: &PathBuf, size: usize, dir: &std::path::Path) -> (Round, u64) {
    let run = dir.join(format!("dora-{size}"));
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(run.join("source.py"), DORA_SOURCE).unwrap();
    std::fs::write(run.join("sink.py"), DORA_SINK).unwrap();
    let out = run.join("latencies.txt");
    let period_ms = (1000.0 / RATE_HZ) as u64;
    std::fs::write(
        run.join("dataflow.yml"),
        format!(
            "nodes:\n  - id: source\n    path: source.py\n    inputs:\n      tick: dora/timer/millis/{period_ms}\n    outputs:\n      - out\n    env:\n      SIZE: \"{size}\"\n  - id: sink\n    path: sink.py\n    inputs:\n      in:\n        source: source/out\n        queue_size: 100\n    env:\n      SKIP: \"{SKIP}\"\n      SAMPLES: \"{SAMPLES}\"\n      OUT: \"{}\"\n",
            out.display()
        ),
    )
    .unwrap();
    let bin = dora.parent().unwrap();
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let log = std::fs::File::create(run.join("dora.log")).unwrap();
    let mut child = std::process::Command::new(dora)
        .args(["run", "dataflow.yml"])
        .current_dir(&run)
        .env("PATH", path)
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .spawn()
        .unwrap();
    let wait_for = |f: &std::path::Path| {
        let deadline = Instant::now() + Duration::from_secs(120);
        while !f.exists() {
            assert!(
                Instant::now() < deadline,
                "dora did not get that far: see {}",
                run.join("dora.log").display()
            );
            std::thread::sleep(Duration::from_millis(2));
        }
    };
    wait_for(&run.join("latencies.txt.warm"));
    let cpu0 = tree_cpu_seconds(child.id());
    wait_for(&out);
    let cpu_s = tree_cpu_seconds(child.id()) - cpu0;
    // SAFETY: kill(2) on our own child; `dora run` stops its nodes on SIGINT.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let _ = child.wait();
    let text = std::fs::read_to_string(&out).unwrap();
    let mut lines = text.lines();
    let missed = lines.next().unwrap().parse().unwrap();
    let lat: Vec<u64> = lines.map(|l| l.parse().unwrap()).collect();
    let _ = std::fs::remove_dir_all(&run);
    (Round { lat, cpu_s }, missed)
}

fn main() {
    let py = python();
    let dir = std::env::temp_dir().join(unique("pybench"));
    std::fs::create_dir_all(&dir).unwrap();
    // One kind per executable: the file's name says which.
    for name in ["py_blobs", "py_latency"] {
        use std::os::unix::fs::PermissionsExt;
        let f = dir.join(format!("{name}.py"));
        std::fs::write(&f, format!("#!{}\n{PY_MODULES}", py.display())).unwrap();
        std::fs::set_permissions(&f, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
    let exec = dir.clone();
    let with_dora = std::env::var_os("DNM_PY_NO_DORA").is_none();
    let dora = if with_dora { dora() } else { PathBuf::new() };
    println!(
        "# One hop: Python → Python against Rust → Rust through a DNM, and dora's Python nodes \
         ({ROUNDS} rounds of {SAMPLES} samples at {RATE_HZ} Hz, the pairs taking turns)\n"
    );
    println!("p50 / p99 µs (CPU µs per message, every process of the system)\n");
    println!(
        "| payload | Rust (DNM) | Python (DNM) | Python (dora 1.1.0) | Python/Rust p50 | dora/Python p50 |"
    );
    println!("|---|---|---|---|---|---|");
    let mut missed = Vec::new();
    let sizes: Vec<usize> = match std::env::var("DNM_PY_SIZES") {
        Ok(v) => v.split(',').map(|s| s.parse().unwrap()).collect(),
        Err(_) => SIZES.to_vec(),
    };
    for size in sizes {
        let (mut rust, mut python, mut dora_r) =
            (Round::default(), Round::default(), Round::default());
        let mut lost = 0;
        for round in 0..ROUNDS {
            let (r, p) = (hop(size, None), hop(size, Some(&exec)));
            // Round by round: the machine's phases show as both pairs moving together.
            eprintln!(
                "{} round {round}: Rust p50 {:.1} µs, Python p50 {:.1} µs",
                human(size),
                percentiles(r.lat.clone()).0,
                percentiles(p.lat.clone()).0
            );
            rust.add(r);
            python.add(p);
            if with_dora {
                let (d, l) = dora_hop(&dora, size, &dir);
                dora_r.add(d);
                lost += l;
            }
        }
        if lost > 0 {
            missed.push(format!("{lost} at {}", human(size)));
        }
        let (rust, python) = (rust.hop(), python.hop());
        let (dora_cell, dora_ratio) = if with_dora {
            let d = dora_r.hop();
            (d.cell(), format!("{:.2}", d.p50_us / python.p50_us))
        } else {
            ("—".to_string(), "—".to_string())
        };
        println!(
            "| {} | {} | {} | {dora_cell} | {:.2} | {dora_ratio} |",
            human(size),
            rust.cell(),
            python.cell(),
            python.p50_us / rust.p50_us,
        );
    }
    if !missed.is_empty() {
        println!("\ndora's sinks missed samples: {}", missed.join(", "));
    }
    let _ = std::fs::remove_dir_all(&dir);
}
