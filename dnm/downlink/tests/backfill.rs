//! The ground's copy filled from a rover's recording over real Zenoh sessions: the stretch the
//! ground never heard live comes from the recording files, decimated as the plan says, and the
//! stretch of a file the rover lost is reported as a gap the rover never recorded; a station
//! started again knows its channels' plans from its own files.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::collections::BTreeMap;
use std::path::Path;
use std::time::{Duration, Instant};

use dnm_downlink::{DownlinkTap, GroundRecord, GroundRecordOptions, HistoryServer};
use dnm_netlist::{Backfill, Decimator, DownlinkEntry, PortRef};
use dnm_record::tap::{ChannelDesc, Tap, Tapped};
use zenoh::Wait;

const TOPIC: &str = "/rover/src/out";
const PERIOD: u64 = 100_000_000; // the plan: 10 Hz
const SOURCE_PERIOD: u64 = 20_000_000; // the output: 50 Hz

fn desc() -> ChannelDesc {
    ChannelDesc {
        topic: TOPIC.into(),
        schema_name: "dnm/Tick".into(),
        schema_encoding: "ros2msg".into(),
        schema: "uint64 origin\nuint64 seq\n".into(),
        message_encoding: "cdr".into(),
        metadata: BTreeMap::from([("dnm".into(), "rover".into())]),
    }
}

/// Bytes of each message (an encapsulation header, a tick, then padding).
const MESSAGE_BYTES: usize = 400;
/// The downlink's budget, bytes a second.
const BUDGET: u64 = 16_000;

fn payload(seq: u64) -> Vec<u8> {
    let mut b = vec![0, 1, 0, 0];
    b.extend(7u64.to_le_bytes());
    b.extend(seq.to_le_bytes());
    b.resize(MESSAGE_BYTES, 0xa5);
    b
}

/// Writes `rec-rover[.n].mcap` holding the output's messages `seqs` (sent every
/// `SOURCE_PERIOD` from `t0`).
fn write_file(dir: &Path, n: u64, t0: u64, seqs: std::ops::Range<u64>) {
    let name = if n == 0 {
        "rec-rover.mcap".to_string()
    } else {
        format!("rec-rover.{n}.mcap")
    };
    let file = std::fs::File::create(dir.join(name)).unwrap();
    let mut w = mcap::WriteOptions::new()
        .profile("ros2")
        .create(std::io::BufWriter::new(file))
        .unwrap();
    let d = desc();
    let schema = w
        .add_schema(&d.schema_name, &d.schema_encoding, d.schema.as_bytes())
        .unwrap();
    let channel = w
        .add_channel(schema, TOPIC, &d.message_encoding, &d.metadata)
        .unwrap();
    for seq in seqs {
        let t = t0 + seq * SOURCE_PERIOD + (seq * 7919 % 13) * 100_000;
        let header = mcap::records::MessageHeader {
            channel_id: channel,
            sequence: seq as u32,
            log_time: t,
            publish_time: t,
        };
        w.write_to_known_channel(&header, &payload(seq)).unwrap();
    }
    w.finish().unwrap();
}

fn sessions() -> (zenoh::Session, zenoh::Session) {
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let config = |listen: bool| {
        let mut c = zenoh::Config::default();
        c.insert_json5("scouting/multicast/enabled", "false")
            .unwrap();
        let key = if listen {
            "listen/endpoints"
        } else {
            "connect/endpoints"
        };
        c.insert_json5(key, &format!("[\"tcp/127.0.0.1:{port}\"]"))
            .unwrap();
        c
    };
    let rover = zenoh::open(config(true)).wait().unwrap();
    let ground = zenoh::open(config(false)).wait().unwrap();
    (rover, ground)
}

#[test]
fn the_ground_fills_its_copy_from_the_recording_and_reports_what_the_rover_lost() {
    let root = std::env::temp_dir().join(format!("dnm-backfill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&root);
    let (rover_dir, ground_dir) = (root.join("rover"), root.join("ground"));
    std::fs::create_dir_all(&rover_dir).unwrap();
    // Three files of 10 s each, well in the past; the middle one is lost.
    let t0 = dnm_proto::clock::now_unix_ns() - 60_000_000_000;
    write_file(&rover_dir, 0, t0, 0..500);
    write_file(&rover_dir, 1, t0, 500..1000);
    write_file(&rover_dir, 2, t0, 1000..1500);
    std::fs::remove_file(rover_dir.join("rec-rover.1.mcap")).unwrap();

    let (rover, ground) = sessions();
    let _history = HistoryServer::start(&rover, "sys", "rover", &rover_dir).unwrap();
    let tap = DownlinkTap::new(rover.clone(), "sys", "rover", Duration::from_secs(1));
    let plan = DownlinkEntry {
        output: PortRef {
            module: "src".into(),
            port: "out".into(),
        },
        rate_hz: 10.0,
        priority: 1,
        backfill: Backfill::OldestFirst,
    };
    let record = station(&ground, &ground_dir);
    // What the plan asks for of the files the rover still has.
    let mut planned = Vec::new();
    for range in [0..500u64, 1000..1500] {
        let mut d = Decimator::new(PERIOD);
        for seq in range {
            let t = t0 + seq * SOURCE_PERIOD + (seq * 7919 % 13) * 100_000;
            if d.keep(t) {
                planned.push((t, seq));
            }
        }
    }
    // The channel goes live with its newest planned message: the ground learns of it, and
    // asks the recording for everything before.
    let (t_newest, newest) = *planned.last().unwrap();
    let d = desc();
    tap.message(Tapped {
        channel: &d,
        log_time: t_newest,
        sequence: newest as u32,
        data: &payload(newest),
        plan: Some(&plan),
    });
    let planned: Vec<u64> = planned.into_iter().map(|(t, _)| t).collect();
    let started = Instant::now();
    let deadline = started + Duration::from_secs(120);
    let status = loop {
        let s = record.status();
        let c = s.channels.iter().find(|c| c.topic == TOPIC).cloned();
        if let Some(c) = c
            && c.received as usize >= planned.len()
            && !c.unrecorded.is_empty()
            && c.gaps == 0
        {
            break (s, c);
        }
        if Instant::now() >= deadline {
            let mut held = std::collections::BTreeSet::new();
            for f in dnm_record::session::files(&ground_dir).unwrap() {
                let bytes = std::fs::read(f).unwrap();
                for m in dnm_record::messages(&bytes).map_while(Result::ok) {
                    held.insert(m.log_time);
                }
            }
            let missing: Vec<_> = planned
                .iter()
                .filter(|t| !held.contains(t))
                .map(|t| (t - t0) / 1_000_000)
                .collect();
            let extra: Vec<_> = held
                .iter()
                .filter(|t| !planned.contains(t))
                .map(|t| (t - t0) / 1_000_000)
                .collect();
            panic!("gave up waiting: missing {missing:?} extra {extra:?} {s:?}");
        }
        std::thread::sleep(Duration::from_millis(200));
    };
    let took = started.elapsed();
    let (all, c) = status;
    // Everything the plan asks for of the files left is held; the lost file's stretch is a
    // gap the rover never recorded.
    assert_eq!(c.received as usize, planned.len(), "{all:?}");
    // The budget held: beyond the bucket's two seconds of burst, the backlog came no faster
    // than the budget lets it (a fifth of slack for the bucket's ticks).
    let bytes = (planned.len() * MESSAGE_BYTES) as f64;
    let least = (bytes - 2.0 * BUDGET as f64) / BUDGET as f64 * 0.8;
    assert!(
        took.as_secs_f64() >= least,
        "{bytes} bytes in {took:?} with a budget of {BUDGET} B/s"
    );
    println!("{bytes} bytes backfilled in {took:?} with a budget of {BUDGET} B/s");
    let lost_from = t0 + 500 * SOURCE_PERIOD;
    let lost_to = t0 + 1000 * SOURCE_PERIOD;
    assert!(
        c.unrecorded
            .iter()
            .any(|g| g.from_ns <= lost_from + PERIOD && g.to_ns + PERIOD >= lost_to),
        "{all:?}"
    );
    drop(record);
    // The ground's session holds exactly the planned messages, at their send times.
    let mut held = Vec::new();
    for f in dnm_record::session::files(&ground_dir).unwrap() {
        let bytes = std::fs::read(f).unwrap();
        for m in dnm_record::messages(&bytes) {
            let m = m.unwrap();
            assert_eq!(m.channel.topic, TOPIC);
            held.push(m.log_time);
        }
    }
    held.sort_unstable();
    assert_eq!(held, planned);
    let manifest = dnm_record::session::manifest(&ground_dir).unwrap();
    assert_eq!(manifest.messages as usize, planned.len());
    drop((tap, _history));
    a_station_started_again_after_a_kill_knows_what_it_holds(&ground, &ground_dir, planned.len());
    let _ = std::fs::remove_dir_all(&root);
}

/// The ground's record of `sys` in `dir`, within [`BUDGET`].
fn station(ground: &zenoh::Session, dir: &Path) -> GroundRecord {
    let options = GroundRecordOptions {
        dir: dir.to_path_buf(),
        budget_bytes_per_s: Some(BUDGET),
        link: None,
    };
    GroundRecord::start(ground, "sys", &options).unwrap()
}

/// Leaves the session in `dir` as a killed station does and starts a station on it again,
/// the rover silent: it knows its channel's plan and the `planned` messages it holds.
fn a_station_started_again_after_a_kill_knows_what_it_holds(
    ground: &zenoh::Session,
    dir: &Path,
    planned: usize,
) {
    // A station started again while the rover is silent knows the channel's plan from its
    // own files: what it holds and what it misses, not a copy that looks whole.
    // As a killed station leaves its file: no summary, no footer.
    for f in dnm_record::session::files(dir).unwrap() {
        let bytes = std::fs::read(&f).unwrap();
        let footer = mcap::read::footer(&bytes).unwrap();
        std::fs::write(&f, &bytes[..footer.summary_start as usize]).unwrap();
    }
    let again = station(ground, dir);
    let s = again.status();
    let c = s.channels.iter().find(|c| c.topic == TOPIC).unwrap();
    assert_eq!(c.rate_hz, Some(10.0), "{s:?}");
    assert_eq!(c.dnm.as_deref(), Some("rover"), "{s:?}");
    assert_eq!(c.received as usize, planned, "{s:?}");
    assert!(c.expected > c.received && c.gaps > 0, "{s:?}");
    // ...and the file the killed station left is whole again: the manifest counts it.
    let manifest = dnm_record::session::manifest(dir).unwrap();
    assert_eq!(manifest.messages as usize, planned, "{manifest:?}");
    assert!(manifest.files.iter().all(|f| f.complete), "{manifest:?}");
    drop(again);
}
