//! `dnm watch`: an output's values as they come, over Zenoh, decoded by its message type (the
//! wiring the system's DNMs answer). The DNM publishes an output on its watch key only while
//! someone subscribes, at the rate asked for; this is that someone, on a terminal.

use std::process::ExitCode;
use std::time::Duration;

use dnm::keys::{self, JPEG_ENCODING, WatchRate};
use dnm_netlist::{PortSpec, Wiring};
use zenoh::Wait;

/// How long the system's DNMs have to say what they carry.
const WIRING_TIMEOUT: Duration = Duration::from_secs(3);

/// What `dnm watch` was asked.
#[derive(clap::Args, Debug)]
pub struct WatchArgs {
    #[arg(long)]
    system: String,
    /// The output, `module.port`.
    output: String,
    /// How often: `full` (every sample), `10hz` or `1hz`. Each line: `#<sequence number>
    /// <send time, UTC> <value as JSON>`.
    #[arg(long, default_value = "10hz")]
    rate: String,
    /// Stop after this many samples (default: until Ctrl-C).
    #[arg(long)]
    count: Option<u64>,
    /// One JSON object per line: `{"unix_ns", "seq", "value"}` (camera frames: their size).
    #[arg(long)]
    json: bool,
    /// Give up (exit status 1) when no sample came for this many seconds (default: wait).
    #[arg(long)]
    timeout: Option<u64>,
}

/// After this long without a sample, say what may be wrong (and go on waiting).
const QUIET_NOTE: Duration = Duration::from_secs(5);

/// Why an output cannot be watched.
#[derive(Debug, thiserror::Error)]
enum WatchCmdError {
    #[error("`{0}` is not `module.port`")]
    Output(String),
    #[error("--rate {0}: use full, 10hz or 1hz")]
    Rate(String),
    #[error(
        "no DNM of system `{0}` answered on Zenoh within {WIRING_TIMEOUT:?}: is it running? (`dnm up` \
         joins Zenoh; to reach another machine give --connect tcp/HOST:PORT, or the system's \
         --zenoh-config)"
    )]
    NoSystem(String),
    #[error(
        "{answers} DNM(s) of system `{system}` answered, but not with a wiring this `dnm` can \
         read: is it the same version as the system's?"
    )]
    Unreadable { system: String, answers: usize },
    #[error("no sample of {0} for {1} s (--timeout)")]
    Quiet(String, u64),
    #[error("system `{system}` has no module `{module}`; its modules: {known}")]
    NoModule {
        system: String,
        module: String,
        known: String,
    },
    #[error("module `{module}` has no output `{port}`; its outputs: {known}")]
    NoPort {
        module: String,
        port: String,
        known: String,
    },
}

pub fn run(z: &dnm::ZenohOptions, args: &WatchArgs) -> anyhow::Result<ExitCode> {
    let (module, port) = args
        .output
        .split_once('.')
        .filter(|(m, p)| !m.is_empty() && !p.is_empty())
        .ok_or_else(|| WatchCmdError::Output(args.output.clone()))?;
    let rate = WatchRate::parse(&args.rate.to_lowercase())
        .ok_or_else(|| WatchCmdError::Rate(args.rate.clone()))?;
    let session = z.open()?;
    let (wirings, unreadable) = wirings(&session, &args.system);
    if wirings.is_empty() && unreadable > 0 {
        return Err(WatchCmdError::Unreadable {
            system: args.system.clone(),
            answers: unreadable,
        }
        .into());
    }
    let (dnm, spec) = find(&args.system, &wirings, module, port)?;
    let key = keys::watch(&args.system, &dnm, module, port, rate);
    let subscriber = session
        .declare_subscriber(&key)
        .wait()
        .map_err(|e| anyhow::anyhow!("subscribing to {key}: {e}"))?;
    if !args.json {
        eprintln!(
            "{module}.{port} on DNM {dnm} ({}), {}; Ctrl-C to stop",
            spec.message.schema_name,
            rate.chunk()
        );
    }
    let mut seen = 0u64;
    let mut quiet = Duration::ZERO;
    let give_up = args.timeout.map(Duration::from_secs);
    while args.count.is_none_or(|n| seen < n) {
        let wait = give_up.map_or(QUIET_NOTE, |g| g.saturating_sub(quiet).min(QUIET_NOTE));
        let sample = match subscriber.recv_timeout(wait) {
            Ok(Some(s)) => s,
            Ok(None) => {
                quiet += wait;
                if give_up.is_some_and(|g| quiet >= g) {
                    return Err(WatchCmdError::Quiet(
                        format!("{module}.{port}"),
                        args.timeout.unwrap_or_default(),
                    )
                    .into());
                }
                if quiet == QUIET_NOTE && seen == 0 {
                    eprintln!(
                        "nothing from {module}.{port} yet: is the module running and in the task \
                         in force (`dnm status`)? does this identity's access allow --rate {}?",
                        rate.chunk()
                    );
                }
                continue;
            }
            Err(e) => anyhow::bail!("the subscription to {key} ended: {e}"),
        };
        quiet = Duration::ZERO;
        seen += 1;
        let header = sample
            .attachment()
            .and_then(|a| keys::decode_header(&a.to_bytes()));
        let bytes = sample.payload().to_bytes();
        let value = if sample.encoding().to_string() == JPEG_ENCODING {
            serde_json::json!({ "jpeg_bytes": bytes.len() })
        } else {
            dnm_netlist::values::decode(&spec.message, &bytes)
        };
        print(args.json, header, &value);
    }
    let _ = session.close().wait();
    Ok(ExitCode::SUCCESS)
}

/// The wirings the system's DNMs answer, and how many answers could not be read as one.
fn wirings(session: &zenoh::Session, system: &str) -> (Vec<Wiring>, usize) {
    let Ok(replies) = session
        .get(keys::wiring(system, "*"))
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(WIRING_TIMEOUT)
        .wait()
    else {
        return (Vec::new(), 0);
    };
    let (mut out, mut unreadable) = (Vec::new(), 0);
    while let Ok(r) = replies.recv() {
        match r
            .result()
            .map(|s| serde_json::from_slice::<Wiring>(&s.payload().to_bytes()))
        {
            Ok(Ok(w)) => out.push(w),
            _ => unreadable += 1,
        }
    }
    (out, unreadable)
}

/// The DNM hosting `module` and the spec of its output `port`, from the newest wiring.
fn find(
    system: &str,
    wirings: &[Wiring],
    module: &str,
    port: &str,
) -> Result<(String, PortSpec), WatchCmdError> {
    let wiring = wirings
        .iter()
        .max_by_key(|w| w.revision)
        .ok_or_else(|| WatchCmdError::NoSystem(system.to_string()))?;
    let m = wiring
        .module(module)
        .ok_or_else(|| WatchCmdError::NoModule {
            system: system.to_string(),
            module: module.to_string(),
            known: names(wiring.modules.iter().map(|m| m.name.as_str())),
        })?;
    let spec = m
        .outputs
        .iter()
        .find(|p| p.name == port)
        .ok_or_else(|| WatchCmdError::NoPort {
            module: module.to_string(),
            port: port.to_string(),
            known: names(m.outputs.iter().map(|p| p.name.as_str())),
        })?;
    Ok((m.dnm.clone(), spec.clone()))
}

fn names<'a>(it: impl Iterator<Item = &'a str>) -> String {
    let v: Vec<&str> = it.collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

fn print(json: bool, header: Option<keys::SampleHeader>, value: &serde_json::Value) {
    let (unix_ns, seq) = header.map_or((0, 0), |h| (h.unix_ns, h.seq));
    if json {
        println!(
            "{}",
            serde_json::json!({ "unix_ns": unix_ns, "seq": seq, "value": value })
        );
    } else {
        println!("#{seq} {} {value}", clock(unix_ns));
    }
}

/// `HH:MM:SS.mmmZ` (UTC) of a wall-clock time, or `-` when the sample carried none.
fn clock(unix_ns: u64) -> String {
    if unix_ns == 0 {
        return "-".into();
    }
    let ms = unix_ns / 1_000_000;
    let s = ms / 1000;
    format!(
        "{:02}:{:02}:{:02}.{:03}Z",
        (s / 3600) % 24,
        (s / 60) % 60,
        s % 60,
        ms % 1000
    )
}
