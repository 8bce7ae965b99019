//! The module process: opens the module's ports in its DNM's shared memory, follows the DNM's
//! plans, and runs the module's step on its trigger. Blocks on an iceoryx2 WaitSet; never spins.

use std::collections::BTreeMap;
use std::marker::PhantomData;
use std::time::Duration;

use dnm_netlist::{KindSpec, ParamValue, Payload, Trigger};
use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::sample::Sample;
use iceoryx2::service::port_factory::blackboard::PortFactory as BlackboardFactory;
use iceoryx2::waitset::WaitSetRunResult;

use crate::msg::Message;
use crate::protocol::*;

type Svc = ipc::Service;
type PortPublisher = Publisher<Svc, [u8], PortHeader>;
type PortSubscriber = Subscriber<Svc, [u8], PortHeader>;
type PortSample = Sample<Svc, [u8], PortHeader>;

/// An error inside a module or its connection to the DNM.
#[derive(Debug, thiserror::Error)]
pub enum ModuleError {
    #[error("parameter `{name}`: {problem}")]
    Param { name: String, problem: String },
    #[error("port `{name}`: {problem}")]
    Port { name: String, problem: String },
    #[error("shared memory: {0}")]
    Ipc(String),
    #[error("launch description: {0}")]
    Launch(String),
    #[error("{0}")]
    Step(String),
}

impl ModuleError {
    /// An error raised by a module's own logic.
    pub fn step(msg: impl Into<String>) -> Self {
        ModuleError::Step(msg.into())
    }
}

fn ipc<E: std::fmt::Debug>(what: &str) -> impl FnOnce(E) -> ModuleError + '_ {
    move |e| ModuleError::Ipc(format!("{what}: {e:?}"))
}

/// A module kind: what a module author implements.
pub trait Module: Sized + 'static {
    /// Ports, parameters and trigger (see [`crate::Kind`]).
    fn kind() -> KindSpec;
    /// Builds the module from its parameters, taking handles to its ports.
    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError>;
    /// One step: read inputs, write outputs. Called on the kind's trigger.
    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError>;
}

/// Typed handle of an input port.
#[derive(Debug)]
pub struct Input<M> {
    index: usize,
    _m: PhantomData<M>,
}

/// Typed handle of an output port.
#[derive(Debug)]
pub struct Output<M> {
    index: usize,
    _m: PhantomData<M>,
}

/// Handle of a variable-size input port.
#[derive(Debug)]
pub struct BytesInput {
    index: usize,
}

/// Handle of a variable-size output port.
#[derive(Debug)]
pub struct BytesOutput {
    index: usize,
}

/// Given to [`Module::new`]: parameters and port handles.
#[derive(Debug)]
pub struct Setup<'a> {
    module: &'a str,
    spec: &'a KindSpec,
    params: &'a BTreeMap<String, ParamValue>,
}

impl<'a> Setup<'a> {
    /// Used by tests and by [`crate::host`] to build a module outside a DNM.
    pub fn new(
        module: &'a str,
        spec: &'a KindSpec,
        params: &'a BTreeMap<String, ParamValue>,
    ) -> Self {
        Self {
            module,
            spec,
            params,
        }
    }

    /// This module's instance name.
    pub fn name(&self) -> &str {
        self.module
    }

    fn param_value(&self, name: &str) -> Result<&ParamValue, ModuleError> {
        self.params
            .get(name)
            .or_else(|| self.spec.param(name).and_then(|p| p.default.as_ref()))
            .ok_or_else(|| ModuleError::Param {
                name: name.into(),
                problem: "not given and has no default".into(),
            })
    }

    fn wrong(name: &str, kind: &str) -> ModuleError {
        ModuleError::Param {
            name: name.into(),
            problem: format!("is not a {kind}"),
        }
    }

    pub fn param_f64(&self, name: &str) -> Result<f64, ModuleError> {
        self.param_value(name)?
            .as_f64()
            .ok_or_else(|| Self::wrong(name, "float"))
    }

    pub fn param_i64(&self, name: &str) -> Result<i64, ModuleError> {
        self.param_value(name)?
            .as_i64()
            .ok_or_else(|| Self::wrong(name, "integer"))
    }

    pub fn param_bool(&self, name: &str) -> Result<bool, ModuleError> {
        self.param_value(name)?
            .as_bool()
            .ok_or_else(|| Self::wrong(name, "boolean"))
    }

    pub fn param_str(&self, name: &str) -> Result<&str, ModuleError> {
        self.param_value(name)?
            .as_str()
            .ok_or_else(|| Self::wrong(name, "string"))
    }

    fn port_index(
        &self,
        name: &str,
        input: bool,
        fixed: Option<usize>,
    ) -> Result<usize, ModuleError> {
        let ports = if input {
            &self.spec.inputs
        } else {
            &self.spec.outputs
        };
        let (index, port) = ports
            .iter()
            .enumerate()
            .find(|(_, p)| p.name == name)
            .ok_or_else(|| ModuleError::Port {
                name: name.into(),
                problem: format!(
                    "kind `{}` declares no {} port of that name",
                    self.spec.name,
                    if input { "input" } else { "output" }
                ),
            })?;
        let layout_ok = match (port.message.payload, fixed) {
            (Payload::Fixed { size_bytes }, Some(size)) => size_bytes == size,
            (Payload::Bytes { .. }, None) => true,
            _ => false,
        };
        if !layout_ok {
            return Err(ModuleError::Port {
                name: name.into(),
                problem: format!("declared as {}, requested with another type", port.message),
            });
        }
        Ok(index)
    }

    pub fn input<M: Message>(&self, name: &str) -> Result<Input<M>, ModuleError> {
        let index = self.port_index(name, true, Some(size_of::<M>()))?;
        Ok(Input {
            index,
            _m: PhantomData,
        })
    }

    pub fn output<M: Message>(&self, name: &str) -> Result<Output<M>, ModuleError> {
        let index = self.port_index(name, false, Some(size_of::<M>()))?;
        Ok(Output {
            index,
            _m: PhantomData,
        })
    }

    pub fn bytes_input(&self, name: &str) -> Result<BytesInput, ModuleError> {
        Ok(BytesInput {
            index: self.port_index(name, true, None)?,
        })
    }

    pub fn bytes_output(&self, name: &str) -> Result<BytesOutput, ModuleError> {
        Ok(BytesOutput {
            index: self.port_index(name, false, None)?,
        })
    }
}

struct OutPort {
    publisher: PortPublisher,
    notifier: Notifier<Svc>,
    seq: u64,
}

/// A subscription to one candidate source, with the newest sample taken from it.
struct SourceConn {
    source: Source,
    subscriber: PortSubscriber,
    latest: Option<PortSample>,
    /// Counts samples taken, so each input knows whether it has seen the latest.
    generation: u64,
}

/// Stands for "no step yet" where a task word is remembered.
const UNSET_WORD: u64 = u64::MAX;

/// Whether a sample was sent at or after `fresh_after_ns` (CLOCK_MONOTONIC).
fn sent_since(sample: &PortSample, fresh_after_ns: u64) -> bool {
    sample.user_header().stamp_ns >= fresh_after_ns
}

impl SourceConn {
    /// Takes everything queued, keeping only the newest sample.
    fn drain(&mut self) -> Result<bool, ModuleError> {
        let mut any = false;
        while let Some(sample) = self.subscriber.receive().map_err(ipc("receive"))? {
            self.latest = Some(sample);
            self.generation += 1;
            any = true;
        }
        Ok(any)
    }
}

/// The routes of one prepared plan: for each declared input (by index), source per task slot.
struct Routes {
    revision: u64,
    tasks: Vec<String>,
    /// `[input][slot]` -> index into `conns`.
    by_input: Vec<Vec<Option<usize>>>,
}

impl Routes {
    fn source(&self, input: usize, slot: u16) -> Option<usize> {
        self.by_input
            .get(input)?
            .get(usize::from(slot))
            .copied()
            .flatten()
    }
}

/// Given to [`Module::step`]: reads inputs under the task active for this step, writes outputs.
pub struct Io<'a> {
    word: u64,
    now_ns: u64,
    ports: Ports<'a>,
}

/// Where a step's inputs come from and its outputs go.
enum Ports<'a> {
    /// A module process: shared memory, under its DNM.
    Shm(Shm<'a>),
    /// A module run without a DNM ([`Offline`]).
    Offline(&'a mut Offline),
}

struct Shm<'a> {
    outputs: &'a mut [OutPort],
    conns: &'a [SourceConn],
    /// Per input: the connection feeding it in this step.
    active: &'a [Option<usize>],
    /// Per input: the generation of its source last returned by `read`.
    seen: &'a mut [Option<(usize, u64)>],
    /// Per input: samples sent before this time are not shown (the input was switched to its
    /// source then).
    fresh_after: &'a [u64],
    routes: Option<&'a Routes>,
    sent: &'a mut u64,
}

impl std::fmt::Debug for Io<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Io")
            .field("word", &self.word)
            .finish_non_exhaustive()
    }
}

impl Shm<'_> {
    fn sample(&self, input: usize) -> Option<&PortSample> {
        let conn = (*self.active.get(input)?)?;
        let after = self.fresh_after.get(input).copied().unwrap_or(0);
        self.conns[conn]
            .latest
            .as_ref()
            .filter(|s| sent_since(s, after))
    }

    fn take_new(&mut self, input: usize) -> Option<&PortSample> {
        let conn = (*self.active.get(input)?)?;
        let c = &self.conns[conn];
        let mark = Some((conn, c.generation));
        if self.seen[input] == mark {
            return None;
        }
        let after = self.fresh_after.get(input).copied().unwrap_or(0);
        let sample = c.latest.as_ref().filter(|s| sent_since(s, after))?;
        self.seen[input] = mark;
        Some(sample)
    }

    fn send(
        &mut self,
        index: usize,
        word: u64,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), ModuleError> {
        let out = &mut self.outputs[index];
        let sample = out.publisher.loan_slice_uninit(len).map_err(ipc("loan"))?;
        // Zero the uninitialised bytes only through the safe API: `write_from_fn` initialises
        // each byte once, then `fill` overwrites what it needs.
        let mut sample = sample.write_from_fn(|_| 0u8);
        fill(sample.payload_mut());
        self.stamp_and_send(index, word, sample)
    }

    /// A fixed-size value, copied once into shared memory (no zeroing first).
    fn send_slice(&mut self, index: usize, word: u64, data: &[u8]) -> Result<(), ModuleError> {
        let sample = self.outputs[index]
            .publisher
            .loan_slice_uninit(data.len())
            .map_err(ipc("loan"))?;
        let sample = sample.write_from_slice(data);
        self.stamp_and_send(index, word, sample)
    }

    fn stamp_and_send(
        &mut self,
        index: usize,
        word: u64,
        mut sample: iceoryx2::sample_mut::SampleMut<Svc, [u8], PortHeader>,
    ) -> Result<(), ModuleError> {
        let out = &mut self.outputs[index];
        // Stamped last, so latency measures delivery, not how long the producer took to fill.
        *sample.user_header_mut() = PortHeader {
            stamp_ns: monotonic_ns(),
            seq: out.seq,
            task_word: word,
        };
        out.seq += 1;
        sample.send().map_err(ipc("send"))?;
        *self.sent += 1;
        out.notifier.notify().map_err(ipc("notify"))?;
        Ok(())
    }
}

impl Io<'_> {
    /// CLOCK_MONOTONIC time at the start of this step, ns.
    pub fn now_ns(&self) -> u64 {
        self.now_ns
    }

    /// The task this step runs under.
    pub fn task(&self) -> Option<&str> {
        match &self.ports {
            Ports::Shm(shm) => {
                let (_, slot) = split_task_word(self.word);
                shm.routes?.tasks.get(usize::from(slot)).map(String::as_str)
            }
            Ports::Offline(o) => o.task.as_deref(),
        }
    }

    /// (netlist revision, task slot) of this step.
    pub fn task_word(&self) -> (u64, u16) {
        split_task_word(self.word)
    }

    /// The newest sample on `input` (header and bytes), new or not.
    fn sample(&self, input: usize) -> Option<(PortHeader, &[u8])> {
        match &self.ports {
            Ports::Shm(shm) => shm.sample(input).map(|s| (*s.user_header(), s.payload())),
            Ports::Offline(o) => o
                .inputs
                .get(input)?
                .as_ref()
                .map(|(h, b, _)| (*h, b.as_slice())),
        }
    }

    /// The newest sample on `input` if this input has not read it yet.
    fn take_new(&mut self, input: usize) -> Option<(PortHeader, &[u8])> {
        match &mut self.ports {
            Ports::Shm(shm) => shm.take_new(input).map(|s| (*s.user_header(), s.payload())),
            Ports::Offline(o) => {
                let (h, b, generation) = o.inputs.get(input)?.as_ref()?;
                if o.seen.get(input).copied().flatten() == Some(*generation) {
                    return None;
                }
                o.seen[input] = Some(*generation);
                Some((*h, b.as_slice()))
            }
        }
    }

    /// The newest value on `input` if it arrived since this input last read it, from the source
    /// connected in the active task.
    pub fn read<M: Message>(&mut self, input: &Input<M>) -> Option<M> {
        let (_, b) = self.take_new(input.index)?;
        bytemuck::try_pod_read_unaligned(b).ok()
    }

    /// The newest value on `input`, new or not.
    pub fn latest<M: Message>(&self, input: &Input<M>) -> Option<M> {
        bytemuck::try_pod_read_unaligned(self.sample(input.index)?.1).ok()
    }

    /// Header (send time, sequence) of the newest sample on an input.
    pub fn header<M>(&self, input: &Input<M>) -> Option<PortHeader> {
        self.sample(input.index).map(|(h, _)| h)
    }

    /// The newest bytes on `input` if they arrived since it last read them. Zero-copy: the slice
    /// is the producer's shared memory.
    pub fn read_bytes(&mut self, input: &BytesInput) -> Option<&[u8]> {
        self.take_new(input.index).map(|(_, b)| b)
    }

    /// Header of the newest bytes sample on an input.
    pub fn bytes_header(&self, input: &BytesInput) -> Option<PortHeader> {
        self.sample(input.index).map(|(h, _)| h)
    }

    fn send(
        &mut self,
        index: usize,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), ModuleError> {
        let word = self.word;
        match &mut self.ports {
            Ports::Shm(shm) => shm.send(index, word, len, fill),
            Ports::Offline(o) => {
                let mut bytes = vec![0u8; len];
                fill(&mut bytes);
                let seq = o.seq.get(index).copied().unwrap_or(0);
                if let Some(s) = o.seq.get_mut(index) {
                    *s += 1;
                }
                o.written.push((
                    index,
                    PortHeader {
                        stamp_ns: self.now_ns,
                        seq,
                        task_word: word,
                    },
                    bytes,
                ));
                Ok(())
            }
        }
    }

    /// Sends `value` on `output`.
    pub fn write<M: Message>(&mut self, output: &Output<M>, value: &M) -> Result<(), ModuleError> {
        let word = self.word;
        match &mut self.ports {
            Ports::Shm(shm) => shm.send_slice(output.index, word, bytemuck::bytes_of(value)),
            Ports::Offline(_) => self.send(output.index, size_of::<M>(), |b| {
                b.copy_from_slice(bytemuck::bytes_of(value));
            }),
        }
    }

    /// Writes `len` bytes straight into shared memory with `fill`, then sends them.
    pub fn write_bytes(
        &mut self,
        output: &BytesOutput,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), ModuleError> {
        self.send(output.index, len, fill)
    }
}

/// A module stepped without a DNM or shared memory: its inputs handed in, what it writes
/// collected. `dnm replay --check` runs a module this way on recorded inputs; module authors
/// can test their kinds with it.
///
/// ```
/// # use dnm_module::{Offline, Stepper};
/// # fn check(module: &mut dyn Stepper, spec: &dnm_netlist::KindSpec, ticks: &[u8]) {
/// let mut io = Offline::new(spec, Some("drive"));
/// io.set_input(0, 1_000, 0, ticks.to_vec());
/// let written = io.step(module, 1_000).unwrap();
/// # }
/// ```
#[derive(Debug, Default)]
pub struct Offline {
    /// Per input: the newest sample (header, bytes, generation).
    inputs: Vec<Option<(PortHeader, Vec<u8>, u64)>>,
    seen: Vec<Option<u64>>,
    seq: Vec<u64>,
    written: Vec<(usize, PortHeader, Vec<u8>)>,
    next: u64,
    task: Option<String>,
}

impl Offline {
    /// For a module of kind `spec`, running under `task`.
    pub fn new(spec: &KindSpec, task: Option<&str>) -> Self {
        Self {
            inputs: vec![None; spec.inputs.len()],
            seen: vec![None; spec.inputs.len()],
            seq: vec![0; spec.outputs.len()],
            written: Vec::new(),
            next: 0,
            task: task.map(str::to_string),
        }
    }

    /// Forgets input `index`'s sample, as a task switch that changes its source does.
    pub fn clear_input(&mut self, index: usize) {
        if let Some(slot) = self.inputs.get_mut(index) {
            *slot = None;
        }
    }

    /// The task the next steps run under.
    pub fn set_task(&mut self, task: Option<&str>) {
        self.task = task.map(str::to_string);
    }

    /// A new sample on input `index` (the kind's input order), sent at `stamp_ns` with `seq`.
    pub fn set_input(&mut self, index: usize, stamp_ns: u64, seq: u64, bytes: Vec<u8>) {
        self.next += 1;
        if let Some(slot) = self.inputs.get_mut(index) {
            *slot = Some((
                PortHeader {
                    stamp_ns,
                    seq,
                    task_word: 0,
                },
                bytes,
                self.next,
            ));
        }
    }

    /// Steps `module` once at `now_ns`; returns what it wrote: (output index, header, bytes).
    pub fn step(
        &mut self,
        module: &mut dyn Stepper,
        now_ns: u64,
    ) -> Result<Vec<(usize, PortHeader, Vec<u8>)>, ModuleError> {
        self.written.clear();
        let mut io = Io {
            word: 0,
            now_ns,
            ports: Ports::Offline(self),
        };
        module.step_io(&mut io)?;
        Ok(std::mem::take(&mut self.written))
    }
}

/// A module of any kind, to be stepped: what [`Registration::make`](crate::Registration)
/// builds.
pub trait Stepper {
    fn step_io(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError>;
}

impl<M: Module> Stepper for M {
    fn step_io(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        self.step(io)
    }
}

/// Builds a module of kind `M` for [`Offline`] stepping.
pub fn make<M: Module + 'static>(setup: &mut Setup<'_>) -> Result<Box<dyn Stepper>, ModuleError> {
    Ok(Box::new(M::new(setup)?))
}

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
    node.service_builder(&service_name)
        .publish_subscribe::<[u8]>()
        .user_header::<PortHeader>()
        .payload_alignment(Alignment::new(8).ok_or_else(|| ModuleError::Ipc("alignment".into()))?)
        .max_publishers(MAX_PORT_PUBLISHERS)
        .max_subscribers(max_subscribers)
        .subscriber_max_buffer_size(crate::protocol::recorder_buffer(payload))
        .subscriber_max_borrowed_samples(PORT_BORROWED)
        .history_size(1)
        .enable_safe_overflow(true)
        .max_nodes(MAX_MODULES)
        .open_or_create()
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
    node.service_builder(&service_name)
        .event()
        .max_listeners(listeners)
        .max_notifiers(MAX_MODULES)
        .max_nodes(MAX_MODULES)
        .open_or_create()
        .map_err(ipc("event service"))
}

/// Opens the DNM's active-task blackboard.
pub fn task_board(node: &Node<Svc>) -> Result<BlackboardFactory<Svc, u64>, ModuleError> {
    let service_name: ServiceName = TASK_SERVICE.try_into().map_err(ipc("service name"))?;
    node.service_builder(&service_name)
        .blackboard_opener::<u64>()
        .max_readers(MAX_MODULES)
        .max_nodes(MAX_MODULES)
        .open()
        .map_err(ipc("task blackboard (is the DNM running?)"))
}

/// Runs module `M` in this process as described by `launch`, until the DNM stops it or a
/// termination signal arrives.
pub fn run<M: Module>(launch: &Launch) -> Result<(), ModuleError> {
    let spec = M::kind();
    let config = dnm_config(&launch.prefix).map_err(ModuleError::Launch)?;
    let node_name: NodeName = launch
        .module
        .as_str()
        .try_into()
        .map_err(ipc("node name"))?;
    let node = NodeBuilder::new()
        .name(&node_name)
        .config(&config)
        .create::<Svc>()
        .map_err(ipc("node"))?;

    // Our side of the conversation with the DNM.
    let task = TaskWatch::on(&node)?;
    let plan_sub = plan_service_factory(&node, &launch.module)?
        .subscriber_builder()
        .create()
        .map_err(ipc("plan subscriber"))?;
    let wake = event_service(&node, &wake_event(&launch.module))?
        .listener_builder()
        .create()
        .map_err(ipc("wake listener"))?;
    let status_pub = status_service_factory(&node, &launch.module)?
        .publisher_builder()
        .create()
        .map_err(ipc("status publisher"))?;
    let dnm_notifier = event_service(&node, DNM_EVENT)?
        .notifier_builder()
        .create()
        .map_err(ipc("DNM notifier"))?;

    let mut outputs = Vec::new();
    for port in &spec.outputs {
        let service = port_service(
            &node,
            &output_service(&launch.module, &port.name),
            &port.message.payload,
        )?;
        let publisher = service
            .publisher_builder()
            .initial_max_slice_len(port.message.payload.max_bytes().max(1))
            .allocation_strategy(match port.message.payload {
                Payload::Fixed { .. } => AllocationStrategy::Static,
                Payload::Bytes { .. } => AllocationStrategy::PowerOfTwo,
            })
            .create()
            .map_err(ipc("publisher"))?;
        let notifier = event_service(&node, &output_event(&launch.module, &port.name))?
            .notifier_builder()
            .create()
            .map_err(ipc("notifier"))?;
        outputs.push(OutPort {
            publisher,
            notifier,
            seq: 0,
        });
    }

    let mut module = {
        let mut setup = Setup::new(&launch.module, &spec, &launch.params);
        M::new(&mut setup)?
    };

    let mut status = Status {
        pid: std::process::id(),
        state: ModuleState::Starting as u32,
        ..Status::default()
    };
    let publish_status = |status: &Status| -> Result<(), ModuleError> {
        status_pub.send_copy(*status).map_err(ipc("status"))?;
        dnm_notifier.notify().map_err(ipc("notify DNM"))?;
        Ok(())
    };

    let mut conns: Vec<SourceConn> = Vec::new();
    let mut listeners: Vec<Listener<Svc>> = Vec::new();
    let mut plans: Vec<Routes> = Vec::new();
    let mut seen: Vec<Option<(usize, u64)>> = vec![None; spec.inputs.len()];
    let mut active: Vec<Option<usize>> = vec![None; spec.inputs.len()];
    let period = match launch.trigger {
        Trigger::Periodic { rate_hz } => Some(
            Duration::try_from_secs_f64(1.0 / rate_hz)
                .ok()
                .filter(|p| !p.is_zero())
                .ok_or_else(|| {
                    ModuleError::Launch(format!(
                        "rate_hz = {rate_hz} gives no usable period; use a rate between {} and {} Hz",
                        dnm_netlist::MIN_RATE_HZ,
                        dnm_netlist::MAX_RATE_HZ
                    ))
                })?,
        ),
        Trigger::OnInput => None,
    };
    let mut last_status_ns = 0u64;
    // The task word of the previous step, each input's source under it, and the time from
    // which each input shows samples.
    let mut last_word = UNSET_WORD;
    let mut last_sources: Vec<Option<Source>> = vec![None; spec.inputs.len()];
    let mut fresh_after: Vec<u64> = vec![0; spec.inputs.len()];

    loop {
        // Work that changes the set of subscriptions waits until the WaitSet is gone.
        let mut pending: Vec<Plan> = Vec::new();
        let mut retire_before: Option<usize> = None;
        {
            let waitset = WaitSetBuilder::new()
                .create::<Svc>()
                .map_err(ipc("waitset"))?;
            let _wake_guard = waitset.attach_notification(&wake).map_err(ipc("attach"))?;
            let tick_guard = match period {
                Some(p) => Some(waitset.attach_interval(p).map_err(ipc("attach interval"))?),
                None => None,
            };
            // A module waiting for input still tells its DNM it is alive.
            let heartbeat_guard = match period {
                Some(_) => None,
                None => Some(
                    waitset
                        .attach_interval(HEARTBEAT)
                        .map_err(ipc("attach heartbeat"))?,
                ),
            };
            let mut _source_guards = Vec::new();
            if period.is_none() {
                for l in &listeners {
                    _source_guards.push(waitset.attach_notification(l).map_err(ipc("attach"))?);
                }
            }

            // Plans already posted (history) are handled before the first wait.
            let mut check_plans = true;
            loop {
                if check_plans {
                    check_plans = false;
                    while let Some(sample) = plan_sub.receive().map_err(ipc("plan receive"))? {
                        let plan: Plan = serde_json::from_slice(sample.payload())
                            .map_err(|e| ModuleError::Ipc(format!("bad plan from DNM: {e}")))?;
                        if plan.stop {
                            status.state = ModuleState::Stopping as u32;
                            publish_status(&status)?;
                            return Ok(());
                        }
                        pending.push(plan);
                    }
                    if !pending.is_empty() {
                        break;
                    }
                }

                let mut ticked = false;
                let mut woken = false;
                let mut beat = false;
                let result = waitset
                    .wait_and_process_once(|id| {
                        if tick_guard.as_ref().is_some_and(|g| id.has_event_from(g)) {
                            ticked = true;
                        } else if heartbeat_guard
                            .as_ref()
                            .is_some_and(|g| id.has_event_from(g))
                        {
                            beat = true;
                        } else {
                            woken = true;
                        }
                        CallbackProgression::Continue
                    })
                    .map_err(ipc("wait"))?;
                if beat {
                    let now_ns = monotonic_ns();
                    if now_ns.saturating_sub(status.heartbeat_ns) >= HEARTBEAT.as_nanos() as u64 / 2
                    {
                        status.heartbeat_ns = now_ns;
                        last_status_ns = now_ns;
                        publish_status(&status)?;
                    }
                }
                if result == WaitSetRunResult::TerminationRequest {
                    status.state = ModuleState::Stopping as u32;
                    publish_status(&status)?;
                    return Ok(());
                }
                // Any signal interrupts the wait (SIGCONT after a stop, for one). SIGINT and
                // SIGTERM are reported as a termination request by the next wait.
                if result == WaitSetRunResult::Interrupt {
                    continue;
                }
                if woken {
                    let mut control = false;
                    wake.try_wait(|_| control = true).map_err(ipc("wake"))?;
                    check_plans = control;
                    for l in &listeners {
                        l.try_wait(|_| ()).map_err(ipc("listener"))?;
                    }
                }

                // The reference swap: one read of the task word decides every input of this step.
                let word = *task.word.get();
                let (revision, slot) = split_task_word(word);
                let routes_idx = plans.iter().position(|p| p.revision == revision);
                if let Some(i) = routes_idx
                    && i > 0
                {
                    // The DNM committed a newer revision: retire older plans and their sources.
                    retire_before = Some(i);
                    break;
                }
                let routes = routes_idx.map(|i| &plans[i]);
                for (input, a) in active.iter_mut().enumerate() {
                    *a = routes.and_then(|r| r.source(input, slot));
                }
                // Words this process has no plan for (it is still preparing) change nothing: the
                // first word it serves counts as its start, whenever it woke up.
                if routes.is_some() && word != last_word {
                    // An input switched to another source shows only what that source sends
                    // from the switch on: what it queued before (it may have gone quiet long
                    // ago) is old. The DNM stamps each store of the word.
                    let switched_at = *task.at.get();
                    for (input, a) in active.iter().enumerate() {
                        let source = a.map(|c| conns[c].source.clone());
                        if last_word != UNSET_WORD && source != last_sources[input] {
                            fresh_after[input] = switched_at;
                        }
                        last_sources[input] = source;
                    }
                    last_word = word;
                }
                for c in active.iter().flatten() {
                    conns[*c].drain()?;
                }
                // An on-input module steps when an input has a sample it has not read that was
                // sent since the input's source became active.
                let due = match period {
                    Some(_) => ticked,
                    None => active.iter().enumerate().any(|(input, c)| {
                        c.is_some_and(|c| {
                            let g = conns[c].generation;
                            conns[c]
                                .latest
                                .as_ref()
                                .is_some_and(|s| sent_since(s, fresh_after[input]))
                                && seen[input] != Some((c, g))
                        })
                    }),
                };
                if !due {
                    continue;
                }
                let now_ns = monotonic_ns();
                let mut io = Io {
                    word,
                    now_ns,
                    ports: Ports::Shm(Shm {
                        outputs: &mut outputs,
                        conns: &conns,
                        active: &active,
                        seen: &mut seen,
                        fresh_after: &fresh_after,
                        routes,
                        sent: &mut status.sent,
                    }),
                };
                status.steps += 1;
                status.last_step_ns = now_ns;
                status.heartbeat_ns = now_ns;
                if let Err(e) = module.step(&mut io) {
                    status.step_errors += 1;
                    tracing::warn!(module = %launch.module, "step failed: {e}");
                }
                if now_ns.saturating_sub(last_status_ns) > 100_000_000 {
                    last_status_ns = now_ns;
                    publish_status(&status)?;
                }
            }
        }
        if let Some(i) = retire_before {
            plans.drain(..i);
            retire(&mut conns, &mut listeners, &mut plans, &mut seen);
        }
        if !pending.is_empty() {
            for plan in pending {
                let revision = plan.revision;
                // A plan this process cannot prepare is reported, not fatal: the DNM refuses
                // the revision and the module goes on serving the one in force.
                if let Err(e) = prepare(&node, &spec, plan, &mut conns, &mut listeners, &mut plans)
                {
                    tracing::error!(module = %launch.module, revision, "cannot prepare: {e}");
                    // The revision in force itself: this process cannot serve it, so it ends and
                    // its restart policy takes over.
                    let (in_force, _) = split_task_word(*task.word.get());
                    if revision == in_force {
                        return Err(e);
                    }
                    status.prepare_failed = revision;
                }
            }
            // A plan that replaced a failed one may leave sources nothing uses.
            retire(&mut conns, &mut listeners, &mut plans, &mut seen);
            status.plan_revision = plans.last().map_or(0, |p| p.revision);
            status.state = ModuleState::Running as u32;
            // A sign of life, so a module that hangs in its first step is found too.
            status.heartbeat_ns = monotonic_ns();
            publish_status(&status)?;
        }
    }
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
    node.service_builder(&name)
        .publish_subscribe::<[u8]>()
        .history_size(PLAN_HISTORY)
        .subscriber_max_buffer_size(4)
        .max_publishers(1)
        .max_subscribers(2)
        .open_or_create()
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
    node.service_builder(&name)
        .publish_subscribe::<Status>()
        .history_size(1)
        .subscriber_max_buffer_size(4)
        .max_publishers(2)
        .max_subscribers(2)
        .enable_safe_overflow(true)
        .open_or_create()
        .map_err(ipc("status service"))
}

/// Opens subscriptions for every source of `plan` not already open, and records its routes.
fn prepare(
    node: &Node<Svc>,
    spec: &KindSpec,
    plan: Plan,
    conns: &mut Vec<SourceConn>,
    listeners: &mut Vec<Listener<Svc>>,
    plans: &mut Vec<Routes>,
) -> Result<(), ModuleError> {
    let mut conn_of_source = Vec::with_capacity(plan.sources.len());
    for (source_idx, source) in plan.sources.iter().enumerate() {
        // The source's layout is that of the inputs it feeds (the netlist checked they match).
        let payload = plan
            .inputs
            .iter()
            .find(|r| r.by_slot.contains(&Some(source_idx as u32)))
            .and_then(|r| spec.input(&r.port))
            .map(|p| p.message.payload)
            .ok_or_else(|| ModuleError::Ipc(format!("plan source {source_idx} feeds no input")))?;
        let (_, buffer) = port_limits(&payload);
        let idx = match conns.iter().position(|c| &c.source == source) {
            Some(i) => i,
            None => {
                let subscriber = port_service(
                    node,
                    &output_service(&source.module, &source.port),
                    &payload,
                )?
                .subscriber_builder()
                .buffer_size(buffer)
                .create()
                .map_err(ipc("subscriber"))?;
                let listener = event_service(node, &output_event(&source.module, &source.port))?
                    .listener_builder()
                    .create()
                    .map_err(ipc("listener"))?;
                conns.push(SourceConn {
                    source: source.clone(),
                    subscriber,
                    latest: None,
                    generation: 0,
                });
                listeners.push(listener);
                conns.len() - 1
            }
        };
        conn_of_source.push(idx);
    }
    let by_input = spec
        .inputs
        .iter()
        .map(|port| {
            plan.inputs
                .iter()
                .find(|r| r.port == port.name)
                .map(|r| {
                    r.by_slot
                        .iter()
                        .map(|s| s.and_then(|s| conn_of_source.get(s as usize).copied()))
                        .collect()
                })
                .unwrap_or_default()
        })
        .collect();
    plans.retain(|p| p.revision < plan.revision);
    plans.push(Routes {
        revision: plan.revision,
        tasks: plan.tasks,
        by_input,
    });
    Ok(())
}

/// Closes subscriptions no remaining plan uses, renumbering the routes that stay.
fn retire(
    conns: &mut Vec<SourceConn>,
    listeners: &mut Vec<Listener<Svc>>,
    plans: &mut [Routes],
    seen: &mut [Option<(usize, u64)>],
) {
    let used: Vec<bool> = (0..conns.len())
        .map(|c| {
            plans
                .iter()
                .any(|p| p.by_input.iter().flatten().any(|s| *s == Some(c)))
        })
        .collect();
    if used.iter().all(|u| *u) {
        return;
    }
    let mut remap = vec![None; conns.len()];
    let mut next = 0;
    for (i, u) in used.iter().enumerate() {
        if *u {
            remap[i] = Some(next);
            next += 1;
        }
    }
    let mut keep = used.iter();
    conns.retain(|_| *keep.next().unwrap_or(&false));
    let mut keep = used.iter();
    listeners.retain(|_| *keep.next().unwrap_or(&false));
    for p in plans.iter_mut() {
        for slots in &mut p.by_input {
            for s in slots.iter_mut() {
                *s = s.and_then(|c| remap[c]);
            }
        }
    }
    for s in seen.iter_mut() {
        *s = s.and_then(|(c, g)| remap[c].map(|c| (c, g)));
    }
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
        let config = dnm_config(&dnm_prefix(system, dnm)).map_err(ModuleError::Launch)?;
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
        let (revision, slot) = split_task_word(*self.word.get());
        (revision, slot, *self.at.get())
    }
}
