//! Operating a running system: a Unix socket per system on this machine that takes one JSON
//! request per line and answers one JSON response per line, and the host that runs a
//! machine's DNMs behind it.
//!
//! ```text
//! $ echo '{"cmd":"status"}' | socat - UNIX-CONNECT:/tmp/dnm-run-0/beetle/rover+drive+vision+ground.sock
//! ```

use std::io::{BufRead, BufReader, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::{self, SyncSender};
use std::thread::JoinHandle;
use std::time::Duration;

use dnm_core::{Command, Commander, Dnm, Reply};
use dnm_netlist::Netlist;

pub use dnm_proto::{Request, Response, merge};

use crate::HostOptions;

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

/// Folder of the admin sockets: `$DNM_RUN_DIR`, else `$XDG_RUNTIME_DIR/dnm`, else
/// `/tmp/dnm-run-<uid>` (one per user).
pub fn run_dir() -> PathBuf {
    if let Some(d) = std::env::var_os("DNM_RUN_DIR") {
        return d.into();
    }
    if let Some(d) = std::env::var_os("XDG_RUNTIME_DIR") {
        return PathBuf::from(d).join("dnm");
    }
    // SAFETY: getuid(2) cannot fail and has no preconditions.
    let uid = unsafe { libc::getuid() };
    std::env::temp_dir().join(format!("dnm-run-{uid}"))
}

/// Creates `dir` (and its parents) for this user only, or checks an existing one: it must be
/// this user's and is made private. Anyone else's folder is refused: its owner could put a
/// socket of their own where `dnm` commands look for the system.
pub fn private_dir(dir: &Path) -> anyhow::Result<()> {
    use std::os::unix::fs::{DirBuilderExt, MetadataExt, PermissionsExt};
    std::fs::DirBuilder::new()
        .recursive(true)
        .mode(0o700)
        .create(dir)
        .map_err(|e| anyhow::anyhow!("creating {}: {e}", dir.display()))?;
    // SAFETY: getuid(2) cannot fail and has no preconditions.
    let uid = unsafe { libc::getuid() };
    for d in [
        dir.parent().filter(|p| *p != std::env::temp_dir()),
        Some(dir),
    ]
    .into_iter()
    .flatten()
    {
        let meta = std::fs::symlink_metadata(d)
            .map_err(|e| anyhow::anyhow!("reading {}: {e}", d.display()))?;
        if !meta.is_dir() || meta.uid() != uid {
            anyhow::bail!(
                "{} belongs to user {} (or is not a folder), not to this user ({uid}): refusing \
                 to put the admin socket there; remove it or set DNM_RUN_DIR",
                d.display(),
                meta.uid()
            );
        }
        if meta.mode() & 0o077 != 0 {
            std::fs::set_permissions(d, std::fs::Permissions::from_mode(0o700))
                .map_err(|e| anyhow::anyhow!("making {} private: {e}", d.display()))?;
        }
    }
    Ok(())
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
    commander: Commander,
    thread: JoinHandle<()>,
}

/// Runs the given DNMs of a netlist in this process, one thread each, each in its own
/// shared-memory namespace, with the system's admin socket. Returns when all DNMs stopped
/// (SIGINT/SIGTERM).
pub fn run_host(
    netlist: Netlist,
    dnms: &[String],
    options: HostOptions,
    zenoh: zenoh::Config,
) -> anyhow::Result<()> {
    Host::start(netlist, dnms, options, zenoh)?.wait();
    Ok(())
}

/// A machine's DNMs running in this process (see [`run_host`]), for programs that drive them
/// from the same process, such as `dnm demo`.
pub struct Host {
    authority: Option<dnm_authority::Authority>,
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
        if let Some(a) = self.authority {
            // Until the DNMs stop; the authority stops with them.
            let handles = self.handles;
            for h in handles {
                let _ = h.thread.join();
            }
            a.stop();
            let _ = std::fs::remove_file(&self.socket);
            return;
        }
        for h in self.handles {
            let _ = h.thread.join();
        }
        let _ = std::fs::remove_file(&self.socket);
    }

    /// Stops every DNM of the process (their modules first) and waits for them.
    pub fn stop(self) {
        dnm_core::request_stop();
        self.wait();
    }

    /// Starts DNMs `dnms` of `netlist` in this process, one thread each, with the admin socket.
    pub fn start(
        netlist: Netlist,
        dnms: &[String],
        options: HostOptions,
        zenoh: zenoh::Config,
    ) -> anyhow::Result<Host> {
        start(netlist, dnms, options, zenoh)
    }
}

fn start(
    netlist: Netlist,
    dnms: &[String],
    options: HostOptions,
    zenoh: zenoh::Config,
) -> anyhow::Result<Host> {
    use anyhow::Context;
    use zenoh::Wait;
    if !dnm_core::clear_stop_if_idle() {
        anyhow::bail!(
            "DNMs of this process are still stopping; wait for them before starting again"
        );
    }
    let session = zenoh::open(zenoh)
        .wait()
        .map_err(|e| anyhow::anyhow!("opening the Zenoh session: {e}"))?;
    tracing::info!(zid = %session.zid(), "on Zenoh");
    // Joining a running system: continue from the netlist, revision and task in force there.
    // A system with an authority needs none of it: its DNMs start empty and the authority has
    // them adopt what it decided.
    let follow = crate::commanded_by_authority(&netlist);
    let mut netlist = netlist;
    let mut joined = None;
    if follow {
        tracing::info!(authority = ?netlist.authority(), "the DNMs take what the authority decides");
    } else if let Some(state) = dnm_zenoh::newest_netlist(&session, &netlist.system, JOIN_TIMEOUT)
        && let Some((newer, revision, task)) = adopt(&state, &netlist.file, dnms)
    {
        tracing::info!(revision, task = ?task, "joining the running system");
        netlist = newer;
        joined = Some((revision, task));
    }
    let mut handles = Vec::new();
    for name in dnms {
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<Commander, String>>(1);
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
                    &netlist, &dnm_name, options, session, joined, follow, &ready_tx,
                )
            })
            .context("spawning DNM thread")?;
        let commander = match ready_rx.recv() {
            Ok(Ok(c)) => c,
            Ok(Err(e)) => {
                // The DNMs already started end their loops (their bridges hold commanders too).
                dnm_core::request_stop();
                for h in handles {
                    let h: DnmHandle = h;
                    drop(h.commander);
                    let _ = h.thread.join();
                }
                let _ = thread.join();
                anyhow::bail!("DNM `{name}` did not start: {e}");
            }
            Err(_) => {
                dnm_core::request_stop();
                anyhow::bail!("DNM `{name}` stopped while starting")
            }
        };
        handles.push(DnmHandle { commander, thread });
    }

    let path = socket_path(&netlist.system, dnms);
    if let Some(dir) = path.parent() {
        private_dir(dir).context("the admin socket folder")?;
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

    let authority = match netlist
        .authority()
        .filter(|a| follow && dnms.iter().any(|d| d == a))
    {
        None => None,
        Some(_) => {
            let Some(dir) = options.state_dir.as_ref() else {
                dnm_core::request_stop();
                for h in handles {
                    drop(h.commander);
                    let _ = h.thread.join();
                }
                anyhow::bail!("the authority did not start: {}", crate::NO_STATE_DIR);
            };
            let db = dir.join(format!("{}-authority.redb", netlist.system));
            let parse: dnm_authority::ParseNetlist = Arc::new(crate::parse_remote_netlist_text);
            let a = dnm_authority::Authority::start(
                session.clone(),
                &netlist,
                parse,
                dnm_authority::AuthorityOptions::new(db),
            );
            match a {
                Ok(a) => Some(a),
                Err(e) => {
                    dnm_core::request_stop();
                    for h in handles {
                        drop(h.commander);
                        let _ = h.thread.join();
                    }
                    anyhow::bail!("the authority did not start: {e}");
                }
            }
        }
    };
    let commanders: Vec<Commander> = handles.iter().map(|h| h.commander.clone()).collect();
    let system = netlist.system.clone();
    let follows = follow
        .then(|| netlist.authority().map(str::to_string))
        .flatten();
    std::thread::Builder::new()
        .name("dnm-admin".into())
        .spawn(move || serve(&listener, &system, follows.as_deref(), &commanders))
        .context("spawning admin thread")?;
    Ok(Host {
        authority,
        session,
        system: netlist.system.clone(),
        handles,
        socket: path,
    })
}

fn run_dnm(
    netlist: &Netlist,
    name: &str,
    options: HostOptions,
    session: zenoh::Session,
    joined: Option<(u64, Option<&str>)>,
    follow: bool,
    ready: &SyncSender<Result<Commander, String>>,
) {
    let started = (|| {
        let mut dnm = Dnm::new(&netlist.system, name, options.dnm)?;
        let parse: dnm_zenoh::ParseNetlist = Arc::new(crate::parse_remote_netlist_text);
        let bridge = dnm_zenoh::Bridge::new(
            session,
            &netlist.system,
            name,
            dnm.prefix(),
            dnm.commander()?,
            parse,
        )
        .map_err(dnm_core::DnmError::Refused)?;
        let bridge = match netlist.authority().filter(|_| follow) {
            Some(a) => bridge
                .follow_authority(a)
                .map_err(dnm_core::DnmError::Refused)?,
            None => bridge,
        };
        dnm.add_plugin(Box::new(bridge));
        if let Some(r) = options.record {
            let recorder = crate::record::Recorder::start(name, dnm.prefix(), r)
                .map_err(dnm_core::DnmError::Refused)?;
            dnm.add_plugin(Box::new(recorder));
        }
        // A DNM joining a running system continues from the netlist and task in force there.
        if let Some((revision, task)) = joined {
            dnm.continue_from(revision.saturating_sub(1), task);
        }
        if !follow {
            dnm.apply(netlist)?;
        }
        let commander = dnm.commander()?;
        Ok::<_, dnm_core::DnmError>((dnm, commander))
    })();
    let mut dnm = match started {
        Ok((dnm, commander)) => {
            let _ = ready.send(Ok(commander));
            dnm
        }
        Err(e) => {
            let _ = ready.send(Err(e.to_string()));
            return;
        }
    };
    if let Err(e) = dnm.run() {
        tracing::error!(dnm = name, "DNM loop failed: {e}");
    }
    dnm.shutdown();
}

/// How long a starting DNM asks the running ones for the netlist in force.
const JOIN_TIMEOUT: Duration = Duration::from_secs(1);

/// The netlist, revision and task joining DNMs take over, if the running system's netlist is
/// valid here and still has all of them.
fn adopt(
    state: &dnm_proto::NetlistState,
    local_file: &Path,
    dnms: &[String],
) -> Option<(Netlist, u64, Option<String>)> {
    let text = state.text.as_ref()?;
    // It came over the network: external kinds only from this computer's module folder.
    match crate::parse_remote_netlist_text(local_file, text) {
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

/// Connections the admin socket serves at once; more are refused as busy.
const ADMIN_CONNECTIONS: usize = 16;

/// Serves each connection on its own thread, so a long apply never holds up a switch.
fn serve(listener: &UnixListener, system: &str, authority: Option<&str>, dnms: &[Commander]) {
    let busy = Arc::new(std::sync::atomic::AtomicUsize::new(0));
    for stream in listener.incoming() {
        let Ok(stream) = stream else { continue };
        let taken = busy
            .fetch_update(
                std::sync::atomic::Ordering::AcqRel,
                std::sync::atomic::Ordering::Acquire,
                |n| (n < ADMIN_CONNECTIONS).then_some(n + 1),
            )
            .is_ok();
        if !taken {
            let refused = Response::error(format!(
                "the admin socket is serving {ADMIN_CONNECTIONS} requests; try again"
            ));
            answer(&stream, &refused);
            continue;
        }
        let (system, dnms, slot) = (system.to_string(), dnms.to_vec(), busy.clone());
        let authority = authority.map(str::to_string);
        let spawned = std::thread::Builder::new()
            .name("dnm-admin-conn".into())
            .spawn(move || {
                serve_one(&stream, &system, authority.as_deref(), &dnms);
                slot.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
            });
        if let Err(e) = spawned {
            busy.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
            tracing::warn!("admin connection dropped: {e}");
        }
    }
}

fn serve_one(stream: &UnixStream, system: &str, authority: Option<&str>, dnms: &[Commander]) {
    let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
    let mut reader = BufReader::new(stream);
    let mut line = String::new();
    if reader.read_line(&mut line).is_err() {
        return;
    }
    let response = match serde_json::from_str::<Request>(&line) {
        Ok(Request::Switch { .. } | Request::Apply { .. }) if authority.is_some() => {
            Response::error(format!(
                "system `{system}` is commanded through its authority, DNM `{}`: send switches \
                 and applies through a ground station (`dnm ground switch TASK`)",
                authority.unwrap_or_default()
            ))
        }
        Ok(req) => dispatch(req, system, dnms),
        Err(e) => Response::error(format!(
            "bad request `{}`: {e}; send e.g. {{\"cmd\":\"status\"}}",
            line.trim()
        )),
    };
    answer(stream, &response);
}

fn answer(mut stream: &UnixStream, response: &Response) {
    let mut out = serde_json::to_string(response)
        .unwrap_or_else(|e| format!("{{\"ok\":false,\"error\":\"cannot encode response: {e}\"}}"));
    out.push('\n');
    let _ = stream.write_all(out.as_bytes());
}

/// Sends a command to every hosted DNM and collects the answers.
fn fan_out<T: Send + 'static>(
    dnms: &[Commander],
    make: impl Fn(Reply<T>) -> Command,
) -> Result<Vec<(String, T)>, String> {
    let mut waiting = Vec::new();
    for c in dnms {
        let (reply, rx) = Reply::channel();
        c.send(make(reply))
            .map_err(|e| format!("DNM `{}`: {e}", c.dnm()))?;
        waiting.push((c.dnm().to_string(), rx));
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

fn dispatch(req: Request, system: &str, dnms: &[Commander]) -> Response {
    match req {
        Request::Status => match fan_out(dnms, Command::Status) {
            Ok(reports) => Response {
                ok: true,
                dnms: reports.into_iter().map(|(_, r)| r).collect(),
                ..Response::default()
            },
            Err(e) => Response::error(e),
        },
        // The DNMs hold the netlist in force (it may have been applied over Zenoh).
        Request::Netlist => match fan_out(dnms, Command::Netlist) {
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
            let results = fan_out(dnms, |reply| Command::Switch {
                task: task.clone(),
                key: None,
                reply,
            });
            match results {
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
            if let Some(missing) = dnms.iter().find(|d| new.dnm(d.dnm()).is_none()) {
                return Response::error(format!(
                    "netlist drops DNM `{}`, which runs here; nothing changed",
                    missing.dnm()
                ));
            }
            let results = fan_out(dnms, |reply| Command::Apply {
                netlist: Box::new(new.clone()),
                key: None,
                reply,
            });
            match results {
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
        Request::Prepare { .. } | Request::Decide { .. } | Request::Adopt { .. } => {
            Response::error(
                "transactions come from the system's authority over Zenoh, not the admin socket",
            )
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_admin_folder_is_made_private_and_anyone_elses_is_refused() {
        use std::os::unix::fs::{MetadataExt, PermissionsExt};
        let base = std::env::temp_dir().join(format!("dnm-private-{}", std::process::id()));
        let dir = base.join("sys");
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o777)).unwrap();
        private_dir(&dir).unwrap();
        assert_eq!(std::fs::metadata(&dir).unwrap().mode() & 0o777, 0o700);
        // SAFETY: getuid(2) has no preconditions.
        if unsafe { libc::getuid() } == 0 {
            // As root, hand it to `nobody`: it must be refused now.
            let path = std::ffi::CString::new(dir.to_str().unwrap()).unwrap();
            // SAFETY: chown(2) on a path we created, with a valid C string.
            assert_eq!(unsafe { libc::chown(path.as_ptr(), 65534, 65534) }, 0);
            let e = private_dir(&dir).unwrap_err().to_string();
            assert!(e.contains("refusing"), "{e}");
        }
        let _ = std::fs::remove_dir_all(&base);
    }
}
