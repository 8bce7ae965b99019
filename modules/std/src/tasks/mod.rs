//! Modules that transform data.

use dnm_module::msg::{PairReading, Tick};
use dnm_module::{Input, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;

/// Forwards every new tick from `in` to `out`.
#[derive(Debug)]
pub struct Relay {
    input: Input<Tick>,
    out: Output<Tick>,
}

impl Module for Relay {
    fn kind() -> KindSpec {
        Kind::new("relay", "forwards every new tick")
            .input::<Tick>("in")
            .output::<Tick>("out")
            .on_input()
            .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            input: setup.input("in")?,
            out: setup.output("out")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        if let Some(t) = io.read(&self.input) {
            io.write(&self.out, &t)?;
        }
        Ok(())
    }
}

/// Reads two tick inputs in one step and reports which origins fed them and under which task.
#[derive(Debug)]
pub struct Pair {
    a: Input<Tick>,
    b: Input<Tick>,
    out: Output<PairReading>,
}

impl Module for Pair {
    fn kind() -> KindSpec {
        Kind::new(
            "pair",
            "reports the origins read on two inputs in the same step",
        )
        .input::<Tick>("a")
        .input::<Tick>("b")
        .output::<PairReading>("out")
        .on_input()
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            a: setup.input("a")?,
            b: setup.input("b")?,
            out: setup.output("out")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let new_a = io.read(&self.a).is_some();
        let new_b = io.read(&self.b).is_some();
        if !(new_a || new_b) {
            return Ok(());
        }
        let (Some(a), Some(b)) = (io.latest(&self.a), io.latest(&self.b)) else {
            return Ok(());
        };
        let (revision, slot) = io.task_word();
        io.write(
            &self.out,
            &PairReading {
                a_origin: a.origin,
                a_seq: a.seq,
                b_origin: b.origin,
                b_seq: b.seq,
                revision,
                task_slot: u64::from(slot),
            },
        )
    }
}
