//! Operating a running system: a Unix socket per system on this machine that takes one JSON
//! request per line and answers one JSON response per line, in front of the machine's DNMs
//! ([`crate::host`]).
//!
//! ```text
//! $ echo '{"cmd":"status"}' | socat - UNIX-CONNECT:/tmp/dnm-run-0/beetle/rover+drive+vision+ground.sock
//! ```

use std::io::{BufRead, BufReader, Read, Write};
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use std::time::Duration;

use dnm_core::answer::{apply_answer, first_refusal_or_all, switch_answer};
use dnm_core::{Command, Commander, Reply};

pub use dnm_proto::{Request, Response, merge};

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

/// Connections the admin socket serves at once; more are refused as busy.
const ADMIN_CONNECTIONS: usize = 16;

/// Serves each connection on its own thread, so a long apply never holds up a switch, until
/// `stop` is set (and the listener shut down wakes the accept). Returns the threads of the
/// connections still being served: each holds the DNMs' commanders, ports of their wake-up
/// events in shared memory, which a thread left running at exit would keep there.
pub(crate) fn serve(
    listener: &UnixListener,
    system: &str,
    authority: Option<&str>,
    dnms: &[Commander],
    stop: &std::sync::atomic::AtomicBool,
) -> Vec<std::thread::JoinHandle<()>> {
    let busy = Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let mut serving: Vec<std::thread::JoinHandle<()>> = Vec::new();
    for stream in listener.incoming() {
        if stop.load(std::sync::atomic::Ordering::Acquire) {
            break;
        }
        let Ok(stream) = stream else { continue };
        serving.retain(|t| !t.is_finished());
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
        match spawned {
            Ok(t) => serving.push(t),
            Err(e) => {
                busy.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
                tracing::warn!("admin connection dropped: {e}");
            }
        }
    }
    serving
}

/// Bytes of one request on the admin socket, at most: an apply carries a netlist's text,
/// escaped as JSON, and a recording keeps netlists of up to 16 MiB.
const MAX_REQUEST_BYTES: u64 = 64 << 20;

fn serve_one(stream: &UnixStream, system: &str, authority: Option<&str>, dnms: &[Commander]) {
    let _ = stream.set_read_timeout(Some(Duration::from_secs(10)));
    // One request, a line, of [`MAX_REQUEST_BYTES`] at most.
    let mut reader = BufReader::new(stream).take(MAX_REQUEST_BYTES);
    let mut line = String::new();
    if reader.read_line(&mut line).is_err() {
        return;
    }
    if !line.ends_with('\n') && line.len() as u64 >= MAX_REQUEST_BYTES {
        answer(
            stream,
            &Response::error(format!(
                "the request is longer than {MAX_REQUEST_BYTES} bytes: send one JSON request on a line"
            )),
        );
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
                Ok(results) => first_refusal_or_all(
                    results
                        .into_iter()
                        .map(|(name, r)| switch_answer(&name, r))
                        .collect(),
                ),
                Err(e) => Response::error(e),
            }
        }
        Request::Apply { file, text } => {
            let new = match crate::local_door(system).accept(&file, &text) {
                Ok(n) => n,
                Err(e) => return Response::error(e.to_string()),
            };
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
                Ok(results) => first_refusal_or_all(
                    results
                        .into_iter()
                        .map(|(name, r)| apply_answer(&name, r))
                        .collect(),
                ),
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

    #[test]
    fn a_request_that_never_ends_is_answered_not_kept() {
        let (ours, theirs) = UnixStream::pair().unwrap();
        // A client streaming bytes without a newline, past what a request may be.
        let writer = std::thread::spawn(move || {
            let chunk = vec![b'x'; 1 << 20];
            let mut theirs = theirs;
            for _ in 0..(MAX_REQUEST_BYTES >> 20) + 2 {
                if theirs.write_all(&chunk).is_err() {
                    break;
                }
            }
            let mut reply = String::new();
            let _ = std::io::BufReader::new(&theirs).read_line(&mut reply);
            reply
        });
        serve_one(&ours, "s", None, &[]);
        drop(ours);
        let reply = writer.join().unwrap();
        assert!(reply.contains("longer than"), "{reply}");
    }
}
