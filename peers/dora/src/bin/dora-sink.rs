//! A dora node that reads payloads stamped by `dora-source` on any input: the peer of our
//! `latency` module. It creates the file `$OUT.first` when its first input arrives (the
//! benchmark waits for it after starting a dataflow) and, when stopped, writes every input's
//! latency (ns, little-endian u64) to `$OUT`.

use std::io::Write;

use dora_node_api::{DoraNode, Event};

fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime(2) with a valid clock and out-pointer.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let out = std::env::var("OUT").ok();
    let (_node, mut events) = DoraNode::init_from_env()?;
    let mut latencies: Vec<u64> = Vec::with_capacity(1 << 16);
    while let Some(event) = events.recv() {
        match event {
            Event::Input { data, .. } => {
                let now = monotonic_ns();
                let Ok(bytes) = <&[u8]>::try_from(&data) else {
                    continue;
                };
                let Some(stamp) = bytes.get(..8) else {
                    continue;
                };
                let stamp = u64::from_le_bytes(stamp.try_into()?);
                if latencies.is_empty()
                    && let Some(out) = &out
                {
                    std::fs::write(format!("{out}.first"), b"")?;
                }
                latencies.push(now.saturating_sub(stamp));
            }
            Event::Stop(_) => break,
            _ => {}
        }
    }
    if let Some(out) = out {
        let mut f = std::io::BufWriter::new(std::fs::File::create(out)?);
        for l in &latencies {
            f.write_all(&l.to_le_bytes())?;
        }
        f.flush()?;
    }
    Ok(())
}
