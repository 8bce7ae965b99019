//! Noticing a module process's exit the moment it happens: a thread per DNM waits (poll(2), no
//! timeout) on a pidfd of every process the DNM starts, and when one exits it asks the DNM's
//! loop to supervise at once and wakes it. The loop alone reaps processes; this thread only
//! watches.

use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, Sender, TryRecvError, channel};
use std::thread::JoinHandle;

use dnm_module::event_service;
use dnm_module::protocol::DNM_EVENT;
use iceoryx2::prelude::*;

use crate::slot::Svc;

/// Watches the DNM's module processes for their exits.
pub(crate) struct Exits {
    tx: Option<Sender<OwnedFd>>,
    /// An eventfd that tells the thread of a new process to watch, or to stop.
    bell: Arc<OwnedFd>,
    thread: Option<JoinHandle<()>>,
}

impl Exits {
    /// Starts the thread for the DNM `name`; an exit sets `prompt` and wakes the DNM.
    pub(crate) fn start(name: &str, config: Config, prompt: Arc<AtomicBool>) -> Option<Self> {
        // SAFETY: eventfd(2) with valid flags; a negative result is checked.
        let fd = unsafe { libc::eventfd(0, libc::EFD_CLOEXEC | libc::EFD_NONBLOCK) };
        if fd < 0 {
            tracing::warn!(
                dnm = name,
                "no eventfd: exits are noticed on the supervision tick"
            );
            return None;
        }
        // SAFETY: `fd` is a new descriptor that nothing else owns.
        let bell = Arc::new(unsafe { OwnedFd::from_raw_fd(fd) });
        let (tx, rx) = channel();
        let dnm = name.to_string();
        let b = bell.clone();
        let thread = std::thread::Builder::new()
            .name(format!("dnm-{name}-exits"))
            .spawn(move || watch_loop(&dnm, &config, &rx, &b, &prompt))
            .map_err(|e| tracing::warn!(dnm = name, "cannot start the exit watch: {e}"))
            .ok()?;
        Some(Self {
            tx: Some(tx),
            bell,
            thread: Some(thread),
        })
    }

    /// Watches process `pid`, a child of this process not reaped yet.
    pub(crate) fn watch(&self, pid: u32) {
        // SAFETY: pidfd_open(2) on our own unreaped child; a negative result is checked.
        let fd = unsafe { libc::syscall(libc::SYS_pidfd_open, pid as libc::pid_t, 0) };
        if fd < 0 {
            tracing::debug!(pid, "no pidfd: its exit is noticed on the supervision tick");
            return;
        }
        // SAFETY: a new descriptor that nothing else owns.
        let fd = unsafe { OwnedFd::from_raw_fd(fd as i32) };
        if let Some(tx) = &self.tx
            && tx.send(fd).is_ok()
        {
            ring(&self.bell);
        }
    }
}

impl Drop for Exits {
    fn drop(&mut self) {
        self.tx = None;
        ring(&self.bell);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn ring(bell: &OwnedFd) {
    let one = 1u64.to_ne_bytes();
    // SAFETY: an 8-byte write to an eventfd we own; a full counter (never reached) only drops
    // a ring the thread does not need, as it drains the channel on every ring.
    let _ = unsafe { libc::write(bell.as_raw_fd(), one.as_ptr().cast(), one.len()) };
}

fn watch_loop(
    dnm: &str,
    config: &Config,
    rx: &Receiver<OwnedFd>,
    bell: &OwnedFd,
    prompt: &AtomicBool,
) {
    let waker = NodeBuilder::new()
        .config(config)
        .create::<Svc>()
        .ok()
        .and_then(|node| {
            let n = event_service(&node, DNM_EVENT)
                .ok()?
                .notifier_builder()
                .create()
                .ok()?;
            Some((node, n))
        });
    if waker.is_none() {
        tracing::warn!(
            dnm,
            "the exit watch cannot wake the DNM: exits wait for its tick"
        );
    }
    let mut watched: Vec<OwnedFd> = Vec::new();
    loop {
        let mut fds: Vec<libc::pollfd> = std::iter::once(bell)
            .chain(&watched)
            .map(|fd| libc::pollfd {
                fd: fd.as_raw_fd(),
                events: libc::POLLIN,
                revents: 0,
            })
            .collect();
        // SAFETY: `fds` is a valid array of `fds.len()` pollfd structures.
        let n = unsafe { libc::poll(fds.as_mut_ptr(), fds.len() as libc::nfds_t, -1) };
        if n < 0 {
            let e = std::io::Error::last_os_error();
            if e.kind() == std::io::ErrorKind::Interrupted {
                continue;
            }
            tracing::error!(dnm, "the exit watch stops: {e}");
            return;
        }
        let before = watched.len();
        let mut i = 0;
        watched.retain(|_| {
            i += 1;
            fds[i].revents == 0
        });
        if watched.len() < before {
            prompt.store(true, Ordering::Release);
            if let Some((_, w)) = &waker {
                let _ = w.notify();
            }
        }
        if fds[0].revents != 0 {
            let mut count = [0u8; 8];
            // SAFETY: an 8-byte read from our nonblocking eventfd.
            let _ = unsafe { libc::read(bell.as_raw_fd(), count.as_mut_ptr().cast(), 8) };
            loop {
                match rx.try_recv() {
                    Ok(fd) => watched.push(fd),
                    Err(TryRecvError::Empty) => break,
                    Err(TryRecvError::Disconnected) => return,
                }
            }
        }
    }
}
