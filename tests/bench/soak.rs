//! Beetle-One left running, to see whether anything grows: two copies side by side on this
//! machine, one recording every port (its files rotating every 10 minutes), one not, for an
//! hour (`DNM_SOAK_MINUTES`). Every minute each `dnm up` process is read from `/proc`: its
//! memory (private, files, shared), open descriptors and threads, its modules' private memory,
//! and the shared-memory files of its system.
//!
//! Growth is judged on the DNM process's private memory after a warm-up (the first
//! [`WARM_UP_MIN`] minutes): a least-squares line through the minute samples, its slope with a
//! 95 % interval; and, with recording, file by file: the lowest and highest memory between
//! two rotations, and how the lowest moved from the file before (what the allocator keeps
//! after the closed files' buffers were given back: a bound shows as these steps falling to
//! the noise). The tables go to stdout, the curve to `docs/bench/soak-memory.png`.
//!
//! Run: `cargo build --release --workspace`, then `cargo bench -p dnm --bench soak`
//! (`DNM_SOAK_MINUTES=10` for a shorter run, `DNM_SOAK_ROTATE=2m` for files every two minutes).

#![allow(clippy::unwrap_used, clippy::expect_used)] // a benchmark harness: failing loudly is right

mod common;
mod plot;

use std::time::{Duration, Instant};

use common::{Up, unique, up_beetle};
use dnm_core::procfs::memory;
use iceoryx2::prelude::{LogLevel, set_log_level};
use plot::Series;

const WARM_UP_MIN: usize = 10;
const EVERY: Duration = Duration::from_secs(60);

/// One reading of a `dnm up` process.
#[derive(Clone, Copy, Default)]
struct Reading {
    anon_kib: u64,
    file_kib: u64,
    shmem_kib: u64,
    fds: usize,
    threads: usize,
    modules_anon_kib: u64,
    shm_files: usize,
}

fn count(dir: String) -> usize {
    std::fs::read_dir(dir).map_or(0, |d| d.count())
}

fn read(pid: u32, system: &str) -> Reading {
    let m = memory(pid).unwrap_or_default();
    let children: Vec<u32> = std::fs::read_dir("/proc")
        .into_iter()
        .flatten()
        .flatten()
        .filter_map(|e| e.file_name().to_str()?.parse::<u32>().ok())
        .filter(|p| {
            let stat = std::fs::read_to_string(format!("/proc/{p}/stat")).unwrap_or_default();
            stat.rsplit_once(')')
                .and_then(|(_, r)| r.split_whitespace().nth(1))
                .and_then(|pp| pp.parse::<u32>().ok())
                == Some(pid)
        })
        .collect();
    let prefix = format!("dnm_{system}_");
    Reading {
        anon_kib: m.anon_kib,
        file_kib: m.file_kib,
        shmem_kib: m.shmem_kib,
        fds: count(format!("/proc/{pid}/fd")),
        threads: count(format!("/proc/{pid}/task")),
        modules_anon_kib: children
            .iter()
            .filter_map(|&c| memory(c))
            .map(|m| m.anon_kib)
            .sum(),
        shm_files: std::fs::read_dir("/dev/shm")
            .into_iter()
            .flatten()
            .flatten()
            .filter(|e| e.file_name().to_string_lossy().starts_with(&prefix))
            .count(),
    }
}

/// Slope (per minute) of a least-squares line through `(x, y)`, and its 95 % half-interval.
fn slope(points: &[(f64, f64)]) -> (f64, f64) {
    let n = points.len() as f64;
    if n < 3.0 {
        return (0.0, f64::NAN);
    }
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = points.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = points.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let b = sxy / sxx;
    let a = my - b * mx;
    let sse: f64 = points.iter().map(|p| (p.1 - a - b * p.0).powi(2)).sum();
    let se = (sse / (n - 2.0) / sxx).sqrt();
    (b, 1.96 * se)
}

/// The recording's file rotation, as `dnm up --record-rotate` takes it (`DNM_SOAK_ROTATE`).
fn rotate() -> String {
    std::env::var("DNM_SOAK_ROTATE").unwrap_or_else(|_| "10m".into())
}

/// [`rotate`] in whole minutes, when it is some.
fn rotate_minutes() -> Option<usize> {
    let r = rotate();
    let n: usize = r
        .trim_end_matches(|c: char| c.is_ascii_alphabetic())
        .parse()
        .ok()?;
    match r.trim_start_matches(|c: char| c.is_ascii_digit()) {
        "m" | "min" => Some(n),
        "h" => Some(n * 60),
        _ => None,
    }
    .filter(|&m| m > 2)
}

/// Per file of the recording after the warm-up (the minutes strictly between two rotations,
/// the samples at a rotation left out: the manifest's thread has just given pages back then):
/// the lowest and the highest private memory of the recording DNM, KiB.
fn per_file(readings: &[[Reading; 2]], every: usize) -> Vec<(usize, u64, u64)> {
    (WARM_UP_MIN.div_ceil(every)..)
        .map(|k| (k * every, (k * every + 1)..((k + 1) * every)))
        .take_while(|(_, minutes)| minutes.end < readings.len())
        .map(|(start, minutes)| {
            let kib: Vec<u64> = minutes.map(|m| readings[m][0].anon_kib).collect();
            let low = kib.iter().copied().min().unwrap_or(0);
            let high = kib.iter().copied().max().unwrap_or(0);
            (start, low, high)
        })
        .collect()
}

fn start(system: &str, record: Option<&std::path::Path>) -> Up {
    let up_args: Vec<String> = match record {
        Some(d) => vec![
            "--record-dir".into(),
            d.display().to_string(),
            "--record-rotate".into(),
            rotate(),
        ],
        None => vec!["--no-record".into()],
    };
    up_beetle(system, &up_args, "soak")
}

fn main() {
    set_log_level(LogLevel::Error);
    let minutes: usize = std::env::var("DNM_SOAK_MINUTES")
        .ok()
        .and_then(|m| m.parse().ok())
        .unwrap_or(60);
    let rec_dir = std::env::temp_dir().join(unique("soakrec"));
    let (rec_sys, bare_sys) = (unique("soakr"), unique("soakn"));
    let recording = start(&rec_sys, Some(&rec_dir));
    let bare = start(&bare_sys, None);
    let runs = [
        ("recording", &recording, &rec_sys),
        ("no recording", &bare, &bare_sys),
    ];
    let began = Instant::now();
    let mut readings: Vec<[Reading; 2]> = Vec::new();
    for minute in 0..=minutes {
        let next = began + EVERY * minute as u32;
        std::thread::sleep(next.saturating_duration_since(Instant::now()));
        let r = runs.map(|(_, up, sys)| read(up.pid(), sys));
        eprintln!(
            "minute {minute}: recording {} KiB, {} fds; no recording {} KiB, {} fds",
            r[0].anon_kib, r[0].fds, r[1].anon_kib, r[1].fds
        );
        readings.push(r);
    }
    let labels = runs.map(|(l, _, _)| l);
    // Stopped first: the recording finishes its files.
    drop(recording);
    drop(bare);
    let files = walk(&rec_dir);
    report(&labels, &readings, files);
    let _ = std::fs::remove_dir_all(&rec_dir);
}

/// MCAP files under `dir`.
fn walk(dir: &std::path::Path) -> usize {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| {
            let p = e.path();
            if p.is_dir() {
                walk(&p)
            } else {
                usize::from(p.extension().is_some_and(|x| x == "mcap"))
            }
        })
        .sum()
}

fn report(labels: &[&str; 2], readings: &[[Reading; 2]], files: usize) {
    let minutes = readings.len() - 1;
    println!(
        "# Beetle-One for {minutes} minutes, recording (files every {}) and not, side by side\n",
        rotate()
    );
    println!(
        "| minute | run | DNM private (KiB) | files / shared (KiB) | fds | threads | modules private (KiB) | shm files |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for (m, r) in readings.iter().enumerate() {
        if m % 5 != 0 && m != minutes {
            continue;
        }
        for (l, x) in labels.iter().zip(r) {
            println!(
                "| {m} | {l} | {} | {} / {} | {} | {} | {} | {} |",
                x.anon_kib,
                x.file_kib,
                x.shmem_kib,
                x.fds,
                x.threads,
                x.modules_anon_kib,
                x.shm_files
            );
        }
    }
    println!("\nThe recording wrote {files} MCAP files.\n");
    println!(
        "After the first {WARM_UP_MIN} minutes, a least-squares line through the minute samples \
         (slope ± its 95 % interval, KiB per hour):\n"
    );
    let mut series = Vec::new();
    for (i, l) in labels.iter().enumerate() {
        let points = |f: fn(&Reading) -> u64| -> Vec<(f64, f64)> {
            readings
                .iter()
                .enumerate()
                .skip(WARM_UP_MIN)
                .map(|(m, r)| (m as f64, f(&r[i]) as f64))
                .collect()
        };
        let (dnm, dnm_ci) = slope(&points(|r| r.anon_kib));
        let (mods, mods_ci) = slope(&points(|r| r.modules_anon_kib));
        println!(
            "- {l}: the DNM {:+.0} ± {:.0} KiB/h, its modules {:+.0} ± {:.0} KiB/h",
            dnm * 60.0,
            dnm_ci * 60.0,
            mods * 60.0,
            mods_ci * 60.0
        );
        series.push(Series {
            name: format!("DNM process, {l}"),
            points: readings
                .iter()
                .enumerate()
                .map(|(m, r)| (m as f64, r[i].anon_kib as f64 / 1024.0))
                .collect(),
        });
    }
    if let Some(every) = rotate_minutes() {
        println!(
            "\nThe recording DNM per file after the warm-up, between its rotations (KiB; step: \
             the lowest against the file before's lowest):\n"
        );
        println!("| file from minute | lowest | highest | step of the lowest |");
        println!("|---|---|---|---|");
        let files = per_file(readings, every);
        for (i, (start, low, high)) in files.iter().enumerate() {
            let step = i.checked_sub(1).map_or_else(String::new, |j| {
                format!("{:+}", *low as i64 - files[j].1 as i64)
            });
            println!("| {start} | {low} | {high} | {step} |");
        }
    }
    match plot::linear(
        "soak-memory",
        "Beetle-One: the DNM process's private memory",
        ("minutes", "MiB"),
        &series,
    ) {
        Ok(p) => println!("\n![soak]({})", p.display()),
        Err(e) => eprintln!("no plot: {e}"),
    }
}
