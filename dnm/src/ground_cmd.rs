//! `dnm ground`: run a ground station, and give it commands through its HTTP/JSON API.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use anyhow::{Context, bail};
use clap::Subcommand;
use dnm_ground::{Entry, LinkStatus, Station, StationOptions};
use dnm_proto::station::{ModuleEdit, Order, SequenceAction, SequenceStatus};

/// The station's API unless `--url` or `$DNM_GROUND_URL` says otherwise.
pub const DEFAULT_URL: &str = "http://127.0.0.1:7480";

#[derive(Subcommand, Debug)]
pub enum GroundCmd {
    /// Run the ground station until Ctrl-C: its outbox, the link to the rover, its API.
    Serve(Serve),
    /// Switch the rover to TASK, now or at a rover time.
    Switch {
        task: String,
        /// `+30s` from now, or seconds since the Unix epoch (rover time).
        #[arg(long)]
        at: Option<String>,
        /// With `--at`: how late after its time the switch may still run (e.g. `5s`, `2m`;
        /// default 60 s); later, the rover refuses it.
        #[arg(long, requires = "at")]
        late_by: Option<String>,
        #[command(flatten)]
        common: Common,
    },
    /// Apply a netlist to the rover.
    Apply {
        netlist: PathBuf,
        #[command(flatten)]
        common: Common,
    },
    /// Replace a module (another kind or other parameters).
    Replace {
        name: String,
        /// Another kind: the module starts from that kind's defaults and the `--param`s given.
        #[arg(long)]
        kind: Option<String>,
        /// `key=value` (repeatable): changes these; the module's other parameters keep their
        /// values unless `--kind` changes the kind (to return one to its default, apply a
        /// netlist without it).
        #[arg(long = "param")]
        params: Vec<String>,
        #[command(flatten)]
        common: Common,
    },
    /// Remove a module and its links.
    Remove {
        name: String,
        #[command(flatten)]
        common: Common,
    },
    /// Cancel a time-tagged switch that has not run yet.
    Cancel {
        seq: u64,
        #[command(flatten)]
        common: Common,
    },
    /// Onboard sequences: upload one, start, pause, resume or cancel it.
    #[command(subcommand)]
    Sequence(SequenceCmd),
    /// The link, the rover's state and the last commands.
    Status {
        #[arg(long)]
        url: Option<String>,
        #[arg(long)]
        json: bool,
    },
}

/// What `dnm ground sequence` does.
#[derive(Subcommand, Debug)]
pub enum SequenceCmd {
    /// Store a sequence file on the rover (checked there against the netlist in force; with
    /// `--check NETLIST`, here first). The netlists its `apply` steps name go with it.
    Upload {
        file: PathBuf,
        /// Check it against this netlist before sending it.
        #[arg(long)]
        check: Option<PathBuf>,
        #[command(flatten)]
        common: Common,
    },
    /// Run a stored sequence from its first step.
    Start {
        name: String,
        #[command(flatten)]
        common: Common,
    },
    /// Hold it before its next step (waits stop counting; guards still watch).
    Pause {
        name: String,
        #[command(flatten)]
        common: Common,
    },
    /// Go on from where it was paused.
    Resume {
        name: String,
        #[command(flatten)]
        common: Common,
    },
    /// Stop it where it is; the rover stays in its task.
    Cancel {
        name: String,
        #[command(flatten)]
        common: Common,
    },
}

#[derive(clap::Args, Debug)]
pub struct Common {
    /// The station's API (default: $DNM_GROUND_URL, else http://127.0.0.1:7480).
    #[arg(long)]
    url: Option<String>,
    /// Wait up to this many seconds for the command's fate, and exit with it: 0 applied, 3
    /// refused or cancelled (the reason printed), 4 not final yet (its state printed). Without
    /// it: 0 once queued, 3 if the station refused it at once. Errors (no station, bad input)
    /// exit 1.
    #[arg(long)]
    wait: Option<u64>,
    #[arg(long)]
    json: bool,
}

fn url(u: &Option<String>) -> String {
    u.clone()
        .or_else(|| std::env::var("DNM_GROUND_URL").ok())
        .unwrap_or_else(|| DEFAULT_URL.into())
}

/// `+30s`, `+500ms` (from now, on the rover's clock as the station last measured it), or
/// seconds since the epoch (rover time): rover time in ns.
pub fn parse_at(at: &str, rover_clock_offset_ms: f64) -> anyhow::Result<u64> {
    if let Some(rel) = at.strip_prefix('+') {
        let ms = dnm_netlist::parse_duration_ms(rel)
            .with_context(|| format!("`{at}`: write e.g. `+30s` or `+2m`"))?;
        let now = dnm_ground::now_unix_ns() as i128 + (rover_clock_offset_ms * 1e6) as i128;
        return u64::try_from((now + i128::from(ms) * 1_000_000).max(0))
            .ok()
            .with_context(|| format!("`{at}` is beyond any time the rover can keep"));
    }
    let s: f64 = at
        .parse()
        .with_context(|| format!("`{at}`: write `+30s` or seconds since the Unix epoch"))?;
    if !(0.0..1.8e10).contains(&s) {
        bail!("`{at}`: seconds since the Unix epoch, before the year 2540");
    }
    Ok((s * 1e9) as u64)
}

fn agent() -> ureq::Agent {
    ureq::Agent::new_with_config(
        ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(330)))
            .build(),
    )
}

/// `Authorization` for a station that needs a token ($DNM_GROUND_TOKEN).
fn bearer() -> Option<String> {
    std::env::var("DNM_GROUND_TOKEN")
        .ok()
        .filter(|t| !t.is_empty())
        .map(|t| format!("Bearer {t}"))
}

fn get(url: &str) -> anyhow::Result<String> {
    let mut req = agent().get(url);
    if let Some(b) = bearer() {
        req = req.header("Authorization", b);
    }
    let mut r = req
        .call()
        .with_context(|| format!("is the ground station running? ({url})"))?;
    let status = r.status().as_u16();
    let body = r.body_mut().read_to_string()?;
    if status >= 400 {
        bail!("{}", error_of(&body));
    }
    Ok(body)
}

/// How complete the station's record of the rover is, a line per channel.
fn print_record(r: &dnm_downlink::RecordStatus) {
    let kbit = |b: f64| b * 8.0 / 1000.0;
    let budget = r.budget_bytes_per_s.map_or("no budget".to_string(), |b| {
        format!("budget {:.1} kbit/s", kbit(b as f64))
    });
    println!(
        "record of the rover in {}: {budget}, requests of {} bytes at most, downlink {:.1} \
         kbit/s measured; backlog {} bytes{}",
        r.dir,
        r.request_bytes,
        kbit(r.measured_bytes_per_s),
        r.backlog_bytes,
        r.seconds_to_clear
            .map_or(String::new(), |s| format!(" (~{s:.0} s to clear)"))
    );
    let now = dnm_proto::clock::now_unix_ns();
    for c in &r.channels {
        let pct = if c.expected > 0 {
            format!(" ({:.1} %)", 100.0 * c.received as f64 / c.expected as f64)
        } else {
            String::new()
        };
        let gap = c.oldest_gap.map_or(String::new(), |g| {
            format!(
                ", {} gap(s), the oldest {:.0} s ago ({:.1} s long)",
                c.gaps,
                now.saturating_sub(g.from_ns) as f64 / 1e9,
                g.to_ns.saturating_sub(g.from_ns) as f64 / 1e9
            )
        });
        let unrecorded = if c.unrecorded.is_empty() {
            String::new()
        } else {
            format!(
                ", {} stretch(es) the rover never recorded",
                c.unrecorded.len()
            )
        };
        println!(
            "  {}: {}/{}{pct}{gap}{unrecorded}",
            c.topic, c.received, c.expected
        );
    }
}

fn error_of(body: &str) -> String {
    serde_json::from_str::<serde_json::Value>(body)
        .ok()
        .and_then(|v| v["error"].as_str().map(str::to_string))
        .unwrap_or_else(|| body.to_string())
}

/// Queues `order` at the station and, if asked, waits for its fate.
fn submit(order: &Order, common: &Common) -> anyhow::Result<ExitCode> {
    let base = url(&common.url);
    let body = serde_json::to_vec(order)?;
    let mut req = agent().post(format!("{base}/commands"));
    if let Some(b) = bearer() {
        req = req.header("Authorization", b);
    }
    let mut r = req
        .content_type("application/json")
        .send(&body[..])
        .with_context(|| format!("is the ground station running? ({base})"))?;
    let status = r.status().as_u16();
    let text = r.body_mut().read_to_string()?;
    if status >= 400 {
        bail!("{}", error_of(&text));
    }
    let mut entry: Entry = serde_json::from_str(&text)?;
    if let Some(w) = common.wait {
        let text = get(&format!("{base}/commands/{}?wait={w}", entry.seq))?;
        entry = serde_json::from_str(&text)?;
    }
    if common.json {
        println!("{}", serde_json::to_string_pretty(&entry)?);
    } else {
        println!("{}", describe(&entry));
    }
    let code = fate_code(entry.state, common.wait.is_some());
    if code == NOT_FINAL {
        eprintln!(
            "not final after {} s: still {}",
            common.wait.unwrap_or_default(),
            format!("{:?}", entry.state).to_lowercase()
        );
    }
    Ok(ExitCode::from(code))
}

/// Exit code of a command that was refused or cancelled: it will not run.
pub const REFUSED: u8 = 3;
/// Exit code of a command whose fate was not known within `--wait`.
pub const NOT_FINAL: u8 = 4;

/// The exit code of a command in `state`, waited for or not.
fn fate_code(state: dnm_ground::CommandState, waited: bool) -> u8 {
    use dnm_ground::CommandState as S;
    match state {
        S::Applied => 0,
        S::Refused | S::Cancelled => REFUSED,
        _ if waited => NOT_FINAL,
        _ => 0,
    }
}

fn describe(e: &Entry) -> String {
    use dnm_proto::station::Fate;
    let what = match &e.order {
        Order::Switch {
            task, at_unix_ns, ..
        } => match at_unix_ns {
            Some(at) => format!("switch to `{task}` at {:.3}", *at as f64 / 1e9),
            None => format!("switch to `{task}`"),
        },
        Order::Apply { file, .. } => format!("apply {file}"),
        Order::Module { edit } => match edit {
            ModuleEdit::Add { name, .. } => format!("add module `{name}`"),
            ModuleEdit::Replace { name, .. } => format!("replace module `{name}`"),
            ModuleEdit::Remove { name } => format!("remove module `{name}`"),
        },
        Order::Cancel { seq } => format!("cancel command {seq}"),
        Order::Sequence { name, action } => {
            let verb = match action {
                SequenceAction::Upload { .. } => "upload",
                SequenceAction::Start => "start",
                SequenceAction::Pause => "pause",
                SequenceAction::Resume => "resume",
                SequenceAction::Cancel => "cancel",
            };
            format!("{verb} sequence `{name}`")
        }
    };
    let fate = match &e.fate {
        Some(Fate::Applied {
            revision,
            task,
            at_unix_ns,
        }) => format!(
            "applied: revision {revision}, task {}, at {:.3}",
            task.as_deref().unwrap_or("-"),
            *at_unix_ns as f64 / 1e9
        ),
        Some(Fate::Refused { reason }) => format!("refused: {reason}"),
        Some(Fate::Scheduled { at_unix_ns }) => {
            format!("scheduled on the rover for {:.3}", *at_unix_ns as f64 / 1e9)
        }
        Some(Fate::Cancelled { target }) => format!("done: command {target} will not run"),
        Some(Fate::CancelledBy { by }) => format!("cancelled by command {by}"),
        Some(Fate::Done { detail, .. }) => format!("done: {detail}"),
        _ => format!("{:?}", e.state).to_lowercase(),
    };
    format!("#{:<4} {what:<36} {fate}", e.seq)
}

fn print_sequence(q: &SequenceStatus) {
    let state = serde_json::to_value(q.state)
        .ok()
        .and_then(|v| v.as_str().map(str::to_string))
        .unwrap_or_default();
    let at = if q.step < q.steps {
        format!("step {}/{}: {}", q.step + 1, q.steps, q.doing)
    } else {
        format!("{} steps", q.steps)
    };
    println!("sequence `{}` {state}, {at}", q.name);
    if !q.why.is_empty() {
        println!("  {}", q.why);
    }
    for e in q.history.iter().rev().take(5).rev() {
        // Said once: some details name their step already.
        let step = e
            .step
            .filter(|_| !e.detail.starts_with("step "))
            .map_or(String::new(), |s| format!(" step {}", s + 1));
        println!(
            "  {} {}{step}: {}",
            e.what,
            e.at_unix_ns as f64 / 1e9,
            e.detail
        );
    }
}

fn print_link(l: &LinkStatus) {
    println!(
        "link {}: rtt {}, last contact {}, loss {:.0}% of the last uplinks, {} commands pending",
        if l.up { "up" } else { "DOWN" },
        l.rtt_ms.map_or("-".into(), |r| format!("{r:.0} ms")),
        l.last_contact_ms
            .map_or("never".into(), |c| format!("{:.1} s ago", c as f64 / 1e3)),
        l.loss * 100.0,
        l.pending
    );
    if let Some(r) = &l.rover {
        println!(
            "rover: revision {}, task {} (authority `{}`)",
            r.revision,
            r.task.as_deref().unwrap_or("-"),
            r.authority
        );
        if let Some(sf) = r.last_safing.as_ref().filter(|_| r.safe) {
            println!(
                "rover SAFE on `{}` (safing {}, at {:.3}): {}; commands given before this \
                 station saw it are refused",
                sf.task,
                sf.epoch,
                sf.at_unix_ns as f64 / 1e9,
                sf.reason
            );
        }
        for (station, seq, at) in &r.scheduled {
            println!("  scheduled: {station} #{seq} at {:.3}", *at as f64 / 1e9);
        }
        for e in &r.events {
            println!("  event {}: {}", e.what, e.detail);
        }
        for q in &r.sequences {
            print_sequence(q);
        }
    }
    if let Some(o) = l.rover_clock_offset_ms {
        println!("rover clock {o:+.0} ms from this station's (relative time tags use it)");
    }
    if let Some(e) = &l.error {
        println!("the rover refused the last uplink: {e}");
    }
}

/// What `dnm ground serve` is given.
#[derive(clap::Args, Debug)]
pub struct Serve {
    #[arg(long)]
    system: String,
    /// The station's name, unique among the system's stations.
    #[arg(long, default_value = "ground-1")]
    station: String,
    /// The outbox database (default: <state dir>/<system>-<station>.redb).
    #[arg(long)]
    db: Option<PathBuf>,
    /// Where the operator API and the web interface listen.
    #[arg(long, default_value = "127.0.0.1:7480")]
    http: std::net::SocketAddr,
    /// The login for an API other machines can reach (required unless `--http` is a
    /// loopback address): clients send `Authorization: Bearer TOKEN`; a browser opens
    /// `/?token=TOKEN` once.
    #[arg(long, env = "DNM_GROUND_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Also watch the rover in Rerun: `spawn` (start a viewer), a viewer's URL
    /// (rerun+http://HOST:PORT/proxy) or a path to save an .rrd to.
    #[arg(long)]
    monitor: Option<String>,
    /// The ground's own record of the rover: the session folder the downlink plan's
    /// outputs, switches and events are written to as they arrive (default:
    /// <system>-<station>-record beside the outbox; a folder of an earlier run is resumed).
    #[arg(long, conflicts_with = "no_record")]
    record: Option<PathBuf>,
    /// Keep no record of the rover at this station.
    #[arg(long)]
    no_record: bool,
    /// The downlink's budget, live and backfill together (e.g. `64kbit`; default: what
    /// the link carries): what the ground missed is asked for within it.
    #[arg(long)]
    downlink_budget: Option<String>,
}

/// Runs a ground station (its outbox, link, API, the ground's record of the rover and
/// optionally a monitor) until Ctrl-C.
fn serve(z: &dnm::ZenohOptions, args: Serve) -> anyhow::Result<ExitCode> {
    let Serve {
        system,
        station,
        db,
        http,
        token,
        monitor,
        record,
        no_record,
        downlink_budget,
    } = args;

    let db = match db {
        Some(db) => db,
        None => dnm::default_state_dir()
            .context(dnm::NO_STATE_DIR)?
            .join(format!("{system}-{station}.redb")),
    };
    // The ground router may come up after the station: wait for it.
    let session = loop {
        match z.open() {
            Ok(s) => break s,
            Err(e) => {
                tracing::warn!("no Zenoh yet ({e}); trying again in 1 s");
                std::thread::sleep(Duration::from_secs(1));
            }
        }
    };
    let st = Arc::new(Station::start(
        session,
        StationOptions::new(&system, &station, &db),
    )?);
    let record = if no_record {
        None
    } else {
        // Beside the outbox by default: a station's state in one place.
        let dir = match record {
            Some(d) => d,
            None => db
                .parent()
                .unwrap_or(std::path::Path::new("."))
                .join(format!("{system}-{station}-record")),
        };
        let budget_bytes_per_s = downlink_budget
            .as_deref()
            .map(|b| crate::linksim::parse_rate(b).map(|r| r as u64))
            .transpose()
            .context("--downlink-budget")?;
        // The backfill keeps out of the commands' way: it slows down when their round trips
        // grow.
        let link = {
            let st = st.clone();
            dnm_downlink::LinkProbe::new(move || {
                let l = st.link();
                dnm_downlink::LinkSample {
                    uplinks: l.uplinks,
                    answered: l.answered,
                    rtt: l.rtt_ms.map(|ms| Duration::from_secs_f64(ms / 1e3)),
                }
            })
        };
        let options = dnm_downlink::GroundRecordOptions {
            dir: dir.clone(),
            budget_bytes_per_s,
            link: Some(link),
        };
        let r = dnm_downlink::GroundRecord::start(st.session(), &system, &options)?;
        println!("the rover's downlink is recorded in {}", dir.display());
        Some(r)
    };
    let status: Option<dnm_ground::http::DownlinkStatus> = record.as_ref().map(|r| {
        let source = r.status_source();
        Arc::new(move || serde_json::to_value(source.status()).unwrap_or_default())
            as dnm_ground::http::DownlinkStatus
    });
    let api = dnm_ground::http::Api::serve_with_record(st.clone(), http, token, status)
        .map_err(anyhow::Error::msg)?;
    println!(
        "ground station `{station}` of `{system}`: outbox {}, API http://{}; Ctrl-C to stop",
        db.display(),
        api.addr()
    );
    let monitor = match monitor {
        Some(m) => {
            let mut args = crate::monitor_cmd::zenoh_flags(z);
            args.extend(["--system".into(), system.clone()]);
            if m == "spawn" {
                args.push("--spawn".into());
            } else if m.contains("://") {
                args.extend(["--viewer".into(), m]);
            } else {
                args.extend(["--save".into(), m]);
            }
            Some(crate::monitor_cmd::start(&args)?)
        }
        None => None,
    };
    wait_for_signal();
    if let Some(m) = monitor {
        crate::monitor_cmd::stop(m);
    }
    drop(api);
    // Its file finished and the session's manifest written.
    drop(record);
    Ok(ExitCode::SUCCESS)
}

pub fn run(z: &dnm::ZenohOptions, cmd: GroundCmd) -> anyhow::Result<ExitCode> {
    match cmd {
        GroundCmd::Serve(args) => serve(z, args),
        GroundCmd::Switch {
            task,
            at,
            late_by,
            common,
        } => {
            let late_by_ms = late_by
                .as_deref()
                .map(|l| {
                    dnm_netlist::parse_duration_ms(l)
                        .with_context(|| format!("--late-by `{l}`: write e.g. `5s` or `2m`"))
                })
                .transpose()?;
            let offset = match &at {
                Some(a) if a.starts_with('+') => {
                    let link: LinkStatus =
                        serde_json::from_str(&get(&format!("{}/link", url(&common.url)))?)?;
                    link.rover_clock_offset_ms.unwrap_or(0.0)
                }
                _ => 0.0,
            };
            let at_unix_ns = at.as_deref().map(|a| parse_at(a, offset)).transpose()?;
            submit(
                &Order::Switch {
                    task,
                    at_unix_ns,
                    late_by_ms,
                },
                &common,
            )
        }
        GroundCmd::Apply { netlist, common } => {
            let text = std::fs::read_to_string(&netlist)
                .with_context(|| format!("reading {}", netlist.display()))?;
            // Refused here already if it does not validate on this machine.
            dnm::parse_netlist(&netlist, &text)?;
            let order = Order::Apply {
                file: netlist.display().to_string(),
                text,
            };
            submit(&order, &common)
        }
        GroundCmd::Replace {
            name,
            kind,
            params,
            common,
        } => {
            let edit = ModuleEdit::Replace { name, kind, params };
            submit(&Order::Module { edit }, &common)
        }
        GroundCmd::Remove { name, common } => submit(
            &Order::Module {
                edit: ModuleEdit::Remove { name },
            },
            &common,
        ),
        GroundCmd::Cancel { seq, common } => submit(&Order::Cancel { seq }, &common),
        GroundCmd::Sequence(cmd) => sequence_cmd(cmd),
        GroundCmd::Status { url: u, json } => {
            let base = url(&u);
            let link: LinkStatus = serde_json::from_str(&get(&format!("{base}/link"))?)?;
            let entries: Vec<Entry> = serde_json::from_str(&get(&format!("{base}/commands"))?)?;
            // A station without a record of the rover answers 404: nothing to show.
            let record: Option<dnm_downlink::RecordStatus> = get(&format!("{base}/downlink"))
                .ok()
                .and_then(|b| serde_json::from_str(&b).ok());
            if json {
                println!(
                    "{}",
                    serde_json::to_string_pretty(
                        &serde_json::json!({ "link": link, "commands": entries, "record": record })
                    )?
                );
            } else {
                print_link(&link);
                if let Some(r) = &record {
                    print_record(r);
                }
                for e in entries.iter().rev().take(20).rev() {
                    println!("{}", describe(e));
                }
            }
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// `dnm ground sequence ...`: the order queued at the station.
fn sequence_cmd(cmd: SequenceCmd) -> anyhow::Result<ExitCode> {
    let (order, common) = match cmd {
        SequenceCmd::Upload {
            file,
            check,
            common,
        } => (sequence_upload(&file, check.as_deref())?, common),
        SequenceCmd::Start { name, common } => (sequence(name, SequenceAction::Start), common),
        SequenceCmd::Pause { name, common } => (sequence(name, SequenceAction::Pause), common),
        SequenceCmd::Resume { name, common } => (sequence(name, SequenceAction::Resume), common),
        SequenceCmd::Cancel { name, common } => (sequence(name, SequenceAction::Cancel), common),
    };
    submit(&order, &common)
}

/// The upload of the sequence in `file`, with the netlists its `apply` steps name (read
/// beside it); checked against `check` first if given.
fn sequence_upload(
    file: &std::path::Path,
    check: Option<&std::path::Path>,
) -> anyhow::Result<Order> {
    let text = std::fs::read_to_string(file)
        .with_context(|| format!("reading the sequence {}", file.display()))?;
    if let Some(n) = check {
        let netlist = dnm::load_netlist(n)?;
        dnm_netlist::Sequence::parse(file, &text, &netlist)?;
    }
    let raw: toml::Value = toml::from_str(&text).with_context(|| {
        format!(
            "{} is not TOML (`dnm check NETLIST --sequence FILE` says where)",
            file.display()
        )
    })?;
    let name = raw
        .get("sequence")
        .and_then(|s| s.get("name"))
        .and_then(|n| n.as_str())
        .with_context(|| format!("{}: no `[sequence] name = \"...\"`", file.display()))?
        .to_string();
    let mut netlists = std::collections::BTreeMap::new();
    let steps = raw
        .get("step")
        .and_then(|s| s.as_array())
        .cloned()
        .unwrap_or_default();
    for f in steps.iter().filter_map(|s| s.get("apply")?.as_str()) {
        let path = file.parent().unwrap_or(std::path::Path::new(".")).join(f);
        let t = std::fs::read_to_string(&path).with_context(|| {
            format!(
                "{}: a step applies {f}, read as {}",
                file.display(),
                path.display()
            )
        })?;
        netlists.insert(f.to_string(), t);
    }
    Ok(Order::Sequence {
        name,
        action: SequenceAction::Upload {
            file: file.display().to_string(),
            text,
            netlists,
        },
    })
}

fn sequence(name: String, action: SequenceAction) -> Order {
    Order::Sequence { name, action }
}

/// Blocks until SIGINT or SIGTERM.
pub fn wait_for_signal() {
    static STOP: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    extern "C" fn on_signal(_: libc::c_int) {
        STOP.store(true, std::sync::atomic::Ordering::Relaxed);
    }
    // SAFETY: the handler only stores into an atomic, which is async-signal-safe.
    unsafe {
        libc::signal(libc::SIGINT, on_signal as *const () as libc::sighandler_t);
        libc::signal(libc::SIGTERM, on_signal as *const () as libc::sighandler_t);
    }
    while !STOP.load(std::sync::atomic::Ordering::Relaxed) {
        std::thread::sleep(Duration::from_millis(200));
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    /// A time tag far beyond any time the rover keeps is refused, never wrapped to an early one.
    #[test]
    fn absurd_time_tags_are_refused_not_wrapped() {
        let e = parse_at("+100000000h", 0.0).unwrap_err();
        assert!(e.to_string().contains("beyond any time"), "{e}");
        assert!(parse_at("99999999999999", 0.0).is_err());
        assert!(parse_at("-5", 0.0).is_err());
        let soon = parse_at("+30s", 0.0).unwrap();
        let now = dnm_ground::now_unix_ns();
        assert!(soon > now && soon < now + 31_000_000_000);
    }
}
