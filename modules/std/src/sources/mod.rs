//! Modules that produce data.

use dnm_module::msg::{Blob, Tick};
use dnm_module::{BytesOutput, Io, Kind, Module, ModuleError, Output, Setup};
use dnm_netlist::KindSpec;

/// Emits a [`Tick`] per step, tagged with its `origin`.
#[derive(Debug)]
pub struct Ticker {
    out: Output<Tick>,
    origin: u64,
    seq: u64,
}

impl Module for Ticker {
    fn kind() -> KindSpec {
        Kind::new(
            "ticker",
            "emits a numbered tick per step, tagged with its origin",
        )
        .output::<Tick>("out")
        .param_i64("origin", 0, "tag written into every tick")
        .periodic(100.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        Ok(Self {
            out: setup.output("out")?,
            origin: setup.param_i64("origin")? as u64,
            seq: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        io.write(
            &self.out,
            &Tick {
                origin: self.origin,
                seq: self.seq,
            },
        )?;
        self.seq += 1;
        Ok(())
    }
}

/// Largest blob the blob source can send.
pub const MAX_BLOB_BYTES: usize = 1 << 20;

/// Emits a byte payload of `bytes` per step. The first 16 bytes hold origin and sequence; the
/// rest is left as loaned (zero-copy: only the header bytes are written per sample).
#[derive(Debug)]
pub struct BlobSource {
    out: BytesOutput,
    bytes: usize,
    origin: u64,
    seq: u64,
}

impl Module for BlobSource {
    fn kind() -> KindSpec {
        Kind::new(
            "blob_source",
            "emits a byte payload of a chosen size per step",
        )
        .bytes_output::<Blob>("out", MAX_BLOB_BYTES)
        .param_i64("bytes", 64, "payload size, 16 to 1048576")
        .param_i64("origin", 0, "tag written into the first 8 bytes")
        .periodic(100.0)
        .build()
    }

    fn new(setup: &mut Setup<'_>) -> Result<Self, ModuleError> {
        let bytes = setup.param_i64("bytes")?;
        if !(16..=MAX_BLOB_BYTES as i64).contains(&bytes) {
            return Err(ModuleError::Param {
                name: "bytes".into(),
                problem: format!("{bytes} is outside 16..={MAX_BLOB_BYTES}"),
            });
        }
        Ok(Self {
            out: setup.bytes_output("out")?,
            bytes: bytes as usize,
            origin: setup.param_i64("origin")? as u64,
            seq: 0,
        })
    }

    fn step(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let (origin, seq) = (self.origin, self.seq);
        io.write_bytes(&self.out, self.bytes, |buf| {
            buf[..8].copy_from_slice(&origin.to_le_bytes());
            buf[8..16].copy_from_slice(&seq.to_le_bytes());
        })?;
        self.seq += 1;
        Ok(())
    }
}
