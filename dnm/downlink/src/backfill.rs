//! Filling the ground's gaps from the rover's recording, within the link's budget: one request
//! at a time to the recording of the DNM that holds the channel (see [`crate::history`]),
//! entries by priority, each newest or oldest first as its plan says, at the `background`
//! priority. A token bucket holds the downlink to the operator's budget: what arrives live
//! spends it too, and a request asks for no more than what is left of it, nor more than the
//! link drains in about a second (see [`crate::pace`]), so that what the backfill puts in the
//! link's queues never holds a command up long.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_proto::keys;
use zenoh::Wait;
use zenoh::qos::Priority;

use crate::copy::{Copies, Gap};
use crate::ground::{Item, Unknown};
use crate::pace::{LinkProbe, MIN_REQUEST_BYTES, Pace};
use crate::protocol::Announce;
use crate::protocol::{HistoryAnswer, HistoryRequest, MAX_ANSWER_BYTES};

/// How often the backfill looks for work when it has none.
const TICK: Duration = Duration::from_millis(500);
/// What arrived in the last this long is not asked for: the live downlink and the publishers'
/// caches fill it first.
pub(crate) const SETTLE: Duration = Duration::from_secs(10);
/// The most a bucket holds: this long at the budget.
const BURST: Duration = Duration::from_secs(2);
/// How often the channels heard of but not announced are asked for...
const ASK_AGAIN: Duration = Duration::from_secs(3);
/// ...and every channel, in case an announcement and the channel's messages were all missed
/// (a station whose subscription was not in place yet when they went).
const ASK_ALL: Duration = Duration::from_secs(30);
/// How long a request waits for its answer.
const ANSWER_TIMEOUT: Duration = Duration::from_secs(10);
/// How often the netlist in force is asked for, to keep it in the ground's session (what a
/// replay of it needs): a few kB each time.
const NETLIST_EVERY: Duration = Duration::from_secs(600);
/// How long a DNM that did not answer is left alone (the others' gaps go first meanwhile).
const BACK_OFF: Duration = Duration::from_secs(5);

/// What the backfill shares with the record.
pub(crate) struct Shared {
    pub copies: Arc<Mutex<Copies>>,
    /// Bytes received, live and backfill (the station's measure of the downlink).
    pub received: Arc<AtomicU64>,
    /// The measured rate, bytes a second (f64 bits).
    pub measured: Arc<AtomicU64>,
    pub budget_bytes_per_s: Option<u64>,
    /// What the station measures of its command link, for the backfill to keep out of its way.
    pub probe: Option<LinkProbe>,
    /// The most a request asks for now, bytes; what the answers delivered lately, bytes a
    /// second (f64 bits).
    pub request_bytes: Arc<AtomicU64>,
    pub delivered: Arc<AtomicU64>,
    /// Topics heard of whose announcement has not arrived.
    pub unknown: Unknown,
}

/// The rate of the downlink measured over a sliding window.
struct Meter {
    window: std::collections::VecDeque<(Instant, u64)>,
}

impl Meter {
    const WINDOW: Duration = Duration::from_secs(5);

    fn update(&mut self, total: u64) -> f64 {
        let now = Instant::now();
        self.window.push_back((now, total));
        // The newest reading at least a window old stays: after a long wait (an answer that
        // took long) the rate is over that wait, not nothing.
        while self
            .window
            .get(1)
            .is_some_and(|(t, _)| now.duration_since(*t) >= Self::WINDOW)
        {
            self.window.pop_front();
        }
        match (self.window.front(), self.window.back()) {
            (Some((t0, b0)), Some((t1, b1))) if t1 > t0 => {
                (b1 - b0) as f64 / t1.duration_since(*t0).as_secs_f64()
            }
            _ => 0.0,
        }
    }
}

/// Runs until `stop` is dropped: fills gaps through `session`, handing what arrives to the
/// writer's queue `items`.
pub(crate) fn run(
    session: &zenoh::Session,
    system: &str,
    shared: &Shared,
    items: &SyncSender<Item>,
    stop: &Receiver<()>,
) {
    let mut tokens = shared.budget_bytes_per_s.map(|b| b as f64);
    let ceiling = shared.budget_bytes_per_s.map_or(MAX_ANSWER_BYTES, |b| {
        (b as f64 * BURST.as_secs_f64()) as u64
    });
    let mut pace = Pace::new(shared.budget_bytes_per_s, ceiling, shared.probe.clone());
    let mut last = (Instant::now(), shared.received.load(Ordering::Relaxed));
    let mut meter = Meter {
        window: Default::default(),
    };
    // The channels announced before this station listened.
    announcements(session, system, items, stop);
    let mut asked = Instant::now();
    // When the netlist in force is asked for next.
    let mut netlist_due = Instant::now();
    // DNMs that did not answer, until when they are left alone.
    let mut quiet: std::collections::HashMap<String, Instant> = Default::default();
    // When each channel was last asked for: entries of one priority take turns.
    let mut turns: std::collections::HashMap<String, Instant> = Default::default();
    loop {
        let unknown = shared.unknown.lock().is_ok_and(|u| !u.is_empty());
        if (unknown && asked.elapsed() >= ASK_AGAIN) || asked.elapsed() >= ASK_ALL {
            announcements(session, system, items, stop);
            asked = Instant::now();
        }
        if Instant::now() >= netlist_due
            && let Some(dnm) = any_dnm(shared)
        {
            // Not heard (the link is down): asked again as often as the announcements.
            let heard = netlist(session, system, &dnm, items, &shared.received, stop);
            netlist_due = Instant::now() + if heard { NETLIST_EVERY } else { ASK_ALL };
        }
        pace.observe();
        shared
            .request_bytes
            .store(pace.request_bytes(), Ordering::Relaxed);
        if let Some(d) = pace.delivered() {
            shared.delivered.store(d.to_bits(), Ordering::Relaxed);
        }
        // Refill the bucket at the budget, less what arrived since (live included).
        let received = shared.received.load(Ordering::Relaxed);
        let rate = meter.update(received);
        shared.measured.store(rate.to_bits(), Ordering::Relaxed);
        if let (Some(t), Some(budget)) = (tokens.as_mut(), shared.budget_bytes_per_s) {
            let dt = last.0.elapsed().as_secs_f64();
            let spent = received.saturating_sub(last.1) as f64;
            *t = (*t + budget as f64 * dt - spent).min(budget as f64 * BURST.as_secs_f64());
        }
        last = (Instant::now(), received);
        let allowance = tokens
            .map_or(MAX_ANSWER_BYTES, |t| t.max(0.0) as u64)
            .min(pace.request_bytes());
        let work = (allowance >= MIN_REQUEST_BYTES)
            .then(|| {
                quiet.retain(|_, until| *until > Instant::now());
                next_request(shared, allowance, &quiet, &turns)
            })
            .flatten();
        let Some((dnm, request)) = work else {
            match stop.recv_timeout(TICK) {
                Err(RecvTimeoutError::Timeout) => continue,
                _ => return,
            }
        };
        turns.insert(request.topic.clone(), Instant::now());
        let asked = Instant::now();
        match ask(
            session,
            system,
            &dnm,
            &request,
            items,
            &shared.received,
            stop,
        ) {
            Some((answer, got)) => {
                // What the answer brought is in the copy before the gaps are looked at again.
                if !written(items) {
                    return;
                }
                tracing::debug!(
                    topic = %request.topic,
                    from = request.from_ns,
                    to = request.to_ns,
                    max_bytes = request.max_bytes,
                    messages = answer.messages,
                    got,
                    rest = ?answer.rest,
                    "backfilled"
                );
                // Replies the link dropped: the stretch is asked for again, not settled, and
                // the link is asked for less.
                if got == answer.messages {
                    pace.answered(request.max_bytes, answer.bytes, asked.elapsed());
                    settle(shared, &request, &answer);
                } else {
                    recheck(shared, &request);
                    pace.lost();
                }
            }
            // No answer (the link is down): wait before asking again.
            None => {
                tracing::debug!(topic = %request.topic, dnm, "no answer from the recording");
                quiet.insert(dnm, Instant::now() + BACK_OFF);
                pace.unheard();
            }
        }
        if !matches!(stop.try_recv(), Err(std::sync::mpsc::TryRecvError::Empty)) {
            return;
        }
    }
}

/// The request that fills the most urgent gap: the entry of the highest priority (lowest
/// number) with gaps, its newest or oldest gap as its plan says; with the DNM to ask (none of
/// the `quiet` ones, which did not answer lately). Entries of one priority take turns (the
/// one asked for longest ago first): a port's standard message and its `/raw` twin fill in
/// together.
fn next_request(
    shared: &Shared,
    max_bytes: u64,
    quiet: &std::collections::HashMap<String, Instant>,
    turns: &std::collections::HashMap<String, Instant>,
) -> Option<(String, HistoryRequest)> {
    let settled = dnm_proto::clock::now_unix_ns().saturating_sub(SETTLE.as_nanos() as u64);
    let copies = shared.copies.lock().ok()?;
    let mut best: Option<(u8, String, Gap, String, bool, u64)> = None;
    let last_turn = |topic: &str| turns.get(topic).copied();
    for (topic, c) in copies.iter() {
        let Some(a) = c.announce.as_ref().filter(|a| !quiet.contains_key(&a.dnm)) else {
            continue;
        };
        let Some(period) = a.period_ns else { continue };
        let gaps = c.gaps(settled);
        let gap = if a.newest_first {
            gaps.last()
        } else {
            gaps.first()
        };
        let Some(gap) = gap else { continue };
        let before = |b: &(u8, String, Gap, String, bool, u64)| {
            a.priority < b.0 || (a.priority == b.0 && last_turn(topic) < last_turn(&b.1))
        };
        if best.as_ref().is_none_or(before) {
            best = Some((
                a.priority,
                topic.clone(),
                *gap,
                a.dnm.clone(),
                a.newest_first,
                period,
            ));
        }
    }
    let (_, topic, gap, dnm, newest_first, period) = best?;
    Some((
        dnm,
        HistoryRequest {
            topic,
            from_ns: gap.from_ns,
            to_ns: gap.to_ns,
            period_ns: Some(period),
            max_bytes,
            newest_first,
        },
    ))
}

/// Sends `request` to DNM `dnm`'s recording and hands the messages of its answer to the
/// writer; the answer, or none if none came.
fn ask(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    request: &HistoryRequest,
    items: &SyncSender<Item>,
    received: &AtomicU64,
    stop: &Receiver<()>,
) -> Option<(HistoryAnswer, u64)> {
    let json = serde_json::to_vec(request).ok()?;
    let replies = session
        .get(keys::downlink_history(system, dnm))
        .payload(json)
        // Replies the link cannot take now are dropped (and the stretch asked for again), never
        // waited for on the rover.
        .congestion_control(zenoh::qos::CongestionControl::Drop)
        // Every reply comes on the same key: none may be merged away.
        .consolidation(zenoh::query::ConsolidationMode::None)
        .priority(Priority::Background)
        .timeout(ANSWER_TIMEOUT)
        .wait()
        .ok()?;
    let (mut answer, mut messages) = (None, 0u64);
    while let Some(reply) = next_reply(&replies, stop) {
        let Ok(sample) = reply.result() else {
            continue;
        };
        let payload = sample.payload().to_bytes();
        // Counted against the budget like what arrives live.
        received.fetch_add(payload.len() as u64, Ordering::Relaxed);
        match sample
            .attachment()
            .and_then(|a| keys::decode_downlink(&a.to_bytes()))
        {
            Some((log_time, sequence)) => {
                messages += 1;
                let item = Item::Message {
                    topic: request.topic.clone(),
                    log_time,
                    sequence,
                    data: payload.into_owned(),
                    backfilled: true,
                };
                if items.send(item).is_err() {
                    return None;
                }
            }
            None => answer = serde_json::from_slice::<HistoryAnswer>(&payload).ok(),
        }
    }
    answer.map(|a| (a, messages))
}

/// A DNM of the rover that announced a channel.
fn any_dnm(shared: &Shared) -> Option<String> {
    let copies = shared.copies.lock().ok()?;
    copies
        .values()
        .find_map(|c| c.announce.as_ref().map(|a| a.dnm.clone()))
}

/// Asks DNM `dnm` for the netlist in force, for the writer to keep; whether it answered.
fn netlist(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    items: &SyncSender<Item>,
    received: &AtomicU64,
    stop: &Receiver<()>,
) -> bool {
    let Ok(replies) = session
        .get(keys::netlist(system, dnm))
        .priority(Priority::Background)
        .timeout(ANSWER_TIMEOUT)
        .wait()
    else {
        return false;
    };
    while let Some(reply) = next_reply(&replies, stop) {
        let Ok(sample) = reply.result() else {
            continue;
        };
        let bytes = sample.payload().to_bytes();
        received.fetch_add(bytes.len() as u64, Ordering::Relaxed);
        if let Ok(n) = serde_json::from_slice::<dnm_proto::NetlistState>(&bytes)
            && n.text.is_some()
        {
            return items.send(Item::Netlist(n)).is_ok();
        }
    }
    false
}

/// Asks the rover's DNMs for the announcements of their downlinked channels.
fn announcements(
    session: &zenoh::Session,
    system: &str,
    items: &SyncSender<Item>,
    stop: &Receiver<()>,
) {
    let Ok(replies) = session
        .get(keys::downlink_channels(system))
        .priority(Priority::Background)
        .timeout(ANSWER_TIMEOUT)
        .wait()
    else {
        return;
    };
    let mut heard = 0;
    while let Some(reply) = next_reply(&replies, stop) {
        if let Ok(sample) = reply.result()
            && let Ok(a) = serde_json::from_slice::<Announce>(&sample.payload().to_bytes())
        {
            heard += 1;
            if items.send(Item::Announce(a)).is_err() {
                return;
            }
        }
    }
    tracing::debug!(heard, "asked for the downlink's channels");
}

/// The next reply to a query; none once its replies ended, or the backfill is stopped (a
/// station told to stop does not wait out a query's timeout).
fn next_reply<T>(
    replies: &zenoh::handlers::FifoChannelHandler<T>,
    stop: &Receiver<()>,
) -> Option<T> {
    loop {
        match replies.recv_timeout(Duration::from_millis(200)) {
            Ok(Some(r)) => return Some(r),
            Ok(None) if matches!(stop.try_recv(), Err(std::sync::mpsc::TryRecvError::Empty)) => {}
            _ => return None,
        }
    }
}

/// Waits until the writer wrote everything queued before; false if it is gone.
fn written(items: &SyncSender<Item>) -> bool {
    let (tx, rx) = std::sync::mpsc::sync_channel(1);
    items.send(Item::Barrier(tx)).is_ok() && rx.recv().is_ok()
}

/// An answer to `request` came back short: its stretch is asked for again.
fn recheck(shared: &Shared, request: &HistoryRequest) {
    if let Ok(mut copies) = shared.copies.lock()
        && let Some(c) = copies.get_mut(&request.topic)
    {
        c.recheck(Gap {
            from_ns: request.from_ns,
            to_ns: request.to_ns,
        });
    }
}

/// Takes in what the recording said of the stretch asked for: a stretch it answered in full
/// that is still a gap of the copy (nothing in it was new) holds nothing more to have, and is
/// marked unrecorded (a gap that stays, never asked for again).
fn settle(shared: &Shared, request: &HistoryRequest, answer: &HistoryAnswer) {
    let Ok(mut copies) = shared.copies.lock() else {
        return;
    };
    let Some(c) = copies.get_mut(&request.topic) else {
        return;
    };
    c.recorded = answer.recorded;
    // What the answer covered came whole.
    let covered = match answer.rest {
        None => Some((request.from_ns, request.to_ns)),
        Some((from, _)) if !request.newest_first => Some((request.from_ns, from.saturating_sub(1))),
        Some((_, to)) => Some((to.saturating_add(1), request.to_ns)),
    };
    if let Some((from_ns, to_ns)) = covered.filter(|(a, b)| a <= b) {
        c.checked(Gap { from_ns, to_ns });
    }
    // What the budget cut off is asked for next, gap or not (a message or two left at the
    // end of a stretch lie closer to those held than a gap).
    if let Some((from_ns, to_ns)) = answer.rest.filter(|(a, b)| a <= b) {
        c.recheck(Gap { from_ns, to_ns });
    }
    let settled = dnm_proto::clock::now_unix_ns().saturating_sub(SETTLE.as_nanos() as u64);
    let unfilled = c
        .gaps(settled.max(request.to_ns))
        .iter()
        .any(|g| g.from_ns == request.from_ns && g.to_ns >= request.to_ns);
    if unfilled && answer.rest.is_none() {
        c.unrecorded(Gap {
            from_ns: request.from_ns,
            to_ns: request.to_ns,
        });
    }
}
