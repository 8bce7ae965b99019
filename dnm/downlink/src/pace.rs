//! How much of the link the backfill takes now. It asks one stretch at a time, so what it
//! can put in the link's queues ahead of a command is one answer: the pace keeps an answer to
//! what the link delivers in about a second. The operator's budget is the ceiling; what a radio
//! really carries changes with its losses and outages, and an answer larger than the link
//! drains quickly waits in its queues in front of the commands. So the pace watches what the
//! commands see (LEDBAT's idea, on the station's own uplinks): their round trip grown well
//! beyond the least seen lately halves the request size, and so do an answer that came back
//! short (the rover dropped replies its link could not take) or not at all, and the first
//! uplink of an outage. An answer that took no longer than a command's round trip now plus
//! its bytes at the budget (and a second) lets the next ask for twice as much. On a lossy
//! link a command's round trip varies by seconds without any queue (a lost segment holds up
//! what follows it until it is sent again): the least of the last few is taken, and what is
//! allowed grows with the least round trip.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What the station measured of its command link so far: uplinks sent and answered, and the
/// round trip of the last one answered.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LinkSample {
    pub uplinks: u64,
    pub answered: u64,
    pub rtt: Option<Duration>,
}

/// Where the backfill reads the station's [`LinkSample`]s.
#[derive(Clone)]
pub struct LinkProbe(Arc<dyn Fn() -> LinkSample + Send + Sync>);

impl LinkProbe {
    pub fn new(f: impl Fn() -> LinkSample + Send + Sync + 'static) -> Self {
        Self(Arc::new(f))
    }
}

impl std::fmt::Debug for LinkProbe {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("LinkProbe")
    }
}

/// The least round trip (of uplinks, and of answers) is the one of the last this long (a
/// link whose delay grew for good is taken as it is after it).
const BASE_WINDOW: Duration = Duration::from_secs(120);
/// The current round trip of the uplinks is the least of the last this many (a lone segment
/// lost and sent again is not queueing).
const FILTER: usize = 3;
/// Queueing the uplinks may meet before the backfill yields: this, or the least round trip if
/// larger (a lossy link's retransmissions hold an uplink up that long without any queue).
const TARGET: Duration = Duration::from_secs(1);
/// An answer that took at most this beyond a command's round trip and its bytes at the
/// budget was drained as quickly as the budget allows.
const QUICK: Duration = Duration::from_secs(1);
/// A request asks for at least this much (a message of the plan may be larger: one is
/// always sent).
pub(crate) const MIN_REQUEST_BYTES: u64 = 1024;
/// The size is halved at most this often (one episode, one cut).
const CUT_EVERY: Duration = Duration::from_secs(2);

/// The backfill's request size, adapted (see the module's docs).
pub(crate) struct Pace {
    budget: Option<u64>,
    ceiling: u64,
    size: u64,
    probe: Option<LinkProbe>,
    seen: LinkSample,
    /// Round trips of the uplinks answered, newest last.
    rtts: VecDeque<(Instant, Duration)>,
    /// How long answers took, newest last.
    answers: VecDeque<(Instant, Duration)>,
    /// What the answers delivered lately, bytes a second.
    delivered: Option<f64>,
    last_cut: Option<Instant>,
    /// The last uplink went unanswered, the last request got no answer (an outage: cut
    /// once, at its start).
    unanswered: bool,
    silent: bool,
}

impl Pace {
    /// Requests of at most `ceiling` bytes under a `budget` (bytes a second), adapted to how
    /// quickly answers come and to what `probe` measures of the commands' link.
    pub fn new(budget: Option<u64>, ceiling: u64, probe: Option<LinkProbe>) -> Self {
        let ceiling = ceiling.max(MIN_REQUEST_BYTES);
        let seen = probe.as_ref().map(|p| (p.0)()).unwrap_or_default();
        Self {
            budget,
            ceiling,
            // It begins small, and grows as the link shows it drains more.
            size: (ceiling / 8).max(MIN_REQUEST_BYTES),
            probe,
            seen,
            rtts: VecDeque::new(),
            answers: VecDeque::new(),
            delivered: None,
            last_cut: None,
            unanswered: false,
            silent: false,
        }
    }

    /// The most the next request may ask for, bytes.
    pub fn request_bytes(&self) -> u64 {
        self.size
    }

    /// What the backfill's answers delivered lately, bytes a second.
    pub fn delivered(&self) -> Option<f64> {
        self.delivered
    }

    /// An answer of `bytes` asked for `asked` came whole after `took`.
    pub fn answered(&mut self, asked: u64, bytes: u64, took: Duration) {
        push(&mut self.answers, Instant::now(), took);
        self.silent = false;
        if bytes > 0 && !took.is_zero() {
            let rate = bytes as f64 / took.as_secs_f64();
            self.delivered = Some(self.delivered.map_or(rate, |d| 0.7 * d + 0.3 * rate));
        }
        // A command's round trip now (none measured: the quickest answer lately), and the
        // answer's bytes at the budget.
        let rtt = self
            .current_rtt()
            .or_else(|| self.answers.iter().map(|(_, d)| *d).min())
            .unwrap_or(took);
        let transfer = self.budget.filter(|b| *b > 0).map_or(Duration::ZERO, |b| {
            Duration::from_secs_f64(bytes as f64 / b as f64)
        });
        // Drained quickly, and not a small remainder that says nothing of the link.
        if took <= rtt + transfer + QUICK && bytes * 2 >= asked {
            self.size = (self.size * 2).min(self.ceiling);
        }
    }

    /// An answer came back short.
    pub fn lost(&mut self) {
        self.silent = false;
        self.cut("an answer came back short");
    }

    /// A request got no answer at all (the link is down, or the rover): the first of a run.
    pub fn unheard(&mut self) {
        if !std::mem::replace(&mut self.silent, true) {
            self.cut("a request got no answer");
        }
    }

    /// Takes in what the station measured of the commands' link since the last call.
    pub fn observe(&mut self) {
        let Some(probe) = &self.probe else {
            return;
        };
        let now = (probe.0)();
        let answered = now.answered.saturating_sub(self.seen.answered);
        let unanswered = now
            .uplinks
            .saturating_sub(self.seen.uplinks)
            .saturating_sub(answered);
        self.seen = now;
        if let Some(rtt) = now.rtt.filter(|_| answered > 0) {
            push(&mut self.rtts, Instant::now(), rtt);
        }
        if unanswered > 0 && answered == 0 {
            if !std::mem::replace(&mut self.unanswered, true) {
                self.cut("an uplink went unanswered");
            }
        } else if answered > 0
            && !std::mem::replace(&mut self.unanswered, false)
            && let Some((queueing, allowed)) = self.queueing()
            && queueing > allowed
        {
            self.cut("the uplinks' round trip grew");
        }
    }

    /// How much longer the uplinks take now than the least lately, and what is allowed.
    fn queueing(&self) -> Option<(Duration, Duration)> {
        let base = self.rtts.iter().map(|(_, r)| *r).min()?;
        let current = self.current_rtt()?;
        Some((current.saturating_sub(base), TARGET.max(base)))
    }

    /// The round trip of the uplinks now: the least of the last few.
    fn current_rtt(&self) -> Option<Duration> {
        self.rtts.iter().rev().take(FILTER).map(|(_, r)| *r).min()
    }

    fn cut(&mut self, why: &str) {
        if self.last_cut.is_some_and(|c| c.elapsed() < CUT_EVERY) {
            return;
        }
        self.last_cut = Some(Instant::now());
        self.size = (self.size / 2).max(MIN_REQUEST_BYTES);
        tracing::debug!(request_bytes = self.size, why, "the backfill slows down");
    }
}

/// Adds `d` at `now` to `window`, forgetting what is older than [`BASE_WINDOW`].
fn push(window: &mut VecDeque<(Instant, Duration)>, now: Instant, d: Duration) {
    window.push_back((now, d));
    while window
        .front()
        .is_some_and(|(at, _)| now.duration_since(*at) > BASE_WINDOW)
    {
        window.pop_front();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    fn probe() -> (Arc<Mutex<LinkSample>>, LinkProbe) {
        let s = Arc::new(Mutex::new(LinkSample::default()));
        let p = {
            let s = s.clone();
            LinkProbe::new(move || *s.lock().unwrap())
        };
        (s, p)
    }

    fn uplink(s: &Mutex<LinkSample>, ms: u64) {
        let mut l = s.lock().unwrap();
        l.uplinks += 1;
        l.answered += 1;
        l.rtt = Some(Duration::from_millis(ms));
    }

    #[test]
    fn answers_as_quick_as_the_budget_grow_it_to_the_ceiling_and_slower_ones_do_not() {
        let (s, probe) = probe();
        let mut p = Pace::new(Some(8_000), 16_000, Some(probe));
        let start = p.request_bytes();
        assert!(start < 16_000);
        uplink(&s, 600);
        p.observe();
        // 0.6 s of round trip and the bytes at 8000 B/s, and a second: quick.
        p.answered(start, start, Duration::from_millis(1_400));
        assert_eq!(p.request_bytes(), start * 2);
        // It waited one and a half seconds more: no more.
        let size = p.request_bytes();
        p.answered(
            size,
            size,
            Duration::from_millis(600 + size * 1000 / 8_000 + 1_500),
        );
        assert_eq!(p.request_bytes(), size);
        // A small remainder that came quickly says nothing of the link.
        p.answered(size, 100, Duration::from_millis(700));
        assert_eq!(p.request_bytes(), size);
        for _ in 0..20 {
            let size = p.request_bytes();
            p.answered(size, size, Duration::from_millis(1_000));
        }
        assert_eq!(p.request_bytes(), 16_000);
        assert!(p.delivered().is_some());
    }

    #[test]
    fn uplinks_queueing_beyond_the_target_halve_it_but_a_lone_slow_uplink_does_not() {
        let (s, probe) = probe();
        let mut p = Pace::new(Some(8_000), 16_000, Some(probe));
        for _ in 0..20 {
            uplink(&s, 600);
            p.observe();
            let size = p.request_bytes();
            p.answered(size, size, Duration::from_millis(700));
        }
        assert_eq!(p.request_bytes(), 16_000);
        // One uplink held up by a retransmission: the filter keeps the least of three.
        uplink(&s, 3_000);
        p.observe();
        assert_eq!(p.request_bytes(), 16_000);
        // Three in a row: the link queues.
        for _ in 0..2 {
            uplink(&s, 3_000);
            p.observe();
        }
        assert_eq!(p.request_bytes(), 8_000);
    }

    #[test]
    fn a_request_unheard_halves_it_once_per_outage() {
        let mut p = Pace::new(None, 64_000, None);
        let start = p.request_bytes();
        for _ in 0..5 {
            p.last_cut = None;
            p.unheard();
        }
        assert_eq!(p.request_bytes(), start / 2);
        p.answered(start / 2, start / 2, Duration::from_millis(100));
        p.last_cut = None;
        p.unheard();
        assert_eq!(p.request_bytes(), start / 2);
    }

    #[test]
    fn an_outage_or_a_short_answer_halves_it_once_per_episode() {
        let (s, probe) = probe();
        let mut p = Pace::new(None, 64_000, Some(probe));
        let start = p.request_bytes();
        s.lock().unwrap().uplinks += 1;
        p.observe();
        assert_eq!(p.request_bytes(), start / 2);
        p.lost();
        assert_eq!(p.request_bytes(), start / 2, "cut once per episode");
        // The outage goes on: no more cuts for it.
        for _ in 0..5 {
            p.last_cut = None;
            s.lock().unwrap().uplinks += 1;
            p.observe();
        }
        assert_eq!(p.request_bytes(), start / 2);
        for _ in 0..100 {
            p.last_cut = None;
            p.lost();
        }
        assert_eq!(p.request_bytes(), MIN_REQUEST_BYTES);
    }
}
