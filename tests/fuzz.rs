//! Fuzzing of everything that parses outside input, bounded so it runs in CI: a running system
//! bombarded over Zenoh with mutated commands, queries and samples (it must stay up and keep
//! working), then the parsers themselves (netlist TOML, command JSON, sample headers and
//! payloads, MCAP recordings) with mutated inputs, none of which may panic.
//!
//! Mutation fuzzing from a corpus of real inputs (byte-level and TOML-structure-aware), seeded:
//! `DNM_FUZZ_SEED` replays a run, `DNM_FUZZ_ROUNDS` makes it longer (default 3). An input that
//! panics is written to `target/fuzz-failures/` and named in the failure.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

mod support;

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::{Path, PathBuf};
use std::time::Duration;

use dnm_netlist::{MessageType, Payload};
use support::ground::Proc;
use support::{eventually, free_port, zenoh_client};
use zenoh::Wait;

/// splitmix64.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

fn seed() -> u64 {
    std::env::var("DNM_FUZZ_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(0x5eed_d11a)
}

fn rounds() -> usize {
    std::env::var("DNM_FUZZ_ROUNDS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(3)
}

const INTERESTING: &[u8] = b"\0\xff\x7f\x80\"'[]{}=,.\n\\#*$/-";

/// One to four byte-level mutations of `input`, with `corpus` to splice from.
fn mutate(rng: &mut Rng, input: &[u8], corpus: &[Vec<u8>]) -> Vec<u8> {
    let mut v = input.to_vec();
    for _ in 0..=rng.below(4) {
        let len = v.len();
        match rng.below(9) {
            0 if len > 0 => {
                let i = rng.below(len);
                v[i] ^= 1 << rng.below(8);
            }
            1 if len > 0 => {
                let i = rng.below(len);
                v[i] = INTERESTING[rng.below(INTERESTING.len())];
            }
            2 if len > 0 => {
                let a = rng.below(len);
                let b = (a + rng.below(64) + 1).min(len);
                v.drain(a..b);
            }
            3 if len > 0 => {
                let a = rng.below(len);
                let b = (a + rng.below(64) + 1).min(len);
                let chunk = v[a..b].to_vec();
                let at = rng.below(len + 1);
                v.splice(at..at, chunk);
            }
            4 => {
                let at = rng.below(len + 1);
                let n = rng.below(16) + 1;
                let bytes: Vec<u8> = (0..n).map(|_| rng.next() as u8).collect();
                v.splice(at..at, bytes);
            }
            5 if !corpus.is_empty() => {
                let other = &corpus[rng.below(corpus.len())];
                if !other.is_empty() {
                    let a = rng.below(other.len());
                    let b = (a + rng.below(256) + 1).min(other.len());
                    let at = rng.below(len + 1);
                    v.splice(at..at, other[a..b].iter().copied());
                }
            }
            6 => v.truncate(rng.below(len + 1)),
            7 => {
                // A number somewhere becomes an extreme one.
                let extreme: &[&[u8]] = &[
                    b"18446744073709551615",
                    b"-9223372036854775808",
                    b"1e308",
                    b"-1",
                    b"0",
                    b"nan",
                ];
                if let Some(i) = v.iter().position(u8::is_ascii_digit) {
                    let end = v[i..]
                        .iter()
                        .position(|c| !c.is_ascii_digit())
                        .map_or(v.len(), |e| i + e);
                    v.splice(i..end, extreme[rng.below(extreme.len())].iter().copied());
                }
            }
            _ => {
                // Repeat a piece many times (long names, deep nesting).
                if len > 0 {
                    let a = rng.below(len);
                    let b = (a + rng.below(8) + 1).min(len);
                    let chunk = v[a..b].to_vec();
                    let at = rng.below(len + 1);
                    let times = rng.below(500) + 1;
                    let rep: Vec<u8> = chunk
                        .iter()
                        .copied()
                        .cycle()
                        .take(chunk.len() * times)
                        .collect();
                    v.splice(at..at, rep);
                }
            }
        }
    }
    v
}

/// A TOML-aware mutation: one value somewhere becomes another (wrong type, extreme, hostile
/// string), or a key or array entry goes or doubles; the result is serialized again.
fn mutate_toml(rng: &mut Rng, text: &str) -> Option<String> {
    let mut doc: toml::Table = toml::from_str(text).ok()?;
    enum Step {
        Key(String),
        Index(usize),
    }
    // A random path down the document, chosen first, then followed mutably.
    let mut root = toml::Value::Table(std::mem::take(&mut doc));
    let mut path = Vec::new();
    {
        let mut v = &root;
        while path.len() < 6 && rng.below(3) != 0 {
            match v {
                toml::Value::Table(t) if !t.is_empty() => {
                    let k = t.keys().nth(rng.below(t.len())).cloned().unwrap();
                    v = &t[&k];
                    path.push(Step::Key(k));
                }
                toml::Value::Array(a) if !a.is_empty() => {
                    let i = rng.below(a.len());
                    v = &a[i];
                    path.push(Step::Index(i));
                }
                _ => break,
            }
        }
    }
    let mut target = &mut root;
    for step in &path {
        target = match (step, target) {
            (Step::Key(k), toml::Value::Table(t)) => t.get_mut(k).unwrap(),
            (Step::Index(i), toml::Value::Array(a)) => &mut a[*i],
            _ => unreachable!("the path was taken from this document"),
        };
    }
    let hostile = [
        toml::Value::String(String::new()),
        toml::Value::String("../../../../etc/passwd".into()),
        toml::Value::String("/usr/bin/touch".into()),
        toml::Value::String("a/b/**".into()),
        toml::Value::String("x".repeat(5000)),
        toml::Value::String("\u{0}\u{202e}é".into()),
        toml::Value::String("src.out -> src.in".into()),
        toml::Value::String("1000000h".into()),
        toml::Value::Integer(i64::MAX),
        toml::Value::Integer(i64::MIN),
        toml::Value::Integer(0),
        toml::Value::Integer(-1),
        toml::Value::Float(f64::NAN),
        toml::Value::Float(f64::INFINITY),
        toml::Value::Float(1e-300),
        toml::Value::Boolean(true),
        toml::Value::Array(Vec::new()),
        toml::Value::Table(toml::Table::new()),
    ];
    match (rng.below(4), &mut *target) {
        (0, toml::Value::Table(t)) if !t.is_empty() => {
            let k = t.keys().nth(rng.below(t.len())).cloned().unwrap();
            t.remove(&k);
        }
        (1, toml::Value::Array(a)) if !a.is_empty() => {
            let i = rng.below(a.len());
            let e = a[i].clone();
            a.push(e);
        }
        _ => *target = hostile[rng.below(hostile.len())].clone(),
    }
    toml::to_string(&root).ok()
}

/// Runs `f` on `input`; a panic saves the input and fails with where it is.
/// An abort (a failed allocation) cannot be caught: the input being tried is always on disk.
fn must_not_panic(target: &str, n: usize, input: &[u8], f: impl FnOnce(&[u8])) {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../target/fuzz-failures");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("trying.bin"), input).unwrap();
    if catch_unwind(AssertUnwindSafe(|| f(input))).is_err() {
        let path = dir.join(format!("{target}-{:x}-{n}.bin", seed()));
        std::fs::write(&path, input).unwrap();
        panic!(
            "{target} panicked on input {n}; saved as {}",
            path.display()
        );
    }
}

fn repo(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..").join(path)
}

/// The netlists of the repository, as a corpus.
fn netlists() -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for dir in ["configs", "examples"] {
        let Ok(entries) = std::fs::read_dir(repo(dir)) else {
            continue;
        };
        for e in entries.flatten() {
            if e.path().extension().is_some_and(|x| x == "toml") {
                out.push(std::fs::read(e.path()).unwrap());
            }
        }
    }
    assert!(!out.is_empty(), "no netlists to start from");
    out
}

fn commands(text: &str) -> Vec<Vec<u8>> {
    [
        serde_json::json!({"client": "c", "id": "1", "cmd": "status"}),
        serde_json::json!({"client": "c", "id": "2", "cmd": "switch", "task": "idle"}),
        serde_json::json!({"client": "c", "id": "3", "cmd": "apply", "file": "x.toml", "text": text}),
        serde_json::json!({"id": "4", "cmd": "prepare", "txn": 7, "revision": 9, "task": "idle"}),
        serde_json::json!({"id": "5", "cmd": "decide", "txn": 7, "commit": true, "at_unix_ns": 1, "revision": 9}),
        serde_json::json!({"id": "6", "cmd": "adopt", "revision": 3, "task": "feed", "file": "f", "text": text}),
        serde_json::json!({"id": "7", "cmd": "netlist"}),
        serde_json::json!({"station": "g", "epoch": 1, "commands": [{"seq": 1, "id": "g-1", "order": {"kind": "switch", "task": "feed"}}]}),
    ]
    .iter()
    .map(|v| serde_json::to_vec(v).unwrap())
    .collect()
}

/// Fast, so the samples to mutate come quickly.
fn netlist_template() -> String {
    support::FEED_NETLIST.replace("RATE", "50")
}

#[test]
fn no_input_from_the_network_or_a_file_panics_a_dnm_or_a_parser() {
    let mut rng = Rng(seed());
    println!("fuzz seed {} ({} rounds)", seed(), rounds());
    let system = format!("fz{}", std::process::id());
    let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let _folder = support::Folder(dir.clone());
    let text = netlist_template().replace("SYSTEM", &system);
    let netlist = dir.join("netlist.toml");
    std::fs::write(&netlist, &text).unwrap();
    let port = free_port();
    let mut up = Proc::dnm(
        &dir,
        "up",
        &[
            "--listen".into(),
            support::endpoint(port),
            "--no-multicast".into(),
            "up".into(),
            netlist.display().to_string(),
            "--record-dir".into(),
            dir.display().to_string(),
        ],
    );
    let session = zenoh_client(port);
    // Relay's last output: (origin, sequence).
    let relay_out = |session: &zenoh::Session| -> Option<(u64, u64)> {
        let r = session
            .get(format!("{system}/port/b/relay/out"))
            .timeout(Duration::from_secs(3))
            .wait()
            .ok()?;
        let b = r.recv().ok()?.result().ok()?.payload().to_bytes().to_vec();
        Some((
            u64::from_le_bytes(b.get(0..8)?.try_into().ok()?),
            u64::from_le_bytes(b.get(8..16)?.try_into().ok()?),
        ))
    };
    eventually("relay forwards src", || relay_out(&session));

    // 1. Over the network: commands, queries and samples, mutated.
    let corpus = commands(&text);
    let sample_key = format!("{system}/port/a/src/out");
    let (tx, rx) = std::sync::mpsc::channel();
    let sub = session
        .declare_subscriber(&sample_key)
        .callback(move |s| {
            let _ = tx.send((
                s.payload().to_bytes().to_vec(),
                s.attachment()
                    .map(|a| a.to_bytes().to_vec())
                    .unwrap_or_default(),
            ));
        })
        .wait()
        .unwrap();
    let (payload, attachment) = rx
        .recv_timeout(Duration::from_secs(30))
        .expect("a real sample to start from");
    drop(sub);
    for n in 0..300 * rounds() {
        let c = &corpus[rng.below(corpus.len())];
        let input = mutate(&mut rng, c, &corpus);
        let dnm = ["a", "b"][rng.below(2)];
        let key = match rng.below(3) {
            0 => format!("{system}/dnm/{dnm}/cmd"),
            1 => format!("{system}/authority"),
            _ => format!("{system}/dnm/{dnm}"),
        };
        let params = if rng.below(4) == 0 {
            format!(
                "?{}",
                String::from_utf8_lossy(&mutate(&mut rng, b"brief", &[]))
            )
        } else {
            String::new()
        };
        // Not every mutated selector is a valid one; those Zenoh refuses locally.
        if let Ok(get) = session
            .get(format!("{key}{params}"))
            .payload(input)
            .timeout(Duration::from_millis(500))
            .wait()
        {
            // Answers are read (and parsed by no one here) only every few queries.
            if n % 8 == 0 {
                while get.recv().is_ok() {}
            }
        }
        let p = mutate(&mut rng, &payload, &[]);
        let a = mutate(&mut rng, &attachment, &[]);
        session.put(&sample_key, p).attachment(a).wait().unwrap();
    }
    // Still up and commanded. The mutated commands may have applied a valid netlist of their
    // own (another rate, another link): the original goes back in force first...
    assert!(up.alive(), "the DNMs' process died");
    if let Ok(r) = dnm::remote::request(
        &session,
        &system,
        &dnm::proto::Request::Netlist,
        Duration::from_secs(10),
    ) && r.netlist.as_deref() != Some(text.as_str())
    {
        println!(
            "the fuzzed commands left another netlist in force:\n{}",
            r.netlist.unwrap_or_default()
        );
    }
    let restored = dnm::remote::request(
        &session,
        &system,
        &dnm::proto::Request::Apply {
            file: "netlist.toml".into(),
            text: text.clone(),
        },
        Duration::from_secs(10),
    )
    .unwrap();
    assert!(restored.ok, "{:?}", restored.error);
    // ...then back to the task that feeds relay, answered by both DNMs...
    let switch = serde_json::json!({"client": "t", "id": "after", "cmd": "switch", "task": "feed"});
    let answers: Vec<bool> = session
        .get(format!("{system}/dnm/*/cmd"))
        .payload(serde_json::to_vec(&switch).unwrap())
        .target(zenoh::query::QueryTarget::All)
        .timeout(Duration::from_secs(5))
        .wait()
        .unwrap()
        .iter()
        .map(|r| r.result().is_ok())
        .collect();
    assert_eq!(answers, [true, true]);
    // ...and still forwarding src's own samples (origin 1, a sequence that keeps rising).
    let a = eventually("relay forwards src again", || {
        relay_out(&session).filter(|(o, _)| *o == 1)
    });
    eventually("src's sequence keeps rising through relay", || {
        relay_out(&session).filter(|(o, q)| *o == 1 && *q > a.1)
    });
    drop(up);

    // 2. The parsers, in this process.
    let tomls = netlists();
    let file = Path::new("fuzzed.toml");
    for n in 0..1500 * rounds() {
        let seed_text = &tomls[rng.below(tomls.len())];
        let input = if rng.below(2) == 0 {
            mutate_toml(&mut rng, std::str::from_utf8(seed_text).unwrap())
                .map(String::into_bytes)
                .unwrap_or_else(|| seed_text.clone())
        } else {
            mutate(&mut rng, seed_text, &tomls)
        };
        must_not_panic("netlist", n, &input, |b| {
            let t = String::from_utf8_lossy(b);
            // The door every netlist from the network comes through.
            let _ = dnm::remote_door("fuzz").accept(&file.to_string_lossy(), &t);
            let _ = dnm::parse_recorded_netlist(file, &t);
        });
    }
    // Sequences, checked against Beetle-One's netlist.
    let beetle = dnm::load_netlist(&repo("configs/beetle.toml")).unwrap();
    let explore = std::fs::read_to_string(repo("configs/sequences/explore.toml")).unwrap();
    let sequences = [explore.clone().into_bytes()];
    for n in 0..1500 * rounds() {
        let input = if rng.below(2) == 0 {
            mutate_toml(&mut rng, &explore)
                .map(String::into_bytes)
                .unwrap_or_else(|| explore.clone().into_bytes())
        } else {
            mutate(&mut rng, &sequences[0], &sequences)
        };
        must_not_panic("sequence", n, &input, |b| {
            let t = String::from_utf8_lossy(b);
            let _ = dnm_netlist::Sequence::parse(Path::new("fuzzed-sequence.toml"), &t, &beetle);
        });
    }
    for n in 0..3000 * rounds() {
        let c = &corpus[rng.below(corpus.len())];
        let input = mutate(&mut rng, c, &corpus);
        must_not_panic("command", n, &input, |b| {
            let _ = serde_json::from_slice::<dnm_proto::RemoteCommand>(b);
            let _ = serde_json::from_slice::<dnm_proto::Request>(b);
            let _ = serde_json::from_slice::<dnm_proto::station::Uplink>(b);
            let _ = serde_json::from_slice::<dnm_proto::station::Order>(b);
            let _ = serde_json::from_slice::<dnm::admin::Request>(b);
            let t = String::from_utf8_lossy(b);
            let _ = dnm_authority::param_value(&t);
            if let Ok(dnm_proto::station::Order::Module { edit }) =
                serde_json::from_slice::<dnm_proto::station::Order>(b)
            {
                let _ = dnm_authority::edit_netlist(&text, &edit);
            }
        });
    }
    // Every message type of the built-in kinds.
    let mut kinds: Vec<MessageType> = Vec::new();
    for spec in dnm::registry().specs() {
        for port in spec.outputs.iter().chain(&spec.inputs) {
            if !kinds.contains(&port.message) {
                kinds.push(port.message.clone());
            }
        }
    }
    kinds.push(MessageType {
        schema_name: "fuzz".into(),
        encoding: "json".into(),
        schema: "{".into(),
        payload: Payload::Bytes { max_bytes: 8 },
        standard: None,
    });
    for n in 0..3000 * rounds() {
        let p = mutate(&mut rng, &payload, &[]);
        let a = mutate(&mut rng, &attachment, &[]);
        must_not_panic("sample", n, &[a.clone(), p.clone()].concat(), |_| {
            let _ = dnm_proto::keys::decode_header(&a);
            for k in &kinds {
                let _ = dnm_record::replay::decode(k, &p);
            }
        });
    }
    // The recording the system just made, mutated.
    let recording = support::mcap_files(&dir)
        .into_iter()
        .next()
        .expect("the system recorded");
    let mcap = std::fs::read(&recording).unwrap();
    assert!(
        dnm_record::stats::stats(&mcap, &dnm::parse_recorded_netlist).is_ok(),
        "the unmutated recording reads"
    );
    let csv = dir.join("csv");
    // A session folder holding the mutated file: its manifest is built from the file's summary
    // and attachments (each round a new name: closed files are cached by name).
    let session = dir.join("session");
    std::fs::create_dir_all(&session).unwrap();
    for n in 0..300 * rounds() {
        let input = mutate(&mut rng, &mcap, &[]);
        must_not_panic("mcap", n, &input, |b| {
            let _ = dnm_record::stats::stats(b, &dnm::parse_recorded_netlist);
            let _ = dnm_record::stats::export_csv(b, &[], &csv);
            let file = session.join(format!("rec-x.{n}.mcap"));
            std::fs::write(&file, b).unwrap();
            let _ = dnm_record::session::index(&session);
            std::fs::remove_file(&file).unwrap();
        });
    }
}
