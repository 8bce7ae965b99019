//! Modules in Python against modules in Rust, in one run: one hop through a DNM, a source
//! writing a payload at 500 Hz and a sink measuring, on reading it, how long ago it was sent
//! (CLOCK_MONOTONIC, one machine), at 64 B, 4 KiB and 1 MiB. Rust → Rust is `blob_source` →
//! `latency`; Python → Python is the same two written in Python with the `dnm` package (the
//! source loans its payload in shared memory and fills it in place; the sink reads it as a
//! numpy view of the sample). Both report on the same kind of output, read from the DNM's
//! shared memory by this process.
//!
//! Run: `scripts/test` once (it makes the Python environment in `target/py`), then
//! `target/py/bin/maturin develop --release -m modules/python/Cargo.toml` (with
//! `VIRTUAL_ENV=target/py`), `cargo build --release --workspace` and
//! `cargo bench -p dnm --bench python` (`DNM_PYTHON` names another Python with `dnm`).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::path::PathBuf;

use common::{human, latencies, percentiles, unique, up};

const SIZES: [usize; 3] = [64, 4096, 1 << 20];
const SAMPLES: usize = 2000;
const RATE_HZ: f64 = 500.0;

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

/// One hop: (p50, p99) µs.
fn hop(size: usize, exec: Option<&PathBuf>) -> (f64, f64) {
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
    let _up = up(&system, &netlist, &[], None, 1);
    percentiles(latencies(&system, "local", "lat", SAMPLES, 100))
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
    println!(
        "# One hop through a DNM: Python → Python against Rust → Rust ({SAMPLES} samples at {RATE_HZ} Hz)\n"
    );
    println!("| payload | Rust p50 / p99 (µs) | Python p50 / p99 (µs) | ratio p50 | ratio p99 |");
    println!("|---|---|---|---|---|");
    for size in SIZES {
        let rust = hop(size, None);
        let python = hop(size, Some(&exec));
        println!(
            "| {} | {:.1} / {:.1} | {:.1} / {:.1} | {:.2} | {:.2} |",
            human(size),
            rust.0,
            rust.1,
            python.0,
            python.1,
            python.0 / rust.0,
            python.1 / rust.1
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}
