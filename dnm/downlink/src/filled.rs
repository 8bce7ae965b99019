//! What the station fills in of its record, told to the ground's monitors: each message of a
//! port that came from the rover's recording is decoded (its port's message type from the
//! wiring the rover's DNMs answer) and published with its send time on
//! `<system>/ground_filled/<dnm>/<module>/<port>`, so a monitor draws the outage where it
//! belongs in time. Nothing of it crosses the radio but the wiring, asked once per DNM.

use std::collections::HashMap;
use std::sync::mpsc::{Receiver, SyncSender, TrySendError};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use dnm_netlist::{MessageType, Wiring};
use dnm_proto::keys;
use dnm_record::standard::StandardMapping;
use zenoh::Wait;

/// Messages waiting to be told, at most; beyond, they are not told (they are in the record).
const QUEUE: usize = 4096;
/// How long the wiring is waited for.
const WIRING_TIMEOUT: Duration = Duration::from_secs(10);
/// A DNM whose wiring could not be had is asked again after this.
const ASK_AGAIN: Duration = Duration::from_secs(30);

/// A message filled in: its channel's topic, send time, sequence and recorded bytes.
pub(crate) struct Filled {
    pub topic: String,
    pub log_time: u64,
    pub sequence: u32,
    pub data: Vec<u8>,
}

/// Hands filled-in messages to a thread that decodes and publishes them.
pub(crate) struct Teller {
    tx: Option<SyncSender<Filled>>,
    thread: Option<JoinHandle<()>>,
}

impl Teller {
    pub fn start(session: &zenoh::Session, system: &str) -> std::io::Result<Self> {
        let (tx, rx) = std::sync::mpsc::sync_channel(QUEUE);
        let mut t = Telling {
            session: session.clone(),
            system: system.to_string(),
            wirings: HashMap::new(),
        };
        let thread = std::thread::Builder::new()
            .name("ground-filled".into())
            .spawn(move || t.run(&rx))?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
        })
    }

    /// Tells `m` if the thread keeps up.
    pub fn tell(&self, m: Filled) {
        if let Some(tx) = &self.tx
            && let Err(TrySendError::Full(_)) = tx.try_send(m)
        {
            tracing::debug!("a filled-in message not told to monitors: they fell behind");
        }
    }
}

impl Drop for Teller {
    fn drop(&mut self) {
        drop(self.tx.take());
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

struct Telling {
    session: zenoh::Session,
    system: String,
    /// Each DNM's wiring, or when it could not be had.
    wirings: HashMap<String, Result<Wiring, Instant>>,
}

impl Telling {
    fn run(&mut self, rx: &Receiver<Filled>) {
        while let Ok(m) = rx.recv() {
            let Some((dnm, module, port, raw)) = port_of(&m.topic) else {
                continue; // switches and events: the record holds them
            };
            let Some(message) = self.message(dnm, module, port) else {
                continue;
            };
            let Some(bytes) = port_bytes(&message, raw, &m.data) else {
                continue;
            };
            let value = dnm_netlist::values::decode(&message, &bytes);
            let Ok(json) = serde_json::to_vec(&value) else {
                continue;
            };
            let _ = self
                .session
                .put(keys::ground_filled(&self.system, dnm, module, port), json)
                .encoding(zenoh::bytes::Encoding::APPLICATION_JSON)
                .attachment(keys::encode_downlink(m.log_time, m.sequence).to_vec())
                .wait();
        }
    }

    /// The message type of `dnm`'s `module.port`, from its wiring.
    fn message(&mut self, dnm: &str, module: &str, port: &str) -> Option<MessageType> {
        let stale = match self.wirings.get(dnm) {
            Some(Ok(w)) => w.module(module).is_none(),
            Some(Err(at)) => at.elapsed() >= ASK_AGAIN,
            None => true,
        };
        if stale {
            let w = wiring(&self.session, &self.system, dnm).ok_or_else(Instant::now);
            self.wirings.insert(dnm.to_string(), w);
        }
        let w = self.wirings.get(dnm)?.as_ref().ok()?;
        w.module(module)?
            .outputs
            .iter()
            .find(|p| p.name == port)
            .map(|p| p.message.clone())
    }
}

/// The wiring DNM `dnm` answers.
fn wiring(session: &zenoh::Session, system: &str, dnm: &str) -> Option<Wiring> {
    let replies = session
        .get(keys::wiring(system, dnm))
        .timeout(WIRING_TIMEOUT)
        .wait()
        .ok()?;
    while let Ok(r) = replies.recv() {
        if let Ok(s) = r.result()
            && let Ok(w) = serde_json::from_slice::<Wiring>(&s.payload().to_bytes())
        {
            return Some(w);
        }
    }
    None
}

/// (DNM, module, port, its own bytes) of a port's channel; none for switches and events.
fn port_of(topic: &str) -> Option<(&str, &str, &str, bool)> {
    let raw = dnm_record::is_raw(topic);
    let port_topic = if raw {
        topic.strip_suffix(dnm_record::RAW_SUFFIX)?
    } else {
        topic
    };
    let mut parts = port_topic.trim_start_matches('/').split('/');
    let (d, m, p) = (parts.next()?, parts.next()?, parts.next()?);
    let port = parts.next().is_none() && !m.starts_with('_') && !p.starts_with('_');
    port.then_some((d, m, p, raw))
}

/// The port's own bytes of a recorded message: its `/raw` channel's as they are; a standard
/// message's where it holds them exactly (else its `/raw` twin is told instead); camera frames
/// are not told (a monitor watches them live).
fn port_bytes(message: &MessageType, raw: bool, data: &[u8]) -> Option<Vec<u8>> {
    if message.encoding == "dnm-image-rgb8" {
        return None;
    }
    if raw {
        return dnm_record::codec::decode(message, data).ok();
    }
    match StandardMapping::of(message) {
        Ok(Some(mapping)) if mapping.exact() => mapping.decode(data).ok(),
        Ok(Some(_)) => None,
        _ => dnm_record::codec::decode(message, data).ok(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_ports_are_told() {
        assert_eq!(
            port_of("/rover/odometry/odom"),
            Some(("rover", "odometry", "odom", false))
        );
        assert_eq!(
            port_of("/rover/odometry/odom/raw"),
            Some(("rover", "odometry", "odom", true))
        );
        assert_eq!(port_of("/rover/_switches"), None);
        assert_eq!(port_of("/rover/_events"), None);
        assert_eq!(port_of("/rover/a/b/c/d"), None);
    }
}
