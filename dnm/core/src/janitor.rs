//! Removing what dead processes left in shared memory, on a thread of its own: a sweep takes
//! tens of milliseconds, and a DNM's thread must stay free for a decided instant.

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, SyncSender, sync_channel};
use std::thread::JoinHandle;

use dnm_module::protocol::DNM_EVENT;
use dnm_module::{event_service, remove_abandoned_services};
use iceoryx2::prelude::*;

use crate::slot::Svc;

/// Sweeps for dead processes when asked, and wakes the DNM when a sweep is done.
pub(crate) struct Janitor {
    tx: Option<SyncSender<()>>,
    counts: Arc<Counts>,
    thread: Option<JoinHandle<()>>,
}

#[derive(Default)]
struct Counts {
    /// Sweeps asked for, and the number of the last one asked for before the finished sweep
    /// started.
    asked: AtomicU64,
    done: AtomicU64,
    /// Dead processes whose shared memory was removed.
    cleaned: AtomicU64,
}

impl Janitor {
    /// Starts the thread for the DNM `name` whose shared memory lives under `config`; a finished
    /// sweep sets `prompt` and wakes the DNM.
    pub(crate) fn start(name: &str, config: Config, prompt: Arc<AtomicBool>) -> Self {
        // One sweep waiting is enough: it covers every exit seen before it starts. The first
        // one, at once, finds what processes of an earlier DNM left half-created.
        let (tx, rx) = sync_channel(1);
        let _ = tx.try_send(());
        let counts = Arc::new(Counts::default());
        let c = counts.clone();
        let dnm = name.to_string();
        let thread = std::thread::Builder::new()
            .name(format!("dnm-{name}-janitor"))
            .spawn(move || sweep_loop(&dnm, &config, &rx, &c, &prompt))
            .map_err(|e| tracing::error!(dnm = name, "cannot start the janitor thread: {e}"))
            .ok();
        if thread.is_none() {
            // Never sweeping must not stop modules from starting.
            counts.done.store(u64::MAX, Ordering::Relaxed);
        }
        Self {
            tx: Some(tx),
            counts,
            thread,
        }
    }

    /// Asks for a sweep (processes exited).
    pub(crate) fn sweep(&self) {
        self.counts.asked.fetch_add(1, Ordering::Relaxed);
        if let Some(tx) = &self.tx {
            // Full: a sweep not yet started covers this one.
            let _ = tx.try_send(());
        }
    }

    /// Whether every sweep asked for is done (what exited is gone from shared memory).
    pub(crate) fn idle(&self) -> bool {
        self.counts.done.load(Ordering::Acquire) >= self.counts.asked.load(Ordering::Relaxed)
    }

    pub(crate) fn cleaned(&self) -> u64 {
        self.counts.cleaned.load(Ordering::Relaxed)
    }
}

impl Drop for Janitor {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn sweep_loop(dnm: &str, config: &Config, rx: &Receiver<()>, counts: &Counts, prompt: &AtomicBool) {
    let node = match NodeBuilder::new().config(config).create::<Svc>() {
        Ok(n) => n,
        Err(e) => {
            tracing::error!(dnm, "the janitor cannot open shared memory: {e:?}");
            counts.done.store(u64::MAX, Ordering::Release);
            return;
        }
    };
    let waker = event_service(&node, DNM_EVENT)
        .ok()
        .and_then(|f| f.notifier_builder().create().ok());
    // While a sweep leaves a service description unfinished but too young to call abandoned,
    // the next sweep comes after iceoryx2's creation timeout, asked for or not: a module that
    // starts later then finds the service already freed instead of waiting that timeout.
    let mut recheck = false;
    loop {
        let next = if recheck {
            match rx.recv_timeout(config.global.creation_timeout) {
                Ok(()) | Err(RecvTimeoutError::Timeout) => true,
                Err(RecvTimeoutError::Disconnected) => false,
            }
        } else {
            rx.recv().is_ok()
        };
        if !next {
            return;
        }
        let asked = counts.asked.load(Ordering::Relaxed);
        let started = std::time::Instant::now();
        let cleaned = node.try_cleanup_dead_nodes().cleanups;
        let abandoned = remove_abandoned_services(config);
        recheck = abandoned.undecided > 0;
        tracing::debug!(dnm, cleaned, ?abandoned, took = ?started.elapsed(), "swept");
        counts.cleaned.fetch_add(cleaned, Ordering::Relaxed);
        counts.done.store(asked, Ordering::Release);
        prompt.store(true, Ordering::Release);
        if let Some(w) = &waker {
            let _ = w.notify();
        }
    }
}
