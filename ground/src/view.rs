//! What the station sees of the running system, for its web interface: every DNM's wiring and
//! glance (refreshed in the background while someone looks, so a page never waits on the
//! radio), the netlist in force, the kinds the rover can run, and outputs watched on demand
//! through the DNMs' watch keys.

use std::collections::{BTreeMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_netlist::{Catalog, MessageType, Wiring};
use dnm_proto::keys::{self, JPEG_ENCODING, WatchRate};
use dnm_proto::{DnmGlance, NetlistState};
use serde::Serialize;
use zenoh::Wait;

/// How often the live view is refreshed while someone looks.
const REFRESH: Duration = Duration::from_secs(1);
/// Nobody asked for this long: stop refreshing (and drop watches not polled for as long).
const IDLE: Duration = Duration::from_secs(15);
/// Longest wait for the DNMs' answers (they cross the radio).
const QUERY_TIMEOUT: Duration = Duration::from_secs(3);
/// Samples of a watched output kept for the page.
const WATCH_KEEP: usize = 300;
/// Outputs watched at once by one station.
const MAX_WATCHES: usize = 16;
/// A decoded sample larger than this (as JSON) is kept as its size only.
const MAX_SAMPLE_JSON: usize = 16 << 10;

static NEXT_WATCH: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(1);

/// The live connection layer as the station last saw it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Live {
    /// The wiring most DNMs on the newest revision report (the task in force included).
    pub wiring: Option<Wiring>,
    /// Every DNM that answered, by name.
    pub glances: BTreeMap<String, DnmGlance>,
    /// Milliseconds since these answers came (`None`: none yet).
    pub age_ms: Option<u64>,
    /// DNMs of the wiring that did not answer the last refresh.
    pub silent: Vec<String>,
}

struct Cached {
    live: Live,
    at: Option<Instant>,
    asked: Instant,
}

/// One watched output.
struct Watch {
    /// Numbers this watch apart from an earlier one of the same output (its samples are
    /// numbered from 1 again).
    id: u64,
    message: MessageType,
    rate: WatchRate,
    samples: Arc<Mutex<WatchBuf>>,
    _sub: zenoh::pubsub::Subscriber<()>,
    polled: Mutex<Instant>,
}

#[derive(Default)]
struct WatchBuf {
    next: u64,
    values: VecDeque<WatchSample>,
    frame: Option<(u64, Vec<u8>)>,
}

/// A sample of a watched output, decoded by its message type's schema.
#[derive(Debug, Clone, Serialize)]
pub struct WatchSample {
    pub seq: u64,
    pub unix_ns: u64,
    pub value: serde_json::Value,
}

/// What a page gets for a watched output.
#[derive(Debug, Clone, Serialize)]
pub struct WatchReply {
    /// Changes when the station watches the output anew: samples are numbered afresh.
    pub watch: u64,
    pub dnm: String,
    pub module: String,
    pub port: String,
    pub schema_name: String,
    /// `10hz` or `1hz` (camera frames).
    pub rate: &'static str,
    /// Samples newer than the `since` asked for, oldest first.
    pub samples: Vec<WatchSample>,
    /// The newest camera frame's number (`/api/frame` serves it as JPEG).
    pub frame: Option<u64>,
}

type WatchKey = (String, String, String);

struct Inner {
    session: zenoh::Session,
    system: String,
    cache: Mutex<Cached>,
    wake: Condvar,
    watches: Mutex<BTreeMap<WatchKey, Arc<Watch>>>,
    stop: AtomicBool,
}

/// The station's view of the system (see the module docs).
pub struct SystemView {
    inner: Arc<Inner>,
    thread: Option<JoinHandle<()>>,
}

impl std::fmt::Debug for SystemView {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SystemView")
            .field("system", &self.inner.system)
            .finish_non_exhaustive()
    }
}

/// Every JSON reply to `key`, decoded; replies that do not decode are skipped.
fn collect<T: serde::de::DeserializeOwned>(session: &zenoh::Session, key: &str) -> Vec<T> {
    let Ok(replies) = session
        .get(key)
        .target(zenoh::query::QueryTarget::All)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(QUERY_TIMEOUT)
        .wait()
    else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result()
            && let Ok(v) = serde_json::from_slice(&s.payload().to_bytes())
        {
            out.push(v);
        }
    }
    out
}

/// The wiring most DNMs on the newest revision report: a radio DNM lagging behind does not
/// decide what the page draws.
fn consensus(wirings: Vec<Wiring>) -> Option<Wiring> {
    let newest = wirings.iter().map(|w| w.revision).max()?;
    let mut votes: BTreeMap<Option<String>, (usize, Wiring)> = BTreeMap::new();
    for w in wirings.into_iter().filter(|w| w.revision == newest) {
        votes
            .entry(w.active_task.clone())
            .or_insert_with(|| (0, w))
            .0 += 1;
    }
    votes.into_values().max_by_key(|(n, _)| *n).map(|(_, w)| w)
}

/// Why an output cannot be watched.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum WatchError {
    #[error("the station has not heard the rover's wiring yet; try again shortly")]
    NoWiring,
    #[error("no module `{0}` in the netlist in force")]
    NoModule(String),
    #[error("module `{module}` has no output `{port}`; its outputs: {outputs}")]
    NoOutput {
        module: String,
        port: String,
        outputs: String,
    },
    #[error("{0} outputs are watched already; close one first")]
    TooMany(usize),
    #[error("subscribing to {key}: {why}")]
    Subscribe { key: String, why: String },
    #[error("the station's watches are unusable after a panic; restart the station")]
    Poisoned,
}

impl SystemView {
    /// Starts the thread that keeps the view fresh.
    pub fn start(session: zenoh::Session, system: &str) -> std::io::Result<Self> {
        let inner = Arc::new(Inner {
            session,
            system: system.to_string(),
            cache: Mutex::new(Cached {
                live: Live::default(),
                at: None,
                asked: Instant::now(),
            }),
            wake: Condvar::new(),
            watches: Mutex::new(BTreeMap::new()),
            stop: AtomicBool::new(false),
        });
        let thread = {
            let inner = inner.clone();
            std::thread::Builder::new()
                .name("ground-view".into())
                .spawn(move || refresh_loop(&inner))?
        };
        Ok(Self {
            inner,
            thread: Some(thread),
        })
    }

    /// The live view as last refreshed; asking keeps it refreshing.
    pub fn live(&self) -> Live {
        let Ok(mut c) = self.inner.cache.lock() else {
            return Live::default();
        };
        let idle = c.asked.elapsed() > IDLE;
        c.asked = Instant::now();
        if idle {
            self.inner.wake.notify_all();
        }
        let mut live = c.live.clone();
        live.age_ms = c.at.map(|t| t.elapsed().as_millis() as u64);
        live
    }

    /// The netlist in force: the newest revision any DNM holds, with its text.
    pub fn netlist(&self) -> Option<NetlistState> {
        collect::<NetlistState>(&self.inner.session, &keys::netlist(&self.inner.system, "*"))
            .into_iter()
            .filter(|n| n.text.is_some())
            .max_by_key(|n| n.revision)
    }

    /// Every kind the rover's DNMs can run (the union of what they answer).
    pub fn kinds(&self) -> Catalog {
        let mut all = Catalog::new();
        let key = format!("{}?kinds", keys::wiring(&self.inner.system, "*"));
        for c in collect::<Catalog>(&self.inner.session, &key) {
            for e in c.iter() {
                if all.get(&e.spec.name).is_none() {
                    all.insert(e.spec.clone(), e.source.clone());
                }
            }
        }
        all
    }

    /// Samples of `module.port` newer than `since`; the first call starts watching it (at
    /// 10 Hz, camera frames at 1 Hz: what a radio link can carry).
    pub fn watch(&self, module: &str, port: &str, since: u64) -> Result<WatchReply, WatchError> {
        let live = self.live();
        let wiring = live.wiring.ok_or(WatchError::NoWiring)?;
        let m = wiring
            .module(module)
            .ok_or_else(|| WatchError::NoModule(module.to_string()))?;
        let p = m
            .outputs
            .iter()
            .find(|p| p.name == port)
            .ok_or_else(|| WatchError::NoOutput {
                module: module.to_string(),
                port: port.to_string(),
                outputs: m
                    .outputs
                    .iter()
                    .map(|p| p.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
            })?;
        let key = (m.dnm.clone(), module.to_string(), port.to_string());
        let watch = {
            let mut watches = self
                .inner
                .watches
                .lock()
                .map_err(|_| WatchError::Poisoned)?;
            match watches.get(&key) {
                Some(w) if w.message == p.message => w.clone(),
                _ => {
                    if watches.len() >= MAX_WATCHES && !watches.contains_key(&key) {
                        return Err(WatchError::TooMany(MAX_WATCHES));
                    }
                    let w = self.subscribe(&key, p.message.clone())?;
                    watches.insert(key.clone(), w.clone());
                    w
                }
            }
        };
        if let Ok(mut t) = watch.polled.lock() {
            *t = Instant::now();
        }
        let buf = watch.samples.lock().map_err(|_| WatchError::Poisoned)?;
        Ok(WatchReply {
            watch: watch.id,
            dnm: key.0,
            module: key.1,
            port: key.2,
            schema_name: watch.message.schema_name.clone(),
            rate: watch.rate.chunk(),
            samples: buf
                .values
                .iter()
                .filter(|s| s.seq > since)
                .cloned()
                .collect(),
            frame: buf.frame.as_ref().map(|(n, _)| *n),
        })
    }

    /// The newest camera frame of a watched output, JPEG.
    pub fn frame(&self, module: &str, port: &str) -> Option<Vec<u8>> {
        let watches = self.inner.watches.lock().ok()?;
        let (_, w) = watches
            .iter()
            .find(|((_, m, p), _)| m == module && p == port)?;
        let buf = w.samples.lock().ok()?;
        buf.frame.as_ref().map(|(_, b)| b.clone())
    }

    fn subscribe(&self, key: &WatchKey, message: MessageType) -> Result<Arc<Watch>, WatchError> {
        let rate = if message.encoding == "dnm-image-rgb8" {
            WatchRate::Hz1
        } else {
            WatchRate::Hz10
        };
        let zkey = keys::watch(&self.inner.system, &key.0, &key.1, &key.2, rate);
        let samples = Arc::new(Mutex::new(WatchBuf::default()));
        let sub = {
            let (samples, message) = (samples.clone(), message.clone());
            self.inner
                .session
                .declare_subscriber(zkey.clone())
                .callback(move |s| {
                    let unix_ns = s
                        .attachment()
                        .and_then(|a| keys::decode_header(&a.to_bytes()))
                        .map(|h| h.unix_ns)
                        .filter(|t| *t > 0)
                        .unwrap_or_else(crate::now_unix_ns);
                    let bytes = s.payload().to_bytes();
                    let Ok(mut b) = samples.lock() else { return };
                    b.next += 1;
                    let seq = b.next;
                    if s.encoding().to_string() == JPEG_ENCODING {
                        b.frame = Some((seq, bytes.to_vec()));
                        return;
                    }
                    let mut value = dnm_netlist::values::decode(&message, &bytes);
                    let json_len = serde_json::to_vec(&value).map_or(usize::MAX, |v| v.len());
                    if json_len > MAX_SAMPLE_JSON {
                        value = serde_json::json!({
                            "bytes": bytes.len(),
                            "note": "too large to show here; record it or watch it in Rerun",
                        });
                    }
                    if b.values.len() >= WATCH_KEEP {
                        b.values.pop_front();
                    }
                    b.values.push_back(WatchSample {
                        seq,
                        unix_ns,
                        value,
                    });
                })
                .wait()
                .map_err(|e| WatchError::Subscribe {
                    key: zkey.to_string(),
                    why: e.to_string(),
                })?
        };
        tracing::info!(key = %zkey, "watching an output for the web interface");
        Ok(Arc::new(Watch {
            id: NEXT_WATCH.fetch_add(1, Ordering::Relaxed),
            message,
            rate,
            samples,
            _sub: sub,
            polled: Mutex::new(Instant::now()),
        }))
    }
}

impl Drop for SystemView {
    fn drop(&mut self) {
        self.inner.stop.store(true, Ordering::Relaxed);
        self.inner.wake.notify_all();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Drops the watches nobody polled lately (their DNMs then stop sending them).
fn drop_unpolled(inner: &Inner) {
    if let Ok(mut w) = inner.watches.lock() {
        w.retain(|_, w| w.polled.lock().is_ok_and(|t| t.elapsed() < IDLE));
    }
}

fn refresh_loop(inner: &Inner) {
    while !inner.stop.load(Ordering::Relaxed) {
        drop_unpolled(inner);
        // Sleep while nobody looks (waking now and then to drop watches left behind).
        {
            let Ok(mut c) = inner.cache.lock() else {
                return;
            };
            while c.asked.elapsed() > IDLE && !inner.stop.load(Ordering::Relaxed) {
                c = match inner.wake.wait_timeout(c, IDLE) {
                    Ok((c, _)) => c,
                    Err(_) => return,
                };
                drop(c);
                drop_unpolled(inner);
                c = match inner.cache.lock() {
                    Ok(c) => c,
                    Err(_) => return,
                };
            }
        }
        let started = Instant::now();
        // Both asked at once: a slow radio DNM costs one timeout, not two.
        let (wirings, glances) = std::thread::scope(|s| {
            let w =
                s.spawn(|| collect::<Wiring>(&inner.session, &keys::wiring(&inner.system, "*")));
            let glances: Vec<DnmGlance> = collect(
                &inner.session,
                &format!("{}?glance", keys::dnm(&inner.system, "*")),
            );
            (w.join().unwrap_or_default(), glances)
        });
        let wiring = consensus(
            wirings
                .into_iter()
                .filter(|w| w.system == inner.system)
                .collect(),
        );
        let glances: BTreeMap<String, DnmGlance> =
            glances.into_iter().map(|g| (g.dnm.clone(), g)).collect();
        if let Ok(mut c) = inner.cache.lock() {
            // Keep the last wiring heard when a refresh gets none (the radio is out).
            if wiring.is_some() || c.live.wiring.is_none() {
                c.live.wiring = wiring;
            }
            // The DNMs that did not answer, against the wiring kept: all of them when the
            // radio is out.
            c.live.silent = c
                .live
                .wiring
                .as_ref()
                .map(|w| {
                    w.dnms
                        .iter()
                        .filter(|d| !glances.contains_key(&d.name))
                        .map(|d| d.name.clone())
                        .collect()
                })
                .unwrap_or_default();
            if !glances.is_empty() {
                c.live.glances = glances;
                c.at = Some(Instant::now());
            }
        }
        let rest = REFRESH.saturating_sub(started.elapsed());
        if let Ok(c) = inner.cache.lock() {
            let _ = inner.wake.wait_timeout(c, rest);
        }
    }
}
