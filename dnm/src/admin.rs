//! Operating a running system: a Unix socket per system on this machine that takes one JSON
//! request per line and answers one JSON response per line, and the host that runs a
//! machine's DNMs behind it.
//!
//! ```text
//! $ echo '{"cmd":"switch","task":"auto"}' | socat - UNIX-CONNECT:/tmp/dnm-run/beetle.sock
//! ```

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::mpsc::{self, Receiver, SyncSender};
use std::thread::JoinHandle;
use std::time::Duration;

use dnm_module::protocol::{DNM_EVENT, dnm_config, dnm_prefix};
use dnm_netlist::Netlist;
use iceoryx2::prelude::*;
use serde::{Deserialize, Serialize};

use crate::{Command, Dnm, DnmOptions, DnmReport, SwitchRecord};

/// A request to a running system.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(tag = "cmd", rename_all = "snake_case")]
pub enum Request {
    /// Every hosted DNM's report.
    Status,
    /// The netlist text in force.
    Netlist,
    /// Switch every hosted DNM to `task`.
    Switch { task: String },
    /// Validate and apply a new netlist; `file` names it in errors.
    Apply { file: String, text: String },
}

/// The answer to a [`Request`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct Response {
    pub ok: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub revision: Option<u64>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub switches: Vec<SwitchRecord>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub dnms: Vec<DnmReport>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub netlist: Option<String>,
}

impl Response {
    pub fn error(msg: impl Into<String>) -> Self {
        Self {
            ok: false,
            error: Some(msg.into()),
            ..Self::default()
        }
    }
}

/// Failure to reach a running system.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    #[error(
        "no running system `{system}` on this machine ({path}: {reason}); start it with `dnm up NETLIST`"
    )]
    NotRunning {
        system: String,
        path: String,
        reason: std::io::Error,
    },
    #[error("talking to system `{system}`: {source}")]
    Io {
        system: String,
        source: std::io::Error,
    },
    #[error("system `{system}` answered something unreadable: {source}")]
    Protocol {
        system: String,
        source: serde_json::Error,
    },
}

/// Folder of the admin sockets: `$DNM_RUN_DIR`, else `/tmp/dnm-run`.
pub fn run_dir() -> PathBuf {
    std::env::var_os("DNM_RUN_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| std::env::temp_dir().join("dnm-run"))
}

/// Admin socket of the process hosting `dnms` of `system`: one per process, so several
/// processes of one system can run on a machine.
pub fn socket_path(system: &str, dnms: &[String]) -> PathBuf {
    run_dir()
        .join(system)
        .join(format!("{}.sock", dnms.join("+")))
}

/// Sends one request to every process of the system on this machine and merges the answers.
pub fn request(system: &str, req: &Request) -> Result<Response, AdminError> {
    let dir = run_dir().join(system);
    let not_running = |reason| AdminError::NotRunning {
        system: system.into(),
        path: dir.display().to_string(),
        reason,
    };
    let mut sockets: Vec<PathBuf> = std::fs::read_dir(&dir)
        .map_err(not_running)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "sock"))
        .collect();
    sockets.sort();
    let mut answers = Vec::new();
    let mut last_refusal = None;
    for path in &sockets {
        match request_one(system, path, req) {
            Ok(r) => answers.push(r),
            // A socket left behind by a process that was killed.
            Err(AdminError::NotRunning { reason, .. }) => last_refusal = Some(reason),
            Err(e) => return Err(e),
        }
    }
    if answers.is_empty() {
        return Err(not_running(last_refusal.unwrap_or_else(|| {
            std::io::Error::new(std::io::ErrorKind::NotFound, "no admin socket")
        })));
    }
    Ok(merge(answers))
}

/// One answer from several processes: all must agree to be ok.
pub fn merge(answers: Vec<Response>) -> Response {
    let mut out = Response {
        ok: true,
        ..Response::default()
    };
    let mut errors = Vec::new();
    for r in answers {
        if !r.ok {
            out.ok = false;
            errors.extend(r.error);
        }
        out.revision = out.revision.max(r.revision);
        out.switches.extend(r.switches);
        out.dnms.extend(r.dnms);
        if out.netlist.is_none() {
            out.netlist = r.netlist;
        }
    }
    if !errors.is_empty() {
        out.error = Some(errors.join("\n"));
    }
    out.dnms.sort_by(|a, b| a.dnm.cmp(&b.dnm));
    out
}

fn request_one(system: &str, path: &Path, req: &Request) -> Result<Response, AdminError> {
    let mut stream = UnixStream::connect(path).map_err(|reason| AdminError::NotRunning {
        system: system.into(),
        path: path.display().to_string(),
        reason,
    })?;
    let io = |source| AdminError::Io {
        system: system.into(),
        source,
    };
    let mut line = serde_json::to_string(req).map_err(|source| AdminError::Protocol {
        system: system.into(),
        source,
    })?;
    line.push('\n');
    stream.write_all(line.as_bytes()).map_err(io)?;
    let mut answer = String::new();
    BufReader::new(stream).read_line(&mut answer).map_err(io)?;
    serde_json::from_str(&answer).map_err(|source| AdminError::Protocol {
        system: system.into(),
        source,
    })
}

struct DnmHandle {
    name: String,
    commands: SyncSender<Command>,
    thread: JoinHandle<()>,
}

/// Runs the given DNMs of a netlist in this process, one thread each, each in its own
/// shared-memory namespace, with the system's admin socket. Returns when all DNMs stopped
/// (SIGINT/SIGTERM).
pub fn run_host(
    netlist: Netlist,
    dnms: &[String],
    options: DnmOptions,
    zenoh: zenoh::Config,
) -> anyhow::Result<()> {
    Host::start(netlist, dnms, options, zenoh)?.wait();
    Ok(())
}

/// A machine's DNMs running in this process (see [`run_host`]), for programs that drive them
/// from the same process, such as `dnm demo`.
pub struct Host {
    session: zenoh::Session,
    system: String,
    handles: Vec<DnmHandle>,
    socket: PathBuf,
}

impl std::fmt::Debug for Host {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Host")
            .field("system", &self.system)
            .field("socket", &self.socket)
            .finish_non_exhaustive()
    }
}

impl Host {
    /// The process's Zenoh session (the DNMs' own): queries and commands sent on it reach the
    /// hosted DNMs and every other DNM of the system.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    pub fn system(&self) -> &str {
        &self.system
    }

    /// Waits until the DNMs stop (SIGINT/SIGTERM or [`Host::stop`]).
    pub fn wait(self) {
        for h in self.handles {
            let _ = h.thread.join();
        }
        let _ = std::fs::remove_file(&self.socket);
    }

    /// Stops every DNM of the process (their modules first) and waits for them.
    pub fn stop(self) {
        crate::dnm::request_stop();
        self.wait();
    }

    /// Starts DNMs `dnms` of `netlist` in this process, one thread each, with the admin socket.
    pub fn start(
        netlist: Netlist,
        dnms: &[String],
        options: DnmOptions,
        zenoh: zenoh::Config,
    ) -> anyhow::Result<Host> {
        start(netlist, dnms, options, zenoh)
    }
}

fn start(
    netlist: Netlist,
    dnms: &[String],
    options: DnmOptions,
    zenoh: zenoh::Config,
) -> anyhow::Result<Host> {
    use anyhow::Context;
    use zenoh::Wait;
    let session = zenoh::open(zenoh)
        .wait()
        .map_err(|e| anyhow::anyhow!("opening the Zenoh session: {e}"))?;
    tracing::info!(zid = %session.zid(), "on Zenoh");
    // Joining a running system: continue from the netlist, revision and task in force there.
    let mut netlist = netlist;
    let mut joined = None;
    if let Some(state) = crate::net::newest_netlist(&session, &netlist.system, JOIN_TIMEOUT) {
        if let Some((newer, revision, task)) = adopt(&state, &netlist.file, dnms) {
            tracing::info!(revision, task = ?task, "joining the running system");
            netlist = newer;
            joined = Some((revision, task));
        }
    }
    let mut handles = Vec::new();
    for name in dnms {
        let (tx, rx) = mpsc::sync_channel::<Command>(16);
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<(), String>>(1);
        let netlist = netlist.clone();
        let options = options.clone();
        let dnm_name = name.clone();
        let session = session.clone();
        let joined = joined.clone();
        let thread = std::thread::Builder::new()
            .name(format!("dnm-{name}"))
            .spawn(move || {
                let joined = joined.as_ref().map(|(r, t)| (*r, t.as_deref()));
                run_dnm(
                    &netlist, &dnm_name, options, session, joined, &rx, &ready_tx,
                )
            })
            .context("spawning DNM thread")?;
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                drop(tx);
                for h in handles {
                    let h: DnmHandle = h;
                    drop(h.commands);
                    let _ = h.thread.join();
                }
                let _ = thread.join();
                anyhow::bail!("DNM `{name}` did not start: {e}");
            }
            Err(_) => anyhow::bail!("DNM `{name}` stopped while starting"),
        }
        handles.push(DnmHandle {
            name: name.clone(),
            commands: tx,
            thread,
        });
    }

    let path = socket_path(&netlist.system, dnms);
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).context("creating the admin socket folder")?;
    }
    if UnixStream::connect(&path).is_ok() {
        anyhow::bail!(
            "DNMs {} of system `{}` are already running on this machine ({})",
            dnms.join(", "),
            netlist.system,
            path.display()
        );
    }
    let _ = std::fs::remove_file(&path);
    let listener =
        UnixListener::bind(&path).with_context(|| format!("binding {}", path.display()))?;
    tracing::info!(socket = %path.display(), "admin socket ready");

    let senders: Vec<(String, SyncSender<Command>)> = handles
        .iter()
        .map(|h| (h.name.clone(), h.commands.clone()))
        .collect();
    let system = netlist.system.clone();
    let hosted: Vec<String> = dnms.to_vec();
    std::thread::Builder::new()
        .name("dnm-admin".into())
        .spawn(move || serve(&listener, &system, &hosted, &senders))
        .context("spawning admin thread")?;
    Ok(Host {
        session,
        system: netlist.system.clone(),
        handles,
        socket: path,
    })
}

fn run_dnm(
    netlist: &Netlist,
    name: &str,
    options: DnmOptions,
    session: zenoh::Session,
    joined: Option<(u64, Option<&str>)>,
    commands: &Receiver<Command>,
    ready: &SyncSender<Result<(), String>>,
) {
    let started = (|| {
        let mut dnm = Dnm::new(&netlist.system, name, options)?;
        let events = dnm.status_listener()?;
        // A DNM joining a running system continues from the netlist and task in force there.
        dnm.attach_zenoh(session)?;
        if let Some((revision, task)) = joined {
            dnm.continue_from(revision.saturating_sub(1), task);
        }
        dnm.apply(netlist, &events)?;
        Ok::<_, crate::DnmError>((dnm, events))
    })();
    let (mut dnm, events) = match started {
        Ok(x) => x,
        Err(e) => {
            let _ = ready.send(Err(e.to_string()));
            return;
        }
    };
    let _ = ready.send(Ok(()));
    if let Err(e) = dnm.run(commands, &events) {
        tracing::error!(dnm = name, "DNM loop failed: {e}");
    }
    dnm.shutdown();
}

/// How long a starting DNM asks the running ones for the netlist in force.
const JOIN_TIMEOUT: Duration = Duration::from_secs(1);

/// The netlist, revision and task joining DNMs take over, if the running system's netlist is
/// valid here and still has all of them.
fn adopt(
    state: &crate::net::NetlistState,
    local_file: &Path,
    dnms: &[String],
) -> Option<(Netlist, u64, Option<String>)> {
    let text = state.text.as_ref()?;
    // Relative `exec` paths resolve against this machine's netlist file, not the sender's.
    match crate::parse_netlist(local_file, text) {
        Ok(n) if dnms.iter().all(|d| n.dnm(d).is_some()) => {
            Some((n, state.revision, state.active_task.clone()))
        }
        Ok(_) => None,
        Err(e) => {
            tracing::warn!("the running system's netlist does not validate here: {e}");
            None
        }
    }
}

/// Wakes the loop of each DNM after a command is queued.
struct Wakers {
    _nodes: Vec<Node<ipc::Service>>,
    notifiers: Vec<iceoryx2::port::notifier::Notifier<ipc::Service>>,
}

impl Wakers {
    fn new(system: &str, dnms: &[String]) -> anyhow::Result<Self> {
        let mut nodes = Vec::new();
        let mut notifiers = Vec::new();
        for d in dnms {
            let config = dnm_config(&dnm_prefix(system, d)).map_err(anyhow::Error::msg)?;
            let node = NodeBuilder::new()
                .config(&config)
                .create::<ipc::Service>()
                .map_err(|e| anyhow::anyhow!("admin node: {e:?}"))?;
            let notifier = dnm_module::event_service(&node, DNM_EVENT)?
                .notifier_builder()
                .create()
                .map_err(|e| anyhow::anyhow!("admin notifier: {e:?}"))?;
            nodes.push(node);
            notifiers.push(notifier);
        }
        Ok(Self {
            _nodes: nodes,
            notifiers,
        })
    }
}

fn serve(
    listener: &UnixListener,
    system: &str,
    hosted: &[String],
    dnms: &[(String, SyncSender<Command>)],
) {
    let wakers = match Wakers::new(system, hosted) {
        Ok(w) => w,
        Err(e) => {
            tracing::error!("admin socket disabled: {e}");
            return;
        }
    };
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
        let mut reader = BufReader::new(&stream);
        let mut line = String::new();
        if reader.read_line(&mut line).is_err() {
            continue;
        }
        let response = match serde_json::from_str::<Request>(&line) {
            Ok(req) => dispatch(req, system, dnms, &wakers),
            Err(e) => Response::error(format!(
                "bad request `{}`: {e}; send e.g. {{\"cmd\":\"status\"}}",
                line.trim()
            )),
        };
        let mut out = serde_json::to_string(&response).unwrap_or_else(|e| {
            format!("{{\"ok\":false,\"error\":\"cannot encode response: {e}\"}}")
        });
        out.push('\n');
        let _ = (&stream).write_all(out.as_bytes());
    }
}

/// Sends a command to every hosted DNM and collects the answers.
fn fan_out<T>(
    dnms: &[(String, SyncSender<Command>)],
    wakers: &Wakers,
    make: impl Fn(SyncSender<T>) -> Command,
) -> Result<Vec<(String, T)>, String> {
    let mut waiting = Vec::new();
    for ((name, tx), waker) in dnms.iter().zip(&wakers.notifiers) {
        let (rtx, rrx) = mpsc::sync_channel(1);
        tx.send(make(rtx))
            .map_err(|_| format!("DNM `{name}` has stopped"))?;
        let _ = waker.notify();
        waiting.push((name.clone(), rrx));
    }
    waiting
        .into_iter()
        .map(|(name, rx)| {
            rx.recv_timeout(Duration::from_secs(30))
                .map(|v| (name.clone(), v))
                .map_err(|_| format!("DNM `{name}` did not answer"))
        })
        .collect()
}

fn dispatch(
    req: Request,
    system: &str,
    dnms: &[(String, SyncSender<Command>)],
    wakers: &Wakers,
) -> Response {
    match req {
        Request::Status => match fan_out(dnms, wakers, Command::Status) {
            Ok(reports) => Response {
                ok: true,
                dnms: reports.into_iter().map(|(_, r)| r).collect(),
                ..Response::default()
            },
            Err(e) => Response::error(e),
        },
        // The DNMs hold the netlist in force (it may have been applied over Zenoh).
        Request::Netlist => match fan_out(dnms, wakers, Command::Netlist) {
            Ok(states) => {
                let newest = states
                    .into_iter()
                    .map(|(_, s)| s)
                    .max_by_key(|s| s.revision);
                Response {
                    ok: true,
                    revision: newest.as_ref().map(|s| s.revision),
                    netlist: newest.and_then(|s| s.text),
                    ..Response::default()
                }
            }
            Err(e) => Response::error(e),
        },
        Request::Switch { task } => {
            match fan_out(dnms, wakers, |r| Command::Switch(task.clone(), r)) {
                Ok(results) => {
                    let mut switches = Vec::new();
                    for (name, r) in results {
                        match r {
                            Ok(s) => switches.push(s),
                            Err(e) => return Response::error(format!("DNM `{name}`: {e}")),
                        }
                    }
                    Response {
                        ok: true,
                        revision: switches.first().map(|s| s.revision),
                        switches,
                        ..Response::default()
                    }
                }
                Err(e) => Response::error(e),
            }
        }
        Request::Apply { file, text } => {
            let new = match crate::parse_netlist(Path::new(&file), &text) {
                Ok(n) => n,
                Err(e) => {
                    return Response::error(format!("netlist refused, nothing changed:\n{e}"));
                }
            };
            if new.system != system {
                return Response::error(format!(
                    "netlist is for system `{}`, this is `{}`; nothing changed",
                    new.system, system
                ));
            }
            if let Some((missing, _)) = dnms.iter().find(|(d, _)| new.dnm(d).is_none()) {
                return Response::error(format!(
                    "netlist drops DNM `{missing}`, which runs here; nothing changed"
                ));
            }
            let boxed = Box::new(new.clone());
            match fan_out(dnms, wakers, |r| Command::Apply(boxed.clone(), r)) {
                Ok(results) => {
                    let mut revision = None;
                    for (name, r) in results {
                        match r {
                            Ok(rev) => revision = Some(rev),
                            Err(e) => return Response::error(format!("DNM `{name}`: {e}")),
                        }
                    }
                    Response {
                        ok: true,
                        revision,
                        ..Response::default()
                    }
                }
                Err(e) => Response::error(e),
            }
        }
    }
}
