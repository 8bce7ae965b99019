//! Applying a netlist as one transaction: prepare (start new modules, post every module its
//! plan, let plugins prepare), wait without blocking until every module has prepared, then
//! commit with one store into the task word, or abort and leave the DNM exactly as it was.
//!
//! Revision numbers are never reused: a failed apply burns its number, so a plan of a failed
//! revision can never be mistaken for the plan of a later one. Modules find the plans of the
//! committed and the pending revision as history, so a module restarted in the middle of an
//! apply serves the committed task at once and the pending one after the commit. Switches to
//! tasks of the committed revision go on while an apply is pending.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Instant;

use dnm_module::port_service_for;
use dnm_module::protocol::*;
use dnm_netlist::Netlist;
use iceoryx2::port::update_connections::UpdateConnections;
use iceoryx2::service::port_factory::PortFactory as _;

use dnm_proto::ModuleRunState;

use crate::command::{CommandKey, Reply};
use crate::error::DnmError;
use crate::node::{COMMAND_QUEUE, Dnm};

/// Time to prepare added to the DNM's `prepare_timeout` for each module process an apply
/// starts.
const PREPARE_PER_START: std::time::Duration = std::time::Duration::from_millis(500);
/// The most that share adds up to: a stuck apply is still reported within a minute.
const MAX_PREPARE: std::time::Duration = std::time::Duration::from_secs(60);
use crate::pending::{Outcome, PendingApply};
use crate::plan::{module_plan, task_slots};
use crate::plugin::{Context, Plugin, PluginPrepareError};
use crate::slot::{ModuleSlot, PortServices, exec_of};

impl Dnm {
    /// Starts applying `netlist`: the answer goes to `reply` when the revision is committed or
    /// refused. Only one apply runs at a time; later ones wait in order.
    pub(crate) fn begin_apply(
        &mut self,
        netlist: Netlist,
        key: Option<CommandKey>,
        reply: Reply<Result<u64, DnmError>>,
    ) {
        if let Some(a) = self.apply.as_mut()
            && key.is_some()
            && a.key == key
        {
            a.replies.push(reply);
            return;
        }
        if self.stopping_all {
            reply.send(Err(DnmError::Stopped));
            return;
        }
        if self.apply.is_some()
            || !self.queued_applies.is_empty()
            || self.waits_for_stopping(&netlist)
        {
            if self.queued_applies.len() >= COMMAND_QUEUE {
                reply.send(Err(DnmError::Busy(self.queued_applies.len())));
                return;
            }
            self.queued_applies.push_back((netlist, key, reply));
            return;
        }
        self.start_apply(netlist, key, reply);
    }

    /// Prepares an apply and makes it the pending one; if preparing fails, answers at once and
    /// returns false (nothing changed).
    pub(crate) fn start_apply(
        &mut self,
        netlist: Netlist,
        key: Option<CommandKey>,
        reply: Reply<Result<u64, DnmError>>,
    ) -> bool {
        match self.prepare_apply(netlist, key.clone(), None) {
            Ok(mut pending) => {
                pending.replies.push(reply);
                self.apply = Some(pending);
                // Modules that are already prepared (none changed) commit at once.
                self.progress_apply();
                true
            }
            Err(e) => {
                if let Some(k) = key {
                    self.remember(k, Outcome::Apply(Err(e.clone())));
                }
                reply.send(Err(e));
                false
            }
        }
    }

    /// Everything of an apply up to waiting for the modules, as the next revision or as the
    /// given one (which must be newer than any tried here). On error nothing has changed.
    pub(crate) fn prepare_apply(
        &mut self,
        netlist: Netlist,
        key: Option<CommandKey>,
        revision: Option<u64>,
    ) -> Result<PendingApply, DnmError> {
        if netlist.dnm(&self.name).is_none() {
            return Err(DnmError::DnmMissing(self.name.clone()));
        }
        // Never reuse a number: a failed apply's plans may still sit in modules' history.
        let next = self.revision.max(self.last_attempt) + 1;
        let revision = match revision {
            Some(r) if r < next => {
                return Err(DnmError::Refused(format!(
                    "revision {r} was already used here; the next free one is {next}"
                )));
            }
            Some(r) => r,
            None => next,
        };
        self.last_attempt = revision;
        let me = self.name.clone();
        let wanted: BTreeMap<String, dnm_netlist::Module> = netlist
            .modules_on(&me)
            .map(|m| (m.name.clone(), m.clone()))
            .collect();
        let removed: Vec<String> = self
            .modules
            .keys()
            .filter(|m| !wanted.contains_key(m.as_str()))
            .cloned()
            .collect();
        let replaced: Vec<String> = self
            .modules
            .iter()
            .filter(|(name, slot)| wanted.get(name.as_str()).is_some_and(|m| *m != slot.decl))
            .map(|(n, _)| n.clone())
            .collect();
        let added: Vec<String> = wanted
            .keys()
            .filter(|m| !self.modules.contains_key(m.as_str()))
            .cloned()
            .collect();
        // Every process this apply starts gets its share of the time: 200 modules starting at
        // once on a small computer take longer than a few.
        let starting = (added.len() + replaced.len()) as u32;
        let prepare_for = (self.options.prepare_timeout + PREPARE_PER_START * starting)
            .min(self.options.prepare_timeout.max(MAX_PREPARE));
        let mut pending = PendingApply {
            netlist,
            revision,
            removed,
            replaced,
            staged: BTreeMap::new(),
            new_ports: Vec::new(),
            prepared_plugins: 0,
            deadline: Instant::now() + prepare_for,
            prepare_for,
            key,
            replies: Vec::new(),
            txn: None,
            task: None,
            ready: Vec::new(),
            held: false,
        };
        match self.stage(&mut pending, &added) {
            Ok(()) => Ok(pending),
            Err(e) => {
                self.undo(pending);
                Err(e)
            }
        }
    }

    fn stage(&mut self, p: &mut PendingApply, added: &[String]) -> Result<(), DnmError> {
        let netlist = &p.netlist;
        // 0. Every port kept has room for its readers: those of this netlist and those of the
        //    one in force, which keep their subscribers until the commit, beside the DNM's own.
        //    A port's subscriber slots are fixed when it is made.
        for m in netlist.modules_on(&self.name) {
            let Some(spec) = netlist.kind_of(&m.name) else {
                continue;
            };
            for port in &spec.outputs {
                let Some(services) = self.ports.get(&output_service(&m.name, &port.name)) else {
                    continue;
                };
                let readers = self.readers_across(netlist, &m.name, &port.name);
                let has = services
                    .data
                    .static_config()
                    .max_subscribers()
                    .min(services.event.static_config().max_listeners());
                check_room(&m.name, &port.name, &self.name, readers, has)?;
            }
        }
        // 1. Output services of new and replaced modules exist before anyone subscribes, with
        //    a subscriber slot for each of their readers.
        for name in added.iter().chain(&p.replaced) {
            let spec = netlist
                .kind_of(name)
                .ok_or_else(|| DnmError::Ipc(format!("no kind for {name}")))?;
            for port in &spec.outputs {
                let service = output_service(name, &port.name);
                if self.ports.contains_key(&service) {
                    continue;
                }
                let readers = self.readers_across(netlist, name, &port.name);
                let payload = &port.message.payload;
                let subscribers = payload.subscribers_for(readers);
                // The service may outlive its last owner (a tool or a reader not yet swept
                // still holds it): then it is opened as it was made, and must have room.
                let data = port_service_for(&self.node, &service, payload, subscribers)
                    .or_else(|_| {
                        port_service_for(&self.node, &service, payload, payload.subscribers_for(0))
                    })
                    .map_err(|e| DnmError::Ipc(e.to_string()))?;
                // Listeners cost no samples: never fewer than every opener asks for.
                let event_name = output_event(name, &port.name);
                let event = dnm_module::event_service_for(
                    &self.node,
                    &event_name,
                    subscribers.max(MAX_PORT_SUBSCRIBERS),
                )
                .or_else(|_| {
                    dnm_module::event_service_for(&self.node, &event_name, MAX_PORT_SUBSCRIBERS)
                })
                .map_err(|e| DnmError::Ipc(e.to_string()))?;
                let has = data
                    .static_config()
                    .max_subscribers()
                    .min(event.static_config().max_listeners());
                check_room(name, &port.name, &self.name, readers, has)?;
                self.ports
                    .insert(service.clone(), PortServices { data, event });
                p.new_ports.push(service);
            }
        }
        // A replacement starts after the commit: its executable must be there now.
        for name in &p.replaced {
            let Some(module) = netlist.module(name) else {
                continue;
            };
            let Some(entry) = netlist.catalog.get(&module.kind) else {
                continue;
            };
            let exec = exec_of(&entry.source, &self.options.module_host);
            if !is_executable(&exec) {
                return Err(DnmError::Spawn {
                    module: name.clone(),
                    exec: exec.display().to_string(),
                    why: "not an executable file".into(),
                });
            }
        }
        // 2. Plugins: remote outputs mirrored here before any plan references them.
        let revision = p.revision;
        let (netlist, prepared) = (&p.netlist, &mut p.prepared_plugins);
        let n = self.plugins.len();
        self.with_plugins(0..n, |plugin, ctx| {
            plugin.prepare(ctx, netlist, revision)?;
            *prepared += 1;
            Ok(())
        })
        .map_err(|(i, why)| DnmError::Plugin {
            plugin: self.plugins[i].name(),
            why: why.to_string(),
        })?;
        let netlist = &p.netlist;
        // 3. New modules: control services, their plan (found as history), then the process.
        for name in added {
            let mut slot =
                ModuleSlot::open(&self.node, netlist, name, self.options.on_input_hung_after)?;
            slot.post_plan(&module_plan(netlist, name, p.revision))?;
            let spawned = self.spawn(&mut slot);
            // Staged even if it failed to start, so the undo releases its services.
            p.staged.insert(name.clone(), slot);
            spawned?;
        }
        // 4. Every module that stays gets the new plan and prepares it beside the current one.
        for (name, slot) in &self.modules {
            if p.removed.contains(name) || p.replaced.contains(name) {
                continue;
            }
            slot.post_plan(&module_plan(netlist, name, p.revision))?;
        }
        Ok(())
    }

    /// Calls `f` on the plugins `order` names, with the DNM's context; stops at the first error
    /// and returns it with the plugin's index.
    fn with_plugins(
        &mut self,
        order: impl IntoIterator<Item = usize>,
        mut f: impl FnMut(&mut dyn Plugin, &Context<'_>) -> Result<(), PluginPrepareError>,
    ) -> Result<(), (usize, PluginPrepareError)> {
        let local_outputs = self.local_outputs();
        let ctx = Context {
            system: &self.system,
            dnm: &self.name,
            prefix: &self.prefix,
            node: &self.node,
            local_outputs: &local_outputs,
        };
        for i in order {
            f(self.plugins[i].as_mut(), &ctx).map_err(|e| (i, e))?;
        }
        Ok(())
    }

    /// Output services of the modules running here.
    pub(crate) fn local_outputs(&self) -> BTreeSet<String> {
        self.modules
            .values()
            .flat_map(|m| {
                m.spec
                    .outputs
                    .iter()
                    .map(|p| output_service(&m.decl.name, &p.name))
            })
            .collect()
    }

    /// Checks a pending apply: commits it when every module has prepared, aborts it when a new
    /// module died or the deadline passed. Never blocks.
    pub(crate) fn progress_apply(&mut self) {
        let Some(p) = self.apply.as_ref() else {
            return;
        };
        if p.held {
            // Prepared: it waits for the authority's decision, up to the hold limit.
            if Instant::now() >= p.deadline
                && let Some(p) = self.apply.take()
            {
                let id = p.txn.unwrap_or_default();
                let why = DnmError::GivenUp {
                    txn: id,
                    limit_s: crate::safe::HOLD_LIMIT.as_secs(),
                };
                self.remember_decided(id, Err(why.clone()));
                self.abort_apply(p, why);
            }
            return;
        }
        let revision = p.revision;
        // A new module that exited while preparing fails the apply.
        let mut exited = None;
        if let Some(a) = self.apply.as_mut() {
            for (name, slot) in a.staged.iter_mut() {
                if let Some(child) = slot.child.as_mut()
                    && crate::group::kill_leftovers(child.id())
                    && let Ok(Some(exit)) = child.try_wait()
                {
                    // Its last status may say why (a module that failed to build).
                    let error = slot.last_error();
                    slot.child = None;
                    let why = match error {
                        Some(e) => format!("{exit}; its last error: {e}"),
                        None => exit.to_string(),
                    };
                    exited = Some((name.clone(), why));
                    break;
                }
            }
        }
        if let Some((module, exit)) = exited {
            let e = DnmError::PrepareExit {
                module,
                revision,
                exit,
            };
            self.fail_apply(e);
            return;
        }
        let Some(p) = self.apply.as_ref() else {
            return;
        };
        // A module that could not prepare the revision fails the apply.
        let refused = self
            .modules
            .iter()
            .filter(|(n, _)| !p.removed.contains(n) && !p.replaced.contains(n))
            .chain(p.staged.iter())
            .find(|(_, s)| s.status.prepare_failed == revision)
            .map(|(n, _)| n.clone());
        if let Some(module) = refused {
            self.fail_apply(DnmError::PrepareFailed { module, revision });
            return;
        }
        let waiting: Vec<String> = self
            .modules
            .iter()
            .filter(|(n, _)| !p.removed.contains(n) && !p.replaced.contains(n))
            .chain(p.staged.iter())
            .filter(|(_, s)| {
                // A module that is down (restarting) prepares when it comes back; it does not
                // hold up the commit, and finds both plans as history.
                s.child.is_some() && s.status.plan_revision < revision
            })
            .map(|(n, s)| {
                // A module that subscribed after the plan was posted gets it (as history) only
                // when the publisher updates its connections; then it needs a wake-up.
                let _ = s.plan_pub.update_connections();
                let _ = s.wake.notify();
                n.clone()
            })
            .collect();
        if waiting.is_empty() {
            if let Some(p) = self.apply.as_mut().filter(|p| p.txn.is_some()) {
                p.held = true;
                p.deadline = Instant::now() + crate::safe::HOLD_LIMIT;
                let ready = std::mem::take(&mut p.ready);
                tracing::info!(dnm = %self.name, revision, "prepared; waiting for the decision");
                self.publish();
                for r in ready {
                    r.send(Ok(()));
                }
            } else if let Some(p) = self.apply.take() {
                self.commit(p);
            }
        } else if Instant::now() >= p.deadline {
            let e = DnmError::PrepareTimeout {
                revision,
                timeout_ms: p.prepare_for.as_millis(),
                modules: waiting.join(", "),
            };
            self.fail_apply(e);
        }
    }

    fn fail_apply(&mut self, e: DnmError) {
        if let Some(p) = self.apply.take() {
            self.abort_apply(p, e);
        }
    }

    /// Undoes a pending apply and answers it with `why`.
    pub(crate) fn abort_apply(&mut self, mut p: PendingApply, why: DnmError) {
        tracing::warn!(dnm = %self.name, revision = p.revision, "apply refused: {why}");
        let replies = std::mem::take(&mut p.replies);
        let ready = std::mem::take(&mut p.ready);
        let key = p.key.take();
        self.undo(p);
        for r in ready {
            r.send(Err(why.clone()));
        }
        if let Some(k) = key {
            self.remember(k, Outcome::Apply(Err(why.clone())));
        }
        // Tools asking right after the answer see the state it reports.
        self.publish();
        for r in replies {
            r.send(Err(why.clone()));
        }
        self.next_apply();
    }

    /// Leaves the DNM as it was before `p`: staged processes stopped and forgotten, their port
    /// services released, plugins aborted, and every module given back the committed plan so
    /// the failed revision's references are dropped.
    fn undo(&mut self, mut p: PendingApply) {
        for (name, mut slot) in std::mem::take(&mut p.staged) {
            let prefix = format!("{name}/");
            let ports: Vec<PortServices> = p
                .new_ports
                .iter()
                .filter(|s| s.starts_with(&prefix))
                .filter_map(|s| self.ports.remove(s))
                .collect();
            if let Some(child) = slot.child.take() {
                self.retire_holding(&name, child, Some(slot), ports);
            }
        }
        for service in &p.new_ports {
            self.ports.remove(service);
        }
        let _ = self.with_plugins((0..p.prepared_plugins).rev(), |plugin, ctx| {
            plugin.abort(ctx, p.revision);
            Ok(())
        });
        if let Some(committed) = &self.netlist {
            for (name, slot) in &self.modules {
                // Twice, so the failed plan leaves the history a restarting module reads.
                let plan = module_plan(committed, name, self.revision);
                for _ in 0..PLAN_HISTORY {
                    if let Err(e) = slot.post_plan(&plan) {
                        tracing::error!(module = %name, "cannot restore the committed plan: {e}");
                    }
                }
            }
        }
    }

    /// Puts a prepared revision in force: one store into the task word, then the rest follows.
    /// Returns the task it left and the one in force.
    pub(crate) fn commit(&mut self, mut p: PendingApply) -> (Option<String>, Option<String>) {
        let revision = p.revision;
        // A decided revision in force: the DNM is no longer safe on its own.
        self.safed = None;
        let netlist = p.netlist.clone();
        // The task the transaction names, else the active task carries over if the new
        // netlist still defines it.
        let tasks = task_slots(&netlist);
        let left = self.active.clone();
        let task = p
            .task
            .clone()
            .filter(|t| tasks.contains(t))
            .or_else(|| self.active.clone().filter(|t| tasks.contains(t)))
            .or_else(|| netlist.initial_task().map(str::to_string));
        let slot = task
            .as_ref()
            .and_then(|t| tasks.iter().position(|x| x == t))
            .map_or(NO_TASK, |s| s as u16);
        self.store_word(task_word(revision, slot), monotonic_ns());
        self.revision = revision;
        self.tasks = tasks;
        self.active = task;
        self.netlist = Some(netlist.clone());
        self.netlist_digest = format!("{:016x}", netlist.digest());
        for slot in self.modules.values() {
            // Wake modules that wait for input so they take the new references now.
            let _ = slot.wake.notify();
        }
        // New modules join.
        for (name, slot) in std::mem::take(&mut p.staged) {
            self.modules.insert(name, slot);
        }
        // Removed modules stop; their port services go unless a module of the new revision
        // keeps the name.
        for name in &p.removed {
            let Some(mut slot) = self.modules.remove(name) else {
                continue;
            };
            let ports: Vec<PortServices> = slot
                .spec
                .outputs
                .iter()
                .filter_map(|port| self.ports.remove(&output_service(name, &port.name)))
                .collect();
            slot.state = ModuleRunState::Stopped;
            if let Some(child) = slot.child.take() {
                tracing::info!(dnm = %self.name, module = %name, "module stopping");
                self.retire_holding(name, child, Some(slot), ports);
            }
        }
        // Replaced modules: the old process stops; the new one starts once it is gone, and
        // finds the new plan as history. A failure to start is a module failure (restarted per
        // its policy), not a failed apply: the revision is committed.
        for name in &p.replaced {
            let old_child = self.modules.get_mut(name).and_then(|s| s.child.take());
            if let Some(child) = old_child {
                self.retire_process(name, child);
            }
            let hung_after = self.options.on_input_hung_after;
            let Some(slot) = self.modules.get_mut(name) else {
                continue;
            };
            if let Err(e) = slot.redeclare(&netlist, hung_after) {
                tracing::error!(module = %name, "cannot replace: {e}");
                slot.state = ModuleRunState::Stopped;
                continue;
            }
            if let Err(e) = slot.post_plan(&module_plan(&netlist, name, revision)) {
                tracing::error!(module = %name, "cannot post the plan of the replacement: {e}");
            }
            slot.state = ModuleRunState::Starting;
            slot.start_at = Some(Instant::now());
        }
        // Routes to and from other DNMs and the recording follow the committed revision.
        let n = self.plugins.len();
        let _ = self.with_plugins(0..n, |plugin, ctx| {
            plugin.commit(ctx, &netlist, revision);
            Ok(())
        });
        tracing::info!(dnm = %self.name, revision, task = ?self.active, "netlist applied");
        if let Some(k) = p.key.take() {
            self.remember(k, Outcome::Apply(Ok(revision)));
        }
        // Tools asking right after the answer see the state it reports.
        self.publish();
        for r in std::mem::take(&mut p.replies) {
            r.send(Ok(revision));
        }
        self.next_apply();
        (left, self.active.clone())
    }

    /// Starts the next queued apply, if any.
    pub(crate) fn next_apply(&mut self) {
        if self.apply.is_some() || self.stopping_all {
            return;
        }
        if self
            .queued_applies
            .front()
            .is_some_and(|(n, _, _)| self.waits_for_stopping(n))
        {
            // Started by supervision once the process is gone.
            return;
        }
        if let Some((netlist, key, reply)) = self.queued_applies.pop_front() {
            // Answered from memory if it was applied meanwhile under the same key.
            if let Some(k) = &key
                && let Some(Outcome::Apply(r)) = self.answered(k)
            {
                reply.send(r);
                return self.next_apply();
            }
            if !self.start_apply(netlist, key, reply) {
                self.next_apply();
            }
        }
    }
}

fn is_executable(path: &std::path::Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(path).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
}

impl Dnm {
    /// Modules on this DNM that read `module.port` in `netlist` or in the netlist in force: both
    /// hold subscribers while an apply is prepared.
    fn readers_across(&self, netlist: &Netlist, module: &str, port: &str) -> usize {
        let mut readers = netlist.reader_names(module, port, &self.name);
        if let Some(current) = &self.netlist {
            readers.extend(current.reader_names(module, port, &self.name));
        }
        readers.len()
    }
}

/// Refuses an apply whose readers of `module.port` on `dnm`, with the DNM's own subscribers,
/// do not fit the `has` slots its port was made with.
fn check_room(
    module: &str,
    port: &str,
    dnm: &str,
    readers: usize,
    has: usize,
) -> Result<(), DnmError> {
    let needed = readers + dnm_netlist::DNM_SUBSCRIBERS;
    if needed <= has {
        return Ok(());
    }
    Err(DnmError::Ipc(format!(
        "output `{module}.{port}` was made for {has} subscribers and this apply needs {needed} \
         ({readers} readers on DNM `{dnm}`, counting those of the netlist in force until the \
         commit, and {} of the DNM's own): remove `{module}` in one apply and add it back in the \
         next, so that its port is made anew",
        dnm_netlist::DNM_SUBSCRIBERS
    )))
}
