//! The station's operator API, HTTP/JSON:
//!
//! | request | answer |
//! |---|---|
//! | `POST /commands` with an order (`{"cmd":"switch","task":"auto"}`, `{"cmd":"switch","task":"auto","at_unix_ns":…}`, `{"cmd":"apply","file":"x.toml","text":"…"}`, `{"cmd":"module","edit":{"op":"replace","name":"camera","params":["fov_deg=60"]}}`, `{"cmd":"cancel","seq":12}`, `{"cmd":"sequence","name":"explore","action":{"do":"start"}}`) | `201` and the entry, `queued` (stored) |
//! | `GET /commands?since=N` | the entries from `N` on (`&last=K`: only the last `K`; `&brief`: applies and sequence uploads without their text) |
//! | `GET /commands/N` (`?wait=30` waits up to 30 s for it to be final) | one entry |
//! | `GET /link` | the link: up, round-trip time, last contact, loss, the rover's state and events |
//!
//! The web interface's page and requests are in [`crate::web`].
//!
//! Errors are `4xx` with `{"error": "…"}` saying what to fix.
//!
//! Access: bound to a loopback address (the default), requests must name that host (a web
//! page elsewhere cannot reach it through its own domain) and a browser's request must come
//! from the station's own page (its `Origin`). Bound to another address, a token is required:
//! `Authorization: Bearer TOKEN`, or once in a browser `/?token=TOKEN`, which sets a cookie.
//! The server speaks plain HTTP: the token crosses the network as it is (README: reach a
//! loopback-bound station through an SSH tunnel or a TLS proxy instead). A request that is not
//! a GET must carry JSON (`Content-Type: application/json`), which another site's form cannot.

use std::io::Read;
use std::net::SocketAddr;
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use dnm_proto::station::{Order, SequenceAction};
use tiny_http::{Header, Method, Response, Server};

use crate::Station;
use crate::view::SystemView;
use crate::web::{self, Web};

/// Largest request body taken (a netlist fits many times).
const MAX_BODY: u64 = 2 << 20;
/// Longest `?wait=` honoured, s.
const MAX_WAIT_S: u64 = 300;
/// Requests served at once (each holds a thread; a `?wait` holds it long); more get `503`.
const MAX_IN_FLIGHT: usize = 64;

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

/// What every request is served with.
struct Ctx {
    in_flight: std::sync::atomic::AtomicUsize,
    station: Arc<Station>,
    web: Web,
    token: Option<String>,
    /// The `Host` values a loopback-bound server answers (none: any, a token guards it).
    hosts: Vec<String>,
    downlink: Option<DownlinkStatus>,
}

/// How complete the station's record of the rover is (JSON), served at `GET /downlink`.
pub type DownlinkStatus = Arc<dyn Fn() -> serde_json::Value + Send + Sync>;

/// Why the operator API did not start.
#[derive(Debug, thiserror::Error)]
pub enum ApiStartError {
    #[error(
        "the operator API on {0} would be reachable from other machines without a login: give it a token (`--token`, or $DNM_GROUND_TOKEN), or listen on 127.0.0.1"
    )]
    NoToken(SocketAddr),
    #[error("a token of at least 16 characters, please (e.g. `openssl rand -hex 16`)")]
    ShortToken,
    #[error("listening on {addr}: {why}")]
    Listen { addr: SocketAddr, why: String },
    #[error("the server has no IP address")]
    NoAddress,
    #[error("starting the API's threads: {0}")]
    Thread(#[source] std::io::Error),
}

impl Api {
    /// Serves `station` on `addr` (port 0 picks one; see [`Api::addr`]), loopback only.
    pub fn serve(station: Arc<Station>, addr: SocketAddr) -> Result<Self, ApiStartError> {
        Self::serve_with(station, addr, None)
    }

    /// Serves `station` on `addr`; an address other machines can reach needs `token`.
    pub fn serve_with(
        station: Arc<Station>,
        addr: SocketAddr,
        token: Option<String>,
    ) -> Result<Self, ApiStartError> {
        Self::serve_with_record(station, addr, token, None)
    }

    /// [`Api::serve_with`], also answering `GET /downlink` with `downlink`'s status of the
    /// station's record of the rover.
    pub fn serve_with_record(
        station: Arc<Station>,
        addr: SocketAddr,
        token: Option<String>,
        downlink: Option<DownlinkStatus>,
    ) -> Result<Self, ApiStartError> {
        let token = token.filter(|t| !t.is_empty());
        if !addr.ip().is_loopback() && token.is_none() {
            return Err(ApiStartError::NoToken(addr));
        }
        if let Some(t) = &token
            && t.len() < 16
        {
            return Err(ApiStartError::ShortToken);
        }
        let server = Arc::new(Server::http(addr).map_err(|e| ApiStartError::Listen {
            addr,
            why: e.to_string(),
        })?);
        let addr = server
            .server_addr()
            .to_ip()
            .ok_or(ApiStartError::NoAddress)?;
        let hosts = if addr.ip().is_loopback() {
            let port = addr.port();
            vec![
                format!("127.0.0.1:{port}"),
                format!("localhost:{port}"),
                format!("[::1]:{port}"),
                addr.to_string(),
            ]
        } else {
            Vec::new()
        };
        let view = SystemView::start(station.session().clone(), station.system())
            .map_err(ApiStartError::Thread)?;
        let ctx = Arc::new(Ctx {
            in_flight: std::sync::atomic::AtomicUsize::new(0),
            station,
            web: Web::new(view),
            token,
            hosts,
            downlink,
        });
        let thread = {
            let server = server.clone();
            std::thread::Builder::new()
                .name("ground-http".into())
                .spawn(move || {
                    use std::sync::atomic::Ordering;
                    for request in server.incoming_requests() {
                        if ctx.in_flight.fetch_add(1, Ordering::AcqRel) >= MAX_IN_FLIGHT {
                            ctx.in_flight.fetch_sub(1, Ordering::AcqRel);
                            let _ = request.respond(error(
                                503,
                                format!("{MAX_IN_FLIGHT} requests in progress; try again"),
                            ));
                            continue;
                        }
                        // A `?wait` holds its own thread, so it never holds up the others.
                        let c = ctx.clone();
                        let spawned = std::thread::Builder::new()
                            .name("ground-http-request".into())
                            .spawn(move || {
                                handle(&c, request);
                                c.in_flight.fetch_sub(1, Ordering::AcqRel);
                            });
                        if let Err(e) = spawned {
                            ctx.in_flight.fetch_sub(1, Ordering::AcqRel);
                            tracing::warn!("no thread for an operator's request: {e}");
                        }
                    }
                })
                .map_err(ApiStartError::Thread)?
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

fn json(status: u16, body: &impl serde::Serialize) -> Resp {
    let bytes = serde_json::to_vec(body).unwrap_or_default();
    with_headers(
        Response::from_data(bytes).with_status_code(status),
        &[
            ("Content-Type", "application/json"),
            ("X-Content-Type-Options", "nosniff"),
            ("Cache-Control", "no-store"),
        ],
    )
}

fn with_headers(mut r: Resp, headers: &[(&str, &str)]) -> Resp {
    for (k, v) in headers {
        if let Ok(h) = Header::from_bytes(k.as_bytes(), v.as_bytes()) {
            r.add_header(h);
        }
    }
    r
}

fn error(status: u16, msg: impl Into<String>) -> Resp {
    json(status, &serde_json::json!({ "error": msg.into() }))
}

fn query_str(query: &str, name: &str) -> Option<String> {
    query
        .split('&')
        .filter_map(|kv| kv.split_once('='))
        .find(|(k, _)| *k == name)
        .map(|(_, v)| percent_decode(v))
}

fn query_u64(query: &str, name: &str) -> Option<u64> {
    query_str(query, name).and_then(|v| v.parse().ok())
}

/// `%41` and `+` decoded; an invalid escape is kept as it is.
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        let hex = b
            .get(i + 1..i + 3)
            .and_then(|h| std::str::from_utf8(h).ok())
            .and_then(|h| u8::from_str_radix(h, 16).ok());
        match (b[i], hex) {
            (b'+', _) => out.push(b' '),
            (b'%', Some(v)) => {
                out.push(v);
                i += 2;
            }
            (c, _) => out.push(c),
        }
        i += 1;
    }
    String::from_utf8_lossy(&out).into_owned()
}

fn header<'a>(request: &'a tiny_http::Request, name: &'static str) -> Option<&'a str> {
    request
        .headers()
        .iter()
        .find(|h| h.field.equiv(name))
        .map(|h| h.value.as_str())
}

/// Compares without stopping at the first difference.
fn same_secret(a: &str, b: &str) -> bool {
    a.len() == b.len()
        && a.bytes()
            .zip(b.bytes())
            .fold(0u8, |acc, (x, y)| acc | (x ^ y))
            == 0
}

/// Why a request is refused, if it is.
fn refusal(ctx: &Ctx, request: &tiny_http::Request, path: &str, query: &str) -> Option<Resp> {
    let host = header(request, "Host").unwrap_or_default();
    if !ctx.hosts.is_empty() && !ctx.hosts.iter().any(|h| h.eq_ignore_ascii_case(host)) {
        return Some(error(
            403,
            format!("this station answers only as {}", ctx.hosts[0]),
        ));
    }
    // Browsers say where a request comes from; only the station's own page (or the operator
    // typing the address) may use it: another site's page cannot even read an output.
    if let Some(site) = header(request, "Sec-Fetch-Site")
        && !matches!(site, "same-origin" | "none")
    {
        return Some(error(403, "requests from another site's page are refused"));
    }
    if let Some(origin) = header(request, "Origin") {
        let origin_host = origin.split_once("://").map_or(origin, |(_, h)| h);
        if origin != "null" && !origin_host.eq_ignore_ascii_case(host) {
            return Some(error(403, "requests from another site's page are refused"));
        }
        if origin == "null" && *request.method() != Method::Get {
            return Some(error(403, "requests from an opaque origin are refused"));
        }
    }
    // A form of another site's page can post `text/plain` without asking: what changes the
    // rover comes as JSON, which a page can send only to its own origin.
    if *request.method() != Method::Get {
        let json = header(request, "Content-Type").is_some_and(|c| {
            c.split(';')
                .next()
                .is_some_and(|t| t.trim().eq_ignore_ascii_case("application/json"))
        });
        if !json {
            return Some(error(
                415,
                "send the body as JSON, with `Content-Type: application/json`",
            ));
        }
    }
    let token = ctx.token.as_deref()?;
    let bearer = header(request, "Authorization").and_then(|v| v.strip_prefix("Bearer "));
    let cookie = header(request, "Cookie").and_then(|c| {
        c.split(';')
            .filter_map(|kv| kv.trim().split_once('='))
            .find(|(k, _)| *k == "dnm_token")
            .map(|(_, v)| v)
    });
    if bearer.or(cookie).is_some_and(|t| same_secret(t, token)) {
        return None;
    }
    if path == "/"
        && let Some(given) = query_str(query, "token")
    {
        if same_secret(&given, token) {
            // Logged in: the token goes into a cookie and out of the address bar.
            let mut r = Response::from_data(Vec::new()).with_status_code(303);
            for (k, v) in [
                ("Location", "/".to_string()),
                (
                    "Set-Cookie",
                    format!("dnm_token={token}; HttpOnly; SameSite=Strict; Path=/"),
                ),
            ] {
                if let Ok(h) = Header::from_bytes(k.as_bytes(), v.as_bytes()) {
                    r.add_header(h);
                }
            }
            return Some(r);
        }
        tracing::warn!("a wrong token for the operator API");
    }
    Some(error(
        401,
        "this station needs its token: `Authorization: Bearer TOKEN`, or open /?token=TOKEN once",
    ))
}

type Resp = Response<std::io::Cursor<Vec<u8>>>;

fn asset(body: &'static str, content_type: &'static str) -> Resp {
    with_headers(
        Response::from_data(body.as_bytes().to_vec()),
        &[
            ("Content-Type", content_type),
            ("Cache-Control", "no-cache"),
            ("X-Frame-Options", "DENY"),
            ("X-Content-Type-Options", "nosniff"),
            ("Referrer-Policy", "no-referrer"),
            (
                "Content-Security-Policy",
                "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; \
                 img-src 'self' blob: data:; connect-src 'self'; frame-ancestors 'none'; \
                 base-uri 'none'; form-action 'self'",
            ),
        ],
    )
}

fn read_body(request: &mut tiny_http::Request) -> Result<Vec<u8>, Resp> {
    let mut body = Vec::new();
    let read = request
        .as_reader()
        .take(MAX_BODY + 1)
        .read_to_end(&mut body);
    match read {
        Err(e) => Err(error(400, format!("reading the body: {e}"))),
        Ok(_) if body.len() as u64 > MAX_BODY => {
            Err(error(413, format!("body over {MAX_BODY} bytes")))
        }
        Ok(_) => Ok(body),
    }
}

/// The web interface's requests (`None`: not one of them).
fn handle_web(
    ctx: &Ctx,
    request: &mut tiny_http::Request,
    path: &str,
    query: &str,
) -> Option<Resp> {
    let web = &ctx.web;
    Some(match (request.method(), path) {
        (Method::Get, "/" | "/index.html") => asset(web::INDEX_HTML, "text/html; charset=utf-8"),
        (Method::Get, "/app.js") => asset(web::APP_JS, "text/javascript; charset=utf-8"),
        (Method::Get, "/style.css") => asset(web::STYLE_CSS, "text/css; charset=utf-8"),
        (Method::Get, "/api/live") => json(
            200,
            &serde_json::json!({
                "system": ctx.station.system(),
                "station": ctx.station.name(),
                "link": ctx.station.link(),
                "live": web.view.live(),
            }),
        ),
        (Method::Get, "/api/netlist") => match web.view.netlist() {
            None => error(
                503,
                "no DNM of the rover has answered with its netlist yet; is the link up?",
            ),
            Some(n) => {
                let text = n.text.clone().unwrap_or_default();
                match web::document(&text) {
                    Ok(doc) => json(
                        200,
                        &serde_json::json!({
                            "revision": n.revision,
                            "file": n.file,
                            "active_task": n.active_task,
                            "text": text,
                            "doc": doc,
                        }),
                    ),
                    Err(e) => error(
                        502,
                        format!("the netlist in force does not read as TOML: {e}"),
                    ),
                }
            }
        },
        (Method::Get, "/api/kinds") => {
            let kinds = web.kinds();
            json(200, &kinds.iter().collect::<Vec<_>>())
        }
        (Method::Post, "/api/check") => {
            let body = match read_body(request) {
                Ok(b) => b,
                Err(r) => return Some(r),
            };
            #[derive(serde::Deserialize)]
            struct Draft {
                #[serde(default)]
                file: String,
                doc: serde_json::Value,
            }
            match serde_json::from_slice::<Draft>(&body) {
                Err(e) => error(
                    400,
                    format!("unreadable draft ({e}); send {{\"file\":\"x.toml\",\"doc\":{{…}}}}"),
                ),
                Ok(d) => {
                    let kinds = web.kinds();
                    if kinds.iter().next().is_none() {
                        // Checked against no kinds, every module would read as unknown.
                        return Some(error(
                            503,
                            "the rover has not told the station the kinds it can run yet; is the link up? the page checks again by itself",
                        ));
                    }
                    json(200, &web::check(&d.doc, &d.file, &kinds))
                }
            }
        }
        (Method::Get, "/api/watch") => {
            let (Some(module), Some(port)) = (query_str(query, "module"), query_str(query, "port"))
            else {
                return Some(error(400, "name the output: /api/watch?module=M&port=P"));
            };
            let since = query_u64(query, "since").unwrap_or(0);
            match web.view.watch(&module, &port, since) {
                Ok(r) => json(200, &r),
                Err(e) => error(404, e.to_string()),
            }
        }
        (Method::Get, "/api/frame") => {
            let (Some(module), Some(port)) = (query_str(query, "module"), query_str(query, "port"))
            else {
                return Some(error(400, "name the output: /api/frame?module=M&port=P"));
            };
            match web.view.frame(&module, &port) {
                None => error(
                    404,
                    format!("no frame of {module}.{port} yet (watch it first)"),
                ),
                Some(jpeg) => with_headers(
                    Response::from_data(jpeg),
                    &[
                        ("Content-Type", "image/jpeg"),
                        ("X-Content-Type-Options", "nosniff"),
                        ("Cache-Control", "no-store"),
                    ],
                ),
            }
        }
        _ => return None,
    })
}

fn handle(ctx: &Ctx, mut request: tiny_http::Request) {
    let url = request.url().to_string();
    let (path, query) = url.split_once('?').unwrap_or((&url, ""));
    let station = &*ctx.station;
    if let Some(r) = refusal(ctx, &request, path, query) {
        if let Err(e) = request.respond(r) {
            tracing::debug!("answering an operator: {e}");
        }
        return;
    }
    if let Some(r) = handle_web(ctx, &mut request, path, query) {
        if let Err(e) = request.respond(r) {
            tracing::debug!("answering an operator: {e}");
        }
        return;
    }
    let response = match (request.method(), path) {
        (Method::Post, "/commands") => match read_body(&mut request) {
            Err(r) => r,
            Ok(body) => match serde_json::from_slice::<Order>(&body) {
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
        },
        (Method::Get, "/commands") => {
            let last = query_u64(query, "last").map(|n| usize::try_from(n).unwrap_or(usize::MAX));
            let mut entries = station.entries(query_u64(query, "since").unwrap_or(1), last);
            // `brief`: applies and sequence uploads without their text (a page polling its
            // outbox).
            if query.split('&').any(|kv| kv == "brief") {
                for e in &mut entries {
                    match &mut e.order {
                        Order::Apply { text, .. } => *text = format!("({} bytes)", text.len()),
                        Order::Sequence {
                            action: SequenceAction::Upload { text, netlists, .. },
                            ..
                        } => {
                            *text = format!("({} bytes)", text.len());
                            for t in netlists.values_mut() {
                                *t = format!("({} bytes)", t.len());
                            }
                        }
                        _ => {}
                    }
                }
            }
            json(200, &entries)
        }
        (Method::Get, "/link") => json(200, &station.link()),
        (Method::Get, "/downlink") => match &ctx.downlink {
            Some(status) => json(200, &status()),
            None => error(
                404,
                "this station keeps no record of the rover (it runs with --no-record)",
            ),
        },
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
            "unknown request; use POST /commands, GET /commands, GET /commands/N, GET /link, GET /downlink",
        ),
    };
    if let Err(e) = request.respond(response) {
        tracing::debug!("answering an operator: {e}");
    }
}
