//! The DNM's lease on its authority: it hears the authority's beat
//! ([`dnm_proto::station::Beat`]) a few times a second and makes itself safe when it must,
//! whoever else is down.
//!
//! With `on_link_loss = { after, task }` in the netlist in force, a DNM that follows an
//! authority puts its own modules on `task`:
//! - when the beat carries the authority's safing (the authority lost every ground station);
//! - when it has not heard a beat for `after` (the authority's computer, or the network to it,
//!   is down): through the authority it has lost the ground too;
//! - when the beat says no ground station was heard for `after` + [`GRACE`] and the authority
//!   has still not made the rover safe (its worker is held up, by a transaction waiting for a
//!   DNM that died, say).
//!
//! Every DNM that is cut off converges on the same task, so none needs another to get there.
//! The beat also carries the authority's wall clock: each DNM measures its own clock's offset,
//! reports it, and refuses transactions while it is beyond [`MAX_CLOCK_OFFSET`].

use dnm_proto::clock::now_unix_ns;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use dnm_core::{Command, Commander, DnmError, Reply, SafeOrder, Snapshot};
use dnm_proto::LeaseReport;
use dnm_proto::station::Beat;

/// Beyond the loss-of-signal time, how long DNMs give the authority to make the rover safe
/// itself before each does it on its own.
pub const GRACE: Duration = Duration::from_secs(1);

/// The largest offset between a DNM's wall clock and its authority's at which it takes part in
/// transactions: the DNMs put a decision in force at one wall-clock instant, so an offset is a
/// switch that much early or late.
pub const MAX_CLOCK_OFFSET: Duration = Duration::from_millis(250);

/// How often the lease is checked.
const CHECK_EVERY: Duration = Duration::from_millis(100);

/// An order not yet seen in force is sent again after this long.
const RESEND_AFTER: Duration = Duration::from_secs(1);

/// Beats that arrive closer together than this, though sent further apart, were held up.
const BURST: Duration = Duration::from_millis(50);

/// Clock offsets kept (the largest is the best estimate: a beat's delay only lowers it).
const OFFSETS: usize = 8;

/// What the lease knows.
#[derive(Debug, Default)]
pub(crate) struct Lease {
    /// `on_link_loss` of the netlist in force: (after, task).
    rule: Option<(Duration, String)>,
    /// When a netlist was first put in force here (the lease runs from then until a beat).
    since: Option<Instant>,
    last: Option<(Instant, Beat)>,
    offsets: VecDeque<f64>,
    /// The last order sent and when.
    sent: Option<(SafeOrder, Instant)>,
    /// The newest of the authority's safings this DNM put in force: a beat announcing it again
    /// (sent before the decision that ended it, and late) is not followed twice.
    followed: u64,
}

impl Lease {
    /// The netlist in force changed.
    pub(crate) fn committed(&mut self, rule: Option<(Duration, String)>) {
        self.rule = rule;
        self.since.get_or_insert_with(Instant::now);
    }

    /// A beat arrived from `authority` (others are ignored).
    pub(crate) fn heard(&mut self, authority: &str, beat: Beat) {
        if beat.authority != authority {
            return;
        }
        let now = Instant::now();
        // Beats held up on the way (this process was stopped, the network stalled) arrive
        // together long after they were sent: only the first of such a burst is taken as a
        // clock sample, and the offset is the largest of the last few (a late sample only
        // lowers it), so a backlog never passes for a clock that is off.
        let burst = self.last.as_ref().is_some_and(|(t, b)| {
            now.duration_since(*t) < BURST
                && beat.at_unix_ns > b.at_unix_ns.saturating_add(BURST.as_nanos() as u64)
        });
        if !burst {
            let offset_ms = (beat.at_unix_ns as f64 - now_unix_ns() as f64) / 1e6;
            self.offsets.push_back(offset_ms);
            if self.offsets.len() > OFFSETS {
                self.offsets.pop_front();
            }
        }
        self.last = Some((now, beat));
    }

    /// The authority's clock minus this DNM's, ms.
    pub(crate) fn clock_offset_ms(&self) -> Option<f64> {
        self.offsets.iter().copied().reduce(f64::max)
    }

    pub(crate) fn report(&self, authority: &str) -> LeaseReport {
        LeaseReport {
            authority: authority.to_string(),
            heard_ms: self
                .last
                .as_ref()
                .map(|(t, _)| t.elapsed().as_millis() as u64),
            clock_offset_ms: self.clock_offset_ms(),
            max_clock_offset_ms: MAX_CLOCK_OFFSET.as_millis() as u64,
        }
    }

    /// Why a transaction must be refused here, if it must: this DNM's clock is too far from
    /// the authority's.
    pub(crate) fn clock_refusal(&self, dnm: &str) -> Option<String> {
        let offset = self.clock_offset_ms()?;
        if offset.abs() <= MAX_CLOCK_OFFSET.as_secs_f64() * 1e3 {
            return None;
        }
        Some(format!(
            "DNM `{dnm}`'s clock is {:.3} s {} the authority's (at most {} ms is taken): it would \
             switch at the wrong moment; synchronise its clock (NTP/PTP) and send the command again",
            offset.abs() / 1e3,
            if offset > 0.0 { "behind" } else { "ahead of" },
            MAX_CLOCK_OFFSET.as_millis()
        ))
    }

    /// What the DNM must do now, if anything: the order to put in force.
    fn due(&self, authority: &str, snapshot: Option<&Snapshot>) -> Option<SafeOrder> {
        let (after, task) = self.rule.as_ref()?;
        let report = &snapshot?.report;
        if report.revision == 0 {
            return None;
        }
        let safed = report.safed.as_ref();
        let on = |task: &str| report.active_task.as_deref() == Some(task);
        match &self.last {
            Some((at, beat)) if at.elapsed() < *after => {
                if let Some(s) = &beat.safing {
                    let followed = s.epoch <= self.followed
                        || safed.is_some_and(|x| x.epoch == Some(s.epoch)) && on(&s.task);
                    return (!followed).then(|| SafeOrder {
                        task: s.task.clone(),
                        epoch: Some(s.epoch),
                        reason: s.reason.clone(),
                    });
                }
                let silent = Duration::from_millis(beat.ground_silent_ms);
                // A sequence running goes on through the silence (the authority makes the
                // rover safe when it ends).
                (silent >= *after + GRACE && safed.is_none() && beat.sequence.is_none()).then(|| SafeOrder {
                    task: task.clone(),
                    epoch: None,
                    reason: format!(
                        "the authority `{authority}` has heard no ground station for {:.1} s and \
                         has not made the rover safe",
                        silent.as_secs_f64()
                    ),
                })
            }
            last => {
                let since = last.as_ref().map(|(t, _)| *t).or(self.since)?;
                let silent = since.elapsed();
                (silent >= *after && safed.is_none()).then(|| SafeOrder {
                    task: task.clone(),
                    epoch: None,
                    reason: format!(
                        "no word from the authority `{authority}` for {:.1} s",
                        silent.as_secs_f64()
                    ),
                })
            }
        }
    }
}

/// Checks the lease every [`CHECK_EVERY`] until `stop`, and hands the DNM what is due.
pub(crate) fn lease_loop(
    dnm: &str,
    authority: &str,
    lease: &Mutex<Lease>,
    snapshot: &dyn Fn() -> Option<Arc<Snapshot>>,
    commander: &Commander,
    stop: &std::sync::atomic::AtomicBool,
) {
    while !stop.load(std::sync::atomic::Ordering::Relaxed) {
        std::thread::sleep(CHECK_EVERY);
        let snap = snapshot();
        let Ok(mut l) = lease.lock() else {
            return;
        };
        if let Some(e) = snap
            .as_ref()
            .and_then(|s| s.report.safed.as_ref())
            .and_then(|s| s.epoch)
        {
            l.followed = l.followed.max(e);
        }
        let Some(order) = l.due(authority, snap.as_deref()) else {
            l.sent = None;
            continue;
        };
        if l.sent.as_ref().is_some_and(|(o, t)| {
            (&o.task, o.epoch) == (&order.task, order.epoch) && t.elapsed() < RESEND_AFTER
        }) {
            continue;
        }
        l.sent = Some((order.clone(), Instant::now()));
        drop(l);
        tracing::warn!(dnm, task = %order.task, epoch = ?order.epoch, "making the DNM safe: {}", order.reason);
        let name = dnm.to_string();
        let reply = Reply::new(move |r: Result<(), DnmError>| {
            if let Err(e) = r {
                tracing::error!(dnm = %name, "could not make the DNM safe: {e}");
            }
        });
        if let Err(e) = commander.send(Command::Safe { order, reply }) {
            tracing::error!(dnm, "could not make the DNM safe: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use dnm_proto::Safed;
    use dnm_proto::station::Safing;

    fn snapshot(task: &str, safed: Option<Safed>) -> Snapshot {
        let report = serde_json::json!({
            "system": "s", "dnm": "drive", "pid": 1, "revision": 3, "netlist_digest": "d",
            "netlist_file": null, "active_task": task, "tasks": ["auto", "safe"],
            "cpu_percent": 0.0, "memory": null, "modules": [], "switches": [],
            "cleaned_dead_nodes": 0, "safed": safed,
        });
        let netlist = serde_json::json!({
            "system": "s", "dnm": "drive", "revision": 3, "digest": "d", "file": null,
            "active_task": task, "text": null,
        });
        Snapshot {
            report: serde_json::from_value(report).unwrap(),
            netlist: serde_json::from_value(netlist).unwrap(),
            taken: std::time::Instant::now(),
        }
    }

    fn beat(ground_silent_ms: u64, safing: Option<Safing>) -> Beat {
        Beat {
            authority: "rover".into(),
            at_unix_ns: now_unix_ns(),
            revision: 3,
            task: Some("auto".into()),
            ground_silent_ms,
            safing,
            sequence: None,
        }
    }

    fn lease(after_ms: u64) -> Lease {
        let mut l = Lease::default();
        l.committed(Some((Duration::from_millis(after_ms), "safe".into())));
        l
    }

    #[test]
    fn a_dnm_that_hears_nothing_for_the_loss_time_makes_itself_safe() {
        let mut l = lease(1000);
        let snap = snapshot("auto", None);
        l.heard("rover", beat(0, None));
        assert_eq!(l.due("rover", Some(&snap)), None);
        // A beat from another authority does not count.
        l.last = l
            .last
            .take()
            .map(|(_, b)| (Instant::now() - Duration::from_secs(2), b));
        l.heard("impostor", beat(0, None));
        let order = l.due("rover", Some(&snap)).expect("safe by its lease");
        assert_eq!((order.task.as_str(), order.epoch), ("safe", None));
        assert!(order.reason.contains("no word from the authority `rover`"));
        // Once safe on its own, nothing more to do.
        let safed = Safed {
            epoch: None,
            at_unix_ns: 1,
            task: "safe".into(),
            reason: order.reason,
        };
        assert_eq!(l.due("rover", Some(&snapshot("safe", Some(safed)))), None);
    }

    #[test]
    fn the_authoritys_safing_is_followed_and_its_silence_on_the_ground_covered() {
        let mut l = lease(1000);
        let safing = Safing {
            epoch: 2,
            at_unix_ns: 1,
            task: "safe".into(),
            reason: "no ground station".into(),
        };
        l.heard("rover", beat(1500, Some(safing.clone())));
        let order = l.due("rover", Some(&snapshot("auto", None))).unwrap();
        assert_eq!(order.epoch, Some(2));
        let followed = Safed {
            epoch: Some(2),
            at_unix_ns: 1,
            task: "safe".into(),
            reason: safing.reason,
        };
        assert_eq!(
            l.due("rover", Some(&snapshot("safe", Some(followed)))),
            None
        );
        // The rover was commanded out of it; a late beat still announcing it is not followed.
        l.followed = 2;
        assert_eq!(l.due("rover", Some(&snapshot("auto", None))), None);
        // The authority heard no station for longer than the loss time and a grace, and has
        // not made the rover safe: the DNM does.
        l.heard("rover", beat(1000 + GRACE.as_millis() as u64, None));
        let order = l.due("rover", Some(&snapshot("auto", None))).unwrap();
        assert_eq!(order.epoch, None);
        assert!(order.reason.contains("has not made the rover safe"));
        // Without a loss-of-signal rule there is nothing to do.
        l.committed(None);
        assert_eq!(l.due("rover", Some(&snapshot("auto", None))), None);
    }

    /// Beats held up for a while (the DNM's process was stopped) arrive in a burst: they do
    /// not pass for a clock that is off.
    #[test]
    fn a_backlog_of_beats_is_not_a_clock_offset() {
        let mut l = lease(1000);
        let now = now_unix_ns();
        for i in 0..20u64 {
            let mut b = beat(0, None);
            b.at_unix_ns = now - 30_000_000_000 + i * 200_000_000;
            l.heard("rover", b);
        }
        std::thread::sleep(BURST * 2);
        l.heard("rover", beat(0, None));
        assert_eq!(l.clock_refusal("drive"), None, "{:?}", l.offsets);
    }

    #[test]
    fn a_beat_from_the_end_of_time_is_heard_without_harm() {
        let mut l = lease(1000);
        let mut b = beat(0, None);
        b.at_unix_ns = u64::MAX;
        l.heard("rover", b.clone());
        l.heard("rover", b);
        assert!(l.clock_refusal("drive").is_some(), "{:?}", l.offsets);
    }

    #[test]
    fn a_clock_far_from_the_authoritys_refuses_transactions() {
        let mut l = lease(1000);
        let mut b = beat(0, None);
        b.at_unix_ns += 120_000_000_000;
        l.heard("rover", b);
        let why = l.clock_refusal("drive").unwrap();
        assert!(why.contains("DNM `drive`'s clock is 120.0"), "{why}");
        assert!(why.contains("behind"), "{why}");
        let mut l = lease(1000);
        l.heard("rover", beat(0, None));
        assert_eq!(l.clock_refusal("drive"), None);
    }
}
