//! The query thread: a DNM's answers to Zenoh tools (the DNM, its netlist, wiring, modules
//! and ports), from the DNM's latest snapshot and the bridge's own last-value readers, at most
//! [`QUERY_QUEUE`](crate::QUERY_QUEUE) at a time; liveliness tokens of the running modules.

use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::mpsc::{self, Receiver};
use std::time::Duration;

use dnm_core::worker::{dbg, err};
use dnm_core::{Commander, DnmReport, Snapshot};
use dnm_module::port_service;
use dnm_module::protocol::{PortHeader, dnm_config};
use dnm_netlist::MessageType;

use crate::shared::{Shared, Svc};
use crate::wire::{encoding, to_wire};
use dnm_proto::keys;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use zenoh::Wait;
use zenoh::bytes::Encoding;
use zenoh::liveliness::LivelinessToken;
use zenoh::query::Query;

/// Which of a DNM's queryables a query reached.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Target {
    Dnm,
    Netlist,
    Wiring,
    Module,
    Port,
}

/// What wakes the query thread.
pub(crate) enum QueryJob {
    /// A query to answer.
    Answer(Target, Query),
    /// The running modules or the local outputs changed: tokens and readers follow.
    Look,
}

/// Takes one slot of a bounded in-flight count; counts a refusal when none is left.
pub(crate) fn admit(in_flight: &AtomicUsize, limit: usize, refused: &AtomicU64) -> bool {
    let taken = in_flight
        .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
            (n < limit).then_some(n + 1)
        })
        .is_ok();
    if !taken {
        refused.fetch_add(1, Ordering::Relaxed);
    }
    taken
}

pub(crate) fn reply_json(query: &Query, key: String, body: &impl serde::Serialize) {
    let bytes = serde_json::to_vec(body).unwrap_or_default();
    if let Err(e) = query
        .reply(key, bytes)
        .encoding(Encoding::APPLICATION_JSON)
        .wait()
    {
        tracing::debug!("zenoh reply: {e}");
    }
}

/// A sample's header and a copy of its bytes.
pub(crate) type LastSample = (PortHeader, Vec<u8>);

/// The last sample of an output, kept for queries.
pub(crate) struct Monitor {
    pub(crate) subscriber: Subscriber<Svc, [u8], PortHeader>,
    pub(crate) message: MessageType,
    pub(crate) last: Option<LastSample>,
}

impl Monitor {
    fn refresh(&mut self) {
        while let Ok(Some(s)) = self.subscriber.receive() {
            self.last = Some((*s.user_header(), s.payload().to_vec()));
        }
    }

    fn json(&mut self) -> serde_json::Value {
        self.refresh();
        match &self.last {
            None => serde_json::json!({ "schema": self.message.schema_name, "seq": null }),
            Some((h, bytes)) => serde_json::json!({
                "schema": self.message.schema_name,
                "seq": h.seq,
                "age_ms": dnm_module::protocol::monotonic_ns().saturating_sub(h.stamp_ns) / 1_000_000,
                "value": dnm_netlist::values::decode(&self.message, bytes),
            }),
        }
    }
}

/// Answers the DNM's queries from its snapshot and the last-value readers; keeps the module
/// liveliness tokens in step with the running modules. Sleeps until a query comes or the bridge
/// asks it to look (never on a timer); returns when the bridge drops its queues.
pub(crate) fn query_loop(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    prefix: &str,
    shared: &Shared,
    commander: &Commander,
    queries: &Receiver<QueryJob>,
) {
    let node = match dnm_config(prefix).map_err(|e| e.to_string()).and_then(|c| {
        NodeBuilder::new()
            .config(&c)
            .create::<Svc>()
            .map_err(|e| format!("{e:?}"))
    }) {
        Ok(n) => n,
        Err(e) => {
            tracing::error!(dnm, "query thread has no shared memory: {e}");
            return;
        }
    };
    let mut monitors: BTreeMap<String, Monitor> = BTreeMap::new();
    let mut tokens: BTreeMap<String, LivelinessToken> = BTreeMap::new();
    let mut last_snapshot: Option<Arc<Snapshot>> = None;
    let mut retry_tokens = false;
    loop {
        // A liveliness token that could not be declared is tried again within a second.
        let job = if retry_tokens {
            match queries.recv_timeout(Duration::from_secs(1)) {
                Ok(job) => Some(job),
                Err(mpsc::RecvTimeoutError::Timeout) => None,
                Err(mpsc::RecvTimeoutError::Disconnected) => return,
            }
        } else {
            match queries.recv() {
                Ok(job) => Some(job),
                Err(_) => return,
            }
        };
        if shared.stop.load(Ordering::Relaxed) {
            return;
        }
        if matches!(job, Some(QueryJob::Look)) {
            shared.look_pending.store(false, Ordering::Release);
        }
        // Outputs changed at a commit: readers follow.
        if let Some(outputs) = shared.outputs.lock().ok().and_then(|mut o| o.take()) {
            let wanted: BTreeMap<String, MessageType> = outputs.into_iter().collect();
            monitors.retain(|s, m| wanted.get(s).is_some_and(|t| *t == m.message));
            for (service, message) in wanted {
                if monitors.contains_key(&service) {
                    continue;
                }
                let sub = port_service(&node, &service, &message.payload)
                    .map_err(err("port service"))
                    .and_then(|p| p.subscriber_builder().create().map_err(dbg("monitor")));
                match sub {
                    Ok(subscriber) => {
                        monitors.insert(
                            service,
                            Monitor {
                                subscriber,
                                message,
                                last: None,
                            },
                        );
                    }
                    Err(e) => tracing::warn!(port = %service, "no last-value reader: {e}"),
                }
            }
        }
        let snapshot = shared.snapshot();
        if retry_tokens
            || snapshot.as_ref().map(Arc::as_ptr) != last_snapshot.as_ref().map(Arc::as_ptr)
        {
            last_snapshot = snapshot.clone();
            if let Some(s) = &snapshot {
                retry_tokens = !sync_tokens(session, system, dnm, &mut tokens, &s.report);
            }
        }
        let Some(QueryJob::Answer(target, query)) = job else {
            continue;
        };
        // The report and a module's figures are asked for live; a brief, the netlist and the
        // wiring are what the DNM watches, never older than a tick.
        let live = match target {
            Target::Dnm => !query.parameters().contains_key("brief"),
            Target::Module => true,
            Target::Netlist | Target::Wiring | Target::Port => false,
        };
        let snapshot = if live {
            shared.fresh_snapshot(commander).or(snapshot)
        } else {
            snapshot
        };
        answer(
            system,
            dnm,
            target,
            &query,
            snapshot.as_deref(),
            shared,
            &mut monitors,
        );
        drop(query);
        shared.queries_in_flight.fetch_sub(1, Ordering::Relaxed);
        shared.answered.fetch_add(1, Ordering::Relaxed);
    }
}

/// Keeps one liveliness token per running module; whether every one could be declared.
pub(crate) fn sync_tokens(
    session: &zenoh::Session,
    system: &str,
    dnm: &str,
    tokens: &mut BTreeMap<String, LivelinessToken>,
    report: &DnmReport,
) -> bool {
    let mut all = true;
    let running: BTreeSet<&str> = report
        .modules
        .iter()
        .filter(|m| m.state == dnm_proto::ModuleRunState::Running)
        .map(|m| m.name.as_str())
        .collect();
    tokens.retain(|m, _| running.contains(m.as_str()));
    for m in running {
        if tokens.contains_key(m) {
            continue;
        }
        match session
            .liveliness()
            .declare_token(keys::module(system, dnm, m))
            .wait()
        {
            Ok(t) => {
                tokens.insert(m.to_string(), t);
            }
            Err(e) => {
                all = false;
                tracing::warn!(module = m, "liveliness token: {e}");
            }
        }
    }
    all
}

pub(crate) fn answer(
    system: &str,
    dnm: &str,
    target: Target,
    query: &Query,
    snapshot: Option<&Snapshot>,
    shared: &Shared,
    monitors: &mut BTreeMap<String, Monitor>,
) {
    match target {
        Target::Dnm => {
            if let Some(s) = snapshot {
                // `?brief`: only what a DNM is running, for the authority's checks across a
                // slow link.
                if query.parameters().contains_key("glance") {
                    reply_json(
                        query,
                        keys::dnm(system, dnm),
                        &dnm_proto::DnmGlance::of(&s.report),
                    );
                } else if query.parameters().contains_key("brief") {
                    let mut brief = dnm_proto::DnmBrief::of(&s.report);
                    // Everything else in a brief is watched (never older than a tick); the
                    // clock offset moves with every beat of the authority: read it live.
                    if shared.authority.get().is_some() {
                        brief.clock_offset_ms =
                            shared.lease.lock().ok().and_then(|l| l.clock_offset_ms());
                    }
                    reply_json(query, keys::dnm(system, dnm), &brief);
                } else {
                    reply_json(query, keys::dnm(system, dnm), &s.report);
                }
            }
        }
        Target::Netlist => {
            if let Some(s) = snapshot {
                reply_json(query, keys::netlist(system, dnm), &s.netlist);
            }
        }
        Target::Wiring => {
            // `?kinds`: every kind this DNM can run (ports, message types, parameters), for
            // editors that compose netlists away from the rover.
            if query.parameters().contains_key("kinds") {
                let kinds = shared.kinds.lock().ok().and_then(|k| k.clone());
                if let Some(k) = kinds {
                    reply_json(query, keys::wiring(system, dnm), &*k);
                }
            } else if let Some(mut w) = shared.wiring.lock().ok().and_then(|w| w.clone()) {
                // The task in force now (switches do not commit a new revision).
                if let Some(s) = snapshot.filter(|s| s.report.revision == w.revision) {
                    w.active_task = s.report.active_task.clone();
                }
                reply_json(query, keys::wiring(system, dnm), &w);
            }
        }
        Target::Module => {
            let Some(s) = snapshot else { return };
            for m in &s.report.modules {
                let key = keys::module(system, dnm, &m.name);
                let matches = zenoh::key_expr::KeyExpr::try_from(key.as_str())
                    .is_ok_and(|k| k.intersects(query.key_expr()));
                if !matches {
                    continue;
                }
                let mut outputs = serde_json::Map::new();
                let prefix = format!("{}/", m.name);
                for (service, monitor) in monitors.range_mut(prefix.clone()..) {
                    let Some(port) = service.strip_prefix(&prefix) else {
                        break;
                    };
                    outputs.insert(port.to_string(), monitor.json());
                }
                let mut v = serde_json::to_value(m).unwrap_or_default();
                if let Some(o) = v.as_object_mut() {
                    o.insert("dnm".into(), dnm.into());
                    o.insert("outputs".into(), serde_json::Value::Object(outputs));
                }
                reply_json(query, key, &v);
            }
        }
        Target::Port => {
            for (service, m) in monitors.iter_mut() {
                let Some((module, port)) = service.split_once('/') else {
                    continue;
                };
                let key = keys::port(system, dnm, module, port);
                let matches = zenoh::key_expr::KeyExpr::try_from(key.as_str())
                    .is_ok_and(|k| k.intersects(query.key_expr()));
                if !matches {
                    continue;
                }
                m.refresh();
                let Some((header, bytes)) = &m.last else {
                    continue;
                };
                if let Err(e) = query
                    .reply(key, bytes.clone())
                    .encoding(encoding(&m.message))
                    .attachment(keys::encode_header(&to_wire(header)).to_vec())
                    .wait()
                {
                    tracing::debug!("zenoh reply: {e}");
                }
            }
        }
    }
}
