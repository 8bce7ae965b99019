//! Safing on a DNM's own: the loss-of-signal task put in force here, by the authority's safing
//! or by the DNM's own lease on its authority, whatever else is held; and the bound on how long
//! a prepared transaction is held without a decision.
//!
//! Every DNM that is cut off converges on the same task (the netlist's `on_link_loss.task`),
//! so no agreement is needed to reach it: a DNM safe on its own is a decided state, which the
//! authority adopts when it hears of it.

use dnm_proto::clock::now_unix_ns;
use std::time::Duration;

use dnm_proto::Safed;

use crate::command::{Reply, SafeOrder};
use crate::error::DnmError;
use crate::node::Dnm;

/// How long a DNM holds a prepared transaction without hearing its decision: then it gives it
/// up (the authority decides within its prepare timeout; a DNM that missed a commit is made to
/// adopt the decided revision). Never holding for ever keeps an authority that died mid-way
/// from blocking every later transaction.
pub(crate) const HOLD_LIMIT: Duration = Duration::from_secs(30);

impl Dnm {
    /// Puts `order.task` in force now, dropping whatever transaction is held or scheduled, and
    /// records why. A repeated order only takes on the authority's epoch.
    pub(crate) fn make_safe(&mut self, order: SafeOrder, reply: Reply<Result<(), DnmError>>) {
        if self.netlist.is_none() {
            // Runs nothing: nothing to make safe.
            return reply.send(Ok(()));
        }
        if !self.tasks.contains(&order.task) {
            return reply.send(Err(DnmError::UnknownTask {
                task: order.task,
                known: self.tasks.join(", "),
            }));
        }
        let on_task = self.active.as_deref() == Some(order.task.as_str());
        let holds = self.holding().is_some();
        if let Some(s) = self.safed.as_mut().filter(|s| s.task == order.task)
            && on_task
            && !holds
        {
            if order.epoch.is_some() && s.epoch != order.epoch {
                s.epoch = order.epoch;
                self.publish();
            }
            return reply.send(Ok(()));
        }
        let why = DnmError::Safed {
            dnm: self.name.clone(),
            reason: order.reason.clone(),
        };
        self.drop_held(&why);
        if !on_task && let Err(e) = self.switch(&order.task) {
            return reply.send(Err(e));
        }
        tracing::warn!(dnm = %self.name, task = %order.task, epoch = ?order.epoch, "made safe: {}", order.reason);
        self.event(
            "_dnm",
            "safed",
            format!("on `{}`: {}", order.task, order.reason),
        );
        self.safed = Some(Safed {
            epoch: order.epoch,
            at_unix_ns: now_unix_ns(),
            task: order.task,
            reason: order.reason,
        });
        self.publish();
        reply.send(Ok(()));
    }

    /// Drops every transaction held or scheduled here: none of them may be put in force any
    /// more. A decision arriving later for one of them is answered with `why`.
    fn drop_held(&mut self, why: &DnmError) {
        if let Some(h) = self.held_switch.take() {
            self.remember_decided(h.id, Err(why.clone()));
        }
        // A prepared transaction, or an adoption under way: neither may put its task in force
        // after the safing.
        if let Some(p) = self.apply.take() {
            if let Some(id) = p.txn {
                self.remember_decided(id, Err(why.clone()));
            }
            self.abort_apply(p, why.clone());
        }
        if let Some((_, reply)) = self.deferred_prepare.take() {
            reply.send(Err(why.clone()));
        }
        if let Some(s) = self.scheduled.take() {
            self.remember_decided(s.decision.id, Err(why.clone()));
            for r in s.replies {
                r.send(Err(why.clone()));
            }
        }
        self.calm();
    }

    /// Gives up a prepared switch held past [`HOLD_LIMIT`] without a decision (a held apply
    /// is given up by [`Dnm::progress_apply`] at its deadline).
    pub(crate) fn give_up_stale_hold(&mut self) {
        let Some(h) = self
            .held_switch
            .as_ref()
            .filter(|h| h.since.elapsed() >= HOLD_LIMIT)
        else {
            return;
        };
        let id = h.id;
        tracing::warn!(
            dnm = %self.name,
            txn = id,
            "no decision on transaction {id} within {} s: given up",
            HOLD_LIMIT.as_secs()
        );
        self.held_switch = None;
        self.remember_decided(
            id,
            Err(DnmError::GivenUp {
                txn: id,
                limit_s: HOLD_LIMIT.as_secs(),
            }),
        );
        self.publish();
    }
}
