//! A dora node that sends one `SIZE`-byte payload on output `out` at every `tick` input: the
//! peer of our `blob_source`. The first 8 bytes are the send time (CLOCK_MONOTONIC ns, written
//! last, as the payload leaves), the next 8 a sequence number.

use dora_node_api::{DoraNode, Event, MetadataParameters, dora_core::config::DataId};

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
    let size: usize = std::env::var("SIZE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(64)
        .max(16);
    let (mut node, mut events) = DoraNode::init_from_env()?;
    let out = DataId::from("out".to_string());
    let mut seq = 0u64;
    while let Some(event) = events.recv() {
        match event {
            Event::Input { .. } => {
                node.send_output_raw(out.clone(), MetadataParameters::default(), size, |buf| {
                    buf[8..16].copy_from_slice(&seq.to_le_bytes());
                    buf[0..8].copy_from_slice(&monotonic_ns().to_le_bytes());
                })?;
                seq += 1;
            }
            Event::Stop(_) => break,
            _ => {}
        }
    }
    Ok(())
}
