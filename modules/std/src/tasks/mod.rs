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

/// Inputs of a [`Merge`].
pub const MERGE_INPUTS: usize = 8;

/// Forwards every new tick of any of its eight inputs (`in0` … `in7`) to `out`, in input order:
/// a multiplexer whose sources a task chooses (inputs a task leaves unlinked read nothing).
#[derive(Debug)]
pub struct Merge {
    inputs: Vec<Input<Tick>>,
    out: Output<Tick>,
}

impl Module for Merge {
    fn kind() -> KindSpec {
        let mut kind = Kind::new(
            "merge",
            "forwards every new tick of any of its inputs in0 … in7",
        );
        for i in 0..MERGE_INPUTS {
            kind = kind.input::<Tick>(&format!("in{i}"));
        }
        kind.output::<Tick>("out").on_input().build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            inputs: (0..MERGE_INPUTS)
                .map(|i| setup.input(&format!("in{i}")))
                .collect::<Result<_, _>>()?,
            out: setup.output("out")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        for input in &self.inputs {
            if let Some(t) = io.read(input) {
                io.write(&self.out, &t)?;
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]

    use std::collections::BTreeMap;

    use dnm_module::{Offline, Setup};

    use super::*;

    /// A tick as it travels: `repr(C)` little-endian fields.
    fn tick(origin: u64, seq: u64) -> Vec<u8> {
        [origin.to_le_bytes(), seq.to_le_bytes()].concat()
    }

    #[test]
    fn merge_forwards_every_new_tick_of_any_input_once() {
        let spec = Merge::kind();
        assert_eq!(spec.inputs.len(), MERGE_INPUTS);
        let params = BTreeMap::new();
        let mut merge = Merge::new(&mut Setup::new("m", &spec, &params)).unwrap();
        let mut io = Offline::new(&spec, None);
        // Nothing read yet: nothing written.
        assert!(io.step(&mut merge, 1).unwrap().is_empty());
        io.set_input(0, 10, 0, tick(1, 5));
        io.set_input(7, 11, 0, tick(2, 9));
        let written = io.step(&mut merge, 20).unwrap();
        let forwarded: Vec<Vec<u8>> = written.into_iter().map(|(_, _, b)| b).collect();
        assert_eq!(forwarded, vec![tick(1, 5), tick(2, 9)]);
        // The same samples are not forwarded twice; a new one on one input is.
        assert!(io.step(&mut merge, 30).unwrap().is_empty());
        io.set_input(3, 40, 1, tick(3, 1));
        let written = io.step(&mut merge, 50).unwrap();
        assert_eq!(written.len(), 1);
        assert_eq!(written[0].2, tick(3, 1));
    }
}
