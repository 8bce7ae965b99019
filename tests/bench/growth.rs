//! How the cost grows with the system, all in one run, each size beside the others:
//!
//! 1. apply: one DNM applying a netlist of 10, 50 and 200 modules (a ticker and a relay per
//!    pair): time until the apply is in force and until every module runs, then the DNM's and
//!    the modules' memory and CPU, and the time to re-apply with one module's rate changed;
//! 2. switch: tasks that change 10, 100 and 1000 links (two sources, 8-input `merge` modules):
//!    the DNM's switch against destroying and creating as many iceoryx2 subscribers;
//! 3. fan-out: one 500 Hz ticker read by 1, 16 and 64 `latency` modules: delivery latency at
//!    the first and the last reader, and the CPU of the whole system.
//!
//! Tables go to stdout as Markdown, plots to `docs/bench/growth-*.png`.
//!
//! Run: `cargo bench -p dnm --bench growth` (or `-- apply`, `-- switch`, `-- fanout` for one
//! part).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;
mod plot;

use std::time::{Duration, Instant};

use common::{cpu_seconds, latencies, percentiles, real_rewiring, unique, up};
use dnm::admin::{Request, request};
use iceoryx2::prelude::{LogLevel, set_log_level};
use plot::Series;

const MODULES: [usize; 3] = [10, 50, 200];
const LINKS: [usize; 3] = [10, 100, 1000];
const READERS: [usize; 3] = [1, 16, 64];
const MERGE_INPUTS: usize = 8;
const SWITCHES: usize = 200;
const SAMPLES: usize = 2000;
const SKIP: usize = 200;

fn main() {
    set_log_level(LogLevel::Error);
    println!("# growth benchmark\n");
    let only: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let wanted = |part: &str| only.is_empty() || only.iter().any(|o| o == part);
    if wanted("apply") {
        apply();
    }
    if wanted("switch") {
        switch();
    }
    if wanted("fanout") {
        fanout();
    }
}

fn plotted(result: Result<std::path::PathBuf, String>) {
    match result {
        Ok(p) => println!("\nplot: {}\n", p.display()),
        Err(e) => println!("\nno plot: {e}\n"),
    }
}

/// Every module of the system's DNMs running.
fn wait_running(system: &str, modules: usize) {
    loop {
        if let Ok(r) = request(system, &Request::Status) {
            let running = r
                .dnms
                .iter()
                .flat_map(|d| &d.modules)
                .filter(|m| m.state == dnm::ModuleRunState::Running)
                .count();
            if running >= modules {
                return;
            }
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

// ------------------------------------------------------------------------------------------

fn pairs_netlist(system: &str, modules: usize, changed_rate: bool) -> String {
    let mut text = format!("[system]\nname = \"{system}\"\ndefault_task = \"run\"\n");
    let mut links = Vec::new();
    for i in 0..modules / 2 {
        let rate = if changed_rate && i == 0 { 20 } else { 10 };
        text += &format!(
            "[[module]]\nname = \"t{i}\"\nkind = \"ticker\"\nrate_hz = {rate}\n\
             [[module]]\nname = \"r{i}\"\nkind = \"relay\"\n"
        );
        links.push(format!("\"t{i}.out -> r{i}.in\""));
    }
    text + &format!("[task.run]\nlinks = [{}]\n", links.join(", "))
}

fn apply() {
    println!(
        "| modules | apply in force (ms) | all running (ms) | CPU to start, DNM / per module (ms) | re-apply, one rate changed (ms) | DNM memory: heap / files / shared (MiB) | DNM heap, added per module (KiB) | module process: heap / files (MiB) | DNM CPU running (% of a core) | modules' CPU running, total (%) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    let mut in_force = Vec::new();
    let mut running = Vec::new();
    let mut reapply = Vec::new();
    let mut dnm_mem = Vec::new();
    let mut prev_heap: Option<(usize, u64)> = None;
    for n in MODULES {
        let system = unique(&format!("a{n}"));
        // Start from the smallest system, then apply the whole netlist.
        let _up = up(&system, &pairs_netlist(&system, 2, false), &[], None, 1);
        let text = pairs_netlist(&system, n, false);
        let dnm_cpu = cpu_seconds(_up.pid());
        let t = Instant::now();
        let r = request(
            &system,
            &Request::Apply {
                file: "growth.toml".into(),
                text,
            },
        )
        .unwrap();
        let applied = t.elapsed();
        assert!(r.ok, "{r:?}");
        wait_running(&system, n);
        let all = t.elapsed();
        // What starting cost: the DNM's CPU over the apply, and each module process's CPU so
        // far: its start-up, and the steps since (at 10 Hz a few ms even for the first started of
        // 200, which ran for the whole apply).
        let dnm_cpu = cpu_seconds(_up.pid()) - dnm_cpu;
        let started = request(&system, &Request::Status).unwrap().dnms.remove(0);
        let module_cpu = started
            .modules
            .iter()
            .filter_map(|m| m.pid.map(cpu_seconds))
            .sum::<f64>()
            / n as f64;
        // Let the CPU meters cover a quiet period.
        std::thread::sleep(Duration::from_secs(3));
        let status = request(&system, &Request::Status).unwrap().dnms.remove(0);
        let t = Instant::now();
        let r = request(
            &system,
            &Request::Apply {
                file: "growth.toml".into(),
                text: pairs_netlist(&system, n, true),
            },
        )
        .unwrap();
        let again = t.elapsed();
        assert!(r.ok, "{r:?}");
        let mem = status.memory.unwrap_or_default();
        let heap_added = match prev_heap {
            Some((m, k)) => format!("{}", (mem.anon_kib.saturating_sub(k)) / (n - m) as u64),
            None => "–".into(),
        };
        prev_heap = Some((n, mem.anon_kib));
        let module_mem: Vec<_> = status.modules.iter().filter_map(|m| m.memory).collect();
        let per = |f: fn(&dnm::proto::Memory) -> u64| {
            module_mem.iter().map(f).sum::<u64>() as f64 / 1024.0 / module_mem.len() as f64
        };
        let modules_cpu: f64 = status.modules.iter().map(|m| m.cpu_percent).sum();
        let ms = |d: Duration| d.as_secs_f64() * 1000.0;
        let mib = |k: u64| k as f64 / 1024.0;
        println!(
            "| {n} | {:.0} | {:.0} | {:.0} / {:.0} | {:.1} | {:.1} / {:.1} / {:.1} | {heap_added} | {:.1} / {:.1} | {:.1} | {:.1} |",
            ms(applied),
            ms(all),
            dnm_cpu * 1000.0,
            module_cpu * 1000.0,
            ms(again),
            mib(mem.anon_kib),
            mib(mem.file_kib),
            mib(mem.shmem_kib),
            per(|m| m.anon_kib),
            per(|m| m.file_kib),
            status.cpu_percent,
            modules_cpu,
        );
        dnm_mem.push((n as f64, mib(mem.anon_kib)));
        in_force.push((n as f64, ms(applied)));
        running.push((n as f64, ms(all)));
        reapply.push((n as f64, ms(again)));
    }
    plotted(plot::log_x(
        "growth-apply",
        "Applying a netlist to one DNM",
        ("modules", "ms"),
        &[
            Series {
                name: "apply in force".into(),
                points: in_force,
            },
            Series {
                name: "all modules running".into(),
                points: running,
            },
            Series {
                name: "re-apply, one rate changed".into(),
                points: reapply,
            },
        ],
        true,
    ));
    plotted(plot::log_x(
        "growth-memory",
        "The DNM's heap",
        ("modules", "MiB"),
        &[Series {
            name: "DNM heap (anonymous memory)".into(),
            points: dnm_mem,
        }],
        false,
    ));
}

// ------------------------------------------------------------------------------------------

fn switch_netlist(system: &str, links: usize) -> String {
    let merges = links.div_ceil(MERGE_INPUTS);
    let mut text = format!(
        "[system]\nname = \"{system}\"\ndefault_task = \"a\"\n\
         [[module]]\nname = \"src_a\"\nkind = \"ticker\"\nrate_hz = 20\nparams = {{ origin = 1 }}\n\
         [[module]]\nname = \"src_b\"\nkind = \"ticker\"\nrate_hz = 20\nparams = {{ origin = 2 }}\n"
    );
    for m in 0..merges {
        text += &format!("[[module]]\nname = \"m{m}\"\nkind = \"merge\"\n");
    }
    let task = |src: &str| {
        (0..links)
            .map(|k| {
                format!(
                    "\"{src}.out -> m{}.in{}\"",
                    k / MERGE_INPUTS,
                    k % MERGE_INPUTS
                )
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    text + &format!(
        "[task.a]\nlinks = [{}]\n[task.b]\nlinks = [{}]\n",
        task("src_a"),
        task("src_b")
    )
}

fn switch() {
    println!(
        "| links changing | modules | DNM switch p50 / p99 (µs) | real rewiring p50 / p99 (µs) | real / DNM at p50 |"
    );
    println!("|---|---|---|---|---|");
    let (mut virt, mut real) = (Vec::new(), Vec::new());
    for links in LINKS {
        let system = unique(&format!("s{links}"));
        let modules = 2 + links.div_ceil(MERGE_INPUTS);
        let _up = up(&system, &switch_netlist(&system, links), &[], None, 1);
        let mut v = Vec::new();
        for i in 0..SWITCHES {
            let task = if i % 2 == 0 { "b" } else { "a" };
            let r = request(&system, &Request::Switch { task: task.into() }).unwrap();
            assert!(r.ok, "{r:?}");
            v.push(r.switches[0].duration_ns);
        }
        // Real rewiring of as many links: each input's subscriber destroyed and created again on
        // live services.
        let r = real_rewiring(links, 20);
        let (v50, v99) = percentiles(v);
        let (r50, r99) = percentiles(r);
        println!(
            "| {links} | {modules} | {v50:.3} / {v99:.3} | {r50:.0} / {r99:.0} | {:.0}x |",
            r50 / v50
        );
        virt.push((links as f64, v50));
        real.push((links as f64, r50));
    }
    plotted(plot::log_x(
        "growth-switch",
        "Changing a task's links (p50)",
        ("links changing", "µs"),
        &[
            Series {
                name: "DNM switch (task word)".into(),
                points: virt,
            },
            Series {
                name: "real rewiring (iceoryx2 subscribers)".into(),
                points: real,
            },
        ],
        true,
    ));
}

// ------------------------------------------------------------------------------------------

fn fanout_netlist(system: &str, readers: usize) -> String {
    let mut text = format!(
        "[system]\nname = \"{system}\"\n\
         [[module]]\nname = \"src\"\nkind = \"ticker\"\nrate_hz = 500\n"
    );
    let mut links = Vec::new();
    for i in 0..readers {
        text += &format!("[[module]]\nname = \"lat{i}\"\nkind = \"latency\"\n");
        links.push(format!("\"src.out -> lat{i}.tick\""));
    }
    text + &format!("[task.run]\nlinks = [{}]\n", links.join(", "))
}

fn fanout() {
    println!(
        "| readers | first reader p50 / p99 (µs) | last reader p50 / p99 (µs) | system CPU, DNM + modules (% of a core) |"
    );
    println!("|---|---|---|---|");
    let (mut first, mut last, mut last99) = (Vec::new(), Vec::new(), Vec::new());
    for readers in READERS {
        let system = unique(&format!("f{readers}"));
        let _up = up(&system, &fanout_netlist(&system, readers), &[], None, 1);
        let a = percentiles(latencies(&system, "local", "lat0", SAMPLES, SKIP));
        let b = percentiles(latencies(
            &system,
            "local",
            &format!("lat{}", readers - 1),
            SAMPLES,
            SKIP,
        ));
        let status = request(&system, &Request::Status).unwrap().dnms.remove(0);
        let cpu = status.cpu_percent + status.modules.iter().map(|m| m.cpu_percent).sum::<f64>();
        println!(
            "| {readers} | {:.1} / {:.1} | {:.1} / {:.1} | {cpu:.0} |",
            a.0, a.1, b.0, b.1
        );
        first.push((readers as f64, a.0));
        last.push((readers as f64, b.0));
        last99.push((readers as f64, b.1));
    }
    plotted(plot::log_x(
        "growth-fanout",
        "One 500 Hz output read by many modules",
        ("readers", "latency (µs)"),
        &[
            Series {
                name: "first reader p50".into(),
                points: first,
            },
            Series {
                name: "last reader p50".into(),
                points: last,
            },
            Series {
                name: "last reader p99".into(),
                points: last99,
            },
        ],
        false,
    ));
}
