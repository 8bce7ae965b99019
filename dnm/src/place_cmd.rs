//! `dnm place`: cluster a netlist's modules onto DNMs and report what each placement costs.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

use anyhow::Context;
use dnm_netlist::Netlist;
use dnm_place::{PlaceOptions, Placement, Prediction, Weighting};
use serde::Serialize;

#[derive(clap::Args, Debug, Clone)]
pub struct PlaceArgs {
    pub netlist: PathBuf,
    /// Every link weighs 1 (default: weighted by bytes × rate).
    #[arg(long, conflicts_with = "weighted")]
    pub plain: bool,
    /// Weight links by bytes per message × messages per second (the default).
    #[arg(long)]
    pub weighted: bool,
    /// Improve the greedy result by moving single modules (never lowers modularity).
    #[arg(long)]
    pub refine: bool,
    /// Most modules on one DNM.
    #[arg(long)]
    pub capacity: Option<usize>,
    /// Most DNMs to use.
    #[arg(long)]
    pub max_dnms: Option<usize>,
    /// Move pinned modules too (what-if studies; the paper's placements had no pins).
    #[arg(long)]
    pub ignore_pins: bool,
    /// Weigh links by the traffic measured in this recording (a DNM's MCAP file); ports it
    /// lacks keep the netlist's prediction.
    #[arg(long)]
    pub from_recording: Option<PathBuf>,
    /// Write the placed netlist (modules' `dnm` fields set) to this file.
    #[arg(long)]
    pub write: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
}

impl PlaceArgs {
    fn weighting(&self) -> Weighting {
        if self.plain {
            Weighting::Plain
        } else {
            Weighting::Weighted
        }
    }
}

/// One row of the comparison table.
#[derive(Debug, Serialize)]
struct Row {
    placement: String,
    predicted: Prediction,
    weighted_modularity: f64,
    plain_modularity: f64,
}

fn row(
    netlist: &Netlist,
    measured: Option<&dnm_place::Measured>,
    name: &str,
    assignment: &BTreeMap<String, String>,
) -> Row {
    Row {
        placement: name.into(),
        predicted: dnm_place::predict_with(netlist, assignment, measured),
        weighted_modularity: dnm_place::modularity_of(netlist, assignment, Weighting::Weighted),
        plain_modularity: dnm_place::modularity_of(netlist, assignment, Weighting::Plain),
    }
}

/// Bytes per message and rate of every recorded port, from a recording's channels.
/// Bytes and rate per output, measured in a recording: one file, or every file of a session
/// folder (counts summed, rates over the time each file covers).
fn measured(path: &Path) -> anyhow::Result<dnm_place::Measured> {
    // (module, port) -> (messages, bytes, seconds)
    let mut sums: BTreeMap<(String, String), (u64, u64, f64)> = BTreeMap::new();
    for file in crate::recording_files(path)? {
        let bytes = std::fs::read(&file).with_context(|| format!("reading {}", file.display()))?;
        let stats = match dnm::stats::stats(&bytes, &dnm::parse_recorded_netlist) {
            Ok(s) => s,
            Err(e) if path.is_dir() => {
                eprintln!("{}: not a readable recording, skipped: {e}", file.display());
                continue;
            }
            Err(e) => anyhow::bail!("{}: not a readable recording: {e}", file.display()),
        };
        for c in stats.channels {
            let mut parts = c.topic.trim_start_matches('/').splitn(3, '/');
            if let (Some(_dnm), Some(module), Some(port)) =
                (parts.next(), parts.next(), parts.next())
                && c.messages > 0
            {
                let e = sums
                    .entry((module.to_string(), port.to_string()))
                    .or_default();
                e.0 += c.messages;
                e.1 += c.bytes;
                // A channel with one message has no rate: its size still counts.
                if c.rate_hz > 0.0 {
                    e.2 += c.messages as f64 / c.rate_hz;
                }
            }
        }
    }
    let mut out = dnm_place::Measured::new();
    for (key, (messages, bytes, seconds)) in sums {
        let rate = if seconds > 0.0 {
            messages as f64 / seconds
        } else {
            0.0
        };
        out.insert(key, (bytes as f64 / messages as f64, rate));
    }
    if out.is_empty() {
        anyhow::bail!("{}: the recording has no port data", path.display());
    }
    Ok(out)
}

pub fn run(args: &PlaceArgs) -> anyhow::Result<ExitCode> {
    let netlist = dnm::load_netlist(&args.netlist).map_err(|e| anyhow::anyhow!("{e}"))?;
    let options = PlaceOptions {
        weighting: args.weighting(),
        refine: args.refine,
        capacity: args.capacity,
        max_dnms: args.max_dnms,
        ignore_pins: args.ignore_pins,
        measured: match &args.from_recording {
            Some(f) => Some(measured(f)?),
            None => None,
        },
    };
    let m = options.measured.as_ref();
    let placement = dnm_place::place(&netlist, &options)
        .with_context(|| format!("placing {}", args.netlist.display()))?;
    let as_written: BTreeMap<String, String> = netlist
        .modules
        .iter()
        .map(|m| (m.name.clone(), m.dnm.clone()))
        .collect();
    let other = |w| {
        dnm_place::place(
            &netlist,
            &PlaceOptions {
                weighting: w,
                ..options.clone()
            },
        )
    };
    let plain = other(Weighting::Plain)?;
    let weighted = other(Weighting::Weighted)?;
    let rows = vec![
        row(&netlist, m, "as written", &as_written),
        row(&netlist, m, "single DNM", &dnm_place::single_dnm(&netlist)),
        row(&netlist, m, "plain Newman", &plain.assignment),
        row(&netlist, m, "weighted Newman", &weighted.assignment),
    ];
    if let Some(out) = &args.write {
        let text = std::fs::read_to_string(&args.netlist)
            .with_context(|| format!("reading {}", args.netlist.display()))?;
        let placed = dnm::placed_text(&text, &placement.assignment, &placement.new_dnms, false)
            .map_err(anyhow::Error::msg)?;
        // The result must be a valid netlist before it is written.
        dnm::parse_netlist(out, &placed).map_err(|e| anyhow::anyhow!("placed netlist: {e}"))?;
        std::fs::write(out, placed).with_context(|| format!("writing {}", out.display()))?;
    }
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "placement": placement,
                "comparison": rows,
                "written": args.write,
            }))?
        );
        return Ok(ExitCode::SUCCESS);
    }
    print_human(&args.netlist, &placement, &rows, args.write.as_deref());
    Ok(ExitCode::SUCCESS)
}

fn print_human(file: &Path, p: &Placement, rows: &[Row], written: Option<&Path>) {
    println!(
        "{}: {} Newman{}: modularity {:.3} ({} graph), {:.3} on the plain graph",
        file.display(),
        match p.weighting {
            Weighting::Plain => "plain",
            Weighting::Weighted => "weighted",
        },
        if p.refined { " + refinement" } else { "" },
        p.modularity,
        match p.weighting {
            Weighting::Plain => "plain",
            Weighting::Weighted => "weighted",
        },
        p.plain_modularity
    );
    for (dnm, modules) in &p.clusters {
        let new = if p.new_dnms.iter().any(|(n, _)| n == dnm) {
            " (new)"
        } else {
            ""
        };
        println!("  DNM {dnm}{new}: {}", modules.join(", "));
    }
    println!("\n  predicted traffic between DNMs:");
    println!(
        "  {:<16} {:>5} {:>14} {:>12} {:>20}",
        "placement", "DNMs", "messages/min", "bytes/s", "modularity w / plain"
    );
    for r in rows {
        println!(
            "  {:<16} {:>5} {:>14.0} {:>12.0} {:>12.3} / {:.3}",
            r.placement,
            r.predicted.dnms_used,
            r.predicted.messages_per_minute,
            r.predicted.bytes_per_second,
            r.weighted_modularity,
            r.plain_modularity
        );
    }
    if let Some(out) = written {
        println!("\n  placed netlist written to {}", out.display());
    }
}
