//! Stepping a module outside a module process, without a DNM or shared memory.

use dnm_netlist::{KindSpec, PortSpec};

use super::author::{Io, Module, ModuleError, Ports, Setup};
use crate::protocol::PortHeader;

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
    outputs: Vec<PortSpec>,
    written: Vec<(usize, PortHeader, Vec<u8>)>,
    next: u64,
    task: Option<String>,
    /// A buffer loaned on an output in this step: (output, bytes).
    loaned: Option<(usize, Vec<u8>)>,
}

impl Offline {
    /// For a module of kind `spec`, running under `task`.
    pub fn new(spec: &KindSpec, task: Option<&str>) -> Self {
        Self {
            inputs: vec![None; spec.inputs.len()],
            seen: vec![None; spec.inputs.len()],
            seq: vec![0; spec.outputs.len()],
            outputs: spec.outputs.clone(),
            written: Vec::new(),
            next: 0,
            task: task.map(str::to_string),
            loaned: None,
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

    /// The task a step runs under.
    pub(crate) fn task(&self) -> Option<&str> {
        self.task.as_deref()
    }

    /// The newest sample on `input` (header and bytes), new or not.
    pub(crate) fn sample(&self, input: usize) -> Option<(PortHeader, &[u8])> {
        self.inputs
            .get(input)?
            .as_ref()
            .map(|(h, b, _)| (*h, b.as_slice()))
    }

    /// The newest sample on `input` if this input has not read it yet.
    pub(crate) fn take_new(&mut self, input: usize) -> Option<(PortHeader, &[u8])> {
        let (h, b, generation) = self.inputs.get(input)?.as_ref()?;
        if self.seen.get(input).copied().flatten() == Some(*generation) {
            return None;
        }
        self.seen[input] = Some(*generation);
        Some((*h, b.as_slice()))
    }

    /// Collects `len` bytes written by `fill` on output `index`, stamped `now_ns` under `word`.
    pub(crate) fn send(
        &mut self,
        index: usize,
        word: u64,
        now_ns: u64,
        len: usize,
        fill: impl FnOnce(&mut [u8]),
    ) {
        let mut bytes = vec![0u8; len];
        fill(&mut bytes);
        let seq = self.seq.get(index).copied().unwrap_or(0);
        if let Some(s) = self.seq.get_mut(index) {
            *s += 1;
        }
        self.written.push((
            index,
            PortHeader {
                stamp_ns: now_ns,
                seq,
                task_word: word,
            },
            bytes,
        ));
    }

    /// The declaration of output `index`.
    pub(crate) fn output(&self, index: usize) -> Option<&PortSpec> {
        self.outputs.get(index)
    }

    pub(crate) fn loan(&mut self, index: usize, len: usize) -> Result<&mut [u8], ModuleError> {
        if index >= self.seq.len() {
            return Err(ModuleError::Port {
                name: index.to_string(),
                problem: "no such output".into(),
            });
        }
        Ok(&mut self.loaned.insert((index, vec![0u8; len])).1)
    }

    pub(crate) fn send_loaned(
        &mut self,
        index: usize,
        word: u64,
        now_ns: u64,
    ) -> Result<(), ModuleError> {
        match self.loaned.take() {
            Some((i, bytes)) if i == index => {
                self.send(index, word, now_ns, bytes.len(), |b| {
                    b.copy_from_slice(&bytes)
                });
                Ok(())
            }
            other => {
                self.loaned = other;
                Err(ModuleError::Port {
                    name: index.to_string(),
                    problem: "nothing loaned on this output in this step".into(),
                })
            }
        }
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
pub(crate) fn make<M: Module + 'static>(
    setup: &mut Setup<'_>,
) -> Result<Box<dyn Stepper>, ModuleError> {
    Ok(Box::new(M::new(setup)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Kind;
    use crate::msg::Tick;

    /// Forwards each new tick, and notes the task and the newest tick's sequence.
    struct Relay {
        input: crate::Input<Tick>,
        output: crate::Output<Tick>,
        seen: Vec<(Option<String>, Option<u64>)>,
    }

    impl Module for Relay {
        fn kind() -> KindSpec {
            Kind::new("relay", "")
                .input::<Tick>("in")
                .output::<Tick>("out")
                .on_input()
                .build()
        }
        fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
            Ok(Self {
                input: setup.input("in")?,
                output: setup.output("out")?,
                seen: Vec::new(),
            })
        }
        fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
            let latest = io.latest(&self.input).map(|t| t.seq);
            self.seen.push((io.task().map(str::to_string), latest));
            if let Some(tick) = io.read(&self.input) {
                io.write(&self.output, &tick)?;
            }
            Ok(())
        }
    }

    /// Writes `len` bytes on a port of at most 64, or loans them.
    struct Sizes {
        out: crate::BytesOutput,
        len: usize,
        loan: bool,
    }

    impl Module for Sizes {
        fn kind() -> KindSpec {
            Kind::new("sizes", "")
                .bytes_output::<crate::msg::Blob>("blob", 64)
                .periodic(10.0)
                .build()
        }
        fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
            Ok(Self {
                out: setup.bytes_output("blob")?,
                len: 0,
                loan: false,
            })
        }
        fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
            if self.loan {
                io.loan_raw(0, self.len)?;
                return io.send_loaned(0);
            }
            io.write_bytes(&self.out, self.len, |_| ())
        }
    }

    #[test]
    fn an_output_sends_at_most_its_max_bytes_and_errors_name_the_port() {
        let spec = Sizes::kind();
        let params = Default::default();
        let mut m = Sizes::new(&mut Setup::new("s", &spec, &params)).unwrap();
        let mut io = Offline::new(&spec, None);
        for loan in [false, true] {
            m.loan = loan;
            m.len = 64;
            assert_eq!(io.step(&mut m, 1).unwrap()[0].2.len(), 64);
            m.len = 65;
            assert_eq!(
                io.step(&mut m, 2).unwrap_err().to_string(),
                "port `blob`: 65 bytes is more than the port's max_bytes (64): declare a larger \
                 max_bytes for it in the kind"
            );
        }
        let mut step = Offline::new(&spec, None);
        let mut io = Io {
            word: 0,
            now_ns: 0,
            ports: Ports::Offline(&mut step),
        };
        assert_eq!(
            io.send_loaned(0).unwrap_err().to_string(),
            "port `blob`: nothing loaned on this output in this step"
        );
    }

    fn tick(seq: u64) -> Vec<u8> {
        bytemuck::bytes_of(&Tick { origin: 1, seq }).to_vec()
    }

    #[test]
    fn an_input_is_read_once_and_what_is_written_is_collected() {
        let spec = Relay::kind();
        let params = Default::default();
        let mut relay = Relay::new(&mut Setup::new("r", &spec, &params)).unwrap();
        let mut io = Offline::new(&spec, Some("drive"));
        assert!(io.step(&mut relay, 10).unwrap().is_empty());

        io.set_input(0, 5, 0, tick(7));
        let written = io.step(&mut relay, 20).unwrap();
        assert_eq!(written.len(), 1);
        let (output, header, bytes) = &written[0];
        assert_eq!((*output, header.stamp_ns, header.seq), (0, 20, 0));
        assert_eq!(bytes, &tick(7));
        // Read already: nothing new, though the latest stays.
        assert!(io.step(&mut relay, 30).unwrap().is_empty());

        io.set_task(None);
        io.set_input(0, 35, 1, tick(8));
        let written = io.step(&mut relay, 40).unwrap();
        assert_eq!(written[0].1.seq, 1);
        io.clear_input(0);
        assert!(io.step(&mut relay, 50).unwrap().is_empty());
        assert_eq!(
            relay.seen,
            [
                (Some("drive".to_string()), None),
                (Some("drive".to_string()), Some(7)),
                (Some("drive".to_string()), Some(7)),
                (None, Some(8)),
                (None, None),
            ]
        );
    }
}
