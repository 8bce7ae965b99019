//! Any output on demand: every output of every local module can be watched on
//! `<system>/watch/<dnm>/<module>/<port>/<rate>` (see [`dnm_proto::keys::watch`]), whether or not
//! a task links it across DNMs.
//!
//! The DNM declares a Zenoh publisher per output and rate, and a matching listener on each. An
//! output nobody watches has no reader in shared memory and costs nothing but the idle
//! declarations. When a watcher subscribes, the watch thread opens its own iceoryx2 subscriber
//! on the output and publishes: every sample for `full` (woken by the port's event), the newest
//! sample of each period for `10hz` and `1hz` (woken by a timer, never by the samples). Camera
//! frames (`dnm-image-rgb8`) go out as JPEG. The thread only ever reads the module's shared
//! memory, whose publisher overwrites the oldest sample of a slow reader: a slow watcher drops
//! samples, it never slows a module.

use std::cell::Cell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use dnm_core::worker::{Control, Sets, dbg, err};
use dnm_module::protocol::{PortHeader, dnm_config, monotonic_ns};
use dnm_module::{event_service, port_service};
use dnm_netlist::MessageType;
use dnm_proto::keys::{self, JPEG_ENCODING, WatchRate};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};

use crate::wire::{encoding, to_wire, traffic_class};

type Svc = ipc::Service;
type TsSvc = ipc_threadsafe::Service;

/// Event service that wakes a DNM's watch thread (new outputs, or a watcher came or went).
pub(crate) const WATCH_EVENT: &str = "_dnm/watch";

/// Encoding of the camera frames that go out as JPEG.
const RGB8: &str = "dnm-image-rgb8";
/// JPEG quality of watched frames (1–100).
const JPEG_QUALITY: u8 = 70;
/// Samples one output's reader takes per wake at most.
const MAX_PER_WAKE: usize = 16;
/// How long a reader that could not be opened waits before it is tried again.
const RETRY_AFTER: Duration = Duration::from_secs(5);

/// A local output that can be watched.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct WatchPort {
    pub module: String,
    pub port: String,
    /// The output's iceoryx2 port and event services.
    pub service: String,
    pub event: String,
    pub message: MessageType,
}

/// One output's publishers and, while watched, its reader.
struct Watched {
    port: WatchPort,
    publishers: Vec<(
        WatchRate,
        zenoh::pubsub::Publisher<'static>,
        Arc<AtomicBool>,
    )>,
    reader: Option<Reader>,
    /// Monotonic time each limited rate (10 Hz, 1 Hz) last published, ns.
    last_sent: [Cell<Option<u64>>; 2],
    /// The (anyone, every sample) watch state a reader could not be opened for, and when: not
    /// tried again for [`RETRY_AFTER`] unless it changes.
    failed_for: Option<((bool, bool), Instant)>,
}

struct Reader {
    subscriber: Subscriber<Svc, [u8], PortHeader>,
    /// The port's event, while someone watches every sample.
    listener: Option<Listener<Svc>>,
}

impl Watched {
    fn open(
        session: &zenoh::Session,
        system: &str,
        dnm: &str,
        port: WatchPort,
        wake: &Arc<Notifier<TsSvc>>,
    ) -> Result<Self, String> {
        let mut publishers = Vec::new();
        let image = port.message.encoding == RGB8;
        for rate in WatchRate::ALL {
            let key = keys::watch(system, dnm, &port.module, &port.port, rate);
            let publisher = session
                .declare_publisher(key)
                .encoding(if image {
                    zenoh::bytes::Encoding::from(JPEG_ENCODING)
                } else {
                    encoding(&port.message).into()
                })
                // Below the routes between DNMs: watching never holds up the rover's own data.
                .priority(match traffic_class(&port.message) {
                    Priority::Data => Priority::DataLow,
                    p => p,
                })
                .congestion_control(CongestionControl::Drop)
                .wait()
                .map_err(err("declaring a watch publisher"))?;
            let matched = Arc::new(AtomicBool::new(false));
            {
                let matched = matched.clone();
                let wake = wake.clone();
                publisher
                    .matching_listener()
                    .callback(move |s| {
                        matched.store(s.matching(), Ordering::Release);
                        let _ = wake.notify();
                    })
                    .background()
                    .wait()
                    .map_err(err("matching listener"))?;
            }
            // (Zenoh calls the listener at once when someone already subscribes.)
            publishers.push((rate, publisher, matched));
        }
        Ok(Self {
            port,
            publishers,
            reader: None,
            last_sent: [Cell::new(None), Cell::new(None)],
            failed_for: None,
        })
    }

    fn matched(&self, rate: WatchRate) -> bool {
        self.publishers
            .iter()
            .any(|(r, _, m)| *r == rate && m.load(Ordering::Acquire))
    }

    /// Who watches now: (anyone at all, someone at every sample).
    fn wanted(&self) -> (bool, bool) {
        (
            WatchRate::ALL.iter().any(|r| self.matched(*r)),
            self.matched(WatchRate::Full),
        )
    }

    /// Whether the reader (and its event) no longer fit who watches.
    fn needs_fit(&self) -> bool {
        let wanted = self.wanted();
        let has = (
            self.reader.is_some(),
            self.reader.as_ref().is_some_and(|r| r.listener.is_some()),
        );
        has != wanted
            && self
                .failed_for
                .is_none_or(|(w, at)| w != wanted || at.elapsed() >= RETRY_AFTER)
    }

    /// Opens or closes the reader (and its event) to fit who watches now.
    fn fit(&mut self, node: &Node<Svc>) {
        if !self.needs_fit() {
            return;
        }
        let (any, full) = self.wanted();
        self.failed_for = None;
        if !any {
            self.reader = None;
            return;
        }
        if self.reader.is_none() {
            match open_subscriber(node, &self.port) {
                Ok(subscriber) => {
                    // What is there was sent before anyone watched.
                    while let Ok(Some(_)) = subscriber.receive() {}
                    tracing::debug!(module = %self.port.module, port = %self.port.port, "watched");
                    self.reader = Some(Reader {
                        subscriber,
                        listener: None,
                    });
                }
                Err(e) => {
                    tracing::warn!(module = %self.port.module, port = %self.port.port, "cannot watch: {e}");
                    self.failed_for = Some(((any, full), Instant::now()));
                    return;
                }
            }
        }
        if let Some(r) = &mut self.reader {
            if full && r.listener.is_none() {
                match event_service(node, &self.port.event)
                    .map_err(|e| e.to_string())
                    .and_then(|s| s.listener_builder().create().map_err(|e| format!("{e:?}")))
                {
                    Ok(l) => r.listener = Some(l),
                    Err(e) => {
                        tracing::warn!("watch listener: {e}");
                        self.failed_for = Some(((any, full), Instant::now()));
                    }
                }
            } else if !full {
                r.listener = None;
            }
        }
    }

    /// Publishes what is due: every new sample at `full`, the newest at the limited rates whose
    /// period has passed.
    fn publish(&self, now_ns: u64) {
        let Some(reader) = &self.reader else { return };
        if let Some(l) = &reader.listener {
            let _ = l.try_wait(|_| ());
        }
        let full = self.matched(WatchRate::Full);
        let mut newest = None;
        // Sending every sample, a bounded number per wake: a watcher slower than the module (a
        // large frame to encode) misses samples, and the thread still hears of new outputs and
        // departed watchers. Only keeping the newest, everything there (taking is cheap).
        let most = if full { MAX_PER_WAKE } else { usize::MAX };
        for _ in 0..most {
            let Ok(Some(s)) = reader.subscriber.receive() else {
                break;
            };
            if full {
                send(
                    &self.publishers,
                    WatchRate::Full,
                    &self.port.message,
                    s.user_header(),
                    s.payload(),
                );
            }
            newest = Some(s);
        }
        for (rate, last) in [WatchRate::Hz10, WatchRate::Hz1]
            .into_iter()
            .zip(&self.last_sent)
        {
            if !self.matched(rate) {
                continue;
            }
            // Half a tick of slack: the timer's wake-ups jitter, and a period measured from a
            // late wake-up must not skip the next tick.
            let due = last.get().is_none_or(|t| {
                now_ns.saturating_sub(t) + WatchRate::Hz10.period_ns() / 2 >= rate.period_ns()
            });
            if let (true, Some(s)) = (due, &newest) {
                send(
                    &self.publishers,
                    rate,
                    &self.port.message,
                    s.user_header(),
                    s.payload(),
                );
                last.set(Some(now_ns));
            }
        }
    }
}

fn open_subscriber(
    node: &Node<Svc>,
    port: &WatchPort,
) -> Result<Subscriber<Svc, [u8], PortHeader>, String> {
    port_service(node, &port.service, &port.message.payload)
        .map_err(err("port service"))?
        .subscriber_builder()
        .create()
        .map_err(dbg("watch subscriber"))
}

fn send(
    publishers: &[(
        WatchRate,
        zenoh::pubsub::Publisher<'static>,
        Arc<AtomicBool>,
    )],
    rate: WatchRate,
    message: &MessageType,
    header: &PortHeader,
    payload: &[u8],
) {
    let Some((_, publisher, _)) = publishers.iter().find(|(r, _, _)| *r == rate) else {
        return;
    };
    let bytes = if message.encoding == RGB8 {
        match jpeg(payload) {
            Some(b) => b,
            None => return,
        }
    } else {
        payload.to_vec()
    };
    let attachment = keys::encode_header(&to_wire(header));
    if let Err(e) = publisher.put(bytes).attachment(attachment.to_vec()).wait() {
        tracing::debug!("watch publish: {e}");
    }
}

/// An rgb8 frame (12-byte header: width, height, row step) as JPEG; `None` if malformed.
pub(crate) fn jpeg(frame: &[u8]) -> Option<Vec<u8>> {
    let word = |i: usize| -> Option<usize> {
        Some(u32::from_le_bytes(frame.get(i * 4..i * 4 + 4)?.try_into().ok()?) as usize)
    };
    let (w, h, step) = (word(0)?, word(1)?, word(2)?);
    if w == 0 || h == 0 || w > usize::from(u16::MAX) || h > usize::from(u16::MAX) || step < w * 3 {
        return None;
    }
    let pixels = frame.get(12..12 + step.checked_mul(h)?)?;
    let packed: Vec<u8> = if step == w * 3 {
        pixels.to_vec()
    } else {
        pixels
            .chunks(step)
            .flat_map(|row| &row[..w * 3])
            .copied()
            .collect()
    };
    let mut out = Vec::new();
    jpeg_encoder::Encoder::new(&mut out, JPEG_QUALITY)
        .encode(&packed, w as u16, h as u16, jpeg_encoder::ColorType::Rgb)
        .ok()?;
    Some(out)
}

/// Serves the watch publishers of the DNM's outputs until the DNM drops its sender.
pub(crate) fn watch_loop(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    prefix: &str,
    control: &Control<WatchPort>,
) -> Result<(), String> {
    // Matching callbacks run on Zenoh's threads: they wake this one through the control event.
    let ts_node = NodeBuilder::new()
        .config(&dnm_config(prefix)?)
        .create::<TsSvc>()
        .map_err(dbg("watch node"))?;
    let wake = Arc::new(
        event_service(&ts_node, WATCH_EVENT)
            .map_err(err("watch event"))?
            .notifier_builder()
            .create()
            .map_err(dbg("watch notifier"))?,
    );
    let mut watched: Vec<Watched> = Vec::new();
    let mut new_set: Option<Vec<WatchPort>> = None;
    loop {
        if let Some(set) = new_set.take() {
            let mut keep: Vec<Watched> = Vec::new();
            for port in set {
                if let Some(i) = watched.iter().position(|w| w.port == port) {
                    keep.push(watched.swap_remove(i));
                    continue;
                }
                match Watched::open(session, system, dnm, port, &wake) {
                    Ok(w) => keep.push(w),
                    Err(e) => tracing::error!("cannot offer an output to watchers: {e}"),
                }
            }
            watched = keep;
        }
        for w in &mut watched {
            w.fit(&control.node);
        }
        let limited = |watched: &[Watched]| {
            watched
                .iter()
                .any(|w| w.matched(WatchRate::Hz10) || w.matched(WatchRate::Hz1))
        };
        let ticking = limited(&watched);
        let waitset = WaitSetBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Svc>()
            .map_err(dbg("watch waitset"))?;
        let _control_guard = waitset
            .attach_notification(&control.listener)
            .map_err(dbg("attach"))?;
        let mut guards = Vec::new();
        for w in &watched {
            if let Some(l) = w.reader.as_ref().and_then(|r| r.listener.as_ref()) {
                guards.push(waitset.attach_notification(l).map_err(dbg("attach"))?);
            }
        }
        let _tick = if ticking {
            Some(
                waitset
                    .attach_interval(Duration::from_nanos(WatchRate::Hz10.period_ns()))
                    .map_err(dbg("attach interval"))?,
            )
        } else {
            None
        };
        loop {
            match control.newest() {
                Sets::Closed => return Ok(()),
                Sets::New(set) => {
                    new_set = Some(set);
                    break;
                }
                Sets::Same => {}
            }
            // A watcher came or went: readers open or close, the wait set follows.
            if watched.iter().any(Watched::needs_fit) || limited(&watched) != ticking {
                break;
            }
            let now = monotonic_ns();
            for w in &watched {
                w.publish(now);
            }
            waitset
                .wait_and_process_once(|_| CallbackProgression::Continue)
                .map_err(dbg("watch wait"))?;
        }
    }
}
