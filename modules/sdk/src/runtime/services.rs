//! The shared-memory services a module and its DNM share, opened with the settings every DNM
//! uses (see [`crate::protocol`]), and [`TaskWatch`], a reader of a DNM's task word.

use dnm_netlist::Payload;
use iceoryx2::prelude::*;
use iceoryx2::service::builder::blackboard::BlackboardOpenError;
use iceoryx2::service::builder::event::{EventOpenError, EventOpenOrCreateError};
use iceoryx2::service::builder::publish_subscribe::{
    PublishSubscribeOpenError, PublishSubscribeOpenOrCreateError,
};
use iceoryx2::service::port_factory::blackboard::PortFactory as BlackboardFactory;

use super::abandoned::remove_abandoned_services;
use super::author::{ModuleError, ipc};
use crate::protocol::*;

pub(crate) type Svc = ipc::Service;

/// Opens (or creates, with the DNM's exact settings) an output port's pub/sub service,
/// admitting at least the default number of subscribers.
pub fn port_service<S: iceoryx2::service::Service>(
    node: &Node<S>,
    name: &str,
    payload: &Payload,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<S, [u8], PortHeader>,
    ModuleError,
> {
    let (max_subscribers, _) = port_limits(payload);
    port_service_for(node, name, payload, max_subscribers)
}

/// [`port_service`] admitting `subscribers` (the DNM creates a port for its readers in the
/// netlist: [`dnm_netlist::Payload::subscribers_for`]).
pub fn port_service_for<S: iceoryx2::service::Service>(
    node: &Node<S>,
    name: &str,
    payload: &Payload,
    max_subscribers: usize,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<S, [u8], PortHeader>,
    ModuleError,
> {
    let service_name: ServiceName = name.try_into().map_err(ipc("service name"))?;
    let alignment = Alignment::new(8).ok_or_else(|| ModuleError::Ipc("alignment".into()))?;
    recovering(node.config(), pub_sub_hangs, || {
        node.service_builder(&service_name)
            .publish_subscribe::<[u8]>()
            .user_header::<PortHeader>()
            .payload_alignment(alignment)
            .max_publishers(MAX_PORT_PUBLISHERS)
            .max_subscribers(max_subscribers)
            .subscriber_max_buffer_size(crate::protocol::recorder_buffer(payload))
            .subscriber_max_borrowed_samples(PORT_BORROWED)
            .history_size(1)
            .enable_safe_overflow(true)
            .max_nodes(MAX_MODULES)
            .open_or_create()
    })
    .map_err(ipc("port service"))
}

/// Opens (or creates) an event service with the settings every DNM uses.
pub fn event_service<S: iceoryx2::service::Service>(
    node: &Node<S>,
    name: &str,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<S>, ModuleError> {
    event_service_for(node, name, MAX_PORT_SUBSCRIBERS)
}

/// [`event_service`] admitting `listeners` (an output's event, one listener per reader).
pub fn event_service_for<S: iceoryx2::service::Service>(
    node: &Node<S>,
    name: &str,
    listeners: usize,
) -> Result<iceoryx2::service::port_factory::event::PortFactory<S>, ModuleError> {
    let service_name: ServiceName = name.try_into().map_err(ipc("service name"))?;
    recovering(node.config(), event_hangs, || {
        node.service_builder(&service_name)
            .event()
            .max_listeners(listeners)
            .max_notifiers(MAX_MODULES)
            .max_nodes(MAX_MODULES)
            .open_or_create()
    })
    .map_err(ipc("event service"))
}

/// Opens the DNM's active-task blackboard.
pub(crate) fn task_board(node: &Node<Svc>) -> Result<BlackboardFactory<Svc, u64>, ModuleError> {
    let service_name: ServiceName = TASK_SERVICE.try_into().map_err(ipc("service name"))?;
    recovering(node.config(), board_hangs, || {
        node.service_builder(&service_name)
            .blackboard_opener::<u64>()
            .max_readers(MAX_MODULES)
            .max_nodes(MAX_MODULES)
            .open()
    })
    .map_err(ipc("task blackboard (is the DNM running?)"))
}

/// The plan service of a module (the DNM publishes, the module subscribes).
pub fn plan_service_factory(
    node: &Node<Svc>,
    module: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, [u8], ()>,
    ModuleError,
> {
    let name: ServiceName = crate::protocol::plan_service(module)
        .as_str()
        .try_into()
        .map_err(ipc("service name"))?;
    recovering(node.config(), pub_sub_hangs, || {
        node.service_builder(&name)
            .publish_subscribe::<[u8]>()
            .history_size(PLAN_HISTORY)
            .subscriber_max_buffer_size(4)
            .max_publishers(1)
            .max_subscribers(2)
            .open_or_create()
    })
    .map_err(ipc("plan service"))
}

/// The status service of a module.
pub fn status_service_factory(
    node: &Node<Svc>,
    module: &str,
) -> Result<
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, Status, ()>,
    ModuleError,
> {
    let name: ServiceName = status_service(module)
        .as_str()
        .try_into()
        .map_err(ipc("service name"))?;
    recovering(node.config(), pub_sub_hangs, || {
        node.service_builder(&name)
            .publish_subscribe::<Status>()
            .history_size(1)
            .subscriber_max_buffer_size(4)
            .max_publishers(2)
            .max_subscribers(2)
            .enable_safe_overflow(true)
            .open_or_create()
    })
    .map_err(ipc("status service"))
}

/// How many times [`recovering`] runs an open.
const OPEN_ATTEMPTS: usize = 3;

/// Runs `open`, which opens or creates a service of `config`'s namespace; when it fails, removes
/// what processes that died creating a service abandoned (see [`super::abandoned`]) and runs it
/// again if that may help: something was removed, or the service hangs in creation (`hangs`)
/// and another process removed it meanwhile. An unfinished description too young to judge is
/// judged again after iceoryx2's creation timeout (this thread sleeps). Runs `open` at most
/// three times.
pub fn recovering<T, E>(
    config: &iceoryx2::config::Config,
    hangs: fn(&E) -> bool,
    mut open: impl FnMut() -> Result<T, E>,
) -> Result<T, E> {
    let mut attempt = 1;
    loop {
        let e = match open() {
            Ok(t) => return Ok(t),
            Err(e) => e,
        };
        if attempt == OPEN_ATTEMPTS {
            return Err(e);
        }
        attempt += 1;
        let mut sweep = remove_abandoned_services(config);
        if sweep.removed == 0 && sweep.undecided > 0 {
            std::thread::sleep(config.global.creation_timeout);
            sweep = remove_abandoned_services(config);
        }
        if sweep.removed == 0 && !hangs(&e) {
            return Err(e);
        }
    }
}

fn event_hangs(e: &EventOpenOrCreateError) -> bool {
    matches!(
        e,
        EventOpenOrCreateError::EventOpenError(EventOpenError::HangsInCreation)
    )
}

fn pub_sub_hangs(e: &PublishSubscribeOpenOrCreateError) -> bool {
    matches!(
        e,
        PublishSubscribeOpenOrCreateError::PublishSubscribeOpenError(
            PublishSubscribeOpenError::HangsInCreation
        )
    )
}

fn board_hangs(e: &BlackboardOpenError) -> bool {
    matches!(e, BlackboardOpenError::HangsInCreation)
}

/// A DNM's task word read from outside the DNM, as its modules read it: for tools and tests
/// that watch several DNMs switch (each read is two loads from shared memory).
pub struct TaskWatch {
    word: iceoryx2::port::reader::EntryHandle<Svc, u64, u64>,
    at: iceoryx2::port::reader::EntryHandle<Svc, u64, u64>,
    _reader: iceoryx2::port::reader::Reader<Svc, u64>,
    _board: BlackboardFactory<Svc, u64>,
    _node: Option<Node<Svc>>,
}

impl std::fmt::Debug for TaskWatch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("TaskWatch")
    }
}

impl TaskWatch {
    /// Opens the task word of DNM `dnm` of `system` on this machine (it must be running).
    pub fn open(system: &str, dnm: &str) -> Result<Self, ModuleError> {
        let config =
            dnm_config(&dnm_prefix(system, dnm)).map_err(|e| ModuleError::Launch(e.to_string()))?;
        let node = NodeBuilder::new()
            .config(&config)
            .create::<Svc>()
            .map_err(ipc("node"))?;
        let mut watch = Self::on(&node)?;
        watch._node = Some(node);
        Ok(watch)
    }

    /// The task word of the DNM whose namespace `node` is in (a module's own view of it).
    pub(crate) fn on(node: &Node<Svc>) -> Result<Self, ModuleError> {
        let board = task_board(node)?;
        let reader = board
            .reader_builder()
            .create()
            .map_err(ipc("blackboard reader"))?;
        let word = reader
            .entry::<u64>(&TASK_WORD_KEY)
            .map_err(ipc("blackboard entry"))?;
        let at = reader
            .entry::<u64>(&SWITCHED_AT_KEY)
            .map_err(ipc("blackboard entry"))?;
        Ok(Self {
            word,
            at,
            _reader: reader,
            _board: board,
            _node: None,
        })
    }

    /// (revision, task slot, CLOCK_MONOTONIC ns of the store).
    pub fn read(&self) -> (u64, u16, u64) {
        let (revision, slot) = split_task_word(self.word());
        (revision, slot, self.switched_at())
    }

    /// The task word.
    pub(crate) fn word(&self) -> u64 {
        *self.word.get()
    }

    /// CLOCK_MONOTONIC ns of the last store of the task word.
    pub(crate) fn switched_at(&self) -> u64 {
        *self.at.get()
    }
}
