//! Operating a system over Zenoh, from any machine that reaches its Zenoh network: the same
//! requests as the local admin socket, sent to every DNM's command key.

use std::collections::BTreeSet;
use std::time::Duration;

use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

use dnm_proto::{DnmReport, RemoteCommand, Request, Response, keys, merge};

/// Times a command is sent to DNMs that have not answered (same id, so applied once).
const ATTEMPTS: usize = 3;

/// The DNMs of `system` whose liveliness tokens are visible.
pub fn alive_dnms(session: &zenoh::Session, system: &str, timeout: Duration) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    if let Ok(replies) = session
        .liveliness()
        .get(keys::all_dnms(system))
        .timeout(timeout)
        .wait()
    {
        while let Ok(r) = replies.recv() {
            if let Ok(s) = r.result() {
                out.extend(keys::dnm_of(system, s.key_expr().as_str()));
            }
        }
    }
    out
}

/// This process's name as a command client: host and process id.
pub fn client_name() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .unwrap_or_else(|_| "host".into());
    format!("dnm-{host}-{}", std::process::id())
}

/// A fresh command id: unique per process and call.
pub fn command_id() -> String {
    use std::sync::atomic::{AtomicU64, Ordering};
    static NEXT: AtomicU64 = AtomicU64::new(0);
    format!(
        "{}-{}-{}",
        std::process::id(),
        dnm_module::protocol::monotonic_ns(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    )
}

/// Why a request reached no DNM, or could not be sent. A DNM's own refusal is an answer (a
/// [`Response`] that is not `ok`), not an error.
#[derive(Debug, thiserror::Error)]
pub enum RequestError {
    #[error(
        "no DNM of system `{0}` answered over Zenoh; check the endpoints (--connect) and that it runs"
    )]
    NoDnm(String),
    #[error("transactions go to one DNM at a time, from the system's authority")]
    Transaction,
    #[error("Zenoh: {0}")]
    Zenoh(#[source] zenoh::Error),
    #[error("encoding the command: {0}")]
    Encode(#[from] serde_json::Error),
}

/// Sends `req` to every DNM of `system` and merges their answers. Switches and applies carry
/// one id and are re-sent to DNMs that did not answer, so each DNM applies them once.
pub fn request(
    session: &zenoh::Session,
    system: &str,
    req: &Request,
    timeout: Duration,
) -> Result<Response, RequestError> {
    match req {
        Request::Status => {
            let mut dnms = Vec::new();
            let replies = session
                .get(keys::all_dnms(system))
                .target(QueryTarget::All)
                .consolidation(ConsolidationMode::None)
                .timeout(timeout)
                .wait()
                .map_err(RequestError::Zenoh)?;
            while let Ok(r) = replies.recv() {
                if let Ok(s) = r.result() {
                    match serde_json::from_slice::<DnmReport>(&s.payload().to_bytes()) {
                        Ok(d) => dnms.push(d),
                        Err(e) => tracing::warn!(key = %s.key_expr(), "unreadable report: {e}"),
                    }
                }
            }
            if dnms.is_empty() {
                return Err(RequestError::NoDnm(system.to_string()));
            }
            Ok(merge(vec![Response {
                ok: true,
                dnms,
                ..Response::default()
            }]))
        }
        Request::Netlist => {
            let state = crate::newest_netlist(session, system, timeout)
                .ok_or_else(|| RequestError::NoDnm(system.to_string()))?;
            Ok(Response {
                ok: true,
                revision: Some(state.revision),
                netlist: state.text,
                ..Response::default()
            })
        }
        Request::Switch { .. } | Request::Apply { .. } => command(session, system, req, timeout),
        Request::Prepare { .. } | Request::Decide { .. } | Request::Adopt { .. } => {
            Err(RequestError::Transaction)
        }
    }
}

fn command(
    session: &zenoh::Session,
    system: &str,
    req: &Request,
    timeout: Duration,
) -> Result<Response, RequestError> {
    let expected = alive_dnms(session, system, timeout);
    if expected.is_empty() {
        return Err(RequestError::NoDnm(system.to_string()));
    }
    let payload = serde_json::to_vec(&RemoteCommand::new(
        client_name(),
        command_id(),
        req.clone(),
    ))?;
    let mut answers: std::collections::BTreeMap<String, Response> = Default::default();
    for _ in 0..ATTEMPTS {
        let missing: Vec<&String> = expected
            .iter()
            .filter(|d| !answers.contains_key(*d))
            .collect();
        if missing.is_empty() {
            break;
        }
        for dnm in missing {
            let replies = session
                .get(keys::cmd(system, dnm))
                .payload(payload.clone())
                .target(QueryTarget::All)
                .consolidation(ConsolidationMode::None)
                .timeout(timeout)
                .wait()
                .map_err(RequestError::Zenoh)?;
            while let Ok(r) = replies.recv() {
                let bytes = match r.result() {
                    Ok(s) => s.payload().to_bytes().into_owned(),
                    // A DNM's error replies are JSON; others (Zenoh's own timeout) mean no
                    // answer yet, so the command is sent again.
                    Err(e) if e.encoding() == &zenoh::bytes::Encoding::APPLICATION_JSON => {
                        e.payload().to_bytes().into_owned()
                    }
                    Err(_) => continue,
                };
                let answer = serde_json::from_slice::<Response>(&bytes).unwrap_or_else(|e| {
                    Response::error(format!("DNM `{dnm}` answered something unreadable: {e}"))
                });
                if !answers.get(dnm).is_some_and(|a| a.ok) {
                    answers.insert(dnm.clone(), answer);
                }
            }
        }
    }
    let unanswered: Vec<String> = expected
        .iter()
        .filter(|d| !answers.contains_key(*d))
        .cloned()
        .collect();
    let mut all: Vec<Response> = answers.into_values().collect();
    if !unanswered.is_empty() {
        all.push(Response::error(format!(
            "DNMs {} did not answer after {ATTEMPTS} attempts; the command may be applied there \
             when they receive it (it is safe to repeat)",
            unanswered.join(", ")
        )));
    }
    Ok(merge(all))
}
