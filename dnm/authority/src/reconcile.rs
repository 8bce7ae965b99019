//! The reconciler: DNMs that missed a decision catch up (the decision sent again, or the
//! decided revision adopted); what the rover's DNMs run.

use crate::*;

/// The newest netlist in force on the reachable DNMs (that still validates here) and its task.
pub(crate) fn running(
    session: &zenoh::Session,
    door: &NetlistDoor,
) -> Option<(Netlist, Option<String>)> {
    let system = door.system();
    let replies = session
        .get(dnm_proto::keys::netlist(system, "*"))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(1))
        .wait()
        .ok()?;
    let mut newest: Option<dnm_proto::NetlistState> = None;
    while let Ok(r) = replies.recv() {
        if let Ok(sample) = r.result()
            && let Ok(n) =
                serde_json::from_slice::<dnm_proto::NetlistState>(&sample.payload().to_bytes())
            && n.text.is_some()
            && newest.as_ref().is_none_or(|x| n.revision > x.revision)
        {
            newest = Some(n);
        }
    }
    let n = newest?;
    let file = n.file.unwrap_or_else(|| "netlist.toml".into());
    let netlist = door.accept(&file, n.text.as_deref()?).ok()?;
    let task = n.active_task.filter(|t| netlist.tasks.contains_key(t));
    Some((netlist, task))
}

/// What every reachable DNM runs.
pub(crate) fn reports(session: &zenoh::Session, system: &str, timeout: Duration) -> Vec<DnmBrief> {
    let Ok(replies) = session
        .get(format!("{}?brief", keys::all_dnms(system)))
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .wait()
    else {
        return Vec::new();
    };
    let mut out = Vec::new();
    while let Ok(r) = replies.recv() {
        if let Ok(sample) = r.result()
            && let Ok(d) = serde_json::from_slice::<DnmBrief>(&sample.payload().to_bytes())
        {
            out.push(d);
        }
    }
    out
}

/// The DNMs one reconciler looks after: those on the rover answer at once, those across the
/// radio may take many seconds (a stalled link, a session being re-established), and waiting
/// for them must never delay a restarted rover DNM's catching up.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Side {
    Rover,
    Radio,
}

impl Side {
    /// How long a pass waits for the DNMs' reports.
    fn report_timeout(self, s: &Shared) -> Duration {
        match self {
            Side::Rover => Duration::from_millis(1500),
            Side::Radio => s.options.prepare_timeout,
        }
    }
}

pub(crate) fn reconcile_loop(s: &Shared, side: Side) {
    while !s.stop.load(Ordering::Relaxed) {
        reconcile(s, side);
        s.pause(s.options.reconcile_every);
    }
}

/// One pass: every DNM that holds a transaction gets its decision (or the order to drop it),
/// every DNM out of step adopts what was decided. Nothing waits under the state lock.
pub(crate) fn reconcile(s: &Shared, side: Side) {
    let (names, before) = match s.core.lock() {
        Ok(core) => (
            core.netlist
                .dnms
                .iter()
                .filter(|d| d.radio == (side == Side::Radio))
                .map(|d| d.name.clone())
                .collect::<Vec<_>>(),
            core.state.next_txn,
        ),
        Err(_) => return,
    };
    if names.is_empty() {
        return;
    }
    let found = reports_of(s, &names, side.report_timeout(s));
    // A DNM of the rover that made itself safe since the last decision, or that has not
    // answered for the loss-of-signal time: the whole rover is made safe before anything else
    // (and before any DNM is made to adopt the task it left). DNMs across the radio follow.
    if side == Side::Rover
        && (safing::adopt_dnm_safing(s, &found) || safing::safe_on_silent_dnm(s, &names, &found))
    {
        return;
    }
    // Taken after the reports: a report is never newer than the decisions it is judged by.
    let snap = match s.core.lock() {
        Ok(core) => Snapshot::of(&core),
        Err(_) => return,
    };
    // A transaction ran meanwhile: rover DNMs' reports may show it half done. Look again
    // later. (DNMs across the radio take no part in transactions; they adopt the newest
    // decision, which the snapshot, taken after their reports, holds.)
    if side == Side::Rover && snap.next_txn != before {
        return;
    }
    for r in found.into_iter().flatten() {
        if let Some(id) = r.holding {
            let known = snap
                .decisions
                .iter()
                .find(|d| d.txn == id)
                .cloned()
                .or_else(|| s.store.decision(id).ok().flatten());
            let d = match known {
                Some(d) => d,
                // Handed out after the snapshot: the worker is running it.
                None if id >= snap.next_txn => continue,
                // Never decided (the authority stopped before it could): dropped.
                None => DecisionRecord {
                    txn: id,
                    commit: false,
                    at_unix_ns: now_unix_ns(),
                    revision: r.revision,
                    task: r.active_task.clone(),
                },
            };
            tracing::info!(dnm = %r.dnm, txn = id, commit = d.commit, "sending a missed decision");
            log_answers(ask_all(
                s,
                std::slice::from_ref(&r.dnm),
                &decide(&d),
                id,
                Duration::from_secs(2),
            ));
            continue;
        }
        if r.preparing.is_some() || snap.in_step(&r) {
            continue;
        }
        // Decided again since the snapshot: these reports are old; look again next pass.
        if side == Side::Rover
            && s.core
                .lock()
                .map_or(true, |c| c.state.next_txn != snap.next_txn)
        {
            return;
        }
        // A DNM that already used the decided revision's number for something else (it was
        // out of reach when a new store chose it) could never adopt it: the decided state
        // gets a number no DNM has used, and every DNM adopts that.
        let used = r.last_attempt.max(r.revision);
        if used >= snap.revision && (r.revision != snap.revision || r.netlist_digest != snap.digest)
        {
            renumber(s, used);
            return;
        }
        // A rover DNM behind is only ever one that restarted (the others hold what they
        // prepared until decided); a radio DNM follows whenever it is reachable.
        tracing::info!(
            dnm = %r.dnm,
            from = r.revision,
            to = snap.revision,
            task = ?snap.task,
            radio = snap.radio.contains(&r.dnm),
            "DNM adopts the decided revision"
        );
        let adopt = Request::Adopt {
            revision: snap.revision,
            task: snap.task.clone(),
            file: snap.file.clone(),
            text: snap.text.clone(),
        };
        log_answers(ask_all(
            s,
            std::slice::from_ref(&r.dnm),
            &adopt,
            snap.revision,
            s.options.prepare_timeout,
        ));
    }
}

/// Gives the decided state a revision number above `used`.
pub(crate) fn renumber(s: &Shared, used: u64) {
    let Ok(mut core) = s.core.lock() else {
        return;
    };
    if core.state.revision > used {
        return;
    }
    let from = core.state.revision;
    // A DNM reporting the last revision there is (it cannot have been given it) is not
    // followed past it: revisions are never used twice.
    let Some(next) = core.state.burned.max(used).checked_add(1) else {
        tracing::error!(
            used,
            "a DNM reports a revision no netlist can follow: ignored"
        );
        return;
    };
    core.state.burned = next;
    core.state.revision = core.state.burned;
    if let Err(e) = s.store.save_state(&core.state) {
        tracing::error!("renumbering the decided revision: {e}");
        return;
    }
    tracing::warn!(
        from,
        to = core.state.revision,
        "a DNM had used the decided revision's number: decided again as a new revision"
    );
    publish_rover(s, &core);
}

pub(crate) fn log_answers(answers: Vec<(String, Result<Response, String>)>) {
    for (d, r) in answers {
        match r {
            Ok(r) if r.ok => {}
            Ok(r) => tracing::warn!(dnm = %d, "{}", r.error.unwrap_or_default()),
            Err(e) => tracing::warn!(dnm = %d, "{e}"),
        }
    }
}
