//! `dnm-monitor` (also `dnm monitor`): watch a running system in Rerun. See the library docs.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Duration;

use anyhow::Context;
use clap::Parser;
use dnm_monitor::{MonitorOptions, run};
use dnm_proto::keys::WatchRate;
use zenoh::Wait;

/// Watch a running system from the ground in a Rerun viewer: the rover's pose, its camera,
/// every numeric field of every port, the live connection graph and a log of events.
#[derive(Parser, Debug)]
#[command(name = "dnm monitor", version)]
struct Cli {
    /// The system (the netlist's `[system] name`).
    #[arg(long, default_value = "beetle")]
    system: String,
    /// Write an .rrd file instead of streaming to a viewer.
    #[arg(long, conflicts_with_all = ["spawn", "viewer"])]
    save: Option<PathBuf>,
    /// Start a viewer (`rerun` on the PATH, e.g. `pip install rerun-sdk==0.36.3`).
    #[arg(long, conflicts_with = "viewer")]
    spawn: bool,
    /// Stream to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy.
    #[arg(long)]
    viewer: Option<String>,
    /// How often numeric outputs are sent: full, 10hz or 1hz.
    #[arg(long, default_value = "10hz", value_parser = parse_rate)]
    rate: WatchRate,
    /// How often camera frames are sent: full, 10hz or 1hz.
    #[arg(long, default_value = "1hz", value_parser = parse_rate)]
    camera_rate: WatchRate,
    /// Seconds between two looks at the wiring and the DNMs' reports.
    #[arg(long, default_value_t = 1.0)]
    status_every: f64,
    /// Stop after this many seconds (default: run until stopped).
    #[arg(long = "for")]
    duration: Option<f64>,
    /// Zenoh JSON5 configuration file (see configs/zenoh/).
    #[arg(long)]
    zenoh_config: Option<PathBuf>,
    /// Zenoh mode (default: client when connecting, else peer).
    #[arg(long)]
    zenoh_mode: Option<String>,
    /// Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable).
    #[arg(long)]
    connect: Vec<String>,
    /// No multicast scouting: use only the endpoints given.
    #[arg(long)]
    no_multicast: bool,
    /// Draw a recorded session read from standard input (what `dnm monitor --session DIR`
    /// writes) instead of a running system; a viewer is started unless --save or --viewer.
    #[arg(long, hide = true)]
    playback: bool,
}

fn parse_rate(s: &str) -> Result<WatchRate, String> {
    WatchRate::parse(s).ok_or_else(|| format!("`{s}`: use full, 10hz or 1hz"))
}

fn seconds(what: &str, s: f64) -> anyhow::Result<Duration> {
    Duration::try_from_secs_f64(s)
        .with_context(|| format!("--{what} {s}: give a number of seconds"))
}

/// Set on SIGINT or SIGTERM: the monitor then finishes its file and exits.
fn stop_on_signal() -> &'static AtomicBool {
    static STOP: AtomicBool = AtomicBool::new(false);
    extern "C" fn on_signal(_: libc::c_int) {
        STOP.store(true, Ordering::Relaxed);
    }
    // SAFETY: the handler only stores into an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
    &STOP
}

fn main() -> ExitCode {
    dnm_router::init_logging("info");
    match main_inner() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {}", dnm_router::error_report(&e));
            ExitCode::FAILURE
        }
    }
}

/// The recording stream the command line asks for.
fn recording(cli: &Cli) -> anyhow::Result<rerun::RecordingStream> {
    let builder = rerun::RecordingStreamBuilder::new("dnm");
    Ok(if let Some(path) = &cli.save {
        // A file is read later: rows batched for two seconds make chunks of many rows each
        // (a tenth of the size of the live default's).
        builder
            .batcher_config(rerun::log::ChunkBatcherConfig {
                flush_tick: Duration::from_secs(2),
                ..rerun::log::ChunkBatcherConfig::DEFAULT
            })
            .save(path)
            .with_context(|| format!("writing {}", path.display()))?
    } else if let Some(url) = &cli.viewer {
        builder
            .connect_grpc_opts(url.clone())
            .with_context(|| format!("connecting to the viewer at {url}"))?
    } else if cli.spawn || cli.playback {
        builder
            .spawn()
            .context("starting a viewer (is `rerun` on the PATH? pip install rerun-sdk==0.36.3)")?
    } else {
        builder
            .connect_grpc()
            .context("connecting to a viewer on the default port (or give --save or --spawn)")?
    })
}

fn main_inner() -> anyhow::Result<()> {
    let cli = Cli::parse();
    let mut options = MonitorOptions::new(&cli.system);
    options.numeric_rate = cli.rate;
    options.camera_rate = cli.camera_rate;
    options.status_every = seconds("status-every", cli.status_every)?;
    options.duration = cli.duration.map(|d| seconds("for", d)).transpose()?;
    if cli.playback {
        let rec = recording(&cli)?;
        let stats = dnm_monitor::play(&mut std::io::stdin().lock(), &rec, &options)?;
        drop(rec);
        eprintln!(
            "monitor: {} samples drawn ({} bytes), {} revisions, {} switches",
            stats.samples, stats.bytes, stats.revisions, stats.switches
        );
        return Ok(());
    }
    let zenoh = dnm_router::ZenohOptions {
        config: cli.zenoh_config.clone(),
        mode: cli
            .zenoh_mode
            .clone()
            .or_else(|| (!cli.connect.is_empty()).then(|| "client".to_string())),
        listen: Vec::new(),
        connect: cli.connect.clone(),
        no_multicast: cli.no_multicast,
    };
    let session = zenoh.open().context("joining Zenoh")?;
    let rec = recording(&cli)?;
    let stats = run(&session, &rec, &options, stop_on_signal())?;
    drop(rec);
    eprintln!(
        "monitor: {} samples ({} bytes) received, {} dropped, {} revisions, {} switches",
        stats.samples, stats.bytes, stats.dropped, stats.revisions, stats.switches
    );
    let _ = session.close().wait();
    Ok(())
}
