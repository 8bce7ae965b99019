//! The command thread: [`RemoteCommand`]s taken on `<system>/dnm/<dnm>/cmd`, checked (the
//! sender's right, the netlist sent) and handed to the DNM through its [`Commander`], one
//! method per request; the reply goes back when the DNM answers.

use std::sync::atomic::Ordering;
use std::sync::mpsc::{Receiver, SyncSender};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use dnm_core::answer::{apply_answer, switch_answer};
use dnm_core::{Command, CommandKey, Commander, Decision, DnmError, Reply, Txn};
use dnm_netlist::NetlistDoor;

use crate::query::admit;
use crate::shared::{APPLIES_IN_FLIGHT, Shared};
use dnm_proto::keys;
use dnm_proto::{RemoteCommand, Request, Response};
use zenoh::Wait;
use zenoh::bytes::Encoding;
use zenoh::query::Query;

pub(crate) enum CommandJob {
    Query(Query),
    Answer(Query, Response),
    /// The bridge is dropping: return.
    Stop,
}

/// Takes commands from Zenoh, hands switches and applies to the DNM, and replies when it
/// answers. A status request is the DNM's own report; a netlist request is answered from its
/// snapshot.
pub(crate) fn command_loop(
    system: &str,
    dnm: &str,
    shared: &Shared,
    commander: &Commander,
    door: &NetlistDoor,
    jobs_tx: &SyncSender<CommandJob>,
    jobs: &Receiver<CommandJob>,
) {
    let c = Commands {
        system,
        dnm,
        shared,
        commander,
        door,
        jobs_tx,
    };
    // Sleeps until a command or an answer comes (never on a timer). The thread holds a sender
    // of its own (for the DNM's answers), so the bridge, as it drops, sets `stop` and sends
    // `Stop`; with the queue full, `stop` ends it after the job at hand.
    loop {
        match jobs.recv() {
            Ok(CommandJob::Answer(query, response)) => c.finish(query, &response),
            Ok(CommandJob::Query(query)) => c.take(query),
            Ok(CommandJob::Stop) | Err(_) => return,
        }
        if shared.stop.load(Ordering::Relaxed) {
            return;
        }
    }
}

/// What the command thread works with; one method per phase of a command and per request.
pub(crate) struct Commands<'a> {
    pub(crate) system: &'a str,
    pub(crate) dnm: &'a str,
    pub(crate) shared: &'a Shared,
    pub(crate) commander: &'a Commander,
    /// Where the netlists of applies, transactions and adoptions come in.
    pub(crate) door: &'a NetlistDoor,
    pub(crate) jobs_tx: &'a SyncSender<CommandJob>,
}

/// A query's bytes as a command, or why they are none.
pub(crate) fn read_command(query: &Query) -> Result<RemoteCommand, String> {
    const EXAMPLE: &str = r#"{"client":"me","id":"42","cmd":"switch","task":"auto"}"#;
    match query.payload().map(|p| p.to_bytes()) {
        Some(b) => serde_json::from_slice(&b)
            .map_err(|e| format!("bad command: {e}; send JSON such as {EXAMPLE}")),
        None => Err(format!("empty command; send JSON such as {EXAMPLE}")),
    }
}

impl Commands<'_> {
    /// Answers a command's query (and frees its place).
    fn finish(&self, query: Query, response: &Response) {
        let key = keys::cmd(self.system, self.dnm);
        let bytes = serde_json::to_vec(response).unwrap_or_default();
        let sent = if response.ok {
            query
                .reply(key, bytes)
                .encoding(Encoding::APPLICATION_JSON)
                .wait()
        } else {
            query
                .reply_err(bytes)
                .encoding(Encoding::APPLICATION_JSON)
                .wait()
        };
        if let Err(e) = sent {
            tracing::debug!("zenoh reply: {e}");
        }
        self.shared
            .commands_in_flight
            .fetch_sub(1, Ordering::Relaxed);
        self.shared.answered.fetch_add(1, Ordering::Relaxed);
    }

    /// Hands a command to the DNM; if it cannot take it, its query is answered here.
    fn hand(&self, command: Command, slot: Arc<Mutex<Option<Query>>>) {
        if let Err(e) = self.commander.send(command)
            && let Some(q) = slot.lock().ok().and_then(|mut s| s.take())
        {
            self.finish(q, &Response::error(format!("DNM `{}`: {e}", self.dnm)));
        }
    }

    /// Why a command must not come from its sender, if it must not: in a system commanded
    /// through its authority, transactions, switches and applies come from it alone.
    fn refusal(&self, cmd: &RemoteCommand) -> Option<String> {
        let system = self.system;
        let authority = self.shared.authority.get()?;
        let from_authority = cmd.client.as_deref() == Some(&format!("authority-{authority}"));
        if from_authority {
            return None;
        }
        match cmd.request {
            Request::Prepare { .. } | Request::Decide { .. } | Request::Adopt { .. } => {
                Some(format!(
                    "transactions of system `{system}` come from its authority, DNM `{authority}`"
                ))
            }
            Request::Switch { .. } | Request::Apply { .. } => Some(format!(
                "system `{system}` is commanded through its authority, DNM `{authority}`: \
                 send switches and applies through a ground station (`dnm ground switch TASK`), \
                 which has every DNM take them together"
            )),
            _ => None,
        }
    }

    /// One command: read, checked against its sender, then handed on.
    fn take(&self, query: Query) {
        let cmd = match read_command(&query) {
            Ok(c) => c,
            Err(e) => return self.finish(query, &Response::error(e)),
        };
        if let Some(why) = self.refusal(&cmd) {
            return self.finish(query, &Response::error(why));
        }
        let key = cmd.id.map(|id| CommandKey {
            client: cmd.client.unwrap_or_default(),
            id,
        });
        match cmd.request {
            Request::Status | Request::Netlist => self.state(query, &cmd.request),
            Request::Switch { task } => self.switch(query, task, key),
            Request::Apply { file, text } => self.apply(query, &file, &text, key),
            Request::Prepare {
                txn,
                revision,
                task,
                file,
                text,
            } => self.prepare(query, txn, revision, task, file, text),
            Request::Decide {
                txn,
                commit,
                at_unix_ns,
                revision,
                task,
            } => self.decide(
                query,
                Decision {
                    id: txn,
                    commit,
                    at_unix_ns,
                    revision,
                    task,
                },
            ),
            Request::Adopt {
                revision,
                task,
                file,
                text,
            } => self.adopt(query, revision, task, &file, &text),
        }
    }

    /// The DNM's report, asked of the DNM (the live figures, as the admin socket answers
    /// them; the reply comes when the DNM answers, this thread does not wait), or its netlist
    /// (the newest snapshot's).
    fn state(&self, query: Query, request: &Request) {
        if matches!(request, Request::Status) {
            let (reply, slot) = answer_slot(self.jobs_tx.clone(), query, |report| Response {
                ok: true,
                dnms: vec![report],
                ..Response::default()
            });
            return self.hand(Command::Status(reply), slot);
        }
        let r = match self.shared.snapshot() {
            None => Response::error(format!("DNM `{}` is starting", self.dnm)),
            Some(s) => Response {
                ok: true,
                revision: Some(s.netlist.revision),
                netlist: s.netlist.text.clone(),
                ..Response::default()
            },
        };
        self.finish(query, &r);
    }

    fn switch(&self, query: Query, task: String, key: Option<CommandKey>) {
        let dnm = self.dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<dnm_proto::SwitchRecord, DnmError>| switch_answer(&dnm, r),
        );
        self.hand(Command::Switch { task, key, reply }, slot);
    }

    fn apply(&self, query: Query, file: &str, text: &str, key: Option<CommandKey>) {
        let (_system, dnm) = (self.system, self.dnm);
        let applies = self.shared.applies_in_flight.clone();
        if !admit(&applies, APPLIES_IN_FLIGHT, &self.shared.refused) {
            return self.finish(
                query,
                &Response::error(format!(
                    "DNM `{dnm}` is busy with {APPLIES_IN_FLIGHT} applies; send it again later (same id)"
                )),
            );
        }
        let release = {
            let applies = applies.clone();
            move || {
                applies.fetch_sub(1, Ordering::AcqRel);
            }
        };
        let netlist = match self.door.accept(file, text) {
            Err(e) => {
                release();
                return self.finish(query, &Response::error(e.to_string()));
            }
            Ok(n) => n,
        };
        let dnm_name = dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<u64, DnmError>| {
                release();
                apply_answer(&dnm_name, r)
            },
        );
        if let Err(e) = self.commander.send(Command::Apply {
            netlist: Box::new(netlist),
            key,
            reply,
        }) {
            // The command (with its reply) came back unsent: free its apply slot here.
            applies.fetch_sub(1, Ordering::AcqRel);
            if let Some(q) = slot.lock().ok().and_then(|mut s| s.take()) {
                self.finish(q, &Response::error(format!("DNM `{dnm}`: {e}")));
            }
        }
    }

    fn prepare(
        &self,
        query: Query,
        txn: u64,
        revision: u64,
        task: Option<String>,
        file: Option<String>,
        text: Option<String>,
    ) {
        let dnm = self.dnm;
        // A DNM whose clock is off would put the decision in force at the wrong moment.
        let clock = self
            .shared
            .lease
            .lock()
            .ok()
            .and_then(|l| l.clock_refusal(dnm));
        if let Some(why) = clock {
            tracing::warn!(dnm, txn, "transaction refused: {why}");
            return self.finish(query, &Response::error(why));
        }
        let netlist = match text.map(|t| {
            let file = file.unwrap_or_else(|| "netlist.toml".into());
            self.door.accept(&file, &t)
        }) {
            None => None,
            Some(Ok(n)) => Some(Box::new(n)),
            Some(Err(e)) => return self.finish(query, &Response::error(e.in_transaction())),
        };
        let dnm_name = dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<(), DnmError>| match r {
                Ok(()) => Response {
                    ok: true,
                    revision: Some(revision),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm_name}`: {e}")),
            },
        );
        let txn = Txn {
            id: txn,
            revision,
            task,
            netlist,
        };
        self.hand(Command::Prepare { txn, reply }, slot);
    }

    fn decide(&self, query: Query, decision: Decision) {
        // A decision is sent shortly before its instant; one far ahead would keep the DNM
        // waiting (and its supervision quiet) for nothing.
        let now = dnm_proto::clock::now_unix_ns();
        if decision.commit && decision.at_unix_ns > now + MAX_DECISION_AHEAD.as_nanos() as u64 {
            return self.finish(
                query,
                &Response::error(format!(
                    "decision {} is for {:.0} s from now; at most {} s ahead is taken \
                     (are the clocks synchronised?)",
                    decision.id,
                    (decision.at_unix_ns - now) as f64 / 1e9,
                    MAX_DECISION_AHEAD.as_secs()
                )),
            );
        }
        let (dnm, revision) = (self.dnm.to_string(), decision.revision);
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<Option<dnm_proto::SwitchRecord>, DnmError>| match r {
                Ok(s) => Response {
                    ok: true,
                    revision: Some(revision),
                    switches: s.into_iter().collect(),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm}`: {e}")),
            },
        );
        self.hand(Command::Decide { decision, reply }, slot);
    }

    fn adopt(&self, query: Query, revision: u64, task: Option<String>, file: &str, text: &str) {
        let netlist = match self.door.accept(file, text) {
            Ok(n) => n,
            Err(e) => return self.finish(query, &Response::error(e.in_transaction())),
        };
        let dnm = self.dnm.to_string();
        let (reply, slot) = answer_slot(
            self.jobs_tx.clone(),
            query,
            move |r: Result<u64, DnmError>| match r {
                Ok(revision) => Response {
                    ok: true,
                    revision: Some(revision),
                    ..Response::default()
                },
                Err(e) => Response::error(format!("DNM `{dnm}`: {e}")),
            },
        );
        let adopt = Command::Adopt {
            revision,
            task,
            netlist: Box::new(netlist),
            reply,
        };
        self.hand(adopt, slot);
    }
}

/// How far ahead of now a decided instant may be.
pub(crate) const MAX_DECISION_AHEAD: Duration = Duration::from_secs(60);

/// A reply for the DNM that hands the query back to the command thread with the response. The
/// query waits in a slot, so it can be answered here if the DNM never takes the command.
#[allow(clippy::type_complexity)]
pub(crate) fn answer_slot<T: Send + 'static>(
    tx: SyncSender<CommandJob>,
    query: Query,
    to_response: impl FnOnce(T) -> Response + Send + 'static,
) -> (Reply<T>, Arc<Mutex<Option<Query>>>) {
    let slot = Arc::new(Mutex::new(Some(query)));
    let held = slot.clone();
    let reply = Reply::new(move |v: T| {
        if let Some(q) = held.lock().ok().and_then(|mut s| s.take()) {
            // Never full: the channel has room for twice the commands admitted.
            let _ = tx.try_send(CommandJob::Answer(q, to_response(v)));
        }
    });
    (reply, slot)
}
