//! The rover making itself safe: the authority's heartbeat (the DNMs' lease on it), its safing
//! when every ground station is lost, and its adopting a safing a DNM made on its own.
//!
//! The rules (README, "Commanding the rover from the ground"):
//! - With `on_link_loss = { after, task }`, no ground station heard for `after`: the authority
//!   records a safing (durably, with a new epoch) and announces it in its beat; every DNM that
//!   hears it puts `task` in force by itself. No transaction: a DNM that cannot be reached
//!   makes itself safe by its lease, so nobody waits for anybody.
//! - A DNM that has not heard the beat for `after` makes itself safe; when the authority hears
//!   of it (the DNM's brief), it adopts it as a safing of the whole rover.
//! - Nothing taken before a safing runs after it: time tags waiting are refused at once, and
//!   every command a station gave before it had seen the safing (its `safings_seen`) is
//!   refused when its turn comes, with the safing as the reason.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use dnm_proto::DnmBrief;
use dnm_proto::keys;
use dnm_proto::station::{Beat, Fate, RoverEvent, Safing};
use zenoh::Wait;
use zenoh::qos::{CongestionControl, Priority};

use crate::store::Finish;
use crate::{AuthorityError, Core, Shared, now_unix_ns, publish_rover};

/// How often the authority beats (and so how soon a DNM hears of a safing at the latest).
pub(crate) const BEAT_EVERY: Duration = Duration::from_millis(200);

/// Records a safing of the whole rover on `task`, refuses every time tag waiting, and
/// announces it at once. `what` names the event (`link_loss`, `safed`).
pub(crate) fn make_safe(
    s: &Shared,
    core: &mut Core,
    task: String,
    what: &str,
    reason: String,
) -> Result<Safing, AuthorityError> {
    let now = now_unix_ns();
    let safing = Safing {
        // Only ever grows, whatever happened to the store: one more than the last, and at
        // least the safing's rover time in milliseconds.
        epoch: (core.state.safings() + 1).max(now / 1_000_000),
        at_unix_ns: now,
        task: task.clone(),
        reason: reason.clone(),
    };
    core.state.task = Some(task);
    core.state.last_safing = Some(safing.clone());
    core.state.safe = true;
    core.state.changed_at_unix_ns = now;
    core.state.event(RoverEvent {
        at_unix_ns: now,
        what: what.into(),
        detail: reason,
        revision: core.state.revision,
        task: core.state.task.clone(),
    });
    let aborted = crate::sequence::abort_for_safing(core, &safing.reason);
    let timers = s.store.timers()?;
    let refusal = refusal(&safing);
    let fates = timers
        .iter()
        .map(|t| {
            (
                t.station.as_str(),
                t.seq,
                t.id.as_str(),
                Fate::Refused {
                    reason: refusal.clone(),
                },
            )
        })
        .collect();
    s.store.finish(Finish {
        fates,
        timers_remove: timers.iter().map(|t| (t.station.as_str(), t.seq)).collect(),
        state: Some(&core.state),
        sequence: aborted.as_ref(),
        ..Finish::default()
    })?;
    tracing::warn!(
        epoch = safing.epoch,
        task = %safing.task,
        refused_time_tags = timers.len(),
        "the rover is made safe: {}",
        safing.reason
    );
    publish_rover(s, core);
    beat_now(s);
    Ok(safing)
}

/// Why a command taken before `safing` does not run.
pub(crate) fn refusal(safing: &Safing) -> String {
    format!(
        "not run: the rover made itself safe (safing {}, on `{}`, at {} ns rover time: {}) after \
         this command was given; nothing given before the station saw the safing runs after \
         it. Send it again if it is still wanted",
        safing.epoch, safing.task, safing.at_unix_ns, safing.reason
    )
}

/// Whether a command given after the station had seen `seen` safings must be refused, and why.
pub(crate) fn stale(core: &Core, seen: u64) -> Option<String> {
    core.state
        .last_safing
        .as_ref()
        .filter(|l| seen < l.epoch)
        .map(refusal)
}

/// Adopts a safing a DNM made on its own since the last decision (it lost the authority, or
/// the authority had lost the ground and could not say so). Returns whether it did.
pub(crate) fn adopt_dnm_safing(s: &Shared, found: &[Option<DnmBrief>]) -> bool {
    let Ok(mut core) = s.core.lock() else {
        return false;
    };
    // The DNM's time of its safing on the authority's clock (its measured offset added):
    // made safe before what was decided since, that decision has it adopt, not this.
    let since = core.state.changed_at_unix_ns as i128;
    let Some((dnm, safed)) = found.iter().flatten().find_map(|b| {
        let x = b.safed.as_ref().filter(|x| x.epoch.is_none())?;
        let at = x.at_unix_ns as i128 + (b.clock_offset_ms.unwrap_or(0.0) * 1e6) as i128;
        (at > since).then(|| (b.dnm.clone(), x.clone()))
    }) else {
        return false;
    };
    if core.state.safe && core.state.task.as_ref() == Some(&safed.task) {
        // The rover is in a safing on that task already (the DNM lost the authority while it
        // was made safe, say): the DNM follows it by the beat; nothing new to refuse.
        return false;
    }
    let reason = format!(
        "DNM `{dnm}` made itself safe on `{}`: {}",
        safed.task, safed.reason
    );
    match make_safe(s, &mut core, safed.task, "safed", reason) {
        Ok(_) => true,
        Err(e) => {
            tracing::error!("adopting the safing of DNM `{dnm}`: {e}");
            false
        }
    }
}

/// How long a rover that is starting up waits for a computer it has not heard yet before it
/// counts it lost: the computers of a rover come up at their own pace.
pub(crate) const START_GRACE: Duration = Duration::from_secs(30);

/// When each DNM of the rover last answered the authority, and whether the rover is starting
/// up. It is starting up until the authority hears a DNM whose first answer shows a netlist in
/// force from before (the authority restarted on a running rover): then a DNM not heard since
/// the authority's start is as lost as one that went quiet, after the loss-of-signal time.
#[derive(Debug)]
pub(crate) struct DnmsHeard {
    last: BTreeMap<String, Instant>,
    /// DNMs that answered in this run.
    answered: BTreeSet<String>,
    starting_up: bool,
}

impl Default for DnmsHeard {
    fn default() -> Self {
        Self {
            last: BTreeMap::new(),
            answered: BTreeSet::new(),
            starting_up: true,
        }
    }
}

impl DnmsHeard {
    /// Takes in a pass's answers (`found` of `names`) at `now`.
    fn pass(&mut self, names: &[String], found: &[Option<DnmBrief>], now: Instant) {
        self.last.retain(|d, _| names.contains(d));
        for (d, b) in names.iter().zip(found) {
            match b {
                Some(b) => {
                    if self.answered.insert(d.clone()) && b.revision > 0 {
                        self.starting_up = false;
                    }
                    self.last.insert(d.clone(), now);
                }
                None => {
                    self.last.entry(d.clone()).or_insert(now);
                }
            }
        }
    }

    /// The first DNM silent for longer than it may be, and for how long.
    fn lost(&self, after: Duration, now: Instant) -> Option<(String, Duration)> {
        self.last.iter().find_map(|(d, t)| {
            let silent = now.duration_since(*t);
            let limit = if self.starting_up && !self.answered.contains(d) {
                after.max(START_GRACE)
            } else {
                after
            };
            (silent >= limit).then(|| (d.clone(), silent))
        })
    }
}

/// Makes the rover safe when a DNM of the rover has not answered for the loss-of-signal time:
/// down or cut off, it has made itself safe by its lease by then, and the others must not go
/// on without it. While the rover starts up, a DNM not heard yet has [`START_GRACE`] to come
/// up. `found` are the answers of `names` in this pass. Returns whether it did.
pub(crate) fn safe_on_silent_dnm(s: &Shared, names: &[String], found: &[Option<DnmBrief>]) -> bool {
    let Ok(mut heard) = s.dnms_heard.lock() else {
        return false;
    };
    let now = Instant::now();
    heard.pass(names, found, now);
    let Ok(mut core) = s.core.lock() else {
        return false;
    };
    let Some(rule) = core.netlist.on_link_loss.clone() else {
        return false;
    };
    let after = Duration::from_millis(rule.after_ms);
    let Some((dnm, silent)) = heard.lost(after, now) else {
        return false;
    };
    drop(heard);
    if core.state.safe && core.state.task.as_ref() == Some(&rule.task) {
        return false;
    }
    let reason = format!(
        "DNM `{dnm}` has not answered for {:.1} s (down or cut off, it is safe by its lease): \
         switching to `{}`",
        silent.as_secs_f64(),
        rule.task
    );
    match make_safe(s, &mut core, rule.task, "dnm_lost", reason) {
        Ok(_) => true,
        Err(e) => {
            tracing::error!("making the rover safe without DNM `{dnm}`: {e}");
            false
        }
    }
}

/// Wakes the beat thread: a beat goes out now.
pub(crate) fn beat_now(s: &Shared) {
    if let Ok(mut b) = s.beat.0.lock() {
        *b = true;
        s.beat.1.notify_all();
    }
}

/// Publishes the beat every [`BEAT_EVERY`], and at once when woken.
pub(crate) fn beat_loop(s: &Shared, publisher: &zenoh::pubsub::Publisher<'_>) {
    while !s.stop.load(Ordering::Relaxed) {
        let beat = {
            let rover = s.rover.lock().map(|r| r.clone()).unwrap_or_default();
            Beat {
                authority: s.name.clone(),
                at_unix_ns: now_unix_ns(),
                revision: rover.revision,
                task: rover.task.clone(),
                ground_silent_ms: s
                    .contact
                    .lock()
                    .map(|c| c.elapsed().as_millis() as u64)
                    .unwrap_or(0),
                safing: rover.last_safing.filter(|_| rover.safe),
                sequence: s.deferring.lock().ok().and_then(|d| d.clone()),
            }
        };
        if let Ok(bytes) = serde_json::to_vec(&beat)
            && let Err(e) = publisher.put(bytes).wait()
        {
            tracing::debug!("beat: {e}");
        }
        let Ok(b) = s.beat.0.lock() else {
            return;
        };
        if let Ok((mut b, _)) = s.beat.1.wait_timeout_while(b, BEAT_EVERY, |b| !*b) {
            *b = false;
        }
    }
}

/// The beat's publisher: first on the link, never blocking (a lost beat is followed by the
/// next).
pub(crate) fn beat_publisher(
    session: &zenoh::Session,
    system: &str,
) -> Result<zenoh::pubsub::Publisher<'static>, AuthorityError> {
    session
        .declare_publisher(keys::authority_beat(system))
        .priority(Priority::InteractiveHigh)
        .congestion_control(CongestionControl::Drop)
        .express(true)
        .wait()
        .map_err(AuthorityError::Zenoh)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn brief(dnm: &str, revision: u64) -> Option<DnmBrief> {
        serde_json::from_value(serde_json::json!({
            "dnm": dnm, "pid": 1, "revision": revision, "netlist_digest": "",
            "active_task": null, "preparing": null, "last_attempt": 0, "holding": null,
            "modules_down": 0,
        }))
        .unwrap()
    }

    fn names() -> Vec<String> {
        vec!["rover".into(), "vision".into()]
    }

    const AFTER: Duration = Duration::from_secs(2);

    #[test]
    fn a_computer_not_up_yet_has_the_start_up_grace() {
        let t0 = Instant::now();
        let mut h = DnmsHeard::default();
        h.pass(&names(), &[brief("rover", 0), None], t0);
        let t = t0 + AFTER * 2;
        h.pass(&names(), &[brief("rover", 1), None], t);
        assert_eq!(h.lost(AFTER, t), None);
        let t = t0 + START_GRACE;
        h.pass(&names(), &[brief("rover", 1), None], t);
        assert_eq!(h.lost(AFTER, t).unwrap().0, "vision");
    }

    #[test]
    fn a_computer_that_answered_once_is_lost_after_the_loss_of_signal_time() {
        let t0 = Instant::now();
        let mut h = DnmsHeard::default();
        h.pass(&names(), &[brief("rover", 0), brief("vision", 0)], t0);
        let t = t0 + AFTER;
        h.pass(&names(), &[brief("rover", 1), None], t);
        assert_eq!(h.lost(AFTER, t), Some(("vision".into(), AFTER)));
    }

    #[test]
    fn a_rover_that_never_heard_a_station_waits_the_start_up_grace_for_it() {
        let dir = std::env::temp_dir().join(format!("dnm-safing-grace-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let store = crate::store::Store::open(&dir.join("a.redb")).unwrap();
        let before = Instant::now();
        let contact = crate::last_contact(&store);
        assert!(contact >= before + START_GRACE);
        // Silence counts from then: none yet.
        assert_eq!(contact.elapsed(), Duration::ZERO);
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn an_authority_restarted_on_a_running_rover_gives_no_grace() {
        // `rover` answers with a netlist in force from before: the rover was running, and
        // `vision` not answering is a fault, not a slow start.
        let t0 = Instant::now();
        let mut h = DnmsHeard::default();
        h.pass(&names(), &[brief("rover", 7), None], t0);
        let t = t0 + AFTER;
        h.pass(&names(), &[brief("rover", 7), None], t);
        assert_eq!(h.lost(AFTER, t).unwrap().0, "vision");
    }
}
