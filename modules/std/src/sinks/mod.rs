//! Modules that consume data.

use dnm_module::msg::{Blob, Tick};
use dnm_module::protocol::{PortHeader, monotonic_ns};
use dnm_module::{BytesInput, Input, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;

use crate::sources::MAX_BLOB_BYTES;

/// Measures one-hop latency of byte payloads (`in`) or ticks (`tick`, a small port many modules
/// can read): for every new sample, emits a [`Tick`]
/// whose `origin` is the payload's sequence number and whose `seq` is the latency in ns from
/// the producer's send to this module's read.
#[derive(Debug)]
pub struct Latency {
    input: BytesInput,
    tick: Input<Tick>,
    out: Output<Tick>,
}

impl Module for Latency {
    fn kind() -> KindSpec {
        Kind::new(
            "latency",
            "reports send-to-read latency of every sample on `in` (bytes) or `tick` (ticks)",
        )
        .bytes_input::<Blob>("in", MAX_BLOB_BYTES)
        .input::<Tick>("tick")
        .output::<Tick>("latency_ns")
        .on_input()
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            input: setup.bytes_input("in")?,
            tick: setup.input("tick")?,
            out: setup.output("latency_ns")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        if let Some(header) = io.header(&self.tick)
            && io.read(&self.tick).is_some()
        {
            self.report(io, header)?;
        }
        if let Some(header) = io.bytes_header(&self.input)
            && io.read_bytes(&self.input).is_some()
        {
            self.report(io, header)?;
        }
        Ok(())
    }
}

impl Latency {
    fn report(&self, io: &mut Io<'_>, header: PortHeader) -> Result<(), ModuleError> {
        let latency_ns = monotonic_ns().saturating_sub(header.stamp_ns);
        io.write(
            &self.out,
            &Tick {
                origin: header.seq,
                seq: latency_ns,
            },
        )
    }
}
