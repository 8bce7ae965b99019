//! `dnm`: check netlists, run a machine's DNMs, and operate the running system.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::{Parser, Subcommand};

mod certs;
mod demo;
mod exec_check;
mod ground_cmd;
mod linksim;
mod monitor_cmd;
mod place_cmd;
mod session_view;
mod watch_cmd;
use dnm::admin::{Request, Response, request};
use dnm::{DnmReport, HostOptions};

#[derive(Parser, Debug)]
#[command(
    name = "dnm",
    version,
    about = "Database node modules: host modules in shared memory, switch tasks by references"
)]
struct Cli {
    #[command(flatten)]
    zenoh: ZenohArgs,
    #[command(subcommand)]
    command: Cmd,
}

/// How to reach Zenoh. `up` always joins Zenoh (peer mode by default); the operating commands
/// (`status`, `switch`, `apply`, `module`) go over Zenoh when `--connect` or `--zenoh-config` is
/// given, else to the system's processes on this machine.
#[derive(clap::Args, Debug)]
struct ZenohArgs {
    /// Zenoh JSON5 configuration file (see configs/zenoh/).
    #[arg(long, global = true)]
    zenoh_config: Option<PathBuf>,
    /// Zenoh mode: peer, client or router.
    #[arg(long, global = true)]
    zenoh_mode: Option<String>,
    /// Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable).
    #[arg(long, global = true)]
    listen: Vec<String>,
    /// Zenoh endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable).
    #[arg(long, global = true)]
    connect: Vec<String>,
    /// No multicast scouting: use only the endpoints given.
    #[arg(long, global = true)]
    no_multicast: bool,
}

impl ZenohArgs {
    fn options(&self) -> dnm::ZenohOptions {
        dnm::ZenohOptions {
            config: self.zenoh_config.clone(),
            mode: self.zenoh_mode.clone(),
            listen: self.listen.clone(),
            connect: self.connect.clone(),
            no_multicast: self.no_multicast,
        }
    }

    fn remote(&self) -> bool {
        self.zenoh_config.is_some() || !self.connect.is_empty()
    }
}

/// Recording of every port to MCAP (on by default).
#[derive(clap::Args, Debug)]
struct RecordArgs {
    /// Do not record.
    #[arg(long)]
    no_record: bool,
    /// Folder of the recordings (default: $DNM_RECORD_DIR, else `recordings`).
    #[arg(long)]
    record_dir: Option<PathBuf>,
    /// Record only this module or `module/port` (repeatable; default: every output).
    #[arg(long)]
    record_only: Vec<String>,
    /// How much of each output the netlist's downlink plan names is kept for the ground to
    /// recover from memory at once (e.g. `10s`); longer gaps are filled from the recording,
    /// within the station's downlink budget.
    #[arg(long, default_value = "10s")]
    downlink_cache: String,
    /// Start a new file of each recording after this long (e.g. `10m`); a file also ends at
    /// 1 GiB.
    #[arg(long, default_value = "1h")]
    record_rotate: String,
}

impl Cmd {
    /// Whether the command runs DNMs that record.
    fn records(&self) -> bool {
        match self {
            Cmd::Up { record, .. } | Cmd::Demo { record, .. } => !record.no_record,
            _ => false,
        }
    }
}

impl RecordArgs {
    fn downlink_cache(&self) -> anyhow::Result<std::time::Duration> {
        let ms = dnm_netlist::parse_duration_ms(&self.downlink_cache).with_context(|| {
            format!(
                "--downlink-cache `{}`: write a duration, e.g. `10s`",
                self.downlink_cache
            )
        })?;
        Ok(std::time::Duration::from_millis(ms.max(1000)))
    }

    fn options(&self) -> anyhow::Result<Option<dnm::record::RecordOptions>> {
        if self.no_record {
            return Ok(None);
        }
        let rotate_ms = dnm_netlist::parse_duration_ms(&self.record_rotate).with_context(|| {
            format!(
                "--record-rotate `{}`: write a duration, e.g. `10m`",
                self.record_rotate
            )
        })?;
        let dir = self.record_dir.clone().unwrap_or_else(|| {
            std::env::var_os("DNM_RECORD_DIR")
                .map(PathBuf::from)
                .unwrap_or_else(|| PathBuf::from("recordings"))
        });
        let mut o = dnm::record::RecordOptions::timestamped(&dir);
        o.only = self.record_only.clone();
        o.rotate_after = std::time::Duration::from_millis(rotate_ms.max(1000));
        Ok(Some(o))
    }
}

/// Sends a request to the running system: over Zenoh if asked to, else on this machine.
fn send(z: &ZenohArgs, system: &str, req: &Request) -> anyhow::Result<Response> {
    if !z.remote() {
        return Ok(request(system, req)?);
    }
    use zenoh::Wait;
    let mut options = z.options();
    if options.mode.is_none() && options.config.is_none() {
        options.mode = Some("client".into());
    }
    let session = options.open()?;
    let r = dnm::remote::request(&session, system, req, Duration::from_secs(5))
        .map_err(anyhow::Error::msg)?;
    let _ = session.close().wait();
    Ok(r)
}

#[derive(Subcommand, Debug)]
enum Cmd {
    /// Validate a netlist and print a summary; exits non-zero listing every error.
    Check {
        netlist: PathBuf,
        /// Also check these onboard sequences against the netlist.
        #[arg(long = "sequence")]
        sequences: Vec<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Start this machine's DNMs and their modules; run until Ctrl-C.
    Up {
        netlist: PathBuf,
        /// DNMs to run here (default: every DNM of the netlist).
        #[arg(long = "dnm")]
        dnms: Vec<String>,
        #[command(flatten)]
        record: RecordArgs,
        /// Where durable state lives, e.g. the authority's database (default: $DNM_STATE_DIR,
        /// else ~/.local/state/dnm).
        #[arg(long)]
        state_dir: Option<PathBuf>,
    },
    /// Report the running system's DNMs and modules.
    Status {
        #[arg(long)]
        system: String,
        #[arg(long)]
        json: bool,
    },
    /// Switch the running system to another task.
    Switch {
        #[arg(long)]
        system: String,
        task: String,
        #[arg(long)]
        json: bool,
    },
    /// Apply a new netlist to the running system (refused with the errors if invalid).
    Apply {
        #[arg(long)]
        system: String,
        netlist: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Add, remove or replace a module of the running system.
    Module {
        #[command(subcommand)]
        op: ModuleOp,
    },
    /// Watch a running system in Rerun: pose, camera, time series, the live connection graph
    /// and events (runs `dnm-monitor`; `dnm monitor --help` lists its options). With
    /// `--session DIR` (a recorded session folder or MCAP file), draw that session instead, at
    /// its recorded times, into a viewer or `--save FILE.rrd`.
    #[command(disable_help_flag = true)]
    Monitor {
        #[arg(trailing_var_arg = true, allow_hyphen_values = true)]
        args: Vec<String>,
    },
    /// Run the simulated Beetle-One rover on this machine and drive a scripted mission:
    /// joystick, autopilot to waypoints, a module replaced live, joystick again; then a summary.
    Demo {
        /// Netlist to run (default: configs/beetle.toml, or the built-in copy).
        #[arg(long)]
        netlist: Option<PathBuf>,
        /// The sequence the rover carries out on board after the joystick driving (default:
        /// configs/sequences/explore.toml, built in).
        #[arg(long)]
        sequence: Option<PathBuf>,
        /// Keep the system running after the mission, until Ctrl-C.
        #[arg(long)]
        keep_running: bool,
        /// Seconds of joystick driving before and after the sequence.
        #[arg(long, default_value_t = 8.0)]
        teleop_seconds: f64,
        /// Print only the summary, as JSON.
        #[arg(long)]
        json: bool,
        /// Watch the mission in a Rerun viewer (started from the PATH), or, when none can be
        /// started, save it to recordings/demo-<time>.rrd.
        #[arg(long)]
        rerun: bool,
        /// Save the Rerun stream to this .rrd file instead of starting a viewer.
        #[arg(long)]
        rerun_save: Option<PathBuf>,
        /// Serve the ground station's web interface on this address while the demo runs
        /// (`--web 127.0.0.1:7480`; with `--keep-running`, until Ctrl-C).
        #[arg(long)]
        web: Option<std::net::SocketAddr>,
        #[command(flatten)]
        record: RecordArgs,
    },
    /// Place modules on DNMs by clustering the module graph (Newman's greedy modularity,
    /// weighted by traffic), and compare the predicted traffic between DNMs.
    Place(place_cmd::PlaceArgs),
    /// Analyse a recording: per channel count, rate, gaps, bytes; task switches; latency
    /// through linked modules; optionally export channels to CSV. FILE is an MCAP file or a
    /// session folder (each of its files in turn).
    Stats {
        file: PathBuf,
        /// Export this channel (topic) to CSV (repeatable).
        #[arg(long)]
        csv: Vec<String>,
        /// Folder for the CSV files.
        #[arg(long, default_value = ".")]
        out: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// List the recording sessions under a folder (default: $DNM_RECORD_DIR, else
    /// `recordings`), or show one session's manifest (its files, DNMs, revisions, time range,
    /// message counts), written again from its files.
    Recordings {
        dir: Option<PathBuf>,
        /// Write the session's manifest again from its files (when they are all closed).
        #[arg(long)]
        write: bool,
        #[arg(long)]
        json: bool,
    },
    /// Replay a recording (a session folder, or one file) into the ports of a system running
    /// on this machine: every DNM's channels in time order, camera frames included.
    Replay {
        file: PathBuf,
        /// System to replay into (default: the recorded one).
        #[arg(long)]
        system: Option<String>,
        /// Replay only this channel (topic, repeatable; default: all).
        #[arg(long)]
        only: Vec<String>,
        /// Speed factor against the recorded timing (default 1.0).
        #[arg(long, default_value_t = 1.0, conflicts_with = "fast")]
        rate: f64,
        /// As fast as consumers keep up, ignoring the recorded timing.
        #[arg(long, conflicts_with = "step")]
        fast: bool,
        /// One message per Enter on standard input.
        #[arg(long)]
        step: bool,
        /// Instead of replaying into a system: run this module's code here on its recorded
        /// inputs and compare what it writes with what it wrote (exit 1 at a divergence).
        #[arg(long, value_name = "MODULE")]
        check: Option<String>,
        /// With --check: run the module with this parameter changed (NAME=VALUE, repeatable).
        #[arg(long, value_name = "NAME=VALUE", requires = "check")]
        set: Vec<String>,
        /// With --check: numbers equal within this relative tolerance (0: bit for bit).
        #[arg(long, default_value_t = 1e-4, requires = "check")]
        tolerance: f64,
        /// With --check: the executables of the recording's kinds this build does not hold
        /// (modules of another language, e.g. Python files; repeatable, one per such kind):
        /// the checked module's steps here, the others only say what kind they are. A
        /// recording alone never runs a program.
        #[arg(long, value_name = "FILE", requires = "check")]
        exec: Vec<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Run a Zenoh router (joins the rover's and the ground's networks), until Ctrl-C.
    Router,
    /// The ground station: run it, and command the rover through it.
    Ground {
        #[command(subcommand)]
        cmd: ground_cmd::GroundCmd,
    },
    /// The system's certificate authority, its identities' certificates, and Zenoh
    /// configurations with mutual TLS and access control generated from the netlist.
    Certs {
        #[command(subcommand)]
        cmd: certs::CertsCmd,
    },
    /// Emulate a radio link between two endpoints (delay, bandwidth, loss, outages), no root
    /// needed.
    Linksim(linksim::LinkArgs),
    /// Print an output's values as they come, decoded by its message type (over Zenoh; the
    /// DNM publishes it only while someone watches).
    Watch(watch_cmd::WatchArgs),
    /// List the standard module kinds.
    Kinds {
        /// Also the kinds this netlist declares (`[kind.NAME] exec = ...`, in any language).
        #[arg(long)]
        netlist: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
}

#[derive(Subcommand, Debug)]
enum ModuleOp {
    /// Add a module, optionally linking it into tasks.
    Add {
        #[arg(long)]
        system: String,
        #[arg(long)]
        name: String,
        #[arg(long)]
        kind: String,
        #[arg(long)]
        dnm: Option<String>,
        /// `key=value`, repeatable.
        #[arg(long = "param")]
        params: Vec<String>,
        /// `TASK:from.port -> to.port`, repeatable. Replaces the link feeding the same input.
        #[arg(long = "link")]
        links: Vec<String>,
        #[arg(long)]
        json: bool,
    },
    /// Remove a module and every link to or from it.
    Remove {
        #[arg(long)]
        system: String,
        #[arg(long)]
        name: String,
        #[arg(long)]
        json: bool,
    },
    /// Replace a module's kind and/or parameters; its links stay.
    Replace {
        #[arg(long)]
        system: String,
        #[arg(long)]
        name: String,
        /// Another kind: the module starts from that kind's defaults and the `--param`s given.
        #[arg(long)]
        kind: Option<String>,
        /// `key=value` (a TOML value), repeatable: changes these; the module's other
        /// parameters keep their values unless `--kind` changes the kind (to return one to its
        /// default, apply a netlist without it).
        #[arg(long = "param")]
        params: Vec<String>,
        #[arg(long)]
        json: bool,
    },
}

fn main() -> ExitCode {
    // Printing into a closed pipe (`dnm check x | head`) ends the program quietly.
    // SAFETY: restoring the default disposition of SIGPIPE before any thread starts.
    unsafe { libc::signal(libc::SIGPIPE, libc::SIG_DFL) };
    let cli = Cli::parse();
    // Before any thread starts: a process that records bounds its allocator (the recorder's
    // large buffers); one that does not keeps glibc's defaults, under which it stays flat and
    // large crossing samples cost no mapping each.
    if cli.command.records() {
        dnm::allocator::bound_for_long_runs();
    }
    // The demo talks to its user on stdout; its DNMs only speak up for warnings.
    dnm::init_logging(if matches!(cli.command, Cmd::Demo { .. }) {
        "warn"
    } else {
        "info"
    });
    iceoryx2::prelude::set_log_level(iceoryx2::prelude::LogLevel::Warn);
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", dnm_router::error_report(&e));
            ExitCode::FAILURE
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<ExitCode> {
    let z = &cli.zenoh;
    match cli.command {
        Cmd::Check {
            netlist,
            sequences,
            json,
        } => check(&netlist, &sequences, json),
        Cmd::Monitor { args } => match session_view::session_arg(&args)? {
            Some((session, rest)) => session_view::run(&session, &rest),
            None => monitor_cmd::run(&z.options(), &args),
        },
        Cmd::Ground { cmd } => ground_cmd::run(&z.options(), cmd),
        Cmd::Certs { cmd } => certs::run(cmd),
        Cmd::Linksim(args) => {
            linksim::run(&args)?;
            Ok(ExitCode::SUCCESS)
        }
        Cmd::Up {
            netlist,
            dnms,
            record,
            state_dir,
        } => up(z, &netlist, dnms, &record, state_dir),
        Cmd::Status { system, json } => {
            let r = send(z, &system, &Request::Status)?;
            answer(&r, json, print_status)
        }
        Cmd::Switch { system, task, json } => {
            let r = send(z, &system, &Request::Switch { task })?;
            answer(&r, json, |r| {
                for s in &r.switches {
                    println!(
                        "switched {} -> {} (revision {}) in {} ns",
                        s.from.as_deref().unwrap_or("(none)"),
                        s.to,
                        s.revision,
                        s.duration_ns
                    );
                }
            })
        }
        Cmd::Apply {
            system,
            netlist,
            json,
        } => {
            let text = std::fs::read_to_string(&netlist)
                .with_context(|| format!("reading {}", netlist.display()))?;
            let r = send(
                z,
                &system,
                &Request::Apply {
                    file: netlist.display().to_string(),
                    text,
                },
            )?;
            answer(&r, json, |r| {
                println!("applied: revision {}", r.revision.unwrap_or(0))
            })
        }
        Cmd::Module { op } => module_op(z, op),
        Cmd::Demo {
            netlist,
            sequence,
            keep_running,
            teleop_seconds,
            json,
            rerun,
            rerun_save,
            web,
            record,
        } => demo::run(
            &z.options(),
            &demo::DemoArgs {
                netlist,
                sequence,
                keep_running,
                json,
                teleop_s: teleop_seconds,
                record: record.options()?,
                rerun: match (rerun, rerun_save) {
                    (_, Some(path)) => Some(demo::RerunOut::Save(path)),
                    (true, None) => Some(demo::RerunOut::Auto),
                    (false, None) => None,
                },
                web,
            },
        ),
        Cmd::Place(args) => place_cmd::run(&args),
        Cmd::Stats {
            file,
            csv,
            out,
            json,
        } => stats(&file, &csv, &out, json),
        Cmd::Recordings { dir, write, json } => recordings(dir, write, json),
        Cmd::Replay {
            file,
            system,
            only,
            rate,
            fast,
            step,
            check,
            set,
            tolerance,
            exec,
            json,
        } => match check {
            Some(module) => check_module(&file, &module, &set, (tolerance, &exec), json),
            None => replay(&file, system.as_deref(), &only, (rate, fast, step), json),
        },
        Cmd::Router => {
            dnm_router::run_router(&z.options())?;
            Ok(ExitCode::SUCCESS)
        }
        Cmd::Kinds { netlist, json } => kinds(netlist.as_deref(), json),
        Cmd::Watch(args) => watch_cmd::run(&z.options(), &args),
    }
}

/// `dnm up`: runs DNMs of a netlist on this machine until Ctrl-C.
fn up(
    z: &ZenohArgs,
    netlist: &Path,
    dnms: Vec<String>,
    record: &RecordArgs,
    state_dir: Option<PathBuf>,
) -> anyhow::Result<ExitCode> {
    let n = dnm::load_netlist(netlist).map_err(|e| anyhow::anyhow!("{e}"))?;
    let dnms = if dnms.is_empty() {
        n.dnms.iter().map(|d| d.name.clone()).collect()
    } else {
        for d in &dnms {
            if n.dnm(d).is_none() {
                bail!("netlist {} declares no DNM `{d}`", netlist.display());
            }
        }
        dnms
    };
    let mut options = HostOptions::standard().context("locating the module host")?;
    options.record = record.options()?.map(|o| o.into_session(&n.system));
    options.downlink_cache = record.downlink_cache()?;
    if let Some(d) = state_dir {
        options.state_dir = Some(d);
    }
    if let Some(r) = &options.record {
        println!(
            "recording every port to {}/{}-<dnm>.mcap (the session's manifest: {}/{})",
            r.dir.display(),
            r.stem,
            r.dir.display(),
            dnm::session::MANIFEST
        );
    }
    println!(
        "system `{}`: DNMs {} up, task {}; Ctrl-C to stop",
        n.system,
        dnms.join(", "),
        n.initial_task().unwrap_or("(none)")
    );
    let zenoh = z.options().config()?;
    dnm::host::run_host(n, &dnms, options, zenoh)?;
    Ok(ExitCode::SUCCESS)
}

/// `dnm stats`: what a recording holds, per channel; CSV export of channels.
fn stats(file: &Path, csv: &[String], out: &Path, json: bool) -> anyhow::Result<ExitCode> {
    let files = recording_files(file)?;
    if files.len() > 1 && !csv.is_empty() {
        bail!(
            "{}: CSV export takes one file of the session (each file has its own rows): {}",
            file.display(),
            files
                .iter()
                .map(|f| f.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    let mut all = Vec::new();
    for f in &files {
        let bytes = std::fs::read(f).with_context(|| format!("reading {}", f.display()))?;
        let s = dnm::stats::stats(&bytes, &dnm::parse_recorded_netlist)
            .map_err(|e| anyhow::anyhow!("{}: not a readable MCAP file: {e}", f.display()))?;
        if !csv.is_empty() {
            let written = dnm::stats::export_csv(&bytes, csv, out).map_err(anyhow::Error::msg)?;
            for t in csv {
                if !written.contains(t) {
                    bail!(
                        "{}: no channel `{t}`; channels: {}",
                        f.display(),
                        s.channels
                            .iter()
                            .map(|c| c.topic.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    );
                }
            }
        }
        if !json {
            print_stats(f, &s);
        }
        all.push((f.display().to_string(), s));
    }
    if json {
        if all.len() == 1 && file.is_file() {
            println!("{}", serde_json::to_string_pretty(&all[0].1)?);
        } else {
            let v: Vec<_> = all
                .iter()
                .map(|(f, s)| serde_json::json!({"file": f, "stats": s}))
                .collect();
            println!("{}", serde_json::to_string_pretty(&v)?);
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `dnm replay`: publishes a recording's samples again, at a rate, as fast as possible or
/// step by step.
fn replay(
    file: &Path,
    system: Option<&str>,
    only: &[String],
    (rate, fast, step): (f64, bool, bool),
    json: bool,
) -> anyhow::Result<ExitCode> {
    let pace = if fast {
        dnm::replay::Pace::Fast
    } else if step {
        dnm::replay::Pace::Step
    } else {
        dnm::replay::Pace::Rate(rate)
    };
    let r = dnm::replay::replay(file, system, only, pace, &dnm::parse_recorded_netlist)
        .map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    if json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "replayed {} messages from {} file(s) on {} in {:.1} s",
            r.messages,
            r.files.len(),
            r.channels.join(", "),
            r.seconds
        );
        for s in &r.skipped {
            println!("not replayed: {s}");
        }
        if r.unreadable > 0 {
            println!(
                "{} messages could not be read back and were left out",
                r.unreadable
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// `dnm kinds`: the built-in module kinds and their ports.
fn kinds(netlist: Option<&Path>, json: bool) -> anyhow::Result<ExitCode> {
    let mut specs = dnm::registry().specs();
    if let Some(path) = netlist {
        let n = dnm::load_netlist(path).map_err(|e| anyhow::anyhow!("{e}"))?;
        for entry in n.catalog.iter() {
            if !specs.iter().any(|s| s.name == entry.spec.name) {
                specs.push(entry.spec.clone());
            }
        }
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&specs)?);
    } else {
        for s in specs {
            let ports = |ps: &[dnm_netlist::PortSpec]| {
                ps.iter()
                    .map(|p| format!("{}: {}", p.name, p.message.schema_name))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            println!(
                "{:<12} {}\n             in [{}] out [{}]",
                s.name,
                s.summary,
                ports(&s.inputs),
                ports(&s.outputs)
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn check_module(
    path: &Path,
    module: &str,
    set: &[String],
    (tolerance, exec): (f64, &[PathBuf]),
    json: bool,
) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        tolerance.is_finite() && tolerance >= 0.0,
        "--tolerance {tolerance}: give a relative tolerance of 0 or more, e.g. 1e-4"
    );
    let mut changes = Vec::new();
    for s in set {
        let (name, value) = s
            .split_once('=')
            .with_context(|| format!("--set {s}: write NAME=VALUE, e.g. --set wheel_radius=0.2"))?;
        changes.push((name.trim().to_string(), value.trim().to_string()));
    }
    // A bare file name is the one in this folder, never one found on the PATH.
    let execs: Vec<PathBuf> = exec
        .iter()
        .map(|e| {
            if e.parent().is_some_and(|p| p.as_os_str().is_empty()) {
                Path::new(".").join(e)
            } else {
                e.clone()
            }
        })
        .collect();
    // Which of them holds which kind, as they described themselves.
    let kinds = std::sync::Arc::new(std::sync::Mutex::new(std::collections::BTreeMap::<
        String,
        PathBuf,
    >::new()));
    let registry = dnm::registry();
    let make = |kind: &str, setup: &mut dnm_module::Setup<'_>| {
        if let Some(r) = registry.find(kind) {
            return Ok((r.make)(setup)?);
        }
        let exec = kinds
            .lock()
            .ok()
            .and_then(|k| k.get(kind).cloned())
            .ok_or_else(|| dnm::check::MakeError::UnknownKind(kind.to_string()))?;
        let stepper = exec_check::ExecStepper::spawn(&exec, kind, setup)?;
        Ok(Box::new(stepper) as Box<dyn dnm_module::Stepper>)
    };
    // The recording's netlist runs nothing, but the executables the operator named.
    let described = kinds.clone();
    let parse = move |file: &Path, text: &str| {
        if execs.is_empty() {
            return dnm::parse_recorded_netlist(file, text);
        }
        let mut describe = |named: &Path| -> Result<_, dnm_netlist::DescribeError> {
            let Some(exec) = execs.iter().find(|e| e.file_name() == named.file_name()) else {
                return Err(dnm_netlist::DescribeError::NotRun(format!(
                    "`{}` is not run for a recording: name it with --exec too",
                    named.display()
                )));
            };
            let spec = dnm::describe_exec(exec)?;
            if let Ok(mut k) = described.lock() {
                k.insert(spec.name.clone(), exec.clone());
            }
            Ok(spec)
        };
        dnm_netlist::Netlist::parse(file, text, &dnm::catalog(), &mut describe)
    };
    let r = dnm::check::check(path, module, &changes, tolerance, &parse, &make)
        .map_err(|e| anyhow::anyhow!("{}: {e}", path.display()))?;
    if json {
        println!("{}", serde_json::to_string_pretty(&r)?);
    } else {
        println!(
            "{} ({}): {} inputs fed, {} steps",
            r.module, r.kind, r.inputs_fed, r.steps
        );
        for (port, c) in &r.outputs {
            println!(
                "  {port}: {} recorded, {} replayed; {} identical, {} within {}",
                c.recorded, c.replayed, c.identical, c.within_tolerance, r.tolerance
            );
        }
        match &r.divergence {
            None if r.ok => println!("deterministic: every recorded output reproduced"),
            None => println!("nothing to compare"),
            Some(d) => {
                println!(
                    "first divergence: {} message #{} (recorded at {} ns): fields {}",
                    d.output,
                    d.index,
                    d.recorded_unix_ns.unwrap_or(0),
                    d.fields.join(", ")
                );
                println!("  recorded: {}", d.recorded.clone().unwrap_or_default());
                println!("  replayed: {}", d.replayed.clone().unwrap_or_default());
            }
        }
        if let Some(u) = &r.first_unrecorded_input {
            println!(
                "the recording lost {} samples of the module's inputs, the first gap to end in {} (#{}..#{}, sent between {} and {} ns){}",
                r.unrecorded_inputs,
                u.source,
                u.from_seq,
                u.to_seq,
                u.after_unix_ns,
                u.before_unix_ns,
                if r.divergence
                    .as_ref()
                    .is_some_and(|d| d.after_unrecorded_inputs)
                {
                    ": the divergence comes after them and may be the recording's, not the module's"
                } else {
                    ""
                }
            );
        }
    }
    Ok(if r.ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn check(path: &Path, sequences: &[PathBuf], json: bool) -> anyhow::Result<ExitCode> {
    let n = match dnm::load_netlist(path) {
        Ok(n) => n,
        Err(e) => return invalid(&e, json),
    };
    let mut checked = Vec::new();
    let mut refused: Option<dnm_netlist::NetlistError> = None;
    for s in sequences {
        match dnm_netlist::Sequence::load(s, &n) {
            Ok(q) => checked.push(q),
            // Every sequence is checked; their errors are reported together.
            Err(e) => match &mut refused {
                None => refused = Some(e),
                Some(all) => {
                    let file = e.file.display().to_string();
                    all.diagnostics
                        .extend(e.diagnostics.into_iter().map(|mut d| {
                            d.field = format!("{file}: {}", d.field);
                            d
                        }));
                }
            },
        }
    }
    if let Some(e) = refused {
        return invalid(&e, json);
    }
    if json {
        let sequences: Vec<_> = checked
            .iter()
            .map(|q| {
                serde_json::json!({
                    "file": q.file.display().to_string(),
                    "name": q.name,
                    "guards": q.guards,
                    "steps": q.steps,
                })
            })
            .collect();
        let summary = serde_json::json!({
            "ok": true,
            "system": n.system,
            "dnms": n.dnms,
            "modules": n.modules,
            "tasks": n.tasks,
            "initial_task": n.initial_task(),
            "sequences": sequences,
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
        return Ok(ExitCode::SUCCESS);
    }
    print_netlist(path, &n);
    for q in &checked {
        println!(
            "  sequence `{}` ({}): {} step{}, {} guard{}, valid",
            q.name,
            q.file.display(),
            q.steps.len(),
            if q.steps.len() == 1 { "" } else { "s" },
            q.guards.len(),
            if q.guards.len() == 1 { "" } else { "s" }
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// `dnm check`'s summary of a valid netlist.
fn print_netlist(path: &Path, n: &dnm_netlist::Netlist) {
    println!("{}: system `{}` is valid", path.display(), n.system);
    for d in &n.dnms {
        let mods: Vec<&str> = n.modules_on(&d.name).map(|m| m.name.as_str()).collect();
        println!(
            "  DNM {}{}: {}",
            d.name,
            d.parent
                .as_ref()
                .map(|p| format!(" (under {p})"))
                .unwrap_or_default(),
            mods.join(", ")
        );
    }
    for (l, a, b) in dnm::crossing_links(n) {
        println!(
            "  route: `{l}` crosses DNMs {a} -> {b} over Zenoh key {}",
            dnm::keys::port(&n.system, &a, &l.from.module, &l.from.port)
        );
    }
    for t in n.tasks.values() {
        let mark = if Some(t.name.as_str()) == n.initial_task() {
            " (initial)"
        } else {
            ""
        };
        println!("  task {}{mark}: {} links", t.name, t.links.len());
        for l in &t.links {
            println!("    {l}");
        }
    }
}

/// `dnm check`'s report of an invalid netlist or sequence: every error, located.
fn invalid(e: &dnm_netlist::NetlistError, json: bool) -> anyhow::Result<ExitCode> {
    if json {
        let diags: Vec<_> = e
            .diagnostics
            .iter()
            .map(|d| {
                serde_json::json!({
                    "file": e.file.display().to_string(),
                    "line": d.location.map(|l| l.0),
                    "column": d.location.map(|l| l.1),
                    "field": d.field,
                    "message": d.message,
                    "help": d.help,
                })
            })
            .collect();
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({"ok": false, "errors": diags}))?
        );
    } else {
        eprint!("{e}");
    }
    Ok(ExitCode::FAILURE)
}

fn answer(r: &Response, json: bool, human: impl Fn(&Response)) -> anyhow::Result<ExitCode> {
    if json {
        println!("{}", serde_json::to_string_pretty(r)?);
    } else if r.ok {
        human(r);
    } else {
        eprintln!("error: {}", r.error.as_deref().unwrap_or("unknown"));
    }
    Ok(if r.ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}

fn print_status(r: &Response) {
    for d in &r.dnms {
        print_dnm(d);
    }
}

fn print_dnm(d: &DnmReport) {
    println!(
        "DNM {} (system {}, pid {}): revision {}, task {}, cpu {:.1}%, rss {} KiB",
        d.dnm,
        d.system,
        d.pid,
        d.revision,
        d.active_task.as_deref().unwrap_or("(none)"),
        d.cpu_percent,
        d.memory.map_or(0, |m| m.private_kib())
    );
    if let Some(p) = d.preparing {
        println!("  preparing revision {p}");
    }
    for m in &d.modules {
        println!(
            "  {:<14} {:<12} {:<8} pid {:>7} restarts {:>2} hangs {:>2} steps {:>8} {:>7.1} Hz cpu {:>5.1}% rss {:>6} KiB",
            m.name,
            m.kind,
            format!("{:?}", m.state).to_lowercase(),
            m.pid.map(|p| p.to_string()).unwrap_or_else(|| "-".into()),
            m.restarts,
            m.hangs,
            m.steps,
            m.rate_hz,
            m.cpu_percent,
            m.memory.map_or(0, |m| m.private_kib())
        );
        if m.state != dnm::ModuleRunState::Running
            && let Some(why) = &m.last_exit
        {
            println!("  {:<14} last exit: {why}", "");
        }
    }
    for e in d.events.iter().rev().take(5).rev() {
        println!("  event: {} {}: {}", e.module, e.what, e.detail);
    }
    if !d.peers.is_empty() {
        let peers: Vec<String> = d
            .peers
            .iter()
            .map(|p| match p.for_ms {
                Some(ms) => format!("{} {} for {:.1} s", p.dnm, p.state, ms as f64 / 1000.0),
                None => format!("{} {}", p.dnm, p.state),
            })
            .collect();
        println!("  peers: {}", peers.join(", "));
    }
    if let Some(r) = &d.recording {
        println!(
            "  recording {}: {} messages, {} bytes, {} dropped, {} files",
            r.file, r.messages, r.bytes, r.dropped, r.files
        );
        if let Some(e) = &r.error {
            println!("  recording STOPPED: {e}");
        }
    }
    for (dir, routes) in [
        ("publishes", &d.routes.published),
        ("mirrors", &d.routes.mirrored),
    ] {
        for r in routes {
            println!(
                "  {dir} {}: {} messages, {} bytes, {} dropped",
                r.key, r.messages, r.bytes, r.dropped
            );
        }
    }
}

/// The MCAP files a path names: itself, or every file of a session folder.
pub(crate) fn recording_files(path: &Path) -> anyhow::Result<Vec<PathBuf>> {
    if !path.is_dir() {
        return Ok(vec![path.to_path_buf()]);
    }
    let files = dnm::session::files(path).map_err(anyhow::Error::msg)?;
    if files.is_empty() {
        bail!("{}: no .mcap files in this folder", path.display());
    }
    Ok(files)
}

fn unix_time(ns: Option<u64>) -> String {
    ns.map_or_else(
        || "—".into(),
        |ns| {
            let name = dnm::session::session_name("", ns / 1_000_000_000);
            name.trim_start_matches('-').to_string()
        },
    )
}

fn duration(start: Option<u64>, end: Option<u64>) -> String {
    match (start, end) {
        (Some(a), Some(b)) if b >= a => format!("{:.1} s", (b - a) as f64 / 1e9),
        _ => "—".into(),
    }
}

/// `dnm recordings [DIR]`: the sessions under a folder, or one session's manifest.
fn recordings(dir: Option<PathBuf>, write: bool, json: bool) -> anyhow::Result<ExitCode> {
    let dir = dir.unwrap_or_else(|| {
        std::env::var_os("DNM_RECORD_DIR")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("recordings"))
    });
    // A session: its manifest is there, or its files are and no session folders are.
    let sessions = dnm::session::sessions(&dir).unwrap_or_default();
    let is_session = dir.join(dnm::session::MANIFEST).is_file()
        || (sessions.is_empty() && dnm::session::files(&dir).is_ok_and(|f| !f.is_empty()));
    if is_session {
        let mut m = dnm::session::manifest(&dir).map_err(anyhow::Error::msg)?;
        if write {
            if m.files.iter().all(|f| f.complete) {
                dnm::session::write_manifest(&dir).map_err(anyhow::Error::msg)?;
                m = dnm::session::manifest(&dir).map_err(anyhow::Error::msg)?;
            } else {
                bail!(
                    "{}: not every file is closed (still recording, or cut short): the manifest is left as it is",
                    dir.display()
                );
            }
        }
        if json {
            println!("{}", serde_json::to_string_pretty(&m)?);
            return Ok(ExitCode::SUCCESS);
        }
        println!(
            "session {}: {} to {} ({}), DNMs {}, revisions {:?}, {} messages, {:.1} MB in {} files (manifest: {})",
            m.session,
            unix_time(m.start_unix_ns),
            unix_time(m.end_unix_ns),
            duration(m.start_unix_ns, m.end_unix_ns),
            m.dnms.join(", "),
            m.revisions,
            m.messages,
            m.bytes as f64 / 1e6,
            m.files.len(),
            dir.join(dnm::session::MANIFEST).display()
        );
        for f in &m.files {
            println!(
                "  {:<28} {:<8} {} revisions {:?}: {} messages over {}, {:.1} MB{}",
                f.name,
                f.dnm.as_deref().unwrap_or("?"),
                if f.complete { "closed" } else { "OPEN/CUT" },
                f.revisions,
                f.messages,
                duration(f.start_unix_ns, f.end_unix_ns),
                f.bytes as f64 / 1e6,
                f.error
                    .as_ref()
                    .map(|e| format!(" — {e}"))
                    .unwrap_or_default()
            );
        }
        return Ok(ExitCode::SUCCESS);
    }
    if !dir.is_dir() {
        bail!(
            "{}: no such folder (recordings go to $DNM_RECORD_DIR, else recordings/)",
            dir.display()
        );
    }
    if json {
        println!("{}", serde_json::to_string_pretty(&sessions)?);
        return Ok(ExitCode::SUCCESS);
    }
    if sessions.is_empty() {
        println!("no recording sessions under {}", dir.display());
    }
    for m in &sessions {
        let open = m.files.iter().filter(|f| !f.complete).count();
        println!(
            "{:<40} {} {:>8}  DNMs {:<28} {:>9} messages {:>8.1} MB  {} files{}",
            m.session,
            unix_time(m.start_unix_ns),
            duration(m.start_unix_ns, m.end_unix_ns),
            m.dnms.join(","),
            m.messages,
            m.bytes as f64 / 1e6,
            m.files.len(),
            if open > 0 {
                format!(" ({open} not closed)")
            } else {
                String::new()
            }
        );
    }
    Ok(ExitCode::SUCCESS)
}

fn print_stats(file: &Path, s: &dnm::stats::Stats) {
    println!(
        "{}: {} messages over {:.1} s, netlist revisions {}",
        file.display(),
        s.messages,
        s.duration_s,
        s.netlist_revisions.join(", ")
    );
    println!(
        "  {:<36} {:<26} {:>8} {:>9} {:>11} {:>8} {:>12}",
        "channel", "schema", "messages", "rate Hz", "max gap ms", "missing", "bytes"
    );
    for c in &s.channels {
        println!(
            "  {:<36} {:<26} {:>8} {:>9.1} {:>11.1} {:>8} {:>12}",
            c.topic, c.schema, c.messages, c.rate_hz, c.max_gap_ms, c.missing, c.bytes
        );
    }
    for l in &s.links {
        println!(
            "  latency {:<40} p50 {:.2} ms, p99 {:.2} ms ({} samples)",
            l.link, l.p50_ms, l.p99_ms, l.samples
        );
    }
    for sw in &s.switches {
        println!(
            "  switch {} -> {} on {} (revision {})",
            sw["from"].as_str().unwrap_or("?"),
            sw["to"].as_str().unwrap_or("?"),
            sw["dnm"].as_str().unwrap_or("?"),
            sw["revision"]
        );
    }
}

/// Module operations are edits of the running netlist, applied like any netlist: validated
/// first, refused with the errors if invalid, nothing running lost.
fn module_op(z: &ZenohArgs, op: ModuleOp) -> anyhow::Result<ExitCode> {
    use dnm::proto::station::ModuleEdit;
    let (system, json) = match &op {
        ModuleOp::Add { system, json, .. }
        | ModuleOp::Remove { system, json, .. }
        | ModuleOp::Replace { system, json, .. } => (system.clone(), *json),
    };
    let current = send(z, &system, &Request::Netlist)?;
    let text = current.netlist.context("the system sent no netlist")?;
    let edit = match op {
        ModuleOp::Add {
            name,
            kind,
            dnm,
            params,
            links,
            ..
        } => ModuleEdit::Add {
            name,
            kind,
            dnm,
            params,
            links,
        },
        ModuleOp::Remove { name, .. } => ModuleEdit::Remove { name },
        ModuleOp::Replace {
            name, kind, params, ..
        } => ModuleEdit::Replace { name, kind, params },
    };
    let (text, what) = dnm_authority::edit_netlist(&text, &edit)
        .map_err(|e| anyhow::anyhow!("system `{system}`: {e}"))?;
    // Named beside the file it came from, so the relative `exec` paths of its kinds resolve
    // as they did.
    let from = send(z, &system, &Request::Status)
        .ok()
        .and_then(|r| r.dnms.into_iter().find_map(|d| d.netlist_file));
    let file = match from {
        Some(f) => format!("{f} (running netlist of `{system}`, edited)"),
        None => format!("<{system} running netlist, edited>"),
    };
    let r = send(z, &system, &Request::Apply { file, text })?;
    answer(&r, json, |r| {
        println!("{what}: revision {}", r.revision.unwrap_or(0))
    })
}
