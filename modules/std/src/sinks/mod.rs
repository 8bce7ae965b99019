//! Modules that consume data.

use dnm_module::msg::{Blob, Tick};
use dnm_module::protocol::monotonic_ns;
use dnm_module::{BytesInput, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;

use crate::sources::MAX_BLOB_BYTES;

/// Measures one-hop latency of byte payloads: for every new sample on `in`, emits a [`Tick`]
/// whose `origin` is the payload's sequence number and whose `seq` is the latency in ns from
/// the producer's send to this module's read.
#[derive(Debug)]
pub struct Latency {
    input: BytesInput,
    out: Output<Tick>,
}

impl Module for Latency {
    fn kind() -> KindSpec {
        Kind::new("latency", "reports send-to-read latency of every sample")
            .bytes_input::<Blob>("in", MAX_BLOB_BYTES)
            .output::<Tick>("latency_ns")
            .on_input()
            .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            input: setup.bytes_input("in")?,
            out: setup.output("latency_ns")?,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let Some(header) = io.bytes_header(&self.input) else {
            return Ok(());
        };
        if io.read_bytes(&self.input).is_none() {
            return Ok(());
        }
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
