//! The DNM's side of the transactions the system's authority runs across its DNMs: prepare and
//! hold, then put in force at the decided instant or drop; and taking over a decision a DNM
//! missed (it restarted, or was cut off).
//!
//! A DNM never puts a transaction in force on its own: a held transaction waits for the
//! decision, while the DNM serves the revision and task in force, for at most
//! [`crate::safe::HOLD_LIMIT`]; then it is given up (the authority has a DNM that missed a
//! commit adopt the decided revision). Safing (`safe.rs`) drops whatever is held.

use dnm_proto::clock::now_unix_ns;
use std::time::{Duration, Instant};

use dnm_module::protocol::monotonic_ns;
use dnm_netlist::Netlist;
use dnm_proto::SwitchRecord;

use crate::command::{Decision, Reply, Txn};
use crate::error::DnmError;
use crate::node::Dnm;
use crate::pending::{
    DECIDED, DecideResult, FINE_WAIT, HeldSwitch, QUIET_BEFORE, QUIET_HOLD, Scheduled,
};

/// The local instant of a wall-clock time (now if it has passed).
fn due_instant(at_unix_ns: u64) -> Instant {
    let now = Instant::now();
    now + Duration::from_nanos(at_unix_ns.saturating_sub(now_unix_ns()))
}

impl Dnm {
    /// The transaction held or scheduled here, if any.
    pub(crate) fn holding(&self) -> Option<u64> {
        self.held_switch
            .as_ref()
            .map(|h| h.id)
            .or_else(|| self.apply.as_ref().and_then(|p| p.txn))
            .or_else(|| self.scheduled.as_ref().map(|s| s.decision.id))
    }

    /// When the scheduled decision is due, wall clock, if one is.
    pub(crate) fn scheduled_at(&self) -> Option<u64> {
        self.scheduled.as_ref().map(|s| s.decision.at_unix_ns)
    }

    fn decided(&self, id: u64) -> Option<DecideResult> {
        self.decided
            .iter()
            .find(|(i, _)| *i == id)
            .map(|(_, r)| r.clone())
    }

    pub(crate) fn remember_decided(&mut self, id: u64, r: DecideResult) {
        self.decided.push_back((id, r));
        if self.decided.len() > DECIDED {
            self.decided.pop_front();
        }
    }

    pub(crate) fn prepare_txn(&mut self, txn: Txn, reply: Reply<Result<(), DnmError>>) {
        // A retried prepare of what is held, scheduled or done already.
        if self.held_switch.as_ref().is_some_and(|h| h.id == txn.id)
            || self
                .scheduled
                .as_ref()
                .is_some_and(|s| s.decision.id == txn.id)
            || self.decided(txn.id).is_some()
        {
            return reply.send(Ok(()));
        }
        if let Some(p) = self.apply.as_mut().filter(|p| p.txn == Some(txn.id)) {
            if p.held {
                reply.send(Ok(()));
            } else {
                p.ready.push(reply);
            }
            return;
        }
        if let Some(other) = self.holding() {
            return reply.send(Err(DnmError::Holding {
                dnm: self.name.clone(),
                txn: other,
                until: " until its decision",
            }));
        }
        if self.stopping_all {
            return reply.send(Err(DnmError::Stopped));
        }
        let Some(netlist) = txn.netlist else {
            let task = txn.task.unwrap_or_default();
            if txn.revision != self.revision {
                return reply.send(Err(DnmError::OtherRevision {
                    dnm: self.name.clone(),
                    in_force: self.revision,
                    wanted: txn.revision,
                }));
            }
            if !self.tasks.contains(&task) {
                return reply.send(Err(DnmError::UnknownTask {
                    task,
                    known: self.tasks.join(", "),
                }));
            }
            self.held_switch = Some(HeldSwitch {
                id: txn.id,
                task,
                since: Instant::now(),
            });
            self.publish();
            return reply.send(Ok(()));
        };
        if self.apply.is_some() || !self.queued_applies.is_empty() {
            return reply.send(Err(DnmError::Applying {
                dnm: self.name.clone(),
                retry: "send the transaction again",
            }));
        }
        if self.waits_for_stopping(&netlist) {
            // A process of a module it starts again is still stopping (an apply undone a
            // moment ago): prepared once it is gone, within the authority's prepare timeout.
            if self.deferred_prepare.is_some() {
                return reply.send(Err(DnmError::StillStopping(self.name.clone())));
            }
            self.deferred_prepare = Some((
                Txn {
                    netlist: Some(netlist),
                    ..txn
                },
                reply,
            ));
            return;
        }
        match self.prepare_apply(*netlist, None, Some(txn.revision)) {
            Ok(mut p) => {
                p.txn = Some(txn.id);
                p.task = txn.task;
                p.ready.push(reply);
                self.apply = Some(p);
                self.progress_apply();
            }
            Err(e) => reply.send(Err(e)),
        }
    }

    /// Prepares a transaction that waited for module processes to stop, once they have.
    pub(crate) fn retry_deferred_prepare(&mut self) {
        let ready = self.deferred_prepare.as_ref().is_some_and(|(t, _)| {
            t.netlist
                .as_ref()
                .is_none_or(|n| !self.waits_for_stopping(n))
        });
        if ready && let Some((txn, reply)) = self.deferred_prepare.take() {
            self.prepare_txn(txn, reply);
        }
    }

    pub(crate) fn decide_txn(&mut self, d: Decision, reply: Reply<DecideResult>) {
        if let Some(r) = self.decided(d.id) {
            return reply.send(r);
        }
        if let Some((_, waiting)) = self.deferred_prepare.take_if(|(t, _)| t.id == d.id) {
            // Decided before it could be prepared: it can only have been dropped.
            waiting.send(Err(DnmError::Dropped(d.id)));
            return reply.send(Ok(None));
        }
        if let Some(s) = self.scheduled.as_mut().filter(|s| s.decision.id == d.id) {
            s.replies.push(reply);
            return;
        }
        let holds_switch = self.held_switch.as_ref().is_some_and(|h| h.id == d.id);
        let holds_apply = self
            .apply
            .as_ref()
            .is_some_and(|p| p.txn == Some(d.id) && p.held);
        if !holds_switch && !holds_apply {
            if !d.commit {
                // Nothing held; a prepare still in progress is dropped too.
                if let Some(p) = self.apply.take_if(|p| p.txn == Some(d.id)) {
                    self.abort_apply(p, DnmError::Dropped(d.id));
                }
                return reply.send(Ok(None));
            }
            if self.revision == d.revision && self.active == d.task {
                return reply.send(Ok(None));
            }
            return reply.send(Err(DnmError::NotHeld {
                dnm: self.name.clone(),
                txn: d.id,
                revision: d.revision,
            }));
        }
        if !d.commit {
            if holds_switch {
                self.held_switch = None;
            } else if let Some(p) = self.apply.take() {
                self.abort_apply(p, DnmError::Dropped(d.id));
            }
            self.remember_decided(d.id, Ok(None));
            self.publish();
            return reply.send(Ok(None));
        }
        let due = due_instant(d.at_unix_ns);
        let late = now_unix_ns().saturating_sub(d.at_unix_ns);
        if late > 0 {
            tracing::warn!(
                dnm = %self.name,
                txn = d.id,
                late_ms = late as f64 / 1e6,
                "the decision arrived after its instant: switching now"
            );
        }
        self.scheduled = Some(Scheduled {
            decision: d,
            due,
            replies: vec![reply],
        });
        self.run_due();
    }

    /// Runs the DNM's thread at real-time priority until the scheduled decision is in force
    /// (if the system allows it: root, or `CAP_SYS_NICE`, or an `RLIMIT_RTPRIO`), so a loaded
    /// machine does not make this DNM switch later than the others. Module processes started
    /// meanwhile do not inherit it.
    pub(crate) fn hurry(&mut self) {
        if self.hurried || self.scheduled.is_none() {
            return;
        }
        self.hurried = true;
        let param = libc::sched_param { sched_priority: 10 };
        // SAFETY: sets this thread's own scheduling policy; the parameter outlives the call.
        let r = unsafe {
            libc::pthread_setschedparam(
                libc::pthread_self(),
                libc::SCHED_FIFO | libc::SCHED_RESET_ON_FORK,
                &param,
            )
        };
        if r != 0 && !self.warned_realtime {
            self.warned_realtime = true;
            tracing::info!(
                dnm = %self.name,
                "no real-time priority for the moment of a switch (error {r}); on a loaded \
                 machine this DNM may switch a little later than the others"
            );
        }
    }

    pub(crate) fn calm(&mut self) {
        if !self.hurried {
            return;
        }
        self.hurried = false;
        let param = libc::sched_param { sched_priority: 0 };
        // SAFETY: as in `hurry`.
        unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_OTHER, &param) };
    }

    /// Whether a switch is about to be decided or put in force: the loop then leaves what can
    /// wait (supervision, starting processes) until it is done, so it never holds up the
    /// store. A prepared switch counts for a short while only: an authority that went away
    /// must not stop supervision.
    pub(crate) fn quiet(&self) -> bool {
        self.until_due().is_some_and(|d| d < QUIET_BEFORE)
            || self
                .held_switch
                .as_ref()
                .is_some_and(|h| h.since.elapsed() < QUIET_HOLD)
    }

    /// How long the loop may wait before it must call [`Dnm::run_due`].
    pub(crate) fn until_due(&self) -> Option<Duration> {
        let s = self.scheduled.as_ref()?;
        Some(
            s.due
                .saturating_duration_since(Instant::now())
                .saturating_sub(FINE_WAIT),
        )
    }

    /// Puts the scheduled decision in force once its instant is near: sleeps out the last
    /// moment (at most [`FINE_WAIT`]), then stores.
    pub(crate) fn run_due(&mut self) {
        let Some(s) = self.scheduled.as_ref() else {
            return;
        };
        let left = s.due.saturating_duration_since(Instant::now());
        if left > FINE_WAIT {
            return;
        }
        if !left.is_zero() {
            std::thread::sleep(left);
        }
        let Some(s) = self.scheduled.take() else {
            return;
        };
        let r = self.put_in_force(&s.decision).map(Some);
        self.calm();
        if let Err(e) = &r {
            tracing::error!(dnm = %self.name, txn = s.decision.id, "decision not put in force: {e}");
        }
        self.remember_decided(s.decision.id, r.clone());
        self.publish();
        for reply in s.replies {
            reply.send(r.clone());
        }
    }

    fn put_in_force(&mut self, d: &Decision) -> Result<SwitchRecord, DnmError> {
        if let Some(h) = self.held_switch.take_if(|h| h.id == d.id) {
            self.safed = None;
            return self.switch(&h.task);
        }
        if let Some(p) = self.apply.take_if(|p| p.txn == Some(d.id) && p.held) {
            let at_ns = monotonic_ns();
            let start = Instant::now();
            let (from, to) = self.commit(p);
            return Ok(SwitchRecord {
                dnm: self.name.clone(),
                revision: self.revision,
                from,
                to: to.unwrap_or_default(),
                duration_ns: start.elapsed().as_nanos() as u64,
                at_ns,
            });
        }
        Err(DnmError::NoLongerHeld(d.id))
    }

    /// The decided revision `revision` has no place for this DNM (an apply removed it): its
    /// modules stop, and it runs nothing until a netlist that declares it is adopted.
    fn retire(&mut self, revision: u64) -> u64 {
        let running: Vec<String> = self
            .modules
            .iter()
            .filter(|(_, s)| s.child.is_some())
            .map(|(n, _)| n.clone())
            .collect();
        // Every module, those waiting to be restarted too.
        let all: Vec<String> = self.modules.keys().cloned().collect();
        for name in &all {
            self.stop_module(name);
        }
        if !running.is_empty() {
            tracing::warn!(
                dnm = %self.name,
                revision,
                "the decided netlist no longer declares this DNM: its modules stop"
            );
            self.event(
                "_dnm",
                "retired",
                format!(
                    "revision {revision} no longer declares DNM `{}`: {} modules stopped",
                    self.name,
                    running.len()
                ),
            );
        }
        self.last_attempt = self.last_attempt.max(revision);
        self.publish();
        revision
    }

    /// Takes over `revision` in `task` as the authority decided it: only a switch when the
    /// revision is in force already, else an apply of `netlist` as that revision.
    pub(crate) fn adopt(
        &mut self,
        revision: u64,
        task: Option<String>,
        netlist: Netlist,
        reply: Reply<Result<u64, DnmError>>,
    ) {
        if let Some(id) = self.holding() {
            return reply.send(Err(DnmError::Holding {
                dnm: self.name.clone(),
                txn: id,
                until: "; decide it first",
            }));
        }
        if netlist.dnm(&self.name).is_none() {
            return reply.send(Ok(self.retire(revision)));
        }
        let same = self
            .netlist
            .as_ref()
            .is_some_and(|n| n.digest() == netlist.digest());
        if revision == self.revision && same {
            if let Some(t) = task.filter(|t| self.active.as_ref() != Some(t)) {
                self.safed = None;
                if let Err(e) = self.switch(&t) {
                    return reply.send(Err(e));
                }
                self.publish();
            }
            return reply.send(Ok(revision));
        }
        if self.apply.is_some() || !self.queued_applies.is_empty() {
            return reply.send(Err(DnmError::Applying {
                dnm: self.name.clone(),
                retry: "adopt again later",
            }));
        }
        match self.prepare_apply(netlist, None, Some(revision)) {
            Ok(mut p) => {
                p.task = task;
                p.replies.push(reply);
                self.apply = Some(p);
                self.progress_apply();
            }
            Err(e) => reply.send(Err(e)),
        }
    }
}
