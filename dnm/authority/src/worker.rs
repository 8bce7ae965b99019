//! The worker: stored commands run one at a time, in arrival order; time tags waiting for their
//! rover time; loss of signal.

use crate::*;

pub(crate) fn worker_loop(s: &Shared) {
    // The job waiting for the rover's DNMs to be in step, and since when.
    let mut gate: Option<(String, Instant)> = None;
    while !s.stop.load(Ordering::Relaxed) {
        match work_once(s, &mut gate) {
            Ok(true) => {}
            Ok(false) => s.sleep(Duration::from_millis(100)),
            Err(e) => {
                tracing::error!("authority: {e}");
                s.sleep(Duration::from_secs(1));
            }
        }
    }
}

/// What the worker does next.
pub(crate) enum Job {
    /// A station was heard again after the link was lost.
    LinkBack,
    LinkLoss {
        task: String,
        silent: Duration,
    },
    Timer(Timer),
    Command(String, Sent),
    /// A sequence's step that is a transaction or its end: (name, run, step).
    Step((String, u64, usize)),
    /// What the sequencer found due.
    Due(sequence::Due),
}

impl Job {
    fn key(&self) -> String {
        match self {
            Job::LinkBack => "link-back".into(),
            Job::LinkLoss { .. } => "link-loss".into(),
            Job::Timer(t) => format!("timer {} {}", t.station, t.seq),
            Job::Command(st, c) => format!("command {st} {}", c.seq),
            Job::Step((name, run, step)) => format!("sequence {name} {run} step {step}"),
            Job::Due(d) => format!("sequence {} {} due {:?}", d.name, d.run, d.what),
        }
    }

    /// Whether it changes what the DNMs run (and so needs them all in step first).
    fn transacts(&self) -> bool {
        match self {
            Job::LinkBack => false,
            // Safing is no transaction: DNMs that cannot be reached make themselves safe.
            Job::LinkLoss { .. } => false,
            Job::Timer(_) => true,
            Job::Command(_, c) => !matches!(c.order, Order::Cancel { .. } | Order::Sequence { .. }),
            Job::Step(_) => true,
            Job::Due(d) => d.transacts(),
        }
    }
}

pub(crate) fn next_job(s: &Shared, core: &Core) -> Result<Option<Job>, AuthorityError> {
    if s.heard.load(Ordering::Relaxed) && core.state.link_lost {
        return Ok(Some(Job::LinkBack));
    }
    if let Some(l) = &core.netlist.on_link_loss {
        let silent = s.contact.lock().map(|c| c.elapsed()).unwrap_or_default();
        // A sequence running goes on through the silence unless the netlist says otherwise;
        // the rover is made safe once it ends.
        if silent >= Duration::from_millis(l.after_ms)
            && !core.state.link_lost
            && sequence::defers_link_loss(core).is_none()
        {
            return Ok(Some(Job::LinkLoss {
                task: l.task.clone(),
                silent,
            }));
        }
    }
    // What a sequence's conditions or waits made due (a guard first).
    if let Some(d) = s.sequencer.peek() {
        return Ok(Some(Job::Due(d)));
    }
    // Time-tagged switches whose time has come (prepared a little ahead).
    let margin = tag_margin(s);
    let now = now_unix_ns();
    let cancels = s.store.pending_cancels()?;
    let timers = s.store.timers()?;
    let due = tag_clock(s, &timers);
    let timer = timers
        .into_iter()
        // A cancel already taken for it runs first (the station's earlier commands with it).
        .filter(|t| !cancels.contains(&(t.station.clone(), t.seq)))
        .min_by_key(|t| t.at_unix_ns);
    // Due by the wall clock and by the monotonic one: a forward step of the wall clock does
    // not fire a tag early.
    let is_due = |t: &Timer, ahead: u64| {
        t.at_unix_ns <= now + ahead
            && due.get(&(t.station.clone(), t.seq)).is_none_or(|d| {
                d.saturating_duration_since(Instant::now()).as_nanos() as u64 <= ahead
            })
    };
    if let Some(t) = timer.as_ref().filter(|t| is_due(t, margin)) {
        return Ok(Some(Job::Timer(t.clone())));
    }
    if let Some(step) = sequence::next_step(core) {
        return Ok(Some(Job::Step(step)));
    }
    let Some((station, sent)) = s.store.next_command()? else {
        return Ok(None);
    };
    // A command that would still hold the worker when a time tag is due to be prepared waits
    // for it: the tag is prepared early and runs at its time, the command right after.
    let busy = s
        .timing
        .lock()
        .map(|t| t.busy)
        .unwrap_or_default()
        .max(MIN_BUSY)
        .as_nanos() as u64;
    if !matches!(sent.order, Order::Cancel { .. })
        && let Some(t) = timer.filter(|t| is_due(t, margin + busy))
    {
        return Ok(Some(Job::Timer(t)));
    }
    Ok(Some(Job::Command(station, sent)))
}

/// Each time tag's instant on the monotonic clock, fixed when the authority first sees the tag
/// (from the wall clock then): a later step of the wall clock moves the wall-clock instant, not
/// this one, and a tag runs only once both have come. Tags no longer waiting are forgotten.
pub(crate) fn tag_clock(s: &Shared, timers: &[Timer]) -> BTreeMap<(String, u64), Instant> {
    let Ok(mut clock) = s.tag_clock.lock() else {
        return BTreeMap::new();
    };
    let now = now_unix_ns();
    clock.retain(|k, _| timers.iter().any(|t| (&t.station, t.seq) == (&k.0, k.1)));
    for t in timers {
        clock.entry((t.station.clone(), t.seq)).or_insert_with(|| {
            Instant::now() + Duration::from_nanos(t.at_unix_ns.saturating_sub(now))
        });
    }
    clock.clone()
}

/// Longest wait for the rover's DNMs to be in step before a transaction is tried anyway (and
/// refused with what the DNMs say).
pub(crate) const READY_WAIT: Duration = Duration::from_secs(30);

/// Does one piece of work if there is one; returns whether it did.
pub(crate) fn work_once(
    s: &Shared,
    gate: &mut Option<(String, Instant)>,
) -> Result<bool, AuthorityError> {
    let lock = || s.core.lock().map_err(|_| AuthorityError::Poisoned);
    let (job, snapshot) = {
        let core = lock()?;
        let Some(job) = next_job(s, &core)? else {
            *gate = None;
            return Ok(false);
        };
        let snapshot = job.transacts().then(|| Snapshot::of(&core));
        (job, snapshot)
    };
    if let Some(snap) = snapshot {
        // A DNM that restarted or missed a decision is brought in step by the reconciler
        // first: a transaction now would only be refused by it.
        let key = job.key();
        let since = match gate.as_ref() {
            Some((k, t)) if *k == key => *t,
            _ => Instant::now(),
        };
        *gate = Some((key, since));
        if since.elapsed() < READY_WAIT
            && let Some(why) = out_of_step(s, &snap)
        {
            tracing::debug!("waiting for the rover's DNMs: {why}");
            return Ok(false);
        }
    }
    *gate = None;
    let mut core = lock()?;
    let core = &mut *core;
    match job {
        Job::LinkBack => {
            core.state.link_lost = false;
            let e = RoverEvent {
                at_unix_ns: now_unix_ns(),
                what: "link_back".into(),
                detail: "a ground station was heard again; the rover stays in its task".into(),
                revision: core.state.revision,
                task: core.state.task.clone(),
            };
            tracing::info!("ground station heard again");
            core.state.event(e);
            s.store.save_state(&core.state)?;
        }
        Job::LinkLoss { task, silent } => {
            let reason = format!(
                "no ground station heard for {:.1} s: switching to `{task}`",
                silent.as_secs_f64()
            );
            s.heard.store(false, Ordering::Relaxed);
            core.state.link_lost = true;
            safing::make_safe(s, core, task, "link_loss", reason)?;
        }
        Job::Timer(t) if let Some(reason) = timer_refusal(core, &t) => {
            tracing::warn!(station = %t.station, seq = t.seq, "time-tagged switch refused: {reason}");
            s.store.finish(Finish {
                fates: vec![(&t.station, t.seq, &t.id, Fate::Refused { reason })],
                timer_remove: Some((&t.station, t.seq)),
                ..Finish::default()
            })?;
        }
        Job::Timer(t) => {
            let origin = Origin {
                cmd: Some((t.station.clone(), t.seq, t.id.clone())),
                timer_remove: Some((t.station.clone(), t.seq)),
                step: None,
                given_unix_ns: None,
            };
            transact(
                s,
                core,
                None,
                Some(t.task.clone()),
                Some(t.at_unix_ns),
                origin,
            );
        }
        Job::Command(station, sent) => run_command(s, core, &station, sent)?,
        Job::Step(step) => sequence::run_step(s, core, step)?,
        Job::Due(due) => {
            s.sequencer.done(&due);
            sequence::apply_due(s, core, due)?;
        }
    }
    publish_rover(s, core);
    Ok(true)
}

/// What the DNMs are checked against, copied out of the lock.
pub(crate) struct Snapshot {
    pub(crate) revision: u64,
    pub(crate) task: Option<String>,
    pub(crate) digest: String,
    pub(crate) next_txn: u64,
    pub(crate) file: String,
    pub(crate) text: String,
    pub(crate) decisions: Vec<DecisionRecord>,
    pub(crate) participants: Vec<String>,
    pub(crate) radio: Vec<String>,
}

impl Snapshot {
    pub(crate) fn of(core: &Core) -> Self {
        let (radio, participants): (Vec<_>, Vec<_>) =
            core.netlist.dnms.iter().partition(|d| d.radio);
        Self {
            revision: core.state.revision,
            task: core.state.task.clone(),
            digest: core.digest.clone(),
            next_txn: core.state.next_txn,
            file: core.state.file.clone(),
            text: core.state.text.clone(),
            decisions: core.state.decisions.clone(),
            participants: participants.into_iter().map(|d| d.name.clone()).collect(),
            radio: radio.into_iter().map(|d| d.name.clone()).collect(),
        }
    }

    pub(crate) fn in_step(&self, r: &DnmBrief) -> bool {
        r.holding.is_none()
            && r.preparing.is_none()
            && r.revision == self.revision
            && r.active_task == self.task
            && r.netlist_digest == self.digest
    }
}

/// Why the rover's DNMs are not all in step with what was decided, if they are not.
pub(crate) fn out_of_step(s: &Shared, snap: &Snapshot) -> Option<String> {
    let found = reports_of(s, &snap.participants, Duration::from_secs(1));
    for (d, r) in snap.participants.iter().zip(found) {
        match r {
            None => return Some(format!("DNM `{d}` does not answer")),
            Some(r) if !snap.in_step(&r) => {
                return Some(format!(
                    "DNM `{d}` is on revision {} task {:?}, holding {:?}",
                    r.revision, r.active_task, r.holding
                ));
            }
            // An apply undone (or a module replaced) a moment ago: its processes are still
            // going, and a new apply would be refused until they are gone.
            Some(r) if r.modules_stopping > 0 => {
                return Some(format!(
                    "DNM `{d}` still stops {} module processes",
                    r.modules_stopping
                ));
            }
            Some(_) => {}
        }
    }
    None
}

pub(crate) fn refuse(
    s: &Shared,
    station: &str,
    sent: &Sent,
    reason: String,
) -> Result<(), AuthorityError> {
    tracing::warn!(station, seq = sent.seq, "command refused: {reason}");
    s.store.finish(Finish {
        fates: vec![(station, sent.seq, &sent.id, Fate::Refused { reason })],
        done: Some((station, sent.seq)),
        ..Finish::default()
    })
}

pub(crate) fn run_command(
    s: &Shared,
    core: &mut Core,
    station: &str,
    sent: Sent,
) -> Result<(), AuthorityError> {
    let origin = Origin::command(station, &sent);
    if let Some(reason) = safing::stale(core, sent.safings_seen) {
        return refuse(s, station, &sent, reason);
    }
    match &sent.order {
        Order::Switch {
            task,
            at_unix_ns,
            late_by_ms,
        } => {
            let late_by = late_by_ms.unwrap_or(DEFAULT_LATE_BY_MS);
            if let Some(at) = *at_unix_ns
                && let Some(why) = too_late(at, late_by)
            {
                return refuse(s, station, &sent, why);
            }
            if !core.netlist.tasks.contains_key(task) {
                let known: Vec<&str> = core.netlist.tasks.keys().map(String::as_str).collect();
                return refuse(
                    s,
                    station,
                    &sent,
                    format!("unknown task `{task}`; the tasks are {}", known.join(", ")),
                );
            }
            let lead = tag_margin(s);
            if at_unix_ns.is_some_and(|at| at > now_unix_ns() + lead)
                && s.store.timers()?.len() >= MAX_TIMERS
            {
                return refuse(
                    s,
                    station,
                    &sent,
                    format!("{MAX_TIMERS} time-tagged switches wait already: cancel some first"),
                );
            }
            if let Some(at) = at_unix_ns.filter(|at| *at > now_unix_ns() + lead) {
                tracing::info!(
                    station,
                    seq = sent.seq,
                    task,
                    at,
                    "time-tagged switch scheduled"
                );
                return s.store.finish(Finish {
                    fates: vec![(
                        station,
                        sent.seq,
                        &sent.id,
                        Fate::Scheduled { at_unix_ns: at },
                    )],
                    done: Some((station, sent.seq)),
                    timer_add: Some(Timer {
                        station: station.to_string(),
                        seq: sent.seq,
                        id: sent.id.clone(),
                        task: task.clone(),
                        at_unix_ns: at,
                        safings_seen: sent.safings_seen,
                        late_by_ms: late_by,
                    }),
                    ..Finish::default()
                });
            }
            transact(s, core, None, Some(task.clone()), *at_unix_ns, origin);
            Ok(())
        }
        Order::Apply { file, text } => match s.door.accept(file, text) {
            Err(e) => refuse(s, station, &sent, e.to_string()),
            Ok(n) => {
                transact(s, core, Some(n), None, None, origin);
                Ok(())
            }
        },
        Order::Module { edit } => {
            let edited = edit_netlist(&core.state.text, edit)
                .map_err(|e| e.to_string())
                .and_then(|(text, what)| {
                    let file = format!("<{} netlist in force, {what}>", s.system);
                    s.door.accept(&file, &text).map_err(|e| match e {
                        AcceptError::Invalid(e) => {
                            format!("{what}: the netlist would not validate:\n{e}")
                        }
                        other => format!("{what}: {other}"),
                    })
                });
            match edited {
                Err(e) => refuse(s, station, &sent, e),
                Ok(n) => {
                    transact(s, core, Some(n), None, None, origin);
                    Ok(())
                }
            }
        }
        Order::Sequence { name, action } => sequence::order(s, core, station, &sent, name, action),
        Order::Cancel { seq } => {
            if let Some(t) = s.store.timer(station, *seq)? {
                tracing::info!(station, seq, "time-tagged switch cancelled");
                return s.store.finish(Finish {
                    fates: vec![
                        (station, *seq, &t.id, Fate::CancelledBy { by: sent.seq }),
                        (
                            station,
                            sent.seq,
                            &sent.id,
                            Fate::Cancelled { target: *seq },
                        ),
                    ],
                    done: Some((station, sent.seq)),
                    timer_remove: Some((station, *seq)),
                    ..Finish::default()
                });
            }
            let why = match s.store.fate(station, *seq)? {
                None if *seq >= sent.seq => format!("command {seq} comes after this cancel"),
                None => format!("command {seq} is not a time-tagged switch waiting for its time"),
                Some(Fate::Applied {
                    revision,
                    at_unix_ns,
                    ..
                }) => format!(
                    "command {seq} already ran (revision {revision}, at {at_unix_ns} ns rover time)"
                ),
                Some(f) => format!("command {seq} is not waiting: {}", describe(&f)),
            };
            refuse(s, station, &sent, format!("nothing to cancel: {why}"))
        }
    }
}

/// Why a time-tagged switch whose time has come may not run, if it may not.
pub(crate) fn timer_refusal(core: &Core, t: &Timer) -> Option<String> {
    if !core.netlist.tasks.contains_key(&t.task) {
        return Some(format!(
            "task `{}` is no longer defined (a netlist applied since removed it)",
            t.task
        ));
    }
    safing::stale(core, t.safings_seen).or_else(|| too_late(t.at_unix_ns, t.late_by_ms))
}

/// Why a time-tagged switch for `at` may no longer run, if it may not: it is more than
/// `late_by_ms` past its time.
pub(crate) fn too_late(at: u64, late_by_ms: u64) -> Option<String> {
    let late = now_unix_ns().saturating_sub(at);
    (late > late_by_ms.saturating_mul(1_000_000)).then(|| {
        format!(
            "not run: its time passed {:.1} s ago and it may run at most {:.1} s late (the \
             rover was out of reach or its authority down); send it again with a new time, or \
             a longer validity (`--late-by`)",
            late as f64 / 1e9,
            late_by_ms as f64 / 1e3
        )
    })
}

pub(crate) fn describe(f: &Fate) -> String {
    match f {
        Fate::Refused { reason } => format!("it was refused ({reason})"),
        Fate::CancelledBy { by } => format!("it was cancelled by command {by}"),
        Fate::Cancelled { .. } => "it is a cancel".into(),
        other => format!("{other:?}"),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;

    /// A time tag runs at most its validity late, and says why it does not.
    #[test]
    fn a_time_tag_past_its_validity_is_refused_with_the_reason() {
        let now = now_unix_ns();
        assert_eq!(too_late(now + 1_000_000_000, 0), None);
        assert_eq!(too_late(now - 1_000_000_000, 60_000), None);
        let why = too_late(now - 90_000_000_000, 60_000).unwrap();
        assert!(why.contains("passed 90.0 s ago"), "{why}");
        assert!(why.contains("at most 60.0 s late"), "{why}");
        // Absurd values neither wrap nor panic.
        assert!(too_late(0, u64::MAX).is_none());
        assert!(too_late(0, 0).is_some());
    }
}
