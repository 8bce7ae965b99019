//! The authority's durable memory (redb): the decided state, the commands taken from each
//! station and their fates, time-tagged commands waiting for their time. Every change is one
//! redb transaction, committed (fsync) before anyone is told about it.

use std::path::Path;

use redb::{Database, ReadableDatabase, ReadableTable, ReadableTableMetadata, TableDefinition};
use serde::{Deserialize, Serialize};

use dnm_proto::station::{Fate, Outcome, RoverEvent, Safing, Sent};

use crate::AuthorityError;
use crate::sequence::SequenceRun;

const META: TableDefinition<'_, &str, &[u8]> = TableDefinition::new("meta");
/// Commands taken and not finished, by `station \0 seq`.
const INBOX: TableDefinition<'_, &str, &[u8]> = TableDefinition::new("inbox");
/// Fates of commands (final, or scheduled), by `station \0 seq`.
const FATES: TableDefinition<'_, &str, &[u8]> = TableDefinition::new("fates");
/// Time-tagged switches waiting, by `station \0 seq`.
const TIMERS: TableDefinition<'_, &str, &[u8]> = TableDefinition::new("timers");
/// Commands in the inbox in the order they arrived (across stations): arrival number -> inbox key.
const ARRIVALS: TableDefinition<'_, u64, &str> = TableDefinition::new("arrivals");
/// The arrival number of each command in the inbox, by inbox key.
const ARRIVAL_OF: TableDefinition<'_, &str, u64> = TableDefinition::new("arrival_of");
/// Every decision, by transaction id: a DNM cut off for long still learns its own.
const DECISIONS: TableDefinition<'_, u64, &[u8]> = TableDefinition::new("decisions");
/// Onboard sequences and where each stands, by name.
const SEQUENCES: TableDefinition<'_, &str, &[u8]> = TableDefinition::new("sequences");

/// Fates in one answer to a station that does not say which it waits for.
pub(crate) const ANSWER_FATES: usize = 32;
/// Fates in one answer, at most.
const MAX_ASKED: usize = 256;

/// Decisions kept for DNMs that missed them.
const DECISIONS_KEPT: usize = 64;
/// Decisions kept in the decisions table (by transaction id); older ones are pruned.
const DECISIONS_STORED: u64 = 1024;
/// Fates kept per station: the fate of command `n` is pruned when `n + FATES_KEPT` is stored
/// (a station has long known it).
const FATES_KEPT: u64 = 4096;
/// Stations the rover keeps a record of; a new one beyond is refused.
pub(crate) const MAX_STATIONS: usize = 64;
/// Outboxes of one station the rover keeps a record of (a station whose outbox is made anew
/// speaks as `<station>.<epoch>`, a record of its own); a new one beyond is refused. A station
/// fills only its own room, never another's.
pub(crate) const MAX_OUTBOXES: usize = 32;
/// Commands of one station taken and not yet run, at most; more are refused when taken (a
/// station must not fill the rover's disk while its worker waits for a DNM).
pub(crate) const MAX_PENDING: usize = 256;
/// Bytes of one command (a netlist's text, mostly); a larger one is refused when taken.
pub(crate) const MAX_COMMAND_BYTES: usize = 1 << 20;
/// Events kept.
const EVENTS_KEPT: usize = 64;

fn key(station: &str, seq: u64) -> String {
    format!("{station}\0{seq:020}")
}

fn split(key: &str) -> Option<(String, u64)> {
    let (s, n) = key.split_once('\0')?;
    Some((s.to_string(), n.parse().ok()?))
}

/// A failure of the store's database.
fn db<E: Into<redb::Error>>(e: E) -> AuthorityError {
    AuthorityError::Store(e.into())
}

/// A record that does not encode or read back.
fn rec(e: serde_json::Error) -> AuthorityError {
    AuthorityError::Record(e)
}

/// One decision, as the DNMs are told it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub(crate) struct DecisionRecord {
    pub(crate) txn: u64,
    pub(crate) commit: bool,
    pub(crate) at_unix_ns: u64,
    pub(crate) revision: u64,
    pub(crate) task: Option<String>,
}

/// What the authority decided last, and its counters.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub(crate) struct State {
    pub(crate) revision: u64,
    pub(crate) task: Option<String>,
    pub(crate) file: String,
    pub(crate) text: String,
    /// The next transaction id.
    pub(crate) next_txn: u64,
    /// The newest revision number handed to any DNM (never used again).
    pub(crate) burned: u64,
    pub(crate) decisions: Vec<DecisionRecord>,
    pub(crate) events: Vec<RoverEvent>,
    /// Switched away on losing the ground; cleared when a station is heard again.
    pub(crate) link_lost: bool,
    /// The rover's newest safing (its epoch counts them).
    #[serde(default)]
    pub(crate) last_safing: Option<Safing>,
    /// Whether that safing is still in force (no decision since).
    #[serde(default)]
    pub(crate) safe: bool,
    /// Rover time of the last decision put in force or safing: a DNM that made itself safe
    /// after it is adopted.
    #[serde(default)]
    pub(crate) changed_at_unix_ns: u64,
}

impl State {
    /// The epoch of the newest safing (0: never safe).
    pub(crate) fn safings(&self) -> u64 {
        self.last_safing.as_ref().map_or(0, |s| s.epoch)
    }

    pub(crate) fn decided(&mut self, d: DecisionRecord) {
        if d.commit {
            self.revision = d.revision;
            self.task = d.task.clone();
            self.safe = false;
            self.changed_at_unix_ns = self.changed_at_unix_ns.max(d.at_unix_ns);
        }
        self.decisions.push(d);
        if self.decisions.len() > DECISIONS_KEPT {
            self.decisions.remove(0);
        }
    }

    pub(crate) fn event(&mut self, e: RoverEvent) {
        self.events.push(e);
        if self.events.len() > EVENTS_KEPT {
            self.events.remove(0);
        }
    }
}

/// A time-tagged switch waiting for its time.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct Timer {
    pub(crate) station: String,
    pub(crate) seq: u64,
    pub(crate) id: String,
    pub(crate) task: String,
    pub(crate) at_unix_ns: u64,
    /// The station's [`Sent::safings_seen`].
    #[serde(default)]
    pub(crate) safings_seen: u64,
    /// How late after `at_unix_ns` it may still run, ms.
    #[serde(default = "default_late_by")]
    pub(crate) late_by_ms: u64,
}

fn default_late_by() -> u64 {
    dnm_proto::station::DEFAULT_LATE_BY_MS
}

/// What finishing a command changes, written in one transaction.
#[derive(Debug, Default)]
pub(crate) struct Finish<'a> {
    /// The command (station, seq, id) and its fate.
    pub(crate) fates: Vec<(&'a str, u64, &'a str, Fate)>,
    /// Taken out of the inbox.
    pub(crate) done: Option<(&'a str, u64)>,
    pub(crate) timer_add: Option<Timer>,
    pub(crate) timer_remove: Option<(&'a str, u64)>,
    /// More time tags taken out (a safing refuses them all).
    pub(crate) timers_remove: Vec<(&'a str, u64)>,
    pub(crate) state: Option<&'a State>,
    pub(crate) decision: Option<&'a DecisionRecord>,
    /// A sequence's progress, stored with the decision its step led to.
    pub(crate) sequence: Option<&'a SequenceRun>,
}

/// What one intake took: the last number taken, the first command out of order (its number,
/// id and the number expected) and numbers another command took.
struct Taken {
    received: u64,
    gap: Option<(u64, String, u64)>,
    taken_by_other: Vec<Outcome>,
}

/// The keys of `station`'s rows below number `seq` in a table keyed `station \0 seq`.
fn keys_below(
    t: &redb::Table<'_, &str, &[u8]>,
    station: &str,
    seq: u64,
) -> Result<Vec<String>, AuthorityError> {
    Ok(
        t.range(key(station, 0).as_str()..key(station, seq).as_str())
            .map_err(db)?
            .filter_map(|r| r.ok().map(|(k, _)| k.value().to_string()))
            .collect(),
    )
}

/// What the station knows final (before `pending_from`) but this store still holds (it was
/// restored from an older copy) ran in the history the store lost: it never runs again.
fn drop_known_final(
    tx: &redb::WriteTransaction,
    station: &str,
    pending_from: u64,
) -> Result<(), AuthorityError> {
    let mut inbox = tx.open_table(INBOX).map_err(db)?;
    let mut timers = tx.open_table(TIMERS).map_err(db)?;
    let stale = keys_below(&inbox, station, pending_from)?;
    let stale_timers = keys_below(&timers, station, pending_from)?;
    if stale.is_empty() && stale_timers.is_empty() {
        return Ok(());
    }
    tracing::warn!(
        station,
        commands = stale.len(),
        time_tags = stale_timers.len(),
        "dropping commands the station knows to be final (this store is older)"
    );
    let mut arrivals = tx.open_table(ARRIVALS).map_err(db)?;
    let mut arrival_of = tx.open_table(ARRIVAL_OF).map_err(db)?;
    for k in &stale {
        inbox.remove(k.as_str()).map_err(db)?;
        if let Some(a) = arrival_of.remove(k.as_str()).map_err(db)? {
            let a = a.value();
            arrivals.remove(a).map_err(db)?;
        }
    }
    for k in &stale_timers {
        timers.remove(k.as_str()).map_err(db)?;
    }
    Ok(())
}

/// One station's commands being taken, in one write transaction.
struct Taking<'t> {
    station: &'t str,
    inbox: redb::Table<'t, &'static str, &'static [u8]>,
    arrivals: redb::Table<'t, u64, &'static str>,
    arrival_of: redb::Table<'t, &'static str, u64>,
    fates: redb::Table<'t, &'static str, &'static [u8]>,
    /// The newest arrival number handed out.
    arrival: u64,
    /// The station's commands in the inbox (up to [`MAX_PENDING`]).
    pending: usize,
    taken: Taken,
}

impl<'t> Taking<'t> {
    fn open(
        tx: &'t redb::WriteTransaction,
        station: &'t str,
        received: u64,
    ) -> Result<Self, AuthorityError> {
        let inbox = tx.open_table(INBOX).map_err(db)?;
        let arrivals = tx.open_table(ARRIVALS).map_err(db)?;
        let arrival = arrivals.last().map_err(db)?.map_or(0, |(k, _)| k.value());
        let pending = inbox
            .range(key(station, 0).as_str()..key(station, u64::MAX).as_str())
            .map_err(db)?
            .take(MAX_PENDING)
            .count();
        Ok(Self {
            station,
            inbox,
            arrivals,
            arrival_of: tx.open_table(ARRIVAL_OF).map_err(db)?,
            fates: tx.open_table(FATES).map_err(db)?,
            arrival,
            pending,
            taken: Taken {
                received,
                gap: None,
                taken_by_other: Vec::new(),
            },
        })
    }

    /// Takes the commands in their order, up to the first that does not follow.
    fn take_all(&mut self, commands: &[Sent]) -> Result<(), AuthorityError> {
        let mut sorted: Vec<&Sent> = commands.iter().collect();
        sorted.sort_by_key(|c| c.seq);
        for c in sorted {
            if c.seq <= self.taken.received {
                self.check_taken(c)?;
                continue;
            }
            if Some(c.seq) != self.taken.received.checked_add(1) {
                let expected = self.taken.received.saturating_add(1);
                self.taken.gap = Some((c.seq, c.id.clone(), expected));
                break;
            }
            self.take(c)?;
        }
        Ok(())
    }

    /// A number already taken: by this very command (a re-send), or by another one, which is
    /// refused explicitly (never skipped).
    fn check_taken(&mut self, c: &Sent) -> Result<(), AuthorityError> {
        let k = key(self.station, c.seq);
        let stored = match self.fates.get(k.as_str()).map_err(db)? {
            Some(v) => serde_json::from_slice::<(String, Fate)>(v.value())
                .ok()
                .map(|(id, _)| id),
            None => self
                .inbox
                .get(k.as_str())
                .map_err(db)?
                .and_then(|v| serde_json::from_slice::<Sent>(v.value()).ok())
                .map(|s| s.id),
        };
        if let Some(other) = stored.filter(|id| *id != c.id) {
            self.taken.taken_by_other.push(Outcome {
                seq: c.seq,
                id: c.id.clone(),
                fate: Fate::Refused {
                    reason: format!(
                        "station `{}`'s number {} is taken by command `{other}`: two stations \
                         share a name, or the outbox was replaced; give each station its own name",
                        self.station, c.seq
                    ),
                },
            });
        }
        Ok(())
    }

    /// The next command: into the inbox in arrival order, or refused at once beyond a bound.
    fn take(&mut self, c: &Sent) -> Result<(), AuthorityError> {
        let bytes = serde_json::to_vec(c).map_err(rec)?;
        let k = key(self.station, c.seq);
        self.taken.received = c.seq;
        let refusal = if bytes.len() > MAX_COMMAND_BYTES {
            Some(format!(
                "command of {} KiB: the rover takes commands of at most {} KiB",
                bytes.len() / 1024,
                MAX_COMMAND_BYTES / 1024
            ))
        } else if self.pending >= MAX_PENDING {
            Some(format!(
                "the rover holds {MAX_PENDING} commands of station `{}` not yet run: send it \
                 again once they have run",
                self.station
            ))
        } else {
            None
        };
        if let Some(reason) = refusal {
            let fate = serde_json::to_vec(&(&c.id, Fate::Refused { reason })).map_err(rec)?;
            self.fates.insert(k.as_str(), fate.as_slice()).map_err(db)?;
            return Ok(());
        }
        self.inbox
            .insert(k.as_str(), bytes.as_slice())
            .map_err(db)?;
        self.pending += 1;
        self.arrival += 1;
        self.arrivals.insert(self.arrival, k.as_str()).map_err(db)?;
        self.arrival_of
            .insert(k.as_str(), self.arrival)
            .map_err(db)?;
        Ok(())
    }

    /// Records how far the station's commands were taken, and when a station was last heard.
    fn close(self, tx: &redb::WriteTransaction) -> Result<Taken, AuthorityError> {
        let Self { station, taken, .. } = self;
        let mut meta = tx.open_table(META).map_err(db)?;
        let bytes = serde_json::to_vec(&taken.received).map_err(rec)?;
        meta.insert(format!("recv\0{station}").as_str(), bytes.as_slice())
            .map_err(db)?;
        let now = dnm_proto::clock::now_unix_ns();
        let bytes = serde_json::to_vec(&now).map_err(rec)?;
        meta.insert("contact", bytes.as_slice()).map_err(db)?;
        Ok(taken)
    }
}

#[derive(Debug)]
pub(crate) struct Store {
    db: Database,
}

impl Store {
    pub(crate) fn open(path: &Path) -> Result<Self, AuthorityError> {
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).map_err(|source| AuthorityError::StoreFolder {
                path: dir.to_path_buf(),
                source,
            })?;
        }
        let database = Database::create(path).map_err(|e| AuthorityError::StoreOpen {
            path: path.to_path_buf(),
            source: e.into(),
        })?;
        let tx = database.begin_write().map_err(db)?;
        for t in [META, INBOX, FATES, TIMERS] {
            tx.open_table(t).map_err(db)?;
        }
        tx.open_table(ARRIVALS).map_err(db)?;
        tx.open_table(ARRIVAL_OF).map_err(db)?;
        tx.open_table(DECISIONS).map_err(db)?;
        tx.open_table(SEQUENCES).map_err(db)?;
        tx.commit().map_err(db)?;
        Ok(Self { db: database })
    }

    /// The sequences stored, by name.
    pub(crate) fn sequences(
        &self,
    ) -> Result<std::collections::BTreeMap<String, SequenceRun>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let t = rx.open_table(SEQUENCES).map_err(db)?;
        let mut out = std::collections::BTreeMap::new();
        for row in t.iter().map_err(db)? {
            let (k, v) = row.map_err(db)?;
            // One record that cannot be read (written by another version, or damaged) costs
            // that sequence, never the authority's start.
            match serde_json::from_slice::<SequenceRun>(v.value()) {
                Ok(run) => {
                    out.insert(k.value().to_string(), run);
                }
                Err(e) => tracing::error!(
                    sequence = k.value(),
                    "the stored sequence cannot be read, left out: {e}; upload it again"
                ),
            }
        }
        Ok(out)
    }

    /// Stores one sequence's progress.
    pub(crate) fn save_sequence(&self, run: &SequenceRun) -> Result<(), AuthorityError> {
        self.finish(Finish {
            sequence: Some(run),
            ..Finish::default()
        })
    }

    fn meta<T: for<'de> Deserialize<'de>>(&self, name: &str) -> Result<Option<T>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let t = rx.open_table(META).map_err(db)?;
        let Some(v) = t.get(name).map_err(db)? else {
            return Ok(None);
        };
        serde_json::from_slice(v.value()).map(Some).map_err(rec)
    }

    pub(crate) fn state(&self) -> Result<Option<State>, AuthorityError> {
        self.meta("state")
    }

    pub(crate) fn save_state(&self, state: &State) -> Result<(), AuthorityError> {
        self.finish(Finish {
            state: Some(state),
            ..Finish::default()
        })
    }

    /// Takes a station's commands in order: each new one goes to the inbox (durably) if it
    /// follows the last taken; a gap stops the intake. Returns the fates of the commands sent,
    /// then news from `pending_from` on (final or scheduled fates), at most [`ANSWER_FATES`]
    /// in all: the answer crosses a slow link, and only what the station does not know yet
    /// is worth its bandwidth.
    pub(crate) fn intake(
        &self,
        station: &str,
        commands: &[Sent],
        pending_from: u64,
        waiting: &[u64],
    ) -> Result<Vec<Outcome>, AuthorityError> {
        let received = self.received_of(station, pending_from)?;
        let tx = self.db.begin_write().map_err(db)?;
        let taken = {
            drop_known_final(&tx, station, pending_from)?;
            let mut t = Taking::open(&tx, station, received)?;
            t.take_all(commands)?;
            t.close(&tx)?
        };
        tx.commit().map_err(db)?;
        self.answer(station, commands, pending_from, waiting, taken)
    }

    /// The last command of `station` taken, as far as this store and the station know.
    fn received_of(&self, station: &str, pending_from: u64) -> Result<u64, AuthorityError> {
        let recv_key = format!("recv\0{station}");
        let received: u64 = match self.meta(&recv_key)? {
            Some(r) => r,
            // A station this rover has no record of (its database was replaced) that has
            // finished commands already: those are final at the station, so numbering goes on
            // from the first it still waits for. Nothing is run twice that the station knows
            // the fate of.
            None if pending_from > 1 => {
                tracing::warn!(
                    station,
                    pending_from,
                    "no record of this station: taking its commands from the first it waits for"
                );
                pending_from - 1
            }
            None => 0,
        };
        // A store restored from an older copy: what the station knows to be final (everything
        // before `pending_from`) never runs again, so numbering goes on from there.
        if pending_from.saturating_sub(1) > received {
            tracing::warn!(
                station,
                received,
                pending_from,
                "this store is behind the station: taking its commands from the first it waits for"
            );
            return Ok(pending_from - 1);
        }
        Ok(received)
    }

    /// The fates of what was sent and of what the station waits for, then news from
    /// `pending_from` on for a station that does not say what it waits for; and where to send
    /// from, when the rover misses some.
    fn answer(
        &self,
        station: &str,
        commands: &[Sent],
        pending_from: u64,
        waiting: &[u64],
        taken: Taken,
    ) -> Result<Vec<Outcome>, AuthorityError> {
        let received = taken.received;
        let mut asked: std::collections::BTreeSet<u64> = commands
            .iter()
            .map(|c| c.seq)
            .chain(waiting.iter().copied())
            .filter(|seq| *seq <= received)
            .collect();
        if waiting.is_empty() {
            asked.extend((pending_from.max(1)..=received).take(ANSWER_FATES));
        }
        let mut out = self.fates_of(station, asked.iter().copied().take(MAX_ASKED))?;
        out.retain(|o| commands.iter().any(|c| c.seq == o.seq) || o.fate != Fate::Acknowledged);
        out.extend(taken.taken_by_other);
        // Commands the station waits for that this rover never took (its store was lost or
        // replaced): the station sends again from the first it has not taken.
        let unknown = waiting.iter().copied().filter(|w| *w > received).min();
        match (taken.gap, unknown) {
            (Some((seq, id, expected)), _) => out.push(Outcome {
                seq,
                id,
                fate: Fate::OutOfOrder { expected },
            }),
            (None, Some(seq)) => out.push(Outcome {
                seq,
                id: String::new(),
                fate: Fate::OutOfOrder {
                    expected: received.saturating_add(1),
                },
            }),
            (None, None) => {}
        }
        Ok(out)
    }

    /// Fates of some of a station's commands: final or scheduled from the fates, else
    /// acknowledged if in the inbox.
    fn fates_of(
        &self,
        station: &str,
        seqs: impl Iterator<Item = u64>,
    ) -> Result<Vec<Outcome>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let fates = rx.open_table(FATES).map_err(db)?;
        let inbox = rx.open_table(INBOX).map_err(db)?;
        let mut out = Vec::new();
        for seq in seqs {
            let k = key(station, seq);
            if let Some(v) = fates.get(k.as_str()).map_err(db)? {
                let (id, fate): (String, Fate) = serde_json::from_slice(v.value()).map_err(rec)?;
                out.push(Outcome { seq, id, fate });
            } else if let Some(v) = inbox.get(k.as_str()).map_err(db)? {
                let sent: Sent = serde_json::from_slice(v.value()).map_err(rec)?;
                out.push(Outcome {
                    seq,
                    id: sent.id,
                    fate: Fate::Acknowledged,
                });
            }
        }
        Ok(out)
    }

    /// When the last uplink was taken (wall clock, ns), if ever.
    pub(crate) fn last_contact_unix_ns(&self) -> Result<Option<u64>, AuthorityError> {
        self.meta("contact")
    }

    /// Whether the rover keeps a record of `station` (an outbox of the station `keyed`, whose
    /// key it speaks on), or has room for one more: [`MAX_STATIONS`] stations, each with
    /// [`MAX_OUTBOXES`] outboxes at most.
    pub(crate) fn admits(&self, station: &str, keyed: &str) -> Result<bool, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let meta = rx.open_table(META).map_err(db)?;
        let recv_key = format!("recv\0{station}");
        if meta.get(recv_key.as_str()).map_err(db)?.is_some() {
            return Ok(true);
        }
        let mine = format!("{keyed}.");
        let mut stations = std::collections::BTreeSet::new();
        let mut outboxes = 0;
        for row in meta
            .range("recv\0".."recv\u{1}")
            .map_err(db)?
            .take(MAX_STATIONS * MAX_OUTBOXES)
        {
            let (k, _) = row.map_err(db)?;
            let name = k.value().trim_start_matches("recv\0");
            if name == keyed || name.starts_with(&mine) {
                outboxes += 1;
                stations.insert(keyed.to_string());
            } else {
                stations.insert(station_of_outbox(name).to_string());
            }
        }
        let room = stations.contains(keyed) || stations.len() < MAX_STATIONS;
        Ok(room && outboxes < MAX_OUTBOXES)
    }

    /// The fate of one command, if it has one.
    pub(crate) fn fate(&self, station: &str, seq: u64) -> Result<Option<Fate>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let fates = rx.open_table(FATES).map_err(db)?;
        let Some(v) = fates.get(key(station, seq).as_str()).map_err(db)? else {
            return Ok(None);
        };
        let (_, fate): (String, Fate) = serde_json::from_slice(v.value()).map_err(rec)?;
        Ok(Some(fate))
    }

    /// The command in the inbox that arrived first, whichever station sent it (each
    /// station's commands arrive in its order). Commands taken by an older version of the
    /// store, without arrival numbers, come first, in station order.
    pub(crate) fn next_command(&self) -> Result<Option<(String, Sent)>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let inbox = rx.open_table(INBOX).map_err(db)?;
        let arrival_of = rx.open_table(ARRIVAL_OF).map_err(db)?;
        let arrivals = rx.open_table(ARRIVALS).map_err(db)?;
        let mut k = None;
        for row in inbox.iter().map_err(db)?.take(1) {
            let (key, _) = row.map_err(db)?;
            if arrival_of.get(key.value()).map_err(db)?.is_none() {
                k = Some(key.value().to_string());
            }
        }
        if k.is_none()
            && let Some((_, key)) = arrivals.first().map_err(db)?
        {
            k = Some(key.value().to_string());
        }
        let Some(k) = k else {
            return Ok(None);
        };
        let Some(v) = inbox.get(k.as_str()).map_err(db)? else {
            return Err(AuthorityError::Inconsistent(format!(
                "inbox key {k:?} in the arrival order but not in the inbox"
            )));
        };
        let Some((station, _)) = split(&k) else {
            return Err(AuthorityError::Inconsistent(format!("bad inbox key {k:?}")));
        };
        let sent: Sent = serde_json::from_slice(v.value()).map_err(rec)?;
        Ok(Some((station, sent)))
    }

    /// The decision on transaction `txn`, if there was one.
    pub(crate) fn decision(&self, txn: u64) -> Result<Option<DecisionRecord>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let t = rx.open_table(DECISIONS).map_err(db)?;
        let Some(v) = t.get(txn).map_err(db)? else {
            return Ok(None);
        };
        serde_json::from_slice(v.value()).map(Some).map_err(rec)
    }

    /// (station, seq) of every time-tagged switch a cancel in the inbox targets.
    pub(crate) fn pending_cancels(&self) -> Result<Vec<(String, u64)>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let inbox = rx.open_table(INBOX).map_err(db)?;
        let mut out = Vec::new();
        for row in inbox.iter().map_err(db)? {
            let (k, v) = row.map_err(db)?;
            let Some((station, _)) = split(k.value()) else {
                continue;
            };
            if let Ok(Sent {
                order: dnm_proto::station::Order::Cancel { seq },
                ..
            }) = serde_json::from_slice::<Sent>(v.value())
            {
                out.push((station, seq));
            }
        }
        Ok(out)
    }

    pub(crate) fn timers(&self) -> Result<Vec<Timer>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let t = rx.open_table(TIMERS).map_err(db)?;
        let mut out = Vec::new();
        for row in t.iter().map_err(db)? {
            let (_, v) = row.map_err(db)?;
            out.push(serde_json::from_slice(v.value()).map_err(rec)?);
        }
        Ok(out)
    }

    pub(crate) fn timer(&self, station: &str, seq: u64) -> Result<Option<Timer>, AuthorityError> {
        let rx = self.db.begin_read().map_err(db)?;
        let t = rx.open_table(TIMERS).map_err(db)?;
        let Some(v) = t.get(key(station, seq).as_str()).map_err(db)? else {
            return Ok(None);
        };
        serde_json::from_slice(v.value()).map(Some).map_err(rec)
    }

    /// Writes everything `f` names in one durable transaction.
    pub(crate) fn finish(&self, f: Finish<'_>) -> Result<(), AuthorityError> {
        let tx = self.db.begin_write().map_err(db)?;
        {
            let mut fates = tx.open_table(FATES).map_err(db)?;
            for (station, seq, id, fate) in &f.fates {
                let bytes = serde_json::to_vec(&(id, fate)).map_err(rec)?;
                fates
                    .insert(key(station, *seq).as_str(), bytes.as_slice())
                    .map_err(db)?;
                if let Some(old) = seq.checked_sub(FATES_KEPT) {
                    fates.remove(key(station, old).as_str()).map_err(db)?;
                }
            }
            let mut inbox = tx.open_table(INBOX).map_err(db)?;
            if let Some((station, seq)) = f.done {
                let k = key(station, seq);
                inbox.remove(k.as_str()).map_err(db)?;
                let mut arrival_of = tx.open_table(ARRIVAL_OF).map_err(db)?;
                if let Some(a) = arrival_of.remove(k.as_str()).map_err(db)? {
                    let a = a.value();
                    tx.open_table(ARRIVALS).map_err(db)?.remove(a).map_err(db)?;
                }
            }
            let mut timers = tx.open_table(TIMERS).map_err(db)?;
            if let Some(t) = &f.timer_add {
                let bytes = serde_json::to_vec(t).map_err(rec)?;
                timers
                    .insert(key(&t.station, t.seq).as_str(), bytes.as_slice())
                    .map_err(db)?;
            }
            if let Some((station, seq)) = f.timer_remove {
                timers.remove(key(station, seq).as_str()).map_err(db)?;
            }
            for (station, seq) in &f.timers_remove {
                timers.remove(key(station, *seq).as_str()).map_err(db)?;
            }
            if let Some(d) = f.decision {
                let mut t = tx.open_table(DECISIONS).map_err(db)?;
                let bytes = serde_json::to_vec(d).map_err(rec)?;
                t.insert(d.txn, bytes.as_slice()).map_err(db)?;
                if ReadableTableMetadata::len(&t).map_err(db)? > DECISIONS_STORED {
                    t.pop_first().map_err(db)?;
                }
            }
            if let Some(run) = f.sequence {
                let mut t = tx.open_table(SEQUENCES).map_err(db)?;
                let bytes = serde_json::to_vec(run).map_err(rec)?;
                t.insert(run.name.as_str(), bytes.as_slice()).map_err(db)?;
            }
            if let Some(state) = f.state {
                let mut meta = tx.open_table(META).map_err(db)?;
                let bytes = serde_json::to_vec(state).map_err(rec)?;
                meta.insert("state", bytes.as_slice()).map_err(db)?;
            }
        }
        tx.commit().map_err(db)
    }
}

/// The station an outbox's name belongs to: `<station>.<epoch in hex>`, or the station's own
/// name (how a record written by another station is counted; its key is not known here).
fn station_of_outbox(name: &str) -> &str {
    match name.rsplit_once('.') {
        Some((station, epoch))
            if !epoch.is_empty() && epoch.chars().all(|c| c.is_ascii_hexdigit()) =>
        {
            station
        }
        _ => name,
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used, clippy::expect_used)]
    use super::*;
    use dnm_proto::station::Order;

    /// A test's folder, removed with it.
    struct Scratch(std::path::PathBuf);

    impl Drop for Scratch {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn store() -> (Store, Scratch) {
        let dir = std::env::temp_dir().join(format!(
            "dnm-authority-store-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        let _ = std::fs::remove_dir_all(&dir);
        let s = Store::open(&dir.join("a.redb")).unwrap();
        (s, Scratch(dir))
    }

    fn sent(seq: u64, id: &str) -> Sent {
        Sent {
            seq,
            id: id.into(),
            order: Order::Switch {
                task: "a".into(),
                at_unix_ns: None,
                late_by_ms: None,
            },
            safings_seen: 0,
            given_unix_ns: None,
        }
    }

    fn done(s: &Store, station: &str, seq: u64, id: &str) {
        s.finish(Finish {
            fates: vec![(station, seq, id, Fate::Refused { reason: "x".into() })],
            done: Some((station, seq)),
            ..Finish::default()
        })
        .unwrap();
    }

    /// Commands run in the order they reached the rover, not by station name, and a station
    /// sending all the time does not hold another back.
    #[test]
    fn commands_run_in_arrival_order_across_stations() {
        let (s, _dir) = store();
        s.intake("zulu", &[sent(1, "z1")], 1, &[]).unwrap();
        s.intake("alpha", &[sent(1, "a1")], 1, &[]).unwrap();
        s.intake("zulu", &[sent(2, "z2")], 1, &[]).unwrap();
        s.intake("alpha", &[sent(2, "a2")], 1, &[]).unwrap();
        let mut order = Vec::new();
        while let Some((station, c)) = s.next_command().unwrap() {
            done(&s, &station, c.seq, &c.id);
            order.push(c.id);
        }
        assert_eq!(order, ["z1", "a1", "z2", "a2"]);
    }

    /// A number another command took is refused by name, never skipped in silence.
    #[test]
    fn a_number_taken_by_another_command_is_refused() {
        let (s, _dir) = store();
        s.intake("g", &[sent(1, "first")], 1, &[]).unwrap();
        let out = s.intake("g", &[sent(1, "other")], 1, &[]).unwrap();
        let o = out
            .iter()
            .find(|o| o.id == "other")
            .expect("an answer for it");
        let Fate::Refused { reason } = &o.fate else {
            panic!("{o:?}");
        };
        assert!(reason.contains("taken by command `first`"), "{reason}");
        // The re-send of the first is answered as usual.
        let out = s.intake("g", &[sent(1, "first")], 1, &[]).unwrap();
        assert_eq!(out[0].fate, Fate::Acknowledged);
    }

    /// A store that lost its record of a station tells it where to send from when the station
    /// waits for commands it never took (the station then sends them again).
    #[test]
    fn a_fresh_store_asks_for_the_commands_it_never_took() {
        let (s, _dir) = store();
        // The station knows 1..=3 final; 4 was acknowledged by the lost store; 5 is new.
        let out = s.intake("g", &[sent(5, "g5")], 4, &[4]).unwrap();
        assert!(
            out.iter()
                .any(|o| o.fate == Fate::OutOfOrder { expected: 4 }),
            "{out:?}"
        );
        let out = s
            .intake("g", &[sent(4, "g4"), sent(5, "g5")], 4, &[])
            .unwrap();
        assert!(out.iter().all(|o| o.fate == Fate::Acknowledged), "{out:?}");
        // Without a gap in what it sends, a waiting command it never took is asked for too.
        let (s, _dir2) = store();
        let out = s.intake("h", &[], 3, &[3]).unwrap();
        assert_eq!(out[0].fate, Fate::OutOfOrder { expected: 3 });
    }

    /// A store restored from an older copy goes on from the first command the station waits
    /// for: nothing the station knows final runs again, nothing after it is lost.
    #[test]
    fn a_restored_store_goes_on_from_what_the_station_waits_for() {
        let (s, _dir) = store();
        s.intake("g", &[sent(1, "g1"), sent(2, "g2"), sent(3, "g3")], 1, &[])
            .unwrap();
        // The copy was taken here; after it, 1..=6 ran (the station knows them final) and the
        // store was put back. 7 is new.
        let out = s.intake("g", &[sent(7, "g7")], 7, &[]).unwrap();
        assert_eq!(out[0].fate, Fate::Acknowledged, "{out:?}");
        let mut ids = Vec::new();
        while let Some((station, c)) = s.next_command().unwrap() {
            done(&s, &station, c.seq, &c.id);
            ids.push(c.id);
        }
        assert_eq!(ids, ["g7"], "nothing the station knows final runs again");
    }

    #[test]
    fn oversized_commands_and_stations_beyond_the_bound_are_refused() {
        let (s, _dir) = store();
        let mut big = sent(1, "big");
        big.order = Order::Apply {
            file: "n.toml".into(),
            text: "#".repeat(MAX_COMMAND_BYTES + 1),
        };
        s.intake("g", &[big], 1, &[]).unwrap();
        assert!(matches!(
            s.fate("g", 1).unwrap(),
            Some(Fate::Refused { .. })
        ));
        assert!(s.next_command().unwrap().is_none());
        for i in 0..MAX_STATIONS {
            s.intake(&format!("s{i}"), &[], 1, &[]).unwrap();
        }
        assert!(s.admits("s0", "s0").unwrap());
        assert!(!s.admits("one-too-many", "one-too-many").unwrap());
        // A station's commands not yet run are bounded too.
        let many: Vec<Sent> = (2..=MAX_PENDING as u64 + 2)
            .map(|i| sent(i, &format!("m{i}")))
            .collect();
        s.intake("g", &many, 1, &[]).unwrap();
        let last = MAX_PENDING as u64 + 2;
        assert!(matches!(
            s.fate("g", last).unwrap(),
            Some(Fate::Refused { .. })
        ));
        assert!(
            s.fate("g", last - 1).unwrap().is_none(),
            "taken, not refused"
        );
    }

    #[test]
    fn a_station_whose_outboxes_fill_its_room_leaves_the_others_theirs() {
        let (s, _dir) = store();
        for epoch in 1..=MAX_OUTBOXES {
            let outbox = format!("x.{epoch:x}");
            assert!(s.admits(&outbox, "x").unwrap(), "{outbox}");
            s.intake(&outbox, &[], 1, &[]).unwrap();
        }
        // Its outboxes known stay known; one more of it is refused.
        assert!(s.admits("x.1", "x").unwrap());
        assert!(!s.admits("x.ffff", "x").unwrap());
        // Another station, and its own outboxes, still have room.
        assert!(s.admits("y", "y").unwrap());
        assert!(s.admits("y.1", "y").unwrap());
        assert_eq!(station_of_outbox("ground-1.19ac4e"), "ground-1");
        assert_eq!(station_of_outbox("ground.one"), "ground.one");
    }

    #[test]
    fn fates_are_pruned_a_bounded_way_back() {
        let (s, _dir) = store();
        for seq in 1..=3 {
            s.finish(Finish {
                fates: vec![("g", seq, "x", Fate::Cancelled { target: 0 })],
                ..Finish::default()
            })
            .unwrap();
        }
        s.finish(Finish {
            fates: vec![("g", FATES_KEPT + 2, "x", Fate::Cancelled { target: 0 })],
            ..Finish::default()
        })
        .unwrap();
        assert!(s.fate("g", 1).unwrap().is_some());
        assert!(s.fate("g", 2).unwrap().is_none());
        assert!(s.fate("g", 3).unwrap().is_some());
    }
}
