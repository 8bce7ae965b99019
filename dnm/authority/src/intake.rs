//! Stations: their uplinks taken (who sent what, what the station already knows is final, each
//! command stored before it is acknowledged) and answered, and the rover's state published for
//! them.

use crate::*;

pub(crate) fn intake_loop(s: &Shared, rx: &mpsc::Receiver<Query>) {
    loop {
        let q = match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(q) => q,
            Err(mpsc::RecvTimeoutError::Timeout) if !s.stop.load(Ordering::Relaxed) => continue,
            Err(_) => return,
        };
        let answer = take_uplink(s, &q);
        let bytes = serde_json::to_vec(&answer).unwrap_or_default();
        if let Err(e) = q.reply(q.key_expr().clone(), bytes).wait() {
            tracing::debug!("answering a station: {e}");
        }
    }
}

pub(crate) fn take_uplink(s: &Shared, q: &Query) -> Downlink {
    let full = || s.rover.lock().map(|r| r.clone()).unwrap_or_default();
    // An answer that takes nothing still says what the rover is doing (the sequences' first
    // events only).
    let rover = || {
        let mut r = full();
        for q in &mut r.sequences {
            q.after(0);
        }
        r
    };
    let refuse = |e: String| Downlink {
        at_unix_ns: now_unix_ns(),
        outcomes: Vec::new(),
        rover: rover(),
        error: Some(e),
    };
    let Some(payload) = q.payload() else {
        return refuse(
            "empty uplink; send JSON {\"station\":\"ground-1\",\"commands\":[...]}".into(),
        );
    };
    let up: Uplink = match serde_json::from_slice(&payload.to_bytes()) {
        Ok(u) => u,
        Err(e) => {
            return refuse(format!(
                "unreadable uplink ({e}); send JSON {{\"station\":\"ground-1\",\"commands\":[{{\"seq\":1,\"id\":\"…\",\"order\":{{\"cmd\":\"switch\",\"task\":\"auto\"}}}}]}}"
            ));
        }
    };
    if up.station.is_empty()
        || up.station.len() > 64
        || up.station.contains(['\0', '/', '*', '$', '?', '#'])
    {
        return refuse(format!(
            "station name `{}` is not usable: 1 to 64 characters, no `/`, `*`, `$`, `?`, `#`",
            up.station
        ));
    }
    // A station speaks only for itself: its name is the key's (which the access control binds
    // to its certificate), the outbox's epoch after a `.`.
    let keyed = keys::station_of(&s.system, q.key_expr().as_str()).unwrap_or_default();
    // (An outbox made anew speaks as `<station>.<epoch in hex>`: nothing else is one.)
    let outbox_of_keyed = up
        .station
        .strip_prefix(keyed)
        .and_then(|r| r.strip_prefix('.'))
        .is_some_and(|epoch| !epoch.is_empty() && epoch.chars().all(|c| c.is_ascii_hexdigit()));
    if up.station != keyed && !outbox_of_keyed {
        tracing::warn!(
            key = %q.key_expr(),
            station = %up.station,
            "uplink refused: a station speaks only for itself"
        );
        return refuse(format!(
            "uplink of station `{}` on the key of station `{keyed}`: a station sends on \
             {} only, as `{keyed}` or, its outbox made anew, `{keyed}.<epoch in hex>`",
            up.station,
            keys::authority_station(&s.system, "<its own name>")
        ));
    }
    if up.commands.len() > MAX_UPLINK_COMMANDS {
        return refuse(format!(
            "{} commands in one uplink: send at most {MAX_UPLINK_COMMANDS} at a time",
            up.commands.len()
        ));
    }
    match s.store.admits(&up.station, keyed) {
        Ok(true) => {}
        Ok(false) => {
            return refuse(format!(
                "the rover keeps a record of at most {} stations and {} outboxes of each; \
                 `{}` is not one of them (a station whose outbox was made anew that often \
                 needs a name of its own: a certificate issued for another name)",
                store::MAX_STATIONS,
                store::MAX_OUTBOXES,
                up.station
            ));
        }
        Err(e) => return refuse(format!("the rover could not read its store: {e}")),
    }
    if let Ok(mut c) = s.contact.lock() {
        *c = Instant::now();
    }
    if !s.heard.swap(true, Ordering::Relaxed) {
        s.wake();
    }
    match s
        .store
        .intake(&up.station, &up.commands, up.pending_from, &up.waiting)
    {
        Ok(outcomes) => {
            if outcomes.iter().any(|o| o.fate == Fate::Acknowledged) {
                s.wake();
            }
            let mut rover = full();
            // Only the sequences' events this station does not hold yet cross the radio.
            for q in &mut rover.sequences {
                q.after(up.sequence_events.get(&q.name).copied().unwrap_or(0));
            }
            Downlink {
                at_unix_ns: now_unix_ns(),
                outcomes,
                rover,
                error: None,
            }
        }
        Err(e) => {
            tracing::error!("taking commands of `{}`: {e}", up.station);
            refuse(format!("the rover could not store the commands: {e}"))
        }
    }
}

pub(crate) fn publish_rover(s: &Shared, core: &Core) {
    let scheduled = s
        .store
        .timers()
        .unwrap_or_default()
        .into_iter()
        .map(|t| (t.station, t.seq, t.at_unix_ns))
        .collect();
    let events = core
        .state
        .events
        .iter()
        .rev()
        .take(STATE_EVENTS)
        .rev()
        .cloned()
        .collect();
    if let Ok(mut r) = s.rover.lock() {
        *r = RoverState {
            authority: s.name.clone(),
            revision: core.state.revision,
            task: core.state.task.clone(),
            events,
            scheduled,
            last_safing: core.state.last_safing.clone(),
            safe: core.state.safe,
            sequences: sequence::statuses(core),
        };
    }
    if let Ok(mut d) = s.deferring.lock() {
        // A sequence that just ended with no station heard: the beat goes on saying so until
        // the worker has made the rover safe (its next job), so no DNM makes itself safe on
        // its own in between.
        let silent = s.contact.lock().map(|c| c.elapsed()).unwrap_or_default();
        let loss_due =
            core.netlist.on_link_loss.as_ref().is_some_and(|l| {
                !core.state.link_lost && silent >= Duration::from_millis(l.after_ms)
            });
        *d = sequence::defers_link_loss(core).or_else(|| d.take().filter(|_| loss_due));
    }
    if let Ok(mut told) = s.told.lock() {
        sequence::tell_new_events(core, &mut told, &mut |e| {
            if let Some(log) = &s.options.sequence_log {
                (log.0)(e);
            }
            if let Ok(json) = serde_json::to_vec(e)
                && let Err(err) = s.sequence_events.put(json).wait()
            {
                tracing::debug!("publishing a sequence event: {err}");
            }
        });
    }
    s.sequencer
        .arm(sequence::active(core).and_then(|r| sequencer::Armed::of(r, &core.netlist)));
}
