//! What a DNM's helper threads share (the Zenoh egress and the recorder's reader): a thread
//! with its own node in the DNM's shared-memory namespace serving a set of ports that the DNM
//! replaces after each applied revision. The DNM sends a new set and notifies the thread's
//! control event; the thread takes the newest set, reopens its ports and goes on. Dropping the
//! [`Worker`] stops the thread.

use std::sync::mpsc::{self, Receiver, Sender};
use std::thread::JoinHandle;

use dnm_module::event_service;
use dnm_module::protocol::dnm_config;
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::prelude::*;

type Svc = ipc::Service;
type TsSvc = ipc_threadsafe::Service;

pub fn dbg<E: std::fmt::Debug>(what: &str) -> impl FnOnce(E) -> String + '_ {
    move |e| format!("{what}: {e:?}")
}

pub fn err<E: std::fmt::Display>(what: &str) -> impl FnOnce(E) -> String + '_ {
    move |e| format!("{what}: {e}")
}

/// Why a helper thread did not start: which of its parts failed, and how.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{what}: {detail}")]
pub struct WorkerStartError {
    pub what: &'static str,
    pub detail: String,
}

fn start_dbg<E: std::fmt::Debug>(what: &'static str) -> impl FnOnce(E) -> WorkerStartError {
    move |e| WorkerStartError {
        what,
        detail: format!("{e:?}"),
    }
}

fn start_err<E: std::fmt::Display>(what: &'static str) -> impl FnOnce(E) -> WorkerStartError {
    move |e| WorkerStartError {
        what,
        detail: e.to_string(),
    }
}

/// What the thread sees: its node, its control listener (attach it to the WaitSet) and the
/// sets the DNM sends.
#[allow(missing_debug_implementations)]
pub struct Control<T> {
    pub node: Node<Svc>,
    pub listener: Listener<Svc>,
    sets: Receiver<Vec<T>>,
}

/// The outcome of [`Control::newest`].
#[allow(missing_debug_implementations)]
pub enum Sets<T> {
    /// Nothing new: keep serving the current set.
    Same,
    /// The newest set sent since the last look.
    New(Vec<T>),
    /// The DNM dropped the worker: return.
    Closed,
}

impl<T> Control<T> {
    /// Consumes pending control events and returns the newest set sent, if any.
    pub fn newest(&self) -> Sets<T> {
        let _ = self.listener.try_wait(|_| ());
        let mut latest = None;
        loop {
            match self.sets.try_recv() {
                Ok(set) => latest = Some(set),
                Err(mpsc::TryRecvError::Empty) => return latest.map_or(Sets::Same, Sets::New),
                Err(mpsc::TryRecvError::Disconnected) => return Sets::Closed,
            }
        }
    }
}

/// The DNM's handle on a helper thread.
#[allow(missing_debug_implementations)]
pub struct Worker<T> {
    sets: Sender<Vec<T>>,
    wake: Notifier<TsSvc>,
    _node: Node<TsSvc>,
    thread: Option<JoinHandle<()>>,
}

impl<T: Send + 'static> Worker<T> {
    /// Starts `body` on a thread named `name`, once its control listener (on service `event`
    /// of the namespace `prefix`) exists, so no notification is lost. The error `body` ends
    /// with is logged.
    pub fn spawn<E: std::fmt::Display>(
        name: String,
        prefix: &str,
        event: &'static str,
        body: impl FnOnce(Control<T>) -> Result<(), E> + Send + 'static,
    ) -> Result<Self, WorkerStartError> {
        let config = dnm_config(prefix).map_err(start_err("shared-memory configuration"))?;
        let (sets, rx) = mpsc::channel::<Vec<T>>();
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<(), WorkerStartError>>(1);
        let thread_config = config.clone();
        let thread_name = name.clone();
        let thread = std::thread::Builder::new()
            .name(name)
            .spawn(move || {
                let started = (|| {
                    let node = NodeBuilder::new()
                        .config(&thread_config)
                        .create::<Svc>()
                        .map_err(start_dbg("node"))?;
                    let listener = event_service(&node, event)
                        .map_err(start_err("control event"))?
                        .listener_builder()
                        .create()
                        .map_err(start_dbg("control listener"))?;
                    Ok::<_, WorkerStartError>(Control {
                        node,
                        listener,
                        sets: rx,
                    })
                })();
                match started {
                    Ok(control) => {
                        let _ = ready_tx.send(Ok(()));
                        if let Err(e) = body(control) {
                            tracing::error!(thread = %thread_name, "stopped: {e}");
                        }
                    }
                    Err(e) => {
                        let _ = ready_tx.send(Err(e));
                    }
                }
            })
            .map_err(start_err("spawning thread"))?;
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => return Err(e),
            Err(_) => {
                return Err(WorkerStartError {
                    what: "helper thread",
                    detail: "stopped while starting".into(),
                });
            }
        }
        let node = NodeBuilder::new()
            .config(&config)
            .create::<TsSvc>()
            .map_err(start_dbg("node"))?;
        let wake = event_service(&node, event)
            .map_err(start_err("control event"))?
            .notifier_builder()
            .create()
            .map_err(start_dbg("control notifier"))?;
        Ok(Self {
            sets,
            wake,
            _node: node,
            thread: Some(thread),
        })
    }

    /// Hands the thread a new set and wakes it.
    pub fn send(&self, set: Vec<T>) {
        if self.sets.send(set).is_ok() {
            let _ = self.wake.notify();
        }
    }
}

impl<T> Drop for Worker<T> {
    fn drop(&mut self) {
        drop(std::mem::replace(&mut self.sets, mpsc::channel().0));
        let _ = self.wake.notify();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}
