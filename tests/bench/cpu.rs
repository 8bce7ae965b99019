//! What Beetle-One's DNM process costs while the rover runs, per thread: `dnm up
//! configs/beetle.toml` (its four DNMs in one process, fifteen modules), with and without
//! recording, [`ROUNDS`] rounds of [`MEASURE`] each after a warm-up, read from
//! `/proc/<pid>/task/*/stat`. With `DNM_BASELINE=/path/to/other/dnm` (another build's `dnm`,
//! its `dnm-module-host` beside it) the same is measured with that build, the builds taking
//! turns in one run, so a change is compared against what it replaces on this machine at the
//! same time. Beside the DNM process, what its fifteen module processes used together.
//!
//! Run: `cargo build --release --workspace`, then `cargo bench -p dnm --bench cpu`.

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use common::{tree_cpu_seconds, unique, up_beetle, use_dnm};
use iceoryx2::prelude::{LogLevel, set_log_level};

const ROUNDS: usize = 3;
const WARM_UP: Duration = Duration::from_secs(10);
const MEASURE: Duration = Duration::from_secs(30);

/// CPU seconds of each thread of `pid`, by thread id: (name, seconds).
fn threads(pid: u32) -> BTreeMap<u32, (String, f64)> {
    // SAFETY: sysconf has no preconditions.
    let tck = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| {
            let tid: u32 = e.file_name().to_str()?.parse().ok()?;
            let stat = std::fs::read_to_string(e.path().join("stat")).ok()?;
            let name = stat[stat.find('(')? + 1..stat.rfind(')')?].to_string();
            let f: Vec<&str> = stat[stat.rfind(')')? + 2..].split_whitespace().collect();
            let ticks: f64 = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
            Some((tid, (name, ticks / tck)))
        })
        .collect()
}

/// What a thread does, from its name (the DNM's name taken off).
fn role(name: &str) -> &'static str {
    const ROLES: [(&str, &str); 13] = [
        ("egress-", "egress (local outputs to Zenoh)"),
        ("tx-", "Zenoh's transmit runtime"),
        ("rx-", "Zenoh's receive runtime"),
        ("app-", "Zenoh runtime"),
        ("acc-", "Zenoh runtime"),
        ("record-in-", "recorder, reading ports"),
        ("record-", "recorder, writing files"),
        ("watch-", "watch (outputs on demand)"),
        ("dnm-", "DNM loops"),
        ("zenoh-", "queries and commands"),
        ("authority", "authority"),
        ("lease-", "leases"),
        ("net-", "Zenoh runtime"),
    ];
    ROLES
        .iter()
        .find(|(p, _)| name.starts_with(p))
        .map_or("other", |(_, r)| r)
}

/// CPU seconds by thread role, the wall time they were used over, and the CPU seconds of the
/// module processes.
type Usage = (BTreeMap<&'static str, f64>, f64, f64);

/// One measurement: CPU seconds by role over [`MEASURE`], the wall time, and what the module
/// processes used meanwhile.
fn measure(recording: bool) -> Usage {
    let system = unique(if recording { "cpur" } else { "cpun" });
    let rec = std::env::temp_dir().join(unique("cpurec"));
    let up_args: Vec<String> = if recording {
        vec!["--record-dir".into(), rec.display().to_string()]
    } else {
        vec!["--no-record".into()]
    };
    let up = up_beetle(&system, &up_args, "cpu");
    std::thread::sleep(WARM_UP);
    let (before, tree0, t0) = (
        threads(up.pid()),
        tree_cpu_seconds(up.pid()),
        Instant::now(),
    );
    std::thread::sleep(MEASURE);
    let (after, tree1, wall) = (
        threads(up.pid()),
        tree_cpu_seconds(up.pid()),
        t0.elapsed().as_secs_f64(),
    );
    drop(up);
    let _ = std::fs::remove_dir_all(&rec);
    let mut by_role = BTreeMap::new();
    for (tid, (name, s)) in &after {
        let was = before.get(tid).map_or(0.0, |(_, b)| *b);
        *by_role.entry(role(name)).or_insert(0.0) += s - was;
    }
    let dnm: f64 = by_role.values().sum();
    (by_role, wall, (tree1 - tree0 - dnm).max(0.0))
}

fn main() {
    set_log_level(LogLevel::Error);
    let mut builds: Vec<(&str, Option<std::path::PathBuf>)> = vec![("this tree", None)];
    if let Some(b) = std::env::var_os("DNM_BASELINE") {
        builds.push(("baseline", Some(b.into())));
    }
    // (build, recording) → CPU seconds by role, wall seconds.
    let mut total: BTreeMap<(usize, bool), Usage> = BTreeMap::new();
    for round in 0..ROUNDS {
        for (b, (label, exe)) in builds.iter().enumerate() {
            use_dnm(exe.clone());
            for recording in [false, true] {
                let (roles, wall, modules) = measure(recording);
                eprintln!(
                    "round {round}, {label}, recording {recording}: {:.2} % of a core, the \
                     modules {:.2} %",
                    roles.values().sum::<f64>() / wall * 100.0,
                    modules / wall * 100.0
                );
                let t = total.entry((b, recording)).or_default();
                for (r, s) in roles {
                    *t.0.entry(r).or_insert(0.0) += s;
                }
                t.1 += wall;
                t.2 += modules;
            }
        }
    }
    println!(
        "# Beetle-One's DNM process (four DNMs, fifteen modules), % of one core by thread role \
         ({ROUNDS} rounds of {} s, builds taking turns)\n",
        MEASURE.as_secs()
    );
    let roles: std::collections::BTreeSet<&str> = total
        .values()
        .flat_map(|(r, _, _)| r.keys().copied())
        .collect();
    let columns: Vec<(usize, bool)> = total.keys().copied().collect();
    let head: Vec<String> = columns
        .iter()
        .map(|(b, rec)| {
            format!(
                "{}, {}",
                builds[*b].0,
                if *rec { "recording" } else { "no recording" }
            )
        })
        .collect();
    println!("| thread role | {} |", head.join(" | "));
    println!("|---|{}", "---|".repeat(columns.len()));
    let pct = |c: &(usize, bool), role: Option<&str>| {
        let (r, wall, _) = &total[c];
        let s: f64 = match role {
            Some(x) => r.get(x).copied().unwrap_or(0.0),
            None => r.values().sum(),
        };
        s / wall * 100.0
    };
    for role in &roles {
        let cells: Vec<String> = columns
            .iter()
            .map(|c| format!("{:.2}", pct(c, Some(role))))
            .collect();
        println!("| {role} | {} |", cells.join(" | "));
    }
    let cells: Vec<String> = columns
        .iter()
        .map(|c| format!("**{:.2}**", pct(c, None)))
        .collect();
    println!("| **the DNM process** | {} |", cells.join(" | "));
    let cells: Vec<String> = columns
        .iter()
        .map(|c| format!("{:.2}", total[c].2 / total[c].1 * 100.0))
        .collect();
    println!("| the module processes, together | {} |", cells.join(" | "));
}
