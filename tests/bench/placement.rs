//! The paper's Table I on our system: CPU use of each DNM process and the number of messages
//! between DNMs per minute, measured (not predicted) for three placements of the same system —
//! everything on one DNM, plain Newman, weighted Newman — for Beetle-One and for a generated
//! 50-module system. One DNM per process, peers on loopback, as on separate computers.
//!
//! Run: `cargo bench -p dnm --bench placement` (Markdown tables on stdout; ~4 minutes).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::time::{Duration, Instant};

use common::{Up, cpu_seconds, free_port, unique, up};
use dnm::admin::{Request, request};
use dnm_place::{PlaceOptions, Weighting};
use iceoryx2::prelude::{LogLevel, set_log_level};

const WARMUP: Duration = Duration::from_secs(3);
const WINDOW: Duration = Duration::from_secs(20);

/// Messages delivered between DNMs so far (every mirror's count).
fn crossing_messages(system: &str) -> u64 {
    request(system, &Request::Status)
        .unwrap()
        .dnms
        .iter()
        .flat_map(|d| d.routes.mirrored.iter().map(|r| r.messages))
        .sum()
}

struct Measured {
    dnms: usize,
    cpu_total: f64,
    cpu_per_dnm: f64,
    messages_per_minute: f64,
}

/// Runs `text` with one process per DNM that has modules and measures it.
fn measure(system: &str, text: &str, assignment: &BTreeMap<String, String>) -> Measured {
    let used: BTreeSet<&String> = assignment.values().collect();
    let mut procs: Vec<Up> = Vec::new();
    let mut ports: Vec<u16> = Vec::new();
    for (i, dnm) in used.iter().enumerate() {
        let port = free_port();
        let mut args = vec![
            "--no-multicast".to_string(),
            "--listen".into(),
            format!("tcp/127.0.0.1:{port}"),
        ];
        for p in &ports {
            args.push("--connect".into());
            args.push(format!("tcp/127.0.0.1:{p}"));
        }
        ports.push(port);
        procs.push(up(system, text, &args, Some(dnm), i + 1));
    }
    std::thread::sleep(WARMUP);
    let cpu0: Vec<f64> = procs.iter().map(|p| cpu_seconds(p.pid())).collect();
    let msgs0 = crossing_messages(system);
    let t0 = Instant::now();
    std::thread::sleep(WINDOW);
    let cpu1: Vec<f64> = procs.iter().map(|p| cpu_seconds(p.pid())).collect();
    let msgs1 = crossing_messages(system);
    let dt = t0.elapsed().as_secs_f64();
    let cpu: Vec<f64> = cpu0
        .iter()
        .zip(&cpu1)
        .map(|(a, b)| (b - a) / dt * 100.0)
        .collect();
    let total: f64 = cpu.iter().sum();
    Measured {
        dnms: procs.len(),
        cpu_total: total,
        cpu_per_dnm: total / procs.len() as f64,
        messages_per_minute: (msgs1 - msgs0) as f64 / dt * 60.0,
    }
}

/// Table I for one system.
fn table(title: &str, file: &Path, text: &str, system: &str) {
    let netlist = dnm::parse_netlist(file, text).unwrap();
    let options = |weighting| PlaceOptions {
        weighting,
        ignore_pins: true,
        ..PlaceOptions::default()
    };
    let single = dnm_place::single_dnm(&netlist);
    let plain = dnm_place::place(&netlist, &options(Weighting::Plain)).unwrap();
    let weighted = dnm_place::place(&netlist, &options(Weighting::Weighted)).unwrap();
    println!("## {title}\n");
    println!(
        "| placement | DNMs | CPU all DNMs (%) | CPU per DNM (%) | messages between DNMs per minute (measured) | predicted | modularity weighted / plain |"
    );
    println!("|---|---|---|---|---|---|---|");
    for (i, (name, assignment, new_dnms)) in [
        ("single DNM", &single, &Vec::new()),
        ("Newman (plain)", &plain.assignment, &plain.new_dnms),
        ("weighted Newman", &weighted.assignment, &weighted.new_dnms),
    ]
    .into_iter()
    .enumerate()
    {
        let placed = dnm::placed_text(text, assignment, new_dnms, true).unwrap();
        let run_system = format!("{system}{i}");
        let placed = placed.replace(
            &format!("name = \"{system}\""),
            &format!("name = \"{run_system}\""),
        );
        let m = measure(&run_system, &placed, assignment);
        let predicted = dnm_place::predict(&netlist, assignment);
        println!(
            "| {name} | {} | {:.1} | {:.1} | {:.0} | {:.0} | {:.3} / {:.3} |",
            m.dnms,
            m.cpu_total,
            m.cpu_per_dnm,
            m.messages_per_minute,
            predicted.messages_per_minute,
            dnm_place::modularity_of(&netlist, assignment, Weighting::Weighted),
            dnm_place::modularity_of(&netlist, assignment, Weighting::Plain),
        );
    }
    println!();
}

/// 50 modules in 10 groups of 5: tick chains (small messages, 20–100 Hz) closed by a `pair`
/// that also reads another chain's source, and blob fans (1–64 KiB at 20 Hz to 4 sinks).
fn generated(system: &str) -> String {
    let mut t = format!("[system]\nname = \"{system}\"\n\n");
    for d in 1..=8 {
        t += &format!("[[dnm]]\nname = \"d{d}\"\n");
        if d > 1 {
            t += "parent = \"d1\"\n";
        }
    }
    let mut links = Vec::new();
    let tick_rates = [20, 50, 50, 100, 20];
    let blob_sizes = [4096, 16384, 65536, 1024, 8192];
    for g in 0..10 {
        if g % 2 == 0 {
            let rate = tick_rates[g / 2];
            t += &format!(
                "[[module]]\nname = \"src{g}\"\nkind = \"ticker\"\nrate_hz = {rate}\nparams = {{ origin = {g} }}\n"
            );
            let mut prev = format!("src{g}");
            for r in ["a", "b", "c"] {
                t += &format!("[[module]]\nname = \"r{g}{r}\"\nkind = \"relay\"\n");
                links.push(format!("\"{prev}.out -> r{g}{r}.in\""));
                prev = format!("r{g}{r}");
            }
            t += &format!("[[module]]\nname = \"p{g}\"\nkind = \"pair\"\n");
            links.push(format!("\"{prev}.out -> p{g}.a\""));
            links.push(format!("\"src{}.out -> p{g}.b\"", (g + 2) % 10));
        } else {
            let bytes = blob_sizes[g / 2];
            t += &format!(
                "[[module]]\nname = \"b{g}\"\nkind = \"blob_source\"\nrate_hz = 20\nparams = {{ bytes = {bytes} }}\n"
            );
            for s in ["a", "b", "c", "d"] {
                t += &format!("[[module]]\nname = \"l{g}{s}\"\nkind = \"latency\"\n");
                links.push(format!("\"b{g}.out -> l{g}{s}.in\""));
            }
        }
    }
    t += &format!("\n[task.run]\nlinks = [{}]\n", links.join(", "));
    t
}

fn main() {
    set_log_level(LogLevel::Error);
    println!(
        "# Table I on our system ({} s measured after {} s warm-up; one DNM per process; pins ignored)\n",
        WINDOW.as_secs(),
        WARMUP.as_secs()
    );
    let beetle_system = unique("t1b");
    let beetle = include_str!("../../configs/beetle.toml")
        .replace("name = \"beetle\"", &format!("name = \"{beetle_system}\""));
    table(
        "Beetle-One (15 modules)",
        Path::new("configs/beetle.toml"),
        &beetle,
        &beetle_system,
    );
    let gen_system = unique("t1g");
    table(
        "Generated system (50 modules)",
        Path::new("generated.toml"),
        &generated(&gen_system),
        &gen_system,
    );
}
