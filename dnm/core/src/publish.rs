//! When a DNM hands its plugins a fresh [`Snapshot`]: at once when what they act on changes,
//! when a tool asks for the live figures ([`Command::Refresh`](crate::Command::Refresh)), and
//! otherwise once every [`SNAPSHOT_EVERY`].
//!
//! A snapshot is the whole report (every module, the last events and switches, the plugins'
//! parts): building one on every supervision tick cost a third of the DNM loop's CPU, for
//! readers that mostly never looked. Readers that act without asking (the lease, the
//! authority's brief, the liveliness tokens of running modules) read only [`Watched`] state,
//! which is never older than a tick; the figures that change with every sample (steps, rates,
//! CPU, memory) are as fresh as a tool's question needs, because the tool asks.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::node::Dnm;
use crate::plugin::{Snapshot, Watched};

/// Longest time between two snapshots when nothing watched changes and nobody asks.
pub const SNAPSHOT_EVERY: Duration = Duration::from_secs(1);

impl Dnm {
    pub(crate) fn watched(&self) -> Watched {
        Watched {
            revision: self.revision,
            last_attempt: self.last_attempt,
            active: self.active.clone(),
            preparing: self.apply.as_ref().map(|a| a.revision),
            holding: self.holding(),
            scheduled_at: self.scheduled_at(),
            stopping: self.stopping.len(),
            safed: self.safed.clone(),
            modules: self
                .modules
                .values()
                .map(|s| {
                    (
                        s.state,
                        s.pid(),
                        s.restarts,
                        s.hangs,
                        s.status.plan_revision,
                    )
                })
                .collect(),
            last_switch_ns: self.switches.back().map(|s| s.at_ns),
            last_event_ns: self.events_log.back().map(|e| e.at_ns),
        }
    }

    /// Hands plugins the DNM's newest state.
    pub(crate) fn publish(&mut self) {
        self.refresh = false;
        if self.plugins.is_empty() {
            return;
        }
        let snapshot = Arc::new(Snapshot {
            report: self.report(),
            netlist: self.netlist_state(),
            taken: Instant::now(),
        });
        self.supervision.snapshots += 1;
        self.published = Some((snapshot.taken, self.watched()));
        for p in &mut self.plugins {
            p.published(&snapshot);
        }
    }

    /// On the supervision tick: a snapshot if anything watched changed since the last one, or
    /// if the last one is [`SNAPSHOT_EVERY`] old.
    pub(crate) fn publish_if_due(&mut self) {
        if self.plugins.is_empty() {
            return;
        }
        let due = match &self.published {
            None => true,
            Some((at, watched)) => at.elapsed() >= SNAPSHOT_EVERY || *watched != self.watched(),
        };
        if due {
            self.publish();
        }
    }
}
