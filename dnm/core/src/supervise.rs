//! Module processes: starting them, noticing exits and hangs, restarting them per policy, and
//! stopping them without ever waiting on the DNM's thread.

use std::process::Child;
use std::time::{Duration, Instant};

use dnm_module::protocol::*;
use dnm_netlist::{RestartMode, Trigger};
use dnm_proto::{ModuleEvent, ModuleRunState};
use iceoryx2::port::update_connections::UpdateConnections;

use crate::error::DnmError;
use crate::node::{Dnm, MEMORY_EVERY};
use crate::slot::{ModuleSlot, PortServices, Stopping};

/// The largest back-off between restarts.
const MAX_BACKOFF: Duration = Duration::from_secs(5);
/// A process that ran this long before it exited ran healthy: it is restarted at once, and its
/// restarts count from zero again (`max_restarts` limits restarts in a row, a crash loop).
const HEALTHY_RUN: Duration = Duration::from_secs(5);

/// The wait before the next restart of a module that has restarted `streak` times in a row:
/// none after a healthy run, then 100 ms doubling to at most [`MAX_BACKOFF`].
fn backoff(streak: u32) -> Duration {
    match streak {
        0 => Duration::ZERO,
        n => Duration::from_millis(100 << (n - 1).min(6)).min(MAX_BACKOFF),
    }
}

impl Dnm {
    /// Starts a module's process with its launch description.
    pub(crate) fn spawn(&self, slot: &mut ModuleSlot) -> Result<(), DnmError> {
        let trigger = match (slot.spec.trigger, slot.decl.rate_hz) {
            (Trigger::Periodic { .. }, Some(rate_hz)) => Trigger::Periodic { rate_hz },
            (t, _) => t,
        };
        let launch = Launch {
            system: self.system.clone(),
            dnm: self.name.clone(),
            prefix: self.prefix.clone(),
            module: slot.decl.name.clone(),
            kind: slot.decl.kind.clone(),
            params: slot.decl.params.clone(),
            trigger,
        };
        let exec = slot.exec(&self.options.module_host);
        let json = serde_json::to_string(&launch).map_err(|e| DnmError::Ipc(e.to_string()))?;
        let mut command = std::process::Command::new(&exec);
        command.arg("run").arg(json);
        // A process group of its own: Ctrl-C in the terminal reaches the DNM, which stops its
        // modules in order, not every module at once behind its back.
        std::os::unix::process::CommandExt::process_group(&mut command, 0);
        // A module must not outlive its DNM: if the DNM's thread dies (even by SIGKILL of the
        // whole process), the kernel sends the module SIGTERM.
        // SAFETY: prctl is async-signal-safe and touches only the child's own state.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut command, || {
                if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let child = command.spawn().map_err(|e| DnmError::Spawn {
            module: slot.decl.name.clone(),
            exec: exec.display().to_string(),
            why: e.to_string(),
        })?;
        tracing::info!(dnm = %self.name, module = %slot.decl.name, pid = child.id(), "module started");
        if let Some(exits) = &self.exits {
            exits.watch(child.id());
        }
        slot.child = Some(child);
        slot.spawned_at = Instant::now();
        slot.state = ModuleRunState::Starting;
        slot.status = Status::default();
        // A new process: its CPU time starts from zero, not from the last one's.
        slot.cpu = crate::procfs::CpuMeter::default();
        slot.start_at = None;
        Ok(())
    }

    /// Asks a process to exit (SIGTERM) and leaves it to supervision, which kills it after the
    /// grace period and reaps it. Never waits.
    pub(crate) fn retire_process(&mut self, module: &str, child: Child) {
        self.retire_holding(module, child, None, Vec::new());
    }

    /// [`Dnm::retire_process`], keeping the module's services until the process is gone.
    pub(crate) fn retire_holding(
        &mut self,
        module: &str,
        child: Child,
        held_slot: Option<ModuleSlot>,
        held_ports: Vec<PortServices>,
    ) {
        crate::group::signal(child.id(), libc::SIGTERM);
        self.stopping.push(Stopping {
            module: module.to_string(),
            child,
            kill_at: Instant::now() + self.options.stop_grace,
            held_slot,
            held_ports,
        });
    }

    /// Whether applying `netlist` would add a module whose previous process is still being
    /// stopped: such an apply waits until it is gone.
    pub(crate) fn waits_for_stopping(&self, netlist: &dnm_netlist::Netlist) -> bool {
        self.stopping.iter().any(|s| {
            !self.modules.contains_key(&s.module)
                && netlist
                    .module(&s.module)
                    .is_some_and(|m| m.dnm == self.name)
        })
    }

    /// Stops a module's process (asynchronously) and marks it stopped.
    pub(crate) fn stop_module(&mut self, name: &str) {
        let Some(slot) = self.modules.get_mut(name) else {
            return;
        };
        slot.state = ModuleRunState::Stopped;
        slot.start_at = None;
        if let Some(child) = slot.child.take() {
            self.retire_process(name, child);
            tracing::info!(dnm = %self.name, module = name, "module stopping");
        }
    }

    /// Takes the modules' heartbeats.
    pub(crate) fn read_statuses(&mut self) {
        let slots = self
            .modules
            .values_mut()
            .chain(self.apply.iter_mut().flat_map(|a| a.staged.values_mut()));
        for slot in slots {
            while let Ok(Some(s)) = slot.status_sub.receive() {
                // Heartbeats of a process we already replaced are ignored.
                if Some(s.pid) == slot.pid() {
                    slot.status = *s;
                    if slot.state == ModuleRunState::Starting {
                        if ModuleState::from_u32(s.state) == ModuleState::Running {
                            slot.state = ModuleRunState::Running;
                        } else {
                            // Its first status: it subscribed to its plans, which it gets
                            // now, not on the next supervision pass.
                            let _ = slot.plan_pub.update_connections();
                            let _ = slot.wake.notify();
                        }
                    }
                }
            }
        }
    }

    pub(crate) fn event(&mut self, module: &str, what: &str, detail: String) {
        let event = ModuleEvent {
            dnm: self.name.clone(),
            module: module.to_string(),
            what: what.to_string(),
            detail,
            at_ns: monotonic_ns(),
        };
        for p in &mut self.plugins {
            p.module_event(&event);
        }
        self.events_log.push_back(event);
        if self.events_log.len() > 64 {
            self.events_log.pop_front();
        }
    }

    /// One supervision pass: exits, hangs, restarts, processes being stopped. Never blocks.
    pub(crate) fn supervise(&mut self) {
        let now = Instant::now();
        let mut pass = Pass::default();
        self.check_processes(now, &mut pass);
        for pid in std::mem::take(&mut pass.to_kill) {
            // (SIGKILL also ends a stopped process.)
            crate::group::signal(pid, libc::SIGKILL);
        }
        self.wake_starting();
        pass.any_died |= self.reap_stopping(now);
        if pass.any_died {
            self.janitor.sweep();
        }
        // An apply that waited for a stopping process may start now.
        if self.apply.is_none() && !self.queued_applies.is_empty() {
            self.next_apply();
        }
        self.start_due(now, &mut pass.events);
        for (module, what, detail) in pass.events {
            self.event(&module, what, detail);
        }
    }

    /// Every running module process: has it exited, hung, or recovered?
    fn check_processes(&mut self, now: Instant, pass: &mut Pass) {
        let now_ns = monotonic_ns();
        let prepare_timeout = self.options.prepare_timeout;
        for (name, slot) in self.modules.iter_mut() {
            let Some(child) = slot.child.as_mut() else {
                continue;
            };
            // (Reaped only once it exited, its leftovers killed first.)
            let gone = crate::group::kill_leftovers(child.id());
            match if gone { child.try_wait() } else { Ok(None) } {
                Ok(Some(exit)) => {
                    pass.any_died = true;
                    pass.events.push(exited(&self.name, name, slot, exit, now));
                    continue;
                }
                Ok(None) => {}
                Err(e) => tracing::warn!(module = %name, "cannot poll module process: {e}"),
            }
            let pid = child.id();
            if let Some((event, kill)) =
                liveness(&self.name, name, slot, now, now_ns, prepare_timeout)
            {
                if kill {
                    pass.to_kill.push(pid);
                }
                pass.events.push(event);
            }
        }
    }

    /// A (re)started process finds its plans as history once the publisher updates its
    /// connections; then it needs a wake-up to read them.
    fn wake_starting(&self) {
        for slot in self.modules.values() {
            if slot.state == ModuleRunState::Starting && slot.child.is_some() {
                let _ = slot.plan_pub.update_connections();
                let _ = slot.wake.notify();
            }
        }
    }

    /// Processes on their way out: forgotten once gone, killed at their deadline. Whether one
    /// went.
    fn reap_stopping(&mut self, now: Instant) -> bool {
        let mut any_died = false;
        let mut i = 0;
        while i < self.stopping.len() {
            let s = &mut self.stopping[i];
            crate::group::kill_leftovers(s.child.id());
            let gone = match s.child.try_wait() {
                Ok(Some(status)) => Some(status.to_string()),
                // Not ours to wait for any more: gone either way.
                Err(e) => Some(format!("not known ({e})")),
                Ok(None) => None,
            };
            if let Some(status) = gone {
                any_died = true;
                tracing::info!(dnm = %self.name, module = %s.module, %status, "module stopped");
                self.stopping.swap_remove(i);
                continue;
            }
            if now >= s.kill_at {
                crate::group::signal(s.child.id(), libc::SIGKILL);
            }
            i += 1;
        }
        any_died
    }

    /// How long until the soonest start that waits only for its time (none while a sweep is
    /// under way: its end wakes the loop).
    pub(crate) fn until_start(&self) -> Option<Duration> {
        if !self.janitor.idle() {
            return None;
        }
        let now = Instant::now();
        self.modules
            .iter()
            .filter(|(n, s)| s.child.is_none() && !self.stopping.iter().any(|x| x.module == **n))
            .filter_map(|(_, s)| s.start_at)
            .min()
            .map(|t| t.saturating_duration_since(now))
    }

    /// Starts that are due: restarts after their back-off, replacements once the process they
    /// replace is gone and its shared memory removed (the sweep wakes this DNM).
    fn start_due(&mut self, now: Instant, events: &mut Vec<Event>) {
        let swept = self.janitor.idle();
        let due: Vec<String> = self
            .modules
            .iter()
            .filter(|(n, s)| {
                swept
                    && s.child.is_none()
                    && s.start_at.is_some_and(|t| t <= now)
                    && !self.stopping.iter().any(|x| x.module == **n)
            })
            .map(|(n, _)| n.clone())
            .collect();
        for name in due {
            let Some(mut slot) = self.modules.remove(&name) else {
                continue;
            };
            let restart = slot.state == ModuleRunState::Failed;
            if restart {
                slot.restarts += 1;
                slot.streak += 1;
            }
            match self.spawn(&mut slot) {
                Ok(()) => events.push((
                    name.clone(),
                    if restart { "restarting" } else { "started" },
                    format!("pid {}", slot.pid().unwrap_or_default()),
                )),
                Err(e) => {
                    tracing::error!(module = %name, "start failed: {e}");
                    slot.last_exit = Some(e.to_string());
                    let retry = slot.decl.restart.mode != RestartMode::Never
                        && slot.streak < slot.decl.restart.max_restarts;
                    if retry {
                        slot.state = ModuleRunState::Failed;
                        slot.start_at = Some(now + MAX_BACKOFF);
                    } else {
                        slot.state = ModuleRunState::Stopped;
                        slot.start_at = None;
                    }
                    events.push((name.clone(), "exited", e.to_string()));
                }
            }
            self.modules.insert(name, slot);
        }
    }

    /// Rate readings on every pass; CPU from `/proc` once a second, memory once every
    /// [`MEMORY_EVERY`] (and at the first second of a process): a reading of every module's
    /// `/proc` files on each pass was most of what an idle DNM's loop cost, and memory moves
    /// slowly.
    pub(crate) fn meter(&mut self) {
        let read_proc = self.proc_read.elapsed() >= Duration::from_secs(1);
        let read_memory = read_proc && self.memory_read.elapsed() >= MEMORY_EVERY;
        if read_proc {
            self.proc_read = Instant::now();
            self.cpu.sample(std::process::id());
        }
        if read_memory {
            self.memory_read = Instant::now();
            self.memory = crate::procfs::memory(std::process::id());
        }
        for slot in self.modules.values_mut() {
            if let Some(pid) = slot.pid() {
                if read_proc {
                    slot.cpu.sample(pid);
                }
                if read_memory || read_proc && slot.memory.is_none() {
                    slot.memory = crate::procfs::memory(pid);
                }
            } else {
                slot.memory = None;
            }
            let (t, steps, _) = slot.rate;
            let dt = t.elapsed().as_secs_f64();
            if dt >= 1.0 {
                let rate = slot.status.steps.saturating_sub(steps) as f64 / dt;
                slot.rate = (Instant::now(), slot.status.steps, rate);
            }
        }
    }

    /// Stops every module and waits for them (SIGTERM, then SIGKILL after the grace period).
    pub fn shutdown(&mut self) {
        self.stopping_all = true;
        self.refuse_queued_commands();
        for (_, _, reply) in std::mem::take(&mut self.queued_applies) {
            reply.send(Err(DnmError::Stopped));
        }
        if let Some(a) = self.apply.take() {
            self.abort_apply(a, DnmError::Stopped);
        }
        let names: Vec<String> = self.modules.keys().cloned().collect();
        for name in names {
            self.stop_module(&name);
        }
        let deadline = Instant::now() + self.options.stop_grace;
        while !self.stopping.is_empty() {
            // What the bridge still hands over while modules stop is answered, not dropped.
            self.refuse_queued_commands();
            self.stopping.retain_mut(|s| {
                crate::group::kill_leftovers(s.child.id());
                !matches!(s.child.try_wait(), Ok(Some(_)) | Err(_))
            });
            if Instant::now() >= deadline {
                for s in &mut self.stopping {
                    crate::group::signal(s.child.id(), libc::SIGKILL);
                    let _ = s.child.wait();
                }
                self.stopping.clear();
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        self.refuse_queued_commands();
        // Plugins finish (the recorder writes its summary and footer).
        self.plugins.clear();
        tracing::info!(dnm = %self.name, "stopped");
    }
}

/// A module event: the module, what happened, the detail.
type Event = (String, &'static str, String);

/// What one supervision pass found.
#[derive(Default)]
struct Pass {
    any_died: bool,
    events: Vec<Event>,
    /// Hung processes to kill (their exits restart them per policy on a later pass).
    to_kill: Vec<u32>,
}

/// A module's process exited: it is failed (and restarted after a back-off) or stopped, per
/// its restart policy.
fn exited(
    dnm: &str,
    name: &str,
    slot: &mut ModuleSlot,
    exit: std::process::ExitStatus,
    now: Instant,
) -> Event {
    // Its last status, posted before it exited, may say why (a step's fatal error).
    let error = slot.last_error().filter(|_| !exit.success());
    slot.child = None;
    let why = match slot.killed_hung.take() {
        Some(h) => format!("{h}; killed ({exit})"),
        None => exit.to_string(),
    };
    let why = match error {
        Some(e) => format!("{why}; its last error: {e}"),
        None => why,
    };
    slot.last_exit = Some(why.clone());
    let short = short_run(slot, now);
    let restart = match slot.decl.restart.mode {
        RestartMode::Always => true,
        RestartMode::OnFailure => !exit.success(),
        RestartMode::Never => false,
    } && slot.streak < slot.decl.restart.max_restarts;
    slot.state = if restart {
        ModuleRunState::Failed
    } else {
        ModuleRunState::Stopped
    };
    if restart {
        // At once after a healthy run; after a short one, 100 ms at least.
        slot.start_at = Some(now + backoff(slot.streak + u32::from(short)));
    }
    tracing::warn!(dnm = %dnm, module = %name, exit = %why, restart, "module exited");
    (
        name.to_string(),
        if restart { "exited" } else { "gave_up" },
        why,
    )
}

/// Whether the process ran shorter than a healthy run; after a healthy one, its restarts count
/// from zero again.
fn short_run(slot: &mut ModuleSlot, now: Instant) -> bool {
    let short = now.duration_since(slot.spawned_at) < HEALTHY_RUN;
    if !short {
        slot.streak = 0;
    }
    short
}

/// A live process: is it still stepping? The event of a hang or a recovery, and whether the
/// hung process is to be killed.
fn liveness(
    dnm: &str,
    name: &str,
    slot: &mut ModuleSlot,
    now: Instant,
    now_ns: u64,
    prepare_timeout: Duration,
) -> Option<(Event, bool)> {
    let alive_ns = slot.status.heartbeat_ns.max(slot.status.last_step_ns);
    let silent = match slot.state {
        ModuleRunState::Running | ModuleRunState::Hung if alive_ns > 0 => {
            Duration::from_nanos(now_ns.saturating_sub(alive_ns))
        }
        // Never reached its first step: count from the start of the process.
        ModuleRunState::Starting => now
            .duration_since(slot.spawned_at)
            .saturating_sub(prepare_timeout),
        _ => Duration::ZERO,
    };
    let hung = silent > slot.hung_after;
    match (slot.state, hung) {
        (ModuleRunState::Running | ModuleRunState::Starting, true) => {
            slot.state = ModuleRunState::Hung;
            slot.hangs += 1;
            let detail = format!(
                "no sign of life for {} ms (deadline {} ms)",
                silent.as_millis(),
                slot.hung_after.as_millis()
            );
            tracing::warn!(dnm = %dnm, module = %name, "{detail}");
            short_run(slot, now);
            let restart = slot.decl.restart.mode != RestartMode::Never
                && slot.streak < slot.decl.restart.max_restarts;
            if restart {
                // The exit is noticed on a later pass and restarts it per its policy.
                slot.killed_hung = Some(format!("hung: {detail}"));
            }
            Some(((name.to_string(), "hung", detail), restart))
        }
        (ModuleRunState::Hung, false) if slot.killed_hung.is_none() => {
            slot.state = ModuleRunState::Running;
            Some((
                (name.to_string(), "recovered", "stepping again".into()),
                false,
            ))
        }
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_restart_after_a_healthy_run_is_at_once_and_a_crash_loop_backs_off() {
        assert_eq!(backoff(0), Duration::ZERO);
        assert_eq!(backoff(1), Duration::from_millis(100));
        assert_eq!(backoff(2), Duration::from_millis(200));
        assert_eq!(backoff(6), Duration::from_millis(3200));
        assert_eq!(backoff(7), MAX_BACKOFF);
        assert_eq!(backoff(u32::MAX), MAX_BACKOFF);
    }
}
