//! The station's operator API, HTTP/JSON:
//!
//! | request | answer |
//! |---|---|
//! | `POST /commands` with an order (`{"cmd":"switch","task":"auto"}`, `{"cmd":"switch","task":"auto","at_unix_ns":…}`, `{"cmd":"apply","file":"x.toml","text":"…"}`, `{"cmd":"module","edit":{"op":"replace","name":"camera","params":["fov_deg=60"]}}`, `{"cmd":"cancel","seq":12}`) | `201` and the entry, `queued` (stored) |
//! | `GET /commands?since=N` | the entries from `N` on |
//! | `GET /commands/N` (`?wait=30` waits up to 30 s for it to be final) | one entry |
//! | `GET /link` | the link: up, round-trip time, last contact, loss, the rover's state and events |
//!
//! Errors are `4xx` with `{"error": "…"}` saying what to fix.

use std::io::Read;
use std::net::SocketAddr;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use dnm_proto::station::Order;
use tiny_http::{Header, Method, Response, Server};

use crate::Station;

/// Largest request body taken (a netlist fits many times).
const MAX_BODY: u64 = 2 << 20;
/// Longest `?wait=` honoured, s.
const MAX_WAIT_S: u64 = 300;

/// The HTTP server of a station.
pub struct Api {
    server: Arc<Server>,
    thread: Option<JoinHandle<()>>,
    addr: SocketAddr,
}

impl std::fmt::Debug for Api {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Api").field("addr", &self.addr).finish()
    }
}

impl Api {
    /// Serves `station` on `addr` (port 0 picks one; see [`Api::addr`]).
    pub fn serve(station: Arc<Station>, addr: SocketAddr) -> Result<Self, String> {
        let server = Arc::new(Server::http(addr).map_err(|e| format!("listening on {addr}: {e}"))?);
        let addr = server
            .server_addr()
            .to_ip()
            .ok_or_else(|| "the server has no IP address".to_string())?;
        let thread = {
            let server = server.clone();
            std::thread::Builder::new()
                .name("ground-http".into())
                .spawn(move || {
                    for request in server.incoming_requests() {
                        // A `?wait` holds its own thread, so it never holds up the others.
                        let station = station.clone();
                        let _ = std::thread::Builder::new()
                            .name("ground-http-request".into())
                            .spawn(move || handle(&station, request));
                    }
                })
                .map_err(|e| e.to_string())?
        };
        tracing::info!(%addr, "operator API ready");
        Ok(Self {
            server,
            thread: Some(thread),
            addr,
        })
    }

    pub fn addr(&self) -> SocketAddr {
        self.addr
    }
}

impl Drop for Api {
    fn drop(&mut self) {
        self.server.unblock();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn json(status: u16, body: &impl serde::Serialize) -> Response<std::io::Cursor<Vec<u8>>> {
    let bytes = serde_json::to_vec_pretty(body).unwrap_or_default();
    let mut r = Response::from_data(bytes).with_status_code(status);
    if let Ok(h) = Header::from_bytes(&b"Content-Type"[..], &b"application/json"[..]) {
        r.add_header(h);
    }
    r
}

fn error(status: u16, msg: impl Into<String>) -> Response<std::io::Cursor<Vec<u8>>> {
    json(status, &serde_json::json!({ "error": msg.into() }))
}

fn query_u64(query: &str, name: &str) -> Option<u64> {
    query
        .split('&')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| *k == name)
        .and_then(|(_, v)| v.parse().ok())
}

fn handle(station: &Station, mut request: tiny_http::Request) {
    let url = request.url().to_string();
    let (path, query) = url.split_once('?').unwrap_or((&url, ""));
    let response = match (request.method(), path) {
        (Method::Post, "/commands") => {
            let mut body = Vec::new();
            let read = request
                .as_reader()
                .take(MAX_BODY + 1)
                .read_to_end(&mut body);
            match read {
                Err(e) => error(400, format!("reading the body: {e}")),
                Ok(_) if body.len() as u64 > MAX_BODY => {
                    error(413, format!("body over {MAX_BODY} bytes"))
                }
                Ok(_) => match serde_json::from_slice::<Order>(&body) {
                    Err(e) => error(
                        400,
                        format!(
                            "unreadable command ({e}); send e.g. {{\"cmd\":\"switch\",\"task\":\"auto\"}}, \
                             {{\"cmd\":\"apply\",\"file\":\"x.toml\",\"text\":\"…\"}} or {{\"cmd\":\"cancel\",\"seq\":3}}"
                        ),
                    ),
                    Ok(order) => match station.submit(order) {
                        Ok(e) => json(201, &e),
                        Err(crate::StationError::Invalid(e)) => error(400, e),
                        Err(e) => error(500, e.to_string()),
                    },
                },
            }
        }
        (Method::Get, "/commands") => json(
            200,
            &station.entries(query_u64(query, "since").unwrap_or(1)),
        ),
        (Method::Get, "/link") => json(200, &station.link()),
        (Method::Get, p) if p.starts_with("/commands/") => {
            match p["/commands/".len()..].parse::<u64>() {
                Err(_) => error(400, "a command is named by its number: /commands/12"),
                Ok(seq) => {
                    let wait = query_u64(query, "wait").unwrap_or(0).min(MAX_WAIT_S);
                    let e = if wait > 0 {
                        station.wait(seq, Duration::from_secs(wait))
                    } else {
                        station.entry(seq)
                    };
                    match e {
                        Some(e) => json(200, &e),
                        None => error(404, format!("no command {seq} in this station's outbox")),
                    }
                }
            }
        }
        _ => error(
            404,
            "unknown request; use POST /commands, GET /commands, GET /commands/N, GET /link",
        ),
    };
    if let Err(e) = request.respond(response) {
        tracing::debug!("answering an operator: {e}");
    }
}
