//! What a module author uses: the [`Module`] trait, typed port handles, [`Setup`] (parameters
//! and ports, given to [`Module::new`]) and [`Io`] (inputs and outputs, given to
//! [`Module::step`]).

use std::collections::BTreeMap;
use std::marker::PhantomData;

use dnm_netlist::{KindSpec, ParamValue, Payload, PortSpec};

use super::offline::Offline;
use super::process::Shm;
use crate::msg::Message;
use crate::protocol::{PortHeader, split_task_word};

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
    /// A step failed so that the module cannot go on (an exception in a module of another
    /// language): the process ends with it, and its DNM applies the restart policy.
    #[error("{0}")]
    Fatal(String),
}

impl ModuleError {
    /// An error raised by a module's own logic.
    pub fn step(msg: impl Into<String>) -> Self {
        ModuleError::Step(msg.into())
    }
}

/// Turns an iceoryx2 error into a [`ModuleError::Ipc`] saying what failed.
pub(crate) fn ipc<E: std::fmt::Debug>(what: &str) -> impl FnOnce(E) -> ModuleError + '_ {
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

    /// Its kind's declaration.
    pub fn spec(&self) -> &KindSpec {
        self.spec
    }

    /// The parameters given to it (defaults not included).
    pub fn params(&self) -> &BTreeMap<String, ParamValue> {
        self.params
    }

    fn param_value(&self, name: &str) -> Result<&ParamValue, ModuleError> {
        if self.spec.param(name).is_none() {
            let declared: Vec<&str> = self.spec.params.iter().map(|p| p.name.as_str()).collect();
            return Err(ModuleError::Param {
                name: name.into(),
                problem: format!(
                    "not declared by kind `{}` (it declares: {}); declare it in the kind",
                    self.spec.name,
                    if declared.is_empty() {
                        "none".to_string()
                    } else {
                        declared.join(", ")
                    }
                ),
            });
        }
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
        let (index, port) = self.port(name, input)?;
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

    /// For bindings of other languages: the index and declaration of port `name` (an input
    /// if `input`), whatever its type; the binding checks what it reads and writes itself.
    pub fn port(&self, name: &str, input: bool) -> Result<(usize, &PortSpec), ModuleError> {
        let ports = if input {
            &self.spec.inputs
        } else {
            &self.spec.outputs
        };
        ports
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
            })
    }

    /// For bindings: the value of parameter `name` (given, else its default).
    pub fn param(&self, name: &str) -> Result<&ParamValue, ModuleError> {
        self.param_value(name)
    }
}

/// Given to [`Module::step`]: reads inputs under the task active for this step, writes outputs.
pub struct Io<'a> {
    pub(crate) word: u64,
    pub(crate) now_ns: u64,
    pub(crate) ports: Ports<'a>,
}

/// Where a step's inputs come from and its outputs go.
pub(crate) enum Ports<'a> {
    /// A module process: shared memory, under its DNM.
    Shm(Shm<'a>),
    /// A module run without a DNM ([`Offline`]).
    Offline(&'a mut Offline),
}

impl std::fmt::Debug for Io<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Io")
            .field("word", &self.word)
            .finish_non_exhaustive()
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
            Ports::Shm(shm) => shm.task(self.word),
            Ports::Offline(o) => o.task(),
        }
    }

    /// (netlist revision, task slot) of this step.
    pub fn task_word(&self) -> (u64, u16) {
        split_task_word(self.word)
    }

    /// The newest sample on `input` (header and bytes), new or not.
    fn sample(&self, input: usize) -> Option<(PortHeader, &[u8])> {
        match &self.ports {
            Ports::Shm(shm) => shm.sample(input),
            Ports::Offline(o) => o.sample(input),
        }
    }

    /// The newest sample on `input` if this input has not read it yet.
    fn take_new(&mut self, input: usize) -> Option<(PortHeader, &[u8])> {
        match &mut self.ports {
            Ports::Shm(shm) => shm.take_new(input),
            Ports::Offline(o) => o.take_new(input),
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

    /// Output `index`'s declaration, or the error of a port that does not exist.
    fn output_spec(&self, index: usize) -> Result<&PortSpec, ModuleError> {
        let spec = match &self.ports {
            Ports::Shm(shm) => shm.output(index),
            Ports::Offline(o) => o.output(index),
        };
        spec.ok_or_else(|| ModuleError::Port {
            name: index.to_string(),
            problem: "no such output".into(),
        })
    }

    /// Refuses `len` bytes on output `index` unless its message type holds them: exactly a
    /// fixed-size message's size, at most a bytes port's `max_bytes`.
    fn check_len(&self, index: usize, len: usize) -> Result<(), ModuleError> {
        let port = self.output_spec(index)?;
        let problem = match port.message.payload {
            Payload::Fixed { size_bytes } if len != size_bytes => format!(
                "{len} bytes for {}, a message of {size_bytes} bytes",
                port.message.schema_name
            ),
            Payload::Bytes { max_bytes } if len > max_bytes => format!(
                "{len} bytes is more than the port's max_bytes ({max_bytes}): declare a larger \
                 max_bytes for it in the kind"
            ),
            _ => return Ok(()),
        };
        Err(ModuleError::Port {
            name: port.name.clone(),
            problem,
        })
    }

    fn send(
        &mut self,
        index: usize,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) -> Result<(), ModuleError> {
        self.check_len(index, len)?;
        let word = self.word;
        match &mut self.ports {
            Ports::Shm(shm) => shm.send(index, word, len, fill),
            Ports::Offline(o) => {
                o.send(index, word, self.now_ns, len, fill);
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

    /// For bindings: the newest sample on input `index` (header and bytes) if the input has
    /// not read it yet. The bytes are the producer's shared memory, valid for this step.
    pub fn take_raw(&mut self, index: usize) -> Option<(PortHeader, &[u8])> {
        self.take_new(index)
    }

    /// For bindings: the newest sample on input `index`, new or not.
    pub fn latest_raw(&self, index: usize) -> Option<(PortHeader, &[u8])> {
        self.sample(index)
    }

    /// For bindings: sends `data` (copied once into shared memory) on output `index`.
    pub fn write_raw(&mut self, index: usize, data: &[u8]) -> Result<(), ModuleError> {
        self.send(index, data.len(), |b| b.copy_from_slice(data))
    }

    /// For bindings: loans `len` zeroed bytes of shared memory on output `index`, to be filled
    /// in place and sent with [`Io::send_loaned`] in this step (given back otherwise).
    pub fn loan_raw(&mut self, index: usize, len: usize) -> Result<&mut [u8], ModuleError> {
        self.check_len(index, len)?;
        match &mut self.ports {
            Ports::Shm(shm) => shm.loan(index, len),
            Ports::Offline(o) => o.loan(index, len),
        }
    }

    /// For bindings: sends what was loaned on output `index`.
    pub fn send_loaned(&mut self, index: usize) -> Result<(), ModuleError> {
        let (word, now) = (self.word, self.now_ns);
        let sent = match &mut self.ports {
            Ports::Shm(shm) => shm.send_loaned(index, word),
            Ports::Offline(o) => o.send_loaned(index, word, now),
        };
        // The runtime knows outputs by index; the author, by name.
        sent.map_err(|e| match (e, self.output_spec(index)) {
            (ModuleError::Port { problem, .. }, Ok(port)) => ModuleError::Port {
                name: port.name.clone(),
                problem,
            },
            (e, _) => e,
        })
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Kind;
    use crate::msg::{Blob, Scalar, Tick};

    fn spec() -> KindSpec {
        Kind::new("k", "")
            .input::<Tick>("tick")
            .bytes_input::<Blob>("blob", 64)
            .output::<Scalar>("value")
            .param_f64("gain", 2.0, "")
            .param_string("label", "x", "")
            .build()
    }

    #[test]
    fn parameters_come_from_the_launch_or_their_default() {
        let spec = spec();
        let params = BTreeMap::from([("gain".to_string(), ParamValue::Float(0.5))]);
        let setup = Setup::new("m", &spec, &params);
        assert_eq!(setup.name(), "m");
        assert_eq!(setup.param_f64("gain").unwrap(), 0.5);
        assert_eq!(setup.param_str("label").unwrap(), "x");
        assert_eq!(
            setup.param_bool("gain").unwrap_err().to_string(),
            "parameter `gain`: is not a boolean"
        );
        assert_eq!(
            setup.param_i64("missing").unwrap_err().to_string(),
            "parameter `missing`: not declared by kind `k` (it declares: gain, label); declare it \
             in the kind"
        );
    }

    #[test]
    fn ports_are_found_by_name_and_layout() {
        let spec = spec();
        let params = BTreeMap::new();
        let setup = Setup::new("m", &spec, &params);
        assert_eq!(setup.input::<Tick>("tick").unwrap().index, 0);
        assert_eq!(setup.bytes_input("blob").unwrap().index, 1);
        assert_eq!(setup.output::<Scalar>("value").unwrap().index, 0);
        assert_eq!(
            setup.output::<Tick>("tick").unwrap_err().to_string(),
            "port `tick`: kind `k` declares no output port of that name"
        );
        let wrong = setup.input::<Scalar>("tick").unwrap_err().to_string();
        assert!(wrong.starts_with("port `tick`: declared as "), "{wrong}");
        assert!(wrong.ends_with(", requested with another type"), "{wrong}");
        assert!(setup.bytes_input("tick").is_err());
        assert!(setup.input::<Tick>("blob").is_err());
    }
}
