//! DNMs linked over Zenoh, as separate processes: two DNMs peered on one network, a third
//! behind a Zenoh router, and a test client that reaches the system through that router.
//!
//! The client uses only the `zenoh` crate, raw keys and JSON (none of our crates): what it does,
//! an operator can do with the standard Zenoh tools.

#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use serde_json::Value;
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

#[path = "support/mod.rs"]
mod support;

use support::{endpoint, eventually, free_port, zenoh_client};

const DNM: &str = env!("CARGO_BIN_EXE_dnm");

/// A child process killed when the test ends, however it ends.
struct Proc(Option<Child>);

impl Proc {
    fn spawn(run_dir: &Path, args: &[String]) -> Self {
        let child = Command::new(DNM)
            .args(args)
            .env("DNM_RUN_DIR", run_dir)
            .env("DNM_RECORD_DIR", run_dir.join("recordings"))
            .env("RUST_LOG", "warn")
            .current_dir(run_dir)
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        Proc(Some(child))
    }

    fn kill9(&mut self) {
        if let Some(mut c) = self.0.take() {
            c.kill().unwrap();
            c.wait().unwrap();
        }
    }

    fn stop(&mut self) {
        if let Some(mut c) = self.0.take() {
            // SAFETY: kill(2) on our own child's pid.
            unsafe { libc::kill(c.id() as i32, libc::SIGTERM) };
            c.wait().unwrap();
        }
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        self.kill9();
    }
}

fn pid_alive(pid: u64) -> bool {
    // /proc/<pid>/stat exists and the process is not a zombie.
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .map(|s| !s.contains(") Z "))
        .unwrap_or(false)
}

/// The system under test: processes plus a Zenoh client behind the router.
struct System {
    name: String,
    netlist: PathBuf,
    run_dir: PathBuf,
    ports: [u16; 3],
    router: Proc,
    dnms: Vec<(String, Proc)>,
    client: zenoh::Session,
}

/// The three DNMs of the systems under test: a, with b and c under it.
macro_rules! three_dnms {
    () => {
        r#"
[[dnm]]
name = "a"

[[dnm]]
name = "b"
parent = "a"

[[dnm]]
name = "c"
parent = "a"
"#
    };
}

const NETLIST: &str = concat!(
    r#"
[system]
name = "SYSTEM"
default_task = "remote"
"#,
    three_dnms!(),
    r#"
[[module]]
name = "src_a"
kind = "ticker"
dnm = "a"
rate_hz = 50.0
params = { origin = 1 }

[[module]]
name = "relay_b"
kind = "relay"
dnm = "b"

[[module]]
name = "src_c"
kind = "ticker"
dnm = "c"
rate_hz = 50.0
params = { origin = 3 }

[[module]]
name = "relay_c"
kind = "relay"
dnm = "c"

# The chain a -> b -> c.
[task.remote]
links = ["src_a.out -> relay_b.in", "relay_b.out -> relay_c.in"]

# relay_c reads its own DNM's ticker instead.
[task.local]
links = ["src_a.out -> relay_b.in", "src_c.out -> relay_c.in"]
"#
);

/// Camera-sized samples (sent by Zenoh in fragments) crossing from a to b over the peer link
/// and to c through the router.
const LARGE: &str = concat!(
    r#"
[system]
name = "SYSTEM"
default_task = "run"
"#,
    three_dnms!(),
    r#"
[[module]]
name = "big"
kind = "blob_source"
dnm = "a"
rate_hz = 20.0
params = { bytes = 300000, origin = 7 }

[[module]]
name = "lat_b"
kind = "latency"
dnm = "b"

[[module]]
name = "lat_c"
kind = "latency"
dnm = "c"

[task.run]
links = ["big.out -> lat_b.in", "big.out -> lat_c.in"]
"#
);

impl System {
    fn start(tag: &str) -> Self {
        Self::start_with(tag, NETLIST)
    }

    fn start_with(tag: &str, text: &str) -> Self {
        let name = format!("zl{}{tag}", std::process::id());
        let run_dir = std::env::temp_dir().join(format!("dnm-test-{name}"));
        std::fs::create_dir_all(&run_dir).unwrap();
        let netlist = run_dir.join("three.toml");
        std::fs::write(&netlist, text.replace("SYSTEM", &name)).unwrap();
        // a and b peer with each other; the router joins them to c, which sees only the router.
        let ports = [free_port(), free_port(), free_port()];
        let [pa, pb, pr] = ports;
        let router = Proc::spawn(
            &run_dir,
            &[
                "--no-multicast".into(),
                "--listen".into(),
                endpoint(pr),
                "router".into(),
            ],
        );
        let mut sys = System {
            client: zenoh_client(pr),
            name,
            netlist,
            run_dir,
            ports,
            router,
            dnms: Vec::new(),
        };
        for d in ["a", "b", "c"] {
            sys.start_dnm(d);
            // Each waits for the previous one, so startup order is deterministic.
            sys.eventually_alive(d);
        }
        let _ = (pa, pb);
        sys
    }

    fn dnm_args(&self, dnm: &str) -> Vec<String> {
        let [pa, pb, pr] = self.ports;
        let mut args: Vec<String> = vec!["--no-multicast".into()];
        let mut zenoh = |k: &str, v: String| {
            args.push(k.into());
            args.push(v);
        };
        match dnm {
            "a" => {
                zenoh("--listen", endpoint(pa));
                zenoh("--connect", endpoint(pr));
            }
            "b" => {
                zenoh("--listen", endpoint(pb));
                zenoh("--connect", endpoint(pa));
                zenoh("--connect", endpoint(pr));
            }
            _ => {
                zenoh("--zenoh-mode", "client".into());
                zenoh("--connect", endpoint(pr));
            }
        }
        args.extend([
            "up".into(),
            self.netlist.display().to_string(),
            "--dnm".into(),
            dnm.into(),
        ]);
        args
    }

    fn start_dnm(&mut self, dnm: &str) {
        let p = Proc::spawn(&self.run_dir, &self.dnm_args(dnm));
        self.dnms.retain(|(d, _)| d != dnm);
        self.dnms.push((dnm.into(), p));
    }

    fn proc(&mut self, dnm: &str) -> &mut Proc {
        &mut self.dnms.iter_mut().find(|(d, _)| d == dnm).unwrap().1
    }

    fn key(&self, rest: &str) -> String {
        format!("{}/{rest}", self.name)
    }

    /// JSON replies to a query, by key.
    fn get(&self, selector: &str, payload: Option<&Value>) -> Vec<(String, Result<Value, Value>)> {
        let mut q = self
            .client
            .get(selector)
            .target(QueryTarget::All)
            .consolidation(ConsolidationMode::None)
            .timeout(Duration::from_secs(5));
        if let Some(p) = payload {
            q = q.payload(serde_json::to_vec(p).unwrap());
        }
        let replies = q.wait().unwrap();
        let mut out = Vec::new();
        while let Ok(r) = replies.recv() {
            match r.result() {
                Ok(s) => {
                    let v = serde_json::from_slice(&s.payload().to_bytes()).unwrap_or(Value::Null);
                    out.push((s.key_expr().to_string(), Ok(v)));
                }
                Err(e) => {
                    let v = serde_json::from_slice(&e.payload().to_bytes()).unwrap_or(Value::Null);
                    out.push((String::new(), Err(v)));
                }
            }
        }
        out.sort_by(|a, b| a.0.cmp(&b.0));
        out
    }

    fn report(&self, dnm: &str) -> Option<Value> {
        self.get(&self.key(&format!("dnm/{dnm}")), None)
            .into_iter()
            .find_map(|(_, r)| r.ok())
    }

    fn eventually_alive(&self, dnm: &str) {
        eventually(
            &format!("DNM {dnm} answers with its modules running"),
            || {
                let r = self.report(dnm)?;
                let modules = r["modules"].as_array()?;
                modules
                    .iter()
                    .all(|m| m["state"] == "running")
                    .then_some(())
            },
        );
    }

    fn peer_state(&self, of: &str, peer: &str) -> Option<String> {
        let r = self.report(of)?;
        r["peers"]
            .as_array()?
            .iter()
            .find(|p| p["dnm"] == peer)
            .and_then(|p| p["state"].as_str().map(str::to_string))
    }

    /// The last `Tick` relay_c sent, read raw from its port key: (origin, seq).
    fn relay_c_last(&self) -> Option<(u64, u64)> {
        let replies = self
            .client
            .get(self.key("port/c/relay_c/out"))
            .timeout(Duration::from_secs(5))
            .wait()
            .unwrap();
        let reply = replies.recv().ok()?;
        let s = reply.result().ok()?;
        let b = s.payload().to_bytes();
        assert_eq!(b.len(), 16, "a Tick is two little-endian u64");
        let origin = u64::from_le_bytes(b[0..8].try_into().unwrap());
        let seq = u64::from_le_bytes(b[8..16].try_into().unwrap());
        Some((origin, seq))
    }

    /// Waits until relay_c's output comes from `origin` and keeps advancing.
    fn relay_c_fed_by(&self, origin: u64) {
        let first = eventually(&format!("relay_c forwards origin {origin}"), || {
            self.relay_c_last().filter(|(o, _)| *o == origin)
        });
        eventually(
            &format!("origin {origin} keeps flowing into relay_c"),
            || {
                self.relay_c_last()
                    .filter(|(o, s)| *o == origin && *s > first.1)
            },
        );
    }

    /// Sends a command to every DNM; returns (dnm key, ok?, reply JSON) sorted.
    fn command(&self, cmd: Value) -> Vec<(String, Result<Value, Value>)> {
        self.get(&self.key("dnm/*/cmd"), Some(&cmd))
    }
}

impl Drop for System {
    fn drop(&mut self) {
        for (_, p) in &mut self.dnms {
            p.stop();
        }
        self.router.stop();
        let _ = std::fs::remove_dir_all(&self.run_dir);
    }
}

#[test]
fn dnms_linked_over_zenoh_route_switch_survive_and_rejoin() {
    let mut sys = System::start("main");

    // 1. A chain spanning three DNMs (a -> b over the peer link, b -> c through the router).
    sys.relay_c_fed_by(1);

    // 2. A raw Zenoh subscriber sees samples of a crossing port, with the documented
    //    attachment (send time, sequence, task word, wall-clock send time).
    let (tx, rx) = std::sync::mpsc::channel();
    let _sub = sys
        .client
        .declare_subscriber(sys.key("port/b/relay_b/out"))
        .callback(move |s| {
            let att = s.attachment().map(|a| a.to_bytes().len());
            let _ = tx.send((
                s.payload().to_bytes().into_owned(),
                att,
                s.encoding().to_string(),
            ));
        })
        .wait()
        .unwrap();
    let (payload, attachment, encoding) = rx.recv_timeout(Duration::from_secs(30)).unwrap();
    assert_eq!(u64::from_le_bytes(payload[0..8].try_into().unwrap()), 1);
    assert_eq!(attachment, Some(32));
    assert!(encoding.contains("dnm_msgs/Tick"), "encoding {encoding}");

    // 3. Module state for tools: every module, its state and the decoded last value.
    let modules = sys.get(&sys.key("module/**"), None);
    let names: Vec<&str> = modules
        .iter()
        .filter_map(|(_, r)| r.as_ref().ok()?["name"].as_str())
        .collect();
    assert_eq!(names, ["src_a", "relay_b", "relay_c", "src_c"]);
    let relay_c = modules
        .iter()
        .find_map(|(k, r)| k.ends_with("/relay_c").then(|| r.clone().unwrap()))
        .unwrap();
    assert_eq!(relay_c["state"], "running");
    assert_eq!(relay_c["dnm"], "c");
    assert_eq!(relay_c["outputs"]["out"]["value"]["origin"], 1);
    // Liveliness tokens list DNMs and modules.
    let tokens: Vec<String> = {
        let replies = sys
            .client
            .liveliness()
            .get(sys.key("**"))
            .timeout(Duration::from_secs(5))
            .wait()
            .unwrap();
        let mut t = Vec::new();
        while let Ok(r) = replies.recv() {
            if let Ok(s) = r.result() {
                t.push(s.key_expr().to_string());
            }
        }
        t.sort();
        t
    };
    for expected in [
        "dnm/a",
        "dnm/b",
        "dnm/c",
        "module/b/relay_b",
        "module/c/src_c",
    ] {
        assert!(
            tokens.contains(&sys.key(expected)),
            "liveliness tokens {tokens:?} lack {expected}"
        );
    }
    // A module's token follows its process with no query to wake the DNM's query thread: a
    // killed module's token goes, and comes back once its DNM has started it again.
    let (tok_tx, tok_rx) = std::sync::mpsc::channel();
    let _tokens_sub = sys
        .client
        .liveliness()
        .declare_subscriber(sys.key("module/c/src_c"))
        .callback(move |s| {
            let _ = tok_tx.send(s.kind());
        })
        .wait()
        .unwrap();
    let src_c_pid = sys.report("c").unwrap()["modules"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "src_c")
        .and_then(|m| m["pid"].as_i64())
        .unwrap();
    // SAFETY: kill(2) on the module process the report names.
    assert_eq!(unsafe { libc::kill(src_c_pid as i32, libc::SIGKILL) }, 0);
    let kinds: Vec<zenoh::sample::SampleKind> = (0..2)
        .map(|_| tok_rx.recv_timeout(Duration::from_secs(30)).unwrap())
        .collect();
    assert_eq!(
        kinds,
        [
            zenoh::sample::SampleKind::Delete,
            zenoh::sample::SampleKind::Put
        ],
        "src_c's token as its process was killed and started again"
    );

    // Only what a remote input needs crosses the network: c publishes nothing, a and b only
    // the outputs linked to another DNM.
    let published = |dnm: &str| -> Vec<String> {
        sys.report(dnm).unwrap()["routes"]["published"]
            .as_array()
            .unwrap()
            .iter()
            .map(|r| r["key"].as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(published("a"), [sys.key("port/a/src_a/out")]);
    assert_eq!(published("b"), [sys.key("port/b/relay_b/out")]);
    assert!(published("c").is_empty());

    // 4. Switch over Zenoh: relay_c's input moves from the remote chain to the local ticker.
    let switch_local = serde_json::json!({"id": "switch-1", "cmd": "switch", "task": "local"});
    let replies = sys.command(switch_local.clone());
    assert_eq!(replies.len(), 3, "{replies:?}");
    let revision = replies[0].1.as_ref().unwrap()["revision"].clone();
    for (_, r) in &replies {
        let r = r.as_ref().unwrap();
        assert_eq!(r["ok"], true);
        assert_eq!(r["switches"][0]["to"], "local");
        assert_eq!(r["revision"], revision);
    }
    sys.relay_c_fed_by(3);
    // A retry of the same command is answered, not applied again.
    let again = sys.command(switch_local);
    assert_eq!(again, replies);
    let switches = sys.report("c").unwrap()["switches"]
        .as_array()
        .unwrap()
        .len();
    assert_eq!(switches, 1);

    // Bad input gets an error reply from every DNM, not silence, and changes nothing.
    let bad = sys.command(serde_json::json!({"id": "bad-1", "cmd": "switch", "task": "nope"}));
    assert_eq!(bad.len(), 3);
    for (_, r) in &bad {
        let e = r.as_ref().unwrap_err();
        assert!(
            e["error"].as_str().unwrap().contains("unknown task `nope`"),
            "{e}"
        );
    }
    let garbage = sys.get(
        &sys.key("dnm/a/cmd"),
        Some(&serde_json::json!({"cmd": "fly"})),
    );
    assert!(
        garbage[0].1.as_ref().unwrap_err()["error"]
            .as_str()
            .unwrap()
            .contains("bad command")
    );
    sys.relay_c_fed_by(3);

    // And back to the remote source.
    let back =
        sys.command(serde_json::json!({"id": "switch-2", "cmd": "switch", "task": "remote"}));
    assert!(back.iter().all(|(_, r)| r.is_ok()), "{back:?}");
    sys.relay_c_fed_by(1);

    // 5. An apply over Zenoh, sent twice with one id, yields one new revision everywhere.
    let text = std::fs::read_to_string(&sys.netlist).unwrap();
    let apply =
        serde_json::json!({"id": "apply-1", "cmd": "apply", "file": "three.toml", "text": text});
    let first = sys.command(apply.clone());
    let second = sys.command(apply);
    assert_eq!(first, second);
    let rev = |r: &Result<Value, Value>| r.as_ref().unwrap()["revision"].as_u64().unwrap();
    let new_revision = rev(&first[0].1);
    assert!(first.iter().all(|(_, r)| rev(r) == new_revision));
    assert_eq!(sys.report("a").unwrap()["revision"], new_revision);
    sys.relay_c_fed_by(1);

    // Re-applying adds and drops Zenoh declarations to match: without task `remote`, nothing
    // of b's is needed elsewhere and c mirrors nothing; the original brings them back.
    let local_only = text
        .replace("default_task = \"remote\"", "default_task = \"local\"")
        .replace(
            "[task.remote]\nlinks = [\"src_a.out -> relay_b.in\", \"relay_b.out -> relay_c.in\"]",
            "",
        );
    assert_ne!(local_only, text);
    let r = sys.command(serde_json::json!({"id": "apply-2", "cmd": "apply", "file": "local.toml", "text": local_only}));
    assert!(r.iter().all(|(_, r)| r.is_ok()), "{r:?}");
    assert!(published("b").is_empty());
    assert_eq!(published("a"), [sys.key("port/a/src_a/out")]);
    assert!(
        sys.report("c").unwrap()["routes"]["mirrored"]
            .as_array()
            .unwrap()
            .is_empty()
    );
    sys.relay_c_fed_by(3);
    let r = sys.command(
        serde_json::json!({"id": "apply-3", "cmd": "apply", "file": "three.toml", "text": text}),
    );
    assert!(r.iter().all(|(_, r)| r.is_ok()), "{r:?}");
    let new_revision = rev(&r[0].1);

    // An apply from the network that names a program as a module kind runs nothing: only
    // executables installed in the module folder may be named, and none is set here. It comes
    // in through `NetlistDoor::accept` (`dnm/netlist/src/door.rs`).
    let evil = format!(
        "{text}\n[[module]]\nname = \"x\"\nkind = \"evil\"\ndnm = \"a\"\n\n[kind.evil]\nexec = \"/usr/bin/touch\"\n"
    );
    let r = sys.command(
        serde_json::json!({"id": "apply-evil", "cmd": "apply", "file": "evil.toml", "text": evil}),
    );
    assert!(!r.is_empty());
    for (_, answer) in &r {
        let e = answer.as_ref().unwrap_err()["error"]
            .as_str()
            .unwrap()
            .to_string();
        assert!(
            e.contains("/usr/bin/touch") && e.contains("DNM_MODULE_DIR"),
            "{e}"
        );
    }
    assert!(!sys.run_dir.join("describe").exists(), "a program ran");
    assert_eq!(published("b"), [sys.key("port/b/relay_b/out")]);
    let back =
        sys.command(serde_json::json!({"id": "switch-2b", "cmd": "switch", "task": "remote"}));
    assert!(back.iter().all(|(_, r)| r.is_ok()), "{back:?}");
    sys.relay_c_fed_by(1);

    // 6. Kill b outright: a and c keep running and report it lost; b's modules go with it.
    let b_pids: Vec<u64> = sys.report("b").unwrap()["modules"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["pid"].as_u64().unwrap())
        .collect();
    sys.proc("b").kill9();
    for observer in ["a", "c"] {
        eventually(&format!("{observer} reports b lost"), || {
            (sys.peer_state(observer, "b")? == "lost").then_some(())
        });
    }
    eventually("b's module processes exit with it", || {
        b_pids.iter().all(|p| !pid_alive(*p)).then_some(())
    });
    let switched =
        sys.command(serde_json::json!({"id": "switch-3", "cmd": "switch", "task": "local"}));
    assert_eq!(switched.len(), 2, "only a and c answer: {switched:?}");
    sys.relay_c_fed_by(3);
    assert_eq!(sys.report("a").unwrap()["modules"][0]["state"], "running");

    // 7. b restarts from the same file and rejoins: it takes over the netlist revision and the
    //    task in force, the others see it alive, and the remote chain works again.
    sys.start_dnm("b");
    sys.eventually_alive("b");
    let b = sys.report("b").unwrap();
    assert_eq!(b["revision"], new_revision);
    assert_eq!(b["active_task"], "local");
    for observer in ["a", "c"] {
        eventually(&format!("{observer} sees b alive again"), || {
            (sys.peer_state(observer, "b")? == "alive").then_some(())
        });
    }
    let back =
        sys.command(serde_json::json!({"id": "switch-4", "cmd": "switch", "task": "remote"}));
    assert_eq!(back.len(), 3);
    sys.relay_c_fed_by(1);

    // 8. The `dnm` command from "another machine": over Zenoh through the router.
    let cli = |args: &[&str]| -> Value {
        let [_, _, pr] = sys.ports;
        let out = Command::new(DNM)
            .args(["--no-multicast", "--connect", &endpoint(pr)])
            .args(args)
            .args(["--system", &sys.name, "--json"])
            .env("DNM_RUN_DIR", sys.run_dir.join("elsewhere"))
            .output()
            .unwrap();
        assert!(
            out.status.success(),
            "dnm {args:?}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        serde_json::from_slice(&out.stdout).unwrap()
    };
    let status = cli(&["status"]);
    assert_eq!(status["dnms"].as_array().unwrap().len(), 3);
    let added = cli(&[
        "module", "add", "--name", "src_x", "--kind", "ticker", "--dnm", "c",
    ]);
    let added_revision = added["revision"].as_u64().unwrap();
    assert_eq!(added_revision, new_revision + 1);
    eventually("src_x runs on c", || {
        let r = sys.report("c")?;
        r["modules"]
            .as_array()?
            .iter()
            .any(|m| m["name"] == "src_x" && m["state"] == "running")
            .then_some(())
    });
    let removed = cli(&["module", "remove", "--name", "src_x"]);
    assert_eq!(removed["revision"].as_u64().unwrap(), added_revision + 1);
    assert_eq!(sys.report("b").unwrap()["revision"], added_revision + 1);
    sys.relay_c_fed_by(1);
}

#[test]
fn large_samples_cross_dnm_processes_whole() {
    // A sample larger than Zenoh's batches is lent to Zenoh from shared memory and sent in
    // fragments; each receiving DNM writes the fragments straight into its mirror.
    let sys = System::start_with("large", LARGE);
    let (tx, rx) = std::sync::mpsc::channel();
    let _sub = sys
        .client
        .declare_subscriber(sys.key("port/a/big/out"))
        .callback(move |s| {
            let _ = tx.send(s.payload().to_bytes().into_owned());
        })
        .wait()
        .unwrap();
    let mut last_seq = None;
    for _ in 0..5 {
        let b = rx.recv_timeout(Duration::from_secs(30)).unwrap();
        assert_eq!(b.len(), 300_000);
        assert_eq!(u64::from_le_bytes(b[0..8].try_into().unwrap()), 7);
        let seq = u64::from_le_bytes(b[8..16].try_into().unwrap());
        // Consecutive: a fragmented sample Zenoh could not send whole would leave a gap (a
        // put reports no drop, and a receiver drops an incomplete chain silently).
        assert!(
            last_seq.is_none_or(|l| seq == l + 1),
            "{seq} after {last_seq:?}"
        );
        last_seq = Some(seq);
        assert!(b[16..].iter().all(|x| *x == 0), "the blob's body changed");
    }
    // Each reader keeps receiving them (no mirror refused one for its size or lacked room).
    for (dnm, module) in [("b", "lat_b"), ("c", "lat_c")] {
        let key = sys.key(&format!("port/{dnm}/{module}/latency_ns"));
        let seen = |above: u64| {
            let r = sys.client.get(&key).timeout(Duration::from_secs(5)).wait();
            let s = r.ok()?.recv().ok()?.into_result().ok()?;
            let b = s.payload().to_bytes();
            let seq = u64::from_le_bytes(b[0..8].try_into().ok()?);
            (seq > above).then_some(seq)
        };
        let first = eventually(&format!("{module} reads the large samples"), || seen(0));
        eventually(&format!("{module} keeps reading them"), || seen(first));
        let report = sys.report(dnm).unwrap();
        let mirrored = report["routes"]["mirrored"].as_array().unwrap();
        assert_eq!(mirrored.len(), 1, "{mirrored:?}");
        assert!(
            mirrored[0]["messages"].as_u64().unwrap() >= 2,
            "{mirrored:?}"
        );
        assert_eq!(mirrored[0]["dropped"], 0, "{mirrored:?}");
    }
    let report = sys.report("a").unwrap();
    let published = report["routes"]["published"].as_array().unwrap();
    assert_eq!(published[0]["dropped"], 0, "{published:?}");
}

#[test]
fn embedded_default_routes_between_dnms_of_one_process() {
    // All three DNMs in one `dnm up`, as the README's main command runs them: crossing links
    // go through the process's one Zenoh session, and one SIGTERM stops every DNM.
    let name = format!("zl{}one", std::process::id());
    let run_dir = std::env::temp_dir().join(format!("dnm-test-{name}"));
    std::fs::create_dir_all(&run_dir).unwrap();
    let netlist = run_dir.join("three.toml");
    std::fs::write(&netlist, NETLIST.replace("SYSTEM", &name)).unwrap();
    let port = free_port();
    let mut up = Proc::spawn(
        &run_dir,
        &[
            "--no-multicast".into(),
            "--listen".into(),
            endpoint(port),
            "up".into(),
            netlist.display().to_string(),
        ],
    );
    let sys = System {
        client: zenoh_client(port),
        name,
        netlist,
        run_dir: run_dir.clone(),
        ports: [port; 3],
        router: Proc(None),
        dnms: Vec::new(),
    };
    for d in ["a", "b", "c"] {
        sys.eventually_alive(d);
    }
    sys.relay_c_fed_by(1);
    let switched = sys.command(serde_json::json!({"id": "s1", "cmd": "switch", "task": "local"}));
    assert_eq!(switched.len(), 3);
    sys.relay_c_fed_by(3);
    let pids: Vec<u64> = ["a", "b", "c"]
        .iter()
        .flat_map(|d| {
            sys.report(d).unwrap()["modules"]
                .as_array()
                .unwrap()
                .iter()
                .map(|m| m["pid"].as_u64().unwrap())
                .collect::<Vec<_>>()
        })
        .collect();
    up.stop();
    assert!(
        pids.iter().all(|p| !pid_alive(*p)),
        "modules outlived their DNMs"
    );
}
