//! Transactions across the rover's DNMs: numbers, refusals, the prepare every DNM holds, the
//! decision stored before it is sent, and its putting in force at one instant.

use crate::*;

/// Runs one transaction on every DNM of the rover: prepare everywhere, decide (stored with
/// the command's fate in one write), then put in force at one instant everywhere.
pub(crate) fn transact(
    s: &Shared,
    core: &mut Core,
    netlist: Option<Netlist>,
    task: Option<String>,
    at: Option<u64>,
    origin: Origin,
) -> Fate {
    let finish = |core: &mut Core, fate: &Fate| origin.record(s, core, fate);
    // The lead counts from here: what the transaction takes before its decision (its stores,
    // the prepare's round trip) comes out of it, as long as what must follow the decision (as
    // measured) still fits before the instant.
    let begun = now_unix_ns();
    let target = netlist.as_ref().unwrap_or(&core.netlist);
    let participants: Vec<String> = target
        .dnms
        .iter()
        .filter(|d| !d.radio)
        .map(|d| d.name.clone())
        .collect();
    let task = task_after(core, target, task);
    let (file, text) = match &netlist {
        Some(n) => (Some(n.file.display().to_string()), Some(n.text.clone())),
        None => (None, None),
    };
    // Numbers first, durably: a restarted authority never hands them out again.
    let (id, revision) = next_numbers(core, netlist.is_some());
    if let Err(e) = s.store.save_state(&core.state) {
        return Fate::Refused {
            reason: format!("the rover could not store the transaction: {e}"),
        };
    }
    let started = Instant::now();
    let prepare = Request::Prepare {
        txn: id,
        revision,
        task: task.clone(),
        file,
        text,
    };
    let votes = ask_all(s, &participants, &prepare, id, s.options.prepare_timeout);
    if netlist.is_none() {
        // A switch prepares at once: its prepare is one round trip to the slowest DNM.
        s.timing
            .lock()
            .map(|mut t| t.round_trip(started.elapsed()))
            .ok();
    }
    let refusals = refusals(&votes);
    if !refusals.is_empty() {
        let decision = DecisionRecord {
            txn: id,
            commit: false,
            at_unix_ns: now_unix_ns(),
            revision,
            task: task.clone(),
        };
        core.state.decided(decision.clone());
        let fate = Fate::Refused {
            reason: format!("nothing changed: {}", refusals.join("; ")),
        };
        let _ = finish(core, &fate);
        let _ = ask_all(
            s,
            &participants,
            &decide(&decision),
            id,
            Duration::from_secs(2),
        );
        tracing::warn!(txn = id, "transaction dropped: {}", refusals.join("; "));
        return fate;
    }
    let at_unix_ns = instant(s, begun, origin.given_unix_ns).max(at.unwrap_or(0));
    let decision = DecisionRecord {
        txn: id,
        commit: true,
        at_unix_ns,
        revision,
        task: task.clone(),
    };
    let before = (
        core.state.clone(),
        core.netlist.clone(),
        core.digest.clone(),
        core.sequences.clone(),
    );
    let removal = netlist
        .as_ref()
        .map(|n| removal(&core.netlist, n, revision, task.clone()));
    core.state.decided(decision.clone());
    if let Some(n) = netlist {
        core.state.file = n.file.display().to_string();
        core.state.text = n.text.clone();
        core.digest = format!("{:016x}", n.digest());
        core.netlist = n;
    }
    let fate = Fate::Applied {
        revision,
        task: task.clone(),
        at_unix_ns,
    };
    let storing = Instant::now();
    let stored = finish(core, &fate);
    s.timing.lock().map(|mut t| t.store(storing.elapsed())).ok();
    if stored.is_ok() {
        // The beat says what is decided before any DNM puts it in force: a DNM must not
        // hear the safing this decision ends after it left it.
        publish_rover(s, core);
        safing::beat_now(s);
    }
    if let Err(e) = stored {
        // Not decided after all: drop it everywhere.
        (core.state, core.netlist, core.digest, core.sequences) = before;
        let abort = DecisionRecord {
            commit: false,
            ..decision
        };
        let _ = ask_all(
            s,
            &participants,
            &decide(&abort),
            id,
            Duration::from_secs(2),
        );
        return Fate::Refused {
            reason: format!("the rover could not store the decision: {e}"),
        };
    }
    let missing = put_in_force(s, &participants, &decision);
    if let Some((removed, request)) = removal.filter(|(r, _)| !r.is_empty()) {
        log_answers(ask_all(s, &removed, &request, id, Duration::from_secs(2)));
    }
    if at.is_none() {
        s.timing.lock().map(|mut t| t.busy(started.elapsed())).ok();
    }
    tracing::info!(
        txn = id,
        revision,
        task = ?task,
        ms = started.elapsed().as_millis() as u64,
        missing = ?missing,
        "decided"
    );
    fate
}

/// The command, time tag or sequence step a transaction runs for: its fate is stored with the
/// decision.
pub(crate) struct Origin {
    /// (station, seq, id).
    pub(crate) cmd: Option<(String, u64, String)>,
    /// The time tag it takes out, if it is one.
    pub(crate) timer_remove: Option<(String, u64)>,
    /// The sequence step (or guard) it runs, if it is one.
    pub(crate) step: Option<crate::sequence::StepOrigin>,
    /// When the operator gave the command, station time, if a station says.
    pub(crate) given_unix_ns: Option<u64>,
}

impl Origin {
    /// A station's command.
    pub(crate) fn command(station: &str, sent: &Sent) -> Self {
        Self {
            cmd: Some((station.to_string(), sent.seq, sent.id.clone())),
            timer_remove: None,
            step: None,
            given_unix_ns: sent.given_unix_ns,
        }
    }

    /// Stores `fate` with the state, its newest decision and the sequence it moves on, in one
    /// write.
    fn record(&self, s: &Shared, core: &mut Core, fate: &Fate) -> Result<(), AuthorityError> {
        if let Some(step) = &self.step {
            step.advance(core, fate);
        }
        let fates = self
            .cmd
            .iter()
            .map(|(st, seq, id)| (st.as_str(), *seq, id.as_str(), fate.clone()))
            .collect();
        let r = s.store.finish(Finish {
            fates,
            done: self.cmd.as_ref().map(|(st, seq, _)| (st.as_str(), *seq)),
            timer_add: None,
            timer_remove: self
                .timer_remove
                .as_ref()
                .map(|(st, seq)| (st.as_str(), *seq)),
            timers_remove: Vec::new(),
            state: Some(&core.state),
            decision: core.state.decisions.last(),
            sequence: self
                .step
                .as_ref()
                .and_then(|st| core.sequences.get(st.name())),
        });
        if let Err(e) = &r {
            tracing::error!("storing a decision: {e}");
        }
        r
    }
}

/// The task in force after a transaction on `target`: the one named, else the active one if
/// it is still defined, else the netlist's initial task.
pub(crate) fn task_after(core: &Core, target: &Netlist, task: Option<String>) -> Option<String> {
    task.filter(|t| target.tasks.contains_key(t))
        .or_else(|| {
            core.state
                .task
                .clone()
                .filter(|t| target.tasks.contains_key(t))
        })
        .or_else(|| target.initial_task().map(str::to_string))
}

/// The next transaction id and the revision it puts in force (a new one for an apply, never
/// used before; the one in force for a switch).
pub(crate) fn next_numbers(core: &mut Core, apply: bool) -> (u64, u64) {
    let id = core.state.next_txn;
    core.state.next_txn += 1;
    let revision = if apply {
        core.state.burned = core.state.burned.max(core.state.revision) + 1;
        core.state.burned
    } else {
        core.state.revision
    };
    (id, revision)
}

/// Why the DNMs refused a prepare, one line each (empty: every DNM is ready).
pub(crate) fn refusals(votes: &[(String, Result<Response, String>)]) -> Vec<String> {
    votes
        .iter()
        .filter_map(|(d, r)| match r {
            Ok(r) if r.ok => None,
            Ok(r) => Some(
                r.error
                    .clone()
                    .unwrap_or_else(|| format!("DNM `{d}` refused")),
            ),
            Err(e) => Some(format!("DNM `{d}`: {e}")),
        })
        .collect()
}

/// The DNMs an apply of `to` removes from `from`, and what they are told once the decision is
/// in force (so they stop their modules).
pub(crate) fn removal(
    from: &Netlist,
    to: &Netlist,
    revision: u64,
    task: Option<String>,
) -> (Vec<String>, Request) {
    let removed = from
        .dnms
        .iter()
        .filter(|d| to.dnm(&d.name).is_none())
        .map(|d| d.name.clone())
        .collect();
    let request = Request::Adopt {
        revision,
        task,
        file: to.file.display().to_string(),
        text: to.text.clone(),
    };
    (removed, request)
}

/// Sends the stored decision until every DNM acknowledges it (after the instant), three times
/// at most; returns those that did not (the reconciler catches them: the decision is stored).
pub(crate) fn put_in_force(
    s: &Shared,
    participants: &[String],
    decision: &DecisionRecord,
) -> Vec<String> {
    let request = decide(decision);
    let mut missing = participants.to_vec();
    for _ in 0..3 {
        let wait = Duration::from_nanos(decision.at_unix_ns.saturating_sub(now_unix_ns()))
            + Duration::from_secs(2);
        let acks = ask_all(s, &missing, &request, decision.txn, wait);
        missing = acks
            .into_iter()
            .filter(|(_, r)| !r.as_ref().is_ok_and(|r| r.ok))
            .map(|(d, _)| d)
            .collect();
        if missing.is_empty() {
            break;
        }
    }
    missing
}

pub(crate) fn decide(d: &DecisionRecord) -> Request {
    Request::Decide {
        txn: d.txn,
        commit: d.commit,
        at_unix_ns: d.at_unix_ns,
        revision: d.revision,
        task: d.task.clone(),
    }
}

/// The instant of a transaction begun at `begun`: the lead after the operator gave the command
/// (`given`, station time) or, when that is unknown or not before `begun` (a station's clock
/// ahead of the rover's), after `begun`; and never sooner than the time to store the decision
/// and for it to reach every DNM (both as measured lately) from now, so every DNM holds it
/// before the instant and they switch together. A station's clock behind the rover's, or a
/// command that waited for the link, only brings the instant to that margin.
fn instant(s: &Shared, begun: u64, given: Option<u64>) -> u64 {
    let from = lead_from(begun, given);
    let least = s.options.switch_lead;
    let (lead, margin) = s
        .timing
        .lock()
        .map(|t| (t.lead(least), t.margin()))
        .unwrap_or((least, least));
    // Half the lead at least follows the decision, whatever was measured (a fresh authority
    // has measured nothing; an apply's prepare can take longer than the lead).
    let margin = margin.max(least / 2);
    (from + lead.as_nanos() as u64).max(now_unix_ns() + margin.as_nanos() as u64)
}

/// Where the lead of a transaction begun at `begun` counts from: when the operator gave the
/// command, unless that is unknown or not before `begun` (a station's clock ahead).
fn lead_from(begun: u64, given: Option<u64>) -> u64 {
    given.filter(|g| *g < begun).unwrap_or(begun)
}

/// How long before its time a time-tagged switch is started: time to prepare it and a lead
/// as long as the one the decision will get (as measured lately), twice over, so it is put in
/// force at its tag.
pub(crate) fn tag_margin(s: &Shared) -> u64 {
    let lead = s
        .timing
        .lock()
        .map(|t| t.lead(s.options.switch_lead))
        .unwrap_or(s.options.switch_lead);
    (lead * 4).as_nanos() as u64
}

/// Sends `req` to each DNM at once and collects their answers.
pub(crate) fn ask_all(
    s: &Shared,
    dnms: &[String],
    req: &Request,
    txn: u64,
    timeout: Duration,
) -> Vec<(String, Result<Response, String>)> {
    let phase = match req {
        Request::Prepare { .. } => "prepare",
        Request::Decide { commit: true, .. } => "commit",
        Request::Decide { .. } => "abort",
        _ => "adopt",
    };
    let cmd = RemoteCommand::new(
        format!("authority-{}", s.name),
        format!("{phase}-{txn}"),
        req.clone(),
    );
    let payload = serde_json::to_vec(&cmd).unwrap_or_default();
    let pending: Vec<_> = dnms
        .iter()
        .map(|d| {
            let r = s
                .session
                .get(keys::cmd(&s.system, d))
                .payload(payload.clone())
                .target(QueryTarget::BestMatching)
                .consolidation(ConsolidationMode::None)
                .priority(Priority::InteractiveHigh)
                .congestion_control(CongestionControl::Block)
                .express(true)
                .timeout(timeout)
                .wait();
            (d.clone(), r)
        })
        .collect();
    pending
        .into_iter()
        .map(|(d, r)| {
            let answer = match r {
                Err(e) => Err(e.to_string()),
                Ok(rx) => match rx.recv() {
                    Err(_) => Err(format!("no answer within {} ms", timeout.as_millis())),
                    Ok(reply) => {
                        let bytes = match reply.result() {
                            Ok(sample) => sample.payload().to_bytes().to_vec(),
                            Err(e) => e.payload().to_bytes().to_vec(),
                        };
                        serde_json::from_slice::<Response>(&bytes)
                            .map_err(|e| format!("unreadable answer: {e}"))
                    }
                },
            };
            (d, answer)
        })
        .collect()
}

/// What the DNMs named run, asked all at once (`None`: no answer in time).
pub(crate) fn reports_of(s: &Shared, dnms: &[String], timeout: Duration) -> Vec<Option<DnmBrief>> {
    let pending: Vec<_> = dnms
        .iter()
        .map(|d| {
            s.session
                .get(format!("{}?brief", keys::dnm(&s.system, d)))
                .priority(Priority::InteractiveHigh)
                .express(true)
                .timeout(timeout)
                .wait()
                .ok()
        })
        .collect();
    pending
        .into_iter()
        .map(|rx| {
            let reply = rx?.recv().ok()?;
            let sample = reply.result().ok()?;
            serde_json::from_slice(&sample.payload().to_bytes()).ok()
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::lead_from;

    #[test]
    fn the_lead_counts_from_the_operator_unless_the_station_clock_is_ahead() {
        let begun = 1_000_000_000;
        // Given 3 ms before the transaction began: the lead counts from then.
        assert_eq!(lead_from(begun, Some(begun - 3_000_000)), begun - 3_000_000);
        // A station whose clock is ahead (or the same instant): from the transaction's start,
        // so a station can never put a switch later than the rover would.
        assert_eq!(lead_from(begun, Some(begun + 5_000_000)), begun);
        assert_eq!(lead_from(begun, Some(begun)), begun);
        // No time given (a sequence's step, a time tag): from the transaction's start.
        assert_eq!(lead_from(begun, None), begun);
    }
}
