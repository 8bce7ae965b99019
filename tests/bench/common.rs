//! What the benchmarks share: bringing systems up with `dnm up`, reading the `latency` module's
//! measurements from a DNM's shared memory, and percentiles.

#![allow(dead_code)] // each benchmark uses its own subset

use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use dnm::admin::{Request, request};
use dnm_module::msg::Tick;
use dnm_module::protocol::{dnm_config, dnm_prefix, output_event, output_service};
use dnm_module::{event_service, port_service};
use dnm_netlist::Payload;
use iceoryx2::prelude::*;

// A bench that loads the system tests' `support` too has this file twice, with two registries
// of ports handed out: those benches (fleet, ground) take every port from `support`'s.
#[path = "../support/port.rs"]
#[allow(clippy::duplicate_mod)]
mod port;
pub use port::free_port;

pub fn human(size: usize) -> String {
    match size {
        s if s >= 1 << 20 => format!("{} MiB", s >> 20),
        s if s >= 1024 => format!("{} KiB", s >> 10),
        s => format!("{s} B"),
    }
}

/// (p50, p99) in µs of nanosecond samples.
pub fn percentiles(mut v: Vec<u64>) -> (f64, f64) {
    v.sort_unstable();
    let p = |q: f64| v[((v.len() - 1) as f64 * q) as usize] as f64 / 1000.0;
    (p(0.5), p(0.99))
}

/// A name unique to this run.
pub fn unique(tag: &str) -> String {
    format!("b{}{tag}", std::process::id())
}

pub fn raw_node(prefix: &str) -> Node<ipc::Service> {
    let config = dnm_config(prefix).unwrap();
    NodeBuilder::new()
        .config(&config)
        .create::<ipc::Service>()
        .unwrap()
}

/// A `dnm up` process, stopped with SIGTERM when dropped.
pub struct Up {
    child: Child,
    dir: std::path::PathBuf,
}

impl Drop for Up {
    fn drop(&mut self) {
        // SAFETY: kill(2) on our own child.
        unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

impl Up {
    pub fn pid(&self) -> u32 {
        self.child.id()
    }
}

/// The `dnm` executable the benchmarks start: this tree's, or another build's (a baseline) after
/// [`use_dnm`].
static DNM_EXE: std::sync::Mutex<Option<std::path::PathBuf>> = std::sync::Mutex::new(None);

/// Makes [`up`] start `exe` (and the `dnm-module-host` beside it); `None`: this tree's.
pub fn use_dnm(exe: Option<std::path::PathBuf>) {
    *DNM_EXE.lock().unwrap() = exe;
}

fn dnm_exe() -> std::path::PathBuf {
    DNM_EXE
        .lock()
        .unwrap()
        .clone()
        .unwrap_or_else(|| env!("CARGO_BIN_EXE_dnm").into())
}

/// Runs `dnm [zenoh args] up NETLIST [--dnm D] --no-record` and waits until `dnms` DNMs of the
/// system on this machine report every module running.
pub fn up(system: &str, netlist: &str, args: &[String], dnm: Option<&str>, dnms: usize) -> Up {
    up_recording(system, netlist, args, dnm, dnms, None)
}

/// [`up`], recording every port into `record_dir` when given.
pub fn up_recording(
    system: &str,
    netlist: &str,
    args: &[String],
    dnm: Option<&str>,
    dnms: usize,
    record_dir: Option<&std::path::Path>,
) -> Up {
    let mut up_args: Vec<String> = match record_dir {
        Some(d) => vec!["--record-dir".into(), d.display().to_string()],
        None => vec!["--no-record".into()],
    };
    if let Some(d) = dnm {
        up_args.extend(["--dnm".into(), d.into()]);
    }
    up_with(system, netlist, args, &up_args, dnm.unwrap_or("all"), dnms)
}

/// Beetle-One (`configs/beetle.toml`) as system `system`, its four DNMs in one `dnm up`
/// listening on a free loopback port, with `up_args` (recording or not). No ground station is
/// in these runs, so the rover's loss of link waits a day before it makes it safe.
pub fn up_beetle(system: &str, up_args: &[String], tag: &str) -> Up {
    let netlist = include_str!("../../configs/beetle.toml")
        .replace("name = \"beetle\"", &format!("name = \"{system}\""))
        .replace("after = \"5s\"", "after = \"24h\"");
    let args: Vec<String> = vec![
        "--no-multicast".into(),
        "--listen".into(),
        format!("tcp/127.0.0.1:{}", free_port()),
    ];
    up_with(system, &netlist, &args, up_args, tag, 4)
}

/// Runs `dnm [args] up NETLIST [up_args]` (its files in a folder named after `tag`) and waits
/// until `dnms` DNMs of the system on this machine report every module running.
pub fn up_with(
    system: &str,
    netlist: &str,
    args: &[String],
    up_args: &[String],
    tag: &str,
    dnms: usize,
) -> Up {
    let dir = std::env::temp_dir().join(format!("dnm-bench-{system}-{tag}"));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("netlist.toml");
    std::fs::write(&path, netlist).unwrap();
    let exe = dnm_exe();
    assert!(
        exe.with_file_name("dnm-module-host").exists(),
        "no dnm-module-host beside {}: build it with `cargo build --release --workspace`",
        exe.display()
    );
    let mut cmd = Command::new(&exe);
    cmd.args(args).arg("up").arg(&path).args(up_args);
    let child = cmd
        .env("DNM_MODULE_HOST", exe.with_file_name("dnm-module-host"))
        .env("RUST_LOG", "warn")
        .stdout(Stdio::null())
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        if let Ok(r) = request(system, &Request::Status)
            && r.dnms.len() >= dnms
            && r.dnms.iter().all(|d| {
                d.modules
                    .iter()
                    .all(|m| m.state == dnm::ModuleRunState::Running)
            })
        {
            break;
        }
        assert!(Instant::now() < deadline, "system {system} did not come up");
        std::thread::sleep(Duration::from_millis(50));
    }
    Up { child, dir }
}

/// A subscriber and a listener on a `latency` module's output (and the node they live on).
struct LatencyPort {
    _node: Node<ipc::Service>,
    sub: iceoryx2::port::subscriber::Subscriber<
        ipc::Service,
        [u8],
        dnm_module::protocol::PortHeader,
    >,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
}

/// Opens the output of the `latency` module `module` on DNM `dnm`.
fn latency_port(system: &str, dnm: &str, module: &str) -> LatencyPort {
    let node = raw_node(&dnm_prefix(system, dnm));
    let payload = Payload::Fixed {
        size_bytes: size_of::<Tick>(),
    };
    let sub = port_service(&node, &output_service(module, "latency_ns"), &payload)
        .unwrap()
        .subscriber_builder()
        .create()
        .unwrap();
    let listener = event_service(&node, &output_event(module, "latency_ns"))
        .unwrap()
        .listener_builder()
        .create()
        .unwrap();
    LatencyPort {
        _node: node,
        sub,
        listener,
    }
}

/// `samples` latencies (ns) measured by the `latency` module `module` on DNM `dnm`, read from
/// that DNM's shared memory; the first `skip` are dropped (start-up).
pub fn latencies(system: &str, dnm: &str, module: &str, samples: usize, skip: usize) -> Vec<u64> {
    latencies_after(system, dnm, module, samples, skip, || ())
}

/// [`latencies`], calling `warm` once the `skip` first are dropped (to start measuring
/// something over the same samples).
pub fn latencies_after(
    system: &str,
    dnm: &str,
    module: &str,
    samples: usize,
    skip: usize,
    mut warm: impl FnMut(),
) -> Vec<u64> {
    let LatencyPort {
        _node,
        sub,
        listener,
    } = latency_port(system, dnm, module);
    let waitset = WaitSetBuilder::new().create::<ipc::Service>().unwrap();
    let _g = waitset.attach_notification(&listener).unwrap();
    let mut lat = Vec::with_capacity(samples);
    let mut skipped = 0;
    if skip == 0 {
        warm();
    }
    while lat.len() < samples {
        waitset
            .wait_and_process_once(|_| CallbackProgression::Continue)
            .unwrap();
        listener.try_wait(|_| ()).unwrap();
        while let Some(s) = sub.receive().unwrap() {
            let t: Tick = bytemuck::pod_read_unaligned(s.payload());
            if skipped < skip {
                skipped += 1;
                if skipped == skip {
                    warm();
                }
                continue;
            }
            lat.push(t.seq);
        }
    }
    lat
}

/// Latencies (ns) measured by the `latency` module `module` on DNM `dnm`, each with the time
/// this process received it, until `stop` is set.
pub fn timed_latencies(
    system: &str,
    dnm: &str,
    module: &str,
    stop: &std::sync::atomic::AtomicBool,
) -> Vec<(Instant, u64)> {
    let LatencyPort {
        _node,
        sub,
        listener,
    } = latency_port(system, dnm, module);
    let mut lat = Vec::new();
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        listener
            .timed_wait(|_| (), Duration::from_millis(100))
            .unwrap();
        while let Some(s) = sub.receive().unwrap() {
            let t: Tick = bytemuck::pod_read_unaligned(s.payload());
            lat.push((Instant::now(), t.seq));
        }
    }
    lat
}

/// What the `latency` module `module` on DNM `dnm` measured, until `stop` is set: per sample,
/// (CLOCK_MONOTONIC ns when this process read it, the sample's sequence number, its latency ns).
/// The measured sample was sent at about the reading time less its latency.
pub fn stamped_latencies(
    system: &str,
    dnm: &str,
    module: &str,
    stop: &std::sync::atomic::AtomicBool,
) -> Vec<(u64, u64, u64)> {
    let LatencyPort {
        _node,
        sub,
        listener,
    } = latency_port(system, dnm, module);
    let mut got = Vec::new();
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        listener
            .timed_wait(|_| (), Duration::from_millis(100))
            .unwrap();
        while let Some(s) = sub.receive().unwrap() {
            let t: Tick = bytemuck::pod_read_unaligned(s.payload());
            got.push((dnm_module::protocol::monotonic_ns(), t.origin, t.seq));
        }
    }
    got
}

/// utime + stime of a process so far, in seconds.
pub fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let after = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let f: Vec<&str> = after.split_whitespace().collect();
    let ticks: f64 = f.get(11).and_then(|x| x.parse().ok()).unwrap_or(0.0)
        + f.get(12).and_then(|x| x.parse().ok()).unwrap_or(0.0);
    // SAFETY: sysconf with a valid name has no side effects.
    ticks / unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64
}

/// Real rewiring of `links` links, `times` times (ns each): as many live iceoryx2 services with
/// publishers, every subscriber destroyed and created again.
pub fn real_rewiring(links: usize, times: usize) -> Vec<u64> {
    let node = raw_node(&format!("{}_", unique(&format!("rw{links}"))));
    let payload = Payload::Fixed {
        size_bytes: size_of::<Tick>(),
    };
    let services: Vec<_> = (0..links)
        .map(|i| port_service(&node, &format!("s{i}/out"), &payload).unwrap())
        .collect();
    let _pubs: Vec<_> = services
        .iter()
        .map(|s| s.publisher_builder().create().unwrap())
        .collect();
    let mut subs: Vec<_> = services
        .iter()
        .map(|s| s.subscriber_builder().create().unwrap())
        .collect();
    let mut real = Vec::new();
    for _ in 0..times {
        let t = Instant::now();
        subs.clear();
        for i in 0..links {
            let s = port_service(&node, &format!("s{i}/out"), &payload).unwrap();
            subs.push(s.subscriber_builder().create().unwrap());
        }
        real.push(t.elapsed().as_nanos() as u64);
    }
    real
}

/// A system whose tasks `a` and `b` differ in ten links: two tickers at 100 Hz (origins 1 and
/// 2) and five `pair` modules whose inputs the two tasks cross; `extra` adds modules.
pub fn crossed_pairs(system: &str, extra: &str) -> String {
    let mut netlist = format!(
        "[system]\nname = \"{system}\"\ndefault_task = \"a\"\n\
         [[module]]\nname = \"src_a\"\nkind = \"ticker\"\nrate_hz = 100\nparams = {{ origin = 1 }}\n\
         [[module]]\nname = \"src_b\"\nkind = \"ticker\"\nrate_hz = 100\nparams = {{ origin = 2 }}\n"
    );
    let (mut a, mut b) = (Vec::new(), Vec::new());
    for i in 0..5 {
        netlist += &format!("[[module]]\nname = \"p{i}\"\nkind = \"pair\"\n");
        a.push(format!("\"src_a.out -> p{i}.a\", \"src_b.out -> p{i}.b\""));
        b.push(format!("\"src_b.out -> p{i}.a\", \"src_a.out -> p{i}.b\""));
    }
    netlist
        + extra
        + &format!(
            "[task.a]\nlinks = [{}]\n[task.b]\nlinks = [{}]\n",
            a.join(", "),
            b.join(", ")
        )
}

/// utime + stime, in seconds, of process `root` and every process descending from it (the
/// processes alive now: what a system of processes costs between two readings).
pub fn tree_cpu_seconds(root: u32) -> f64 {
    let mut parent = std::collections::BTreeMap::new();
    for entry in std::fs::read_dir("/proc").into_iter().flatten().flatten() {
        let Some(pid) = entry
            .file_name()
            .to_str()
            .and_then(|n| n.parse::<u32>().ok())
        else {
            continue;
        };
        let stat = std::fs::read_to_string(entry.path().join("stat")).unwrap_or_default();
        let ppid = stat
            .rsplit_once(')')
            .and_then(|(_, r)| r.split_whitespace().nth(1))
            .and_then(|p| p.parse::<u32>().ok());
        if let Some(ppid) = ppid {
            parent.insert(pid, ppid);
        }
    }
    let descends = |mut pid: u32| loop {
        if pid == root {
            return true;
        }
        match parent.get(&pid) {
            Some(&p) if p != 0 && p != pid => pid = p,
            _ => return false,
        }
    };
    parent
        .keys()
        .filter(|&&p| descends(p))
        .map(|&p| cpu_seconds(p))
        .sum()
}

/// A TCP proxy on a free loopback port to `to`, adding every byte it carries toward `to` to
/// `toward` and every byte back to `back` (the same counter for both counts both ways).
/// Returns its port.
pub fn counting_proxy(
    to: u16,
    toward: std::sync::Arc<std::sync::atomic::AtomicU64>,
    back: std::sync::Arc<std::sync::atomic::AtomicU64>,
) -> u16 {
    use std::sync::atomic::Ordering;
    let listener = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let port = listener.local_addr().unwrap().port();
    std::thread::spawn(move || {
        for client in listener.incoming().flatten() {
            let Ok(server) = std::net::TcpStream::connect(("127.0.0.1", to)) else {
                continue;
            };
            for (mut from, mut into, count) in [
                (
                    client.try_clone().unwrap(),
                    server.try_clone().unwrap(),
                    toward.clone(),
                ),
                (server, client, back.clone()),
            ] {
                std::thread::spawn(move || {
                    let mut buf = vec![0u8; 64 * 1024];
                    while let Ok(n) = std::io::Read::read(&mut from, &mut buf) {
                        if n == 0 || std::io::Write::write_all(&mut into, &buf[..n]).is_err() {
                            break;
                        }
                        count.fetch_add(n as u64, Ordering::Relaxed);
                    }
                    let _ = into.shutdown(std::net::Shutdown::Both);
                });
            }
        }
    });
    port
}
