//! A secured system, attacked over the network as anyone could: certificates made with
//! `dnm certs`, a router admitting only mutual TLS with access control generated from the
//! netlist, two DNM computers, an operator, an observer, and clients without the right
//! certificate.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

mod support;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use dnm_ground::CommandState;
use dnm_proto::keys::{SampleHeader, encode_header};
use dnm_proto::station::Order;
use serde_json::{Value, json};
use support::ground::{Api, Proc};
use support::{eventually, free_port};
use zenoh::Wait;
use zenoh::query::{ConsolidationMode, QueryTarget};

/// Slow enough that a forged sample stays relay's last output until the next tick.
fn netlist_template() -> String {
    support::FEED_NETLIST.replace("RATE", "0.5")
}

/// Runs `dnm ARGS` to completion; panics with its output if it fails.
fn dnm(args: &[&str]) -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(args)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "dnm {args:?}: {text}");
    text
}

struct Secured {
    system: String,
    dir: PathBuf,
    pki: PathBuf,
    netlist: PathBuf,
    endpoint: String,
}

impl Drop for Secured {
    fn drop(&mut self) {
        // (A test's processes are its locals, declared after the system: gone by now.)
        support::remove_unless_failed(&self.dir);
    }
}

impl Secured {
    fn new() -> Self {
        Self::with("sec", &netlist_template())
    }

    /// A system of `template` (SYSTEM replaced), its authority and identities.
    fn with(tag: &str, template: &str) -> Self {
        let system = format!("{tag}{}", std::process::id());
        let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let netlist = dir.join("netlist.toml");
        std::fs::write(&netlist, template.replace("SYSTEM", &system)).unwrap();
        let pki = dir.join("pki");
        let p = pki.to_str().unwrap();
        dnm(&["certs", "init", "--dir", p, "--system", &system]);
        for (name, role, dnms) in [
            ("computer-a", "rover", &["a"][..]),
            ("computer-b", "rover", &["b"]),
            ("rover-router", "router", &[]),
            ("ground-1", "operator", &[]),
            ("science", "observer", &[]),
        ] {
            let mut args = vec!["certs", "issue", "--dir", p, name, "--role", role];
            for d in dnms {
                args.extend(["--dnm", d]);
            }
            dnm(&args);
        }
        let endpoint = format!("tls/127.0.0.1:{}", free_port());
        Self {
            system,
            dir,
            pki,
            netlist,
            endpoint,
        }
    }

    /// The Zenoh configuration of identity `name`, made by `dnm certs config`.
    fn config(&self, name: &str) -> PathBuf {
        let out = self.dir.join(format!("{name}.json5"));
        if !out.exists() {
            let side = if name == "rover-router" {
                "--listen"
            } else {
                "--connect"
            };
            dnm(&[
                "certs",
                "config",
                "--dir",
                self.pki.to_str().unwrap(),
                name,
                "--netlist",
                self.netlist.to_str().unwrap(),
                side,
                &self.endpoint,
                "--out",
                out.to_str().unwrap(),
            ]);
        }
        out
    }

    /// A session as identity `name` (once the router listens).
    fn session(&self, name: &str) -> zenoh::Session {
        let path = self.config(name);
        eventually(&format!("{name} connects"), || {
            zenoh::open(zenoh::Config::from_file(&path).unwrap())
                .wait()
                .ok()
        })
    }

    fn key(&self, rest: &str) -> String {
        format!("{}/{rest}", self.system)
    }

    /// The rover's router: TLS only, with the generated access control.
    fn router(&self) -> Proc {
        Proc::dnm(
            &self.dir,
            "router",
            &[
                "--zenoh-config".into(),
                self.config("rover-router").display().to_string(),
                "router".into(),
            ],
        )
    }

    fn up(&self, dnm: &str) -> Proc {
        let config = self.config(&format!("computer-{dnm}"));
        Proc::dnm(
            &self.dir,
            dnm,
            &[
                "--zenoh-config".into(),
                config.display().to_string(),
                "up".into(),
                self.netlist.display().to_string(),
                "--dnm".into(),
                dnm.into(),
                "--no-record".into(),
                "--state-dir".into(),
                self.dir.join("state").display().to_string(),
            ],
        )
    }
}

/// Every answer to a query: (ok, JSON).
fn ask(session: &zenoh::Session, selector: &str, body: Option<&Value>) -> Vec<(bool, Value)> {
    let mut q = session
        .get(selector)
        .target(QueryTarget::All)
        .consolidation(ConsolidationMode::None)
        .timeout(Duration::from_secs(3));
    if let Some(b) = body {
        q = q.payload(serde_json::to_vec(b).unwrap());
    }
    let replies = q.wait().unwrap();
    let mut out = Vec::new();
    while let Ok(r) = replies.recv() {
        match r.result() {
            Ok(s) => out.push((
                true,
                serde_json::from_slice(&s.payload().to_bytes()).unwrap_or(Value::Null),
            )),
            Err(e) => out.push((
                false,
                serde_json::from_slice(&e.payload().to_bytes()).unwrap_or(Value::Null),
            )),
        }
    }
    out
}

/// The origin of relay's last output.
fn relay_origin(s: &Secured, session: &zenoh::Session) -> Option<u64> {
    let replies = session
        .get(s.key("port/b/relay/out"))
        .timeout(Duration::from_secs(3))
        .wait()
        .unwrap();
    let b = replies
        .recv()
        .ok()?
        .result()
        .ok()?
        .payload()
        .to_bytes()
        .to_vec();
    Some(u64::from_le_bytes(b.get(0..8)?.try_into().ok()?))
}

fn active_tasks(s: &Secured, session: &zenoh::Session) -> Vec<String> {
    let mut tasks: Vec<String> = ["a", "b"]
        .iter()
        .filter_map(|d| {
            ask(session, &s.key(&format!("dnm/{d}")), None)
                .into_iter()
                .find(|(ok, _)| *ok)
                .and_then(|(_, r)| r["active_task"].as_str().map(str::to_string))
        })
        .collect();
    tasks.sort();
    tasks
}

/// Puts a well-formed sample of origin 999 on the key of `src.out` (owned by DNM `a`), ten
/// times, and says whether relay (on DNM `b`) ever forwarded it.
fn forged_reaches_relay(s: &Secured, from: &zenoh::Session, observer: &zenoh::Session) -> bool {
    let key = s.key("port/a/src/out");
    let mut seen = false;
    for seq in 0..10u64 {
        let mut payload = 999u64.to_le_bytes().to_vec();
        payload.extend_from_slice(&(1_000_000 + seq).to_le_bytes());
        let header = SampleHeader {
            stamp_ns: 0,
            seq: 1_000_000 + seq,
            task_word: 0,
            unix_ns: 0,
        };
        from.put(&key, payload)
            .attachment(encode_header(&header).to_vec())
            .wait()
            .unwrap();
        std::thread::sleep(Duration::from_millis(100));
        seen |= relay_origin(s, observer) == Some(999);
    }
    for _ in 0..10 {
        std::thread::sleep(Duration::from_millis(100));
        seen |= relay_origin(s, observer) == Some(999);
    }
    seen
}

fn refusals(log: &Path) -> Vec<String> {
    std::fs::read_to_string(log)
        .unwrap_or_default()
        .lines()
        .filter(|l| l.contains("access refused"))
        .map(str::to_string)
        .collect()
}

#[test]
fn only_the_operator_commands_a_secured_system() {
    let s = Secured::new();
    // A DNM may come up before its router: it waits for it.
    let _a = s.up("a");
    std::thread::sleep(Duration::from_secs(1));
    let router = s.router();
    let _b = s.up("b");
    let operator = s.session("ground-1");
    eventually("src's samples cross to relay", || {
        (relay_origin(&s, &operator) == Some(1)).then_some(())
    });

    // Without a certificate of the system's authority there is no link at all.
    let ca = s.pki.join("ca.pem").display().to_string();
    let stranger = json!({
        "mode": "client",
        "connect": { "endpoints": [s.endpoint], "timeout_ms": 3000, "exit_on_failure": true },
        "scouting": { "multicast": { "enabled": false } },
        "transport": { "link": { "tls": { "root_ca_certificate": ca } } },
    });
    let open = zenoh::open(zenoh::Config::from_json5(&stranger.to_string()).unwrap()).wait();
    assert!(open.is_err(), "a client without a certificate connected");
    let plain = json!({
        "mode": "client",
        "connect": {
            "endpoints": [s.endpoint.replace("tls/", "tcp/")],
            "timeout_ms": 3000,
            "exit_on_failure": true,
        },
        "scouting": { "multicast": { "enabled": false } },
    });
    let open = zenoh::open(zenoh::Config::from_json5(&plain.to_string()).unwrap()).wait();
    assert!(open.is_err(), "a plain TCP client connected");
    // A certificate from another authority is no better.
    let other = s.dir.join("other-pki");
    let o = other.to_str().unwrap();
    dnm(&["certs", "init", "--dir", o, "--system", &s.system]);
    dnm(&[
        "certs", "issue", "--dir", o, "ground-1", "--role", "operator",
    ]);
    let forged = std::fs::read_to_string(s.config("ground-1"))
        .unwrap()
        .replace(
            &format!("{}/ground-1", s.pki.display()),
            &format!("{o}/ground-1"),
        );
    let mut forged: Value = serde_json::from_str(&forged).unwrap();
    forged["connect"]["timeout_ms"] = json!(3000);
    forged["connect"]["exit_on_failure"] = json!(true);
    let open = zenoh::open(zenoh::Config::from_json5(&forged.to_string()).unwrap()).wait();
    assert!(
        open.is_err(),
        "a certificate of another authority was admitted"
    );

    // The observer reads module state...
    let observer = s.session("science");
    let report = ask(&observer, &s.key("dnm/a"), None);
    assert_eq!(report.len(), 1, "{report:?}");
    assert_eq!(report[0].1["modules"][0]["name"], "src");
    assert_eq!(report[0].1["modules"][0]["state"], "running");
    // ...but its switch reaches no DNM, and the router records the refusal.
    let switch = json!({"id": "science-switch", "cmd": "switch", "task": "idle"});
    let answers = ask(&observer, &s.key("dnm/*/cmd"), Some(&switch));
    assert!(answers.is_empty(), "{answers:?}");
    assert_eq!(active_tasks(&s, &operator), ["feed", "feed"]);
    eventually("the router records the refusal", || {
        refusals(&router.log)
            .into_iter()
            .find(|l| l.contains("CertCommonName(science)") && l.contains("Query (ingress)"))
    });
    // It watches any output at the limited rates, never every sample.
    let slow = Arc::new(AtomicU64::new(0));
    let _slow = {
        let slow = slow.clone();
        observer
            .declare_subscriber(s.key("watch/a/src/out/1hz"))
            .callback(move |_| {
                slow.fetch_add(1, Ordering::Relaxed);
            })
            .wait()
            .unwrap()
    };
    eventually("the observer watches an output at 1 Hz", || {
        (slow.load(Ordering::Relaxed) >= 2).then_some(())
    });
    let fast = Arc::new(AtomicU64::new(0));
    let _fast = {
        let fast = fast.clone();
        observer
            .declare_subscriber(s.key("watch/a/src/out/full"))
            .callback(move |_| {
                fast.fetch_add(1, Ordering::Relaxed);
            })
            .wait()
            .unwrap()
    };
    eventually("the router records the refused full-rate watch", || {
        let what = format!(
            "Declare Subscriber (ingress) on {}",
            s.key("watch/a/src/out/full")
        );
        refusals(&router.log)
            .into_iter()
            .find(|l| l.contains(&what))
    });
    // The ticker sends 10 a second: a full-rate watch would have had them.
    std::thread::sleep(Duration::from_millis(1500));
    assert_eq!(fast.load(Ordering::Relaxed), 0);

    // Nor can it answer for a DNM (a rogue netlist) or a command.
    let _rogue = observer
        .declare_queryable(s.key("dnm/a/netlist"))
        .callback(|q| {
            let _ = q.reply(q.key_expr().clone(), r#"{"revision": 999}"#).wait();
        })
        .wait()
        .unwrap();
    std::thread::sleep(Duration::from_millis(500));
    let netlists = ask(&operator, &s.key("dnm/a/netlist"), None);
    assert_eq!(netlists.len(), 1, "{netlists:?}");
    assert_ne!(netlists[0].1["revision"], 999);

    // Nor can one of the system's computers answer for another's DNM.
    let computer_b = s.session("computer-b");
    let mut rogues = Vec::new();
    for key in ["dnm/a/netlist", "dnm/a/cmd"] {
        rogues.push(
            computer_b
                .declare_queryable(s.key(key))
                .callback(|q| {
                    let _ = q
                        .reply(q.key_expr().clone(), r#"{"ok": true, "revision": 999}"#)
                        .wait();
                })
                .wait()
                .unwrap(),
        );
    }
    std::thread::sleep(Duration::from_millis(500));
    let netlists = ask(&operator, &s.key("dnm/a/netlist"), None);
    assert_eq!(netlists.len(), 1, "{netlists:?}");
    assert_ne!(netlists[0].1["revision"], 999);

    // The operator's switch works, on every DNM (and only they answer it).
    let switch = json!({"id": "op-switch-1", "cmd": "switch", "task": "idle"});
    let answers = ask(&operator, &s.key("dnm/*/cmd"), Some(&switch));
    assert_eq!(answers.len(), 2, "{answers:?}");
    assert!(answers.iter().all(|(ok, _)| *ok), "{answers:?}");
    assert_eq!(active_tasks(&s, &operator), ["idle", "idle"]);
    let back = json!({"id": "op-switch-2", "cmd": "switch", "task": "feed"});
    assert!(
        ask(&operator, &s.key("dnm/*/cmd"), Some(&back))
            .iter()
            .all(|(ok, _)| *ok)
    );

    // A sample on a mirrored port's key from anyone but the port's owner never reaches a module:
    // not from the operator, the observer, or the system's other computer.
    for (who, session) in [
        ("operator", &operator),
        ("observer", &observer),
        ("computer-b", &computer_b),
    ] {
        assert!(
            !forged_reaches_relay(&s, session, &operator),
            "a sample from the {who} reached relay"
        );
    }
    // The same sample from the owner's identity does (so the ones above were well-formed).
    let computer_a = s.session("computer-a");
    assert!(forged_reaches_relay(&s, &computer_a, &operator));

    // An apply from the operator naming a program as a module kind runs nothing: it comes in
    // through `NetlistDoor::accept` (`dnm/netlist/src/door.rs`), the one way a netlist from
    // outside enters a DNM or the authority.
    let text = netlist_template().replace("SYSTEM", &s.system);
    let evil = format!(
        "{text}\n[[module]]\nname = \"x\"\nkind = \"evil\"\ndnm = \"a\"\n\n[kind.evil]\nexec = \"/usr/bin/touch\"\n"
    );
    let apply = json!({"id": "op-apply-evil", "cmd": "apply", "file": "evil.toml", "text": evil});
    // Each DNM asked on its own key, as `dnm` does: an error answer carries the key the query
    // named, and a computer may answer only on its own DNMs' keys.
    let answers: Vec<(bool, Value)> = ["a", "b"]
        .iter()
        .flat_map(|d| ask(&operator, &s.key(&format!("dnm/{d}/cmd")), Some(&apply)))
        .collect();
    assert_eq!(answers.len(), 2, "{answers:?}");
    for (ok, a) in &answers {
        let e = a["error"].as_str().unwrap_or_default();
        assert!(
            !ok && e.contains("/usr/bin/touch") && e.contains("DNM_MODULE_DIR"),
            "{a}"
        );
    }
    assert!(!Path::new("describe").exists(), "a program ran");
    assert_eq!(active_tasks(&s, &operator), ["feed", "feed"]);
}

#[test]
fn through_the_authority_only_the_operators_station_commands() {
    let template = netlist_template().replace(
        "default_task = \"feed\"",
        "default_task = \"feed\"\nauthority = \"a\"",
    );
    let s = Secured::with("seca", &template);
    let router = s.router();
    let _a = s.up("a");
    let _b = s.up("b");
    let operator = s.session("ground-1");
    // The DNMs start empty and take what the authority decided.
    eventually("both DNMs adopt the authority's netlist", || {
        (active_tasks(&s, &operator) == ["feed", "feed"]).then_some(())
    });
    // A station named `name` with the certificate of `identity`.
    let station_as = |identity: &str, name: &str| -> (Proc, Api) {
        let http = format!("127.0.0.1:{}", free_port());
        let p = Proc::dnm(
            &s.dir,
            &format!("station-{name}"),
            &[
                "--zenoh-config".into(),
                s.config(identity).display().to_string(),
                "ground".into(),
                "serve".into(),
                "--system".into(),
                s.system.clone(),
                "--station".into(),
                name.into(),
                "--db".into(),
                s.dir.join(format!("{name}.redb")).display().to_string(),
                "--http".into(),
                http.clone(),
            ],
        );
        let api = Api(format!("http://{http}"));
        eventually("the station's API", || api.up().then_some(()));
        (p, api)
    };
    let station = |name: &str| station_as(name, name);

    // The operator's station commands the rover through the authority.
    let (_op_station, op) = station("ground-1");
    let e = op.submit(&Order::Switch {
        task: "idle".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    let applied = op.entry(e.seq, 60);
    assert_eq!(applied.state, CommandState::Applied, "{applied:?}");
    // Every DNM switches at the decided instant (a little after the decision).
    eventually("both DNMs switch to idle", || {
        (active_tasks(&s, &operator) == ["idle", "idle"]).then_some(())
    });

    // An observer's station is never heard: its command is never acknowledged, whatever the
    // operator does meanwhile, and the router records the refusal.
    let (_obs_station, obs) = station("science");
    let o = obs.submit(&Order::Switch {
        task: "feed".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    let e = op.submit(&Order::Switch {
        task: "idle".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    assert_eq!(op.entry(e.seq, 60).state, CommandState::Applied);
    eventually("the router records the observer's uplink refused", || {
        refusals(&router.log).into_iter().find(|l| {
            l.contains("CertCommonName(science)")
                && l.contains(&format!("{}/authority/station/science", s.system))
        })
    });
    let o = obs.entry(o.seq, 0);
    assert!(
        matches!(o.state, CommandState::Queued | CommandState::Sent),
        "{o:?}"
    );
    assert_eq!(active_tasks(&s, &operator), ["idle", "idle"]);

    // A station is its certificate: the operator's certificate does not speak as another
    // station (its uplinks are refused by the router, and recorded there).
    let (_impostor, imp) = station_as("ground-1", "ground-2");
    let i = imp.submit(&Order::Switch {
        task: "feed".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    eventually("the router records the impostor's uplink refused", || {
        refusals(&router.log).into_iter().find(|l| {
            l.contains("CertCommonName(ground-1)")
                && l.contains(&format!("{}/authority/station/ground-2", s.system))
        })
    });
    let i = imp.entry(i.seq, 0);
    assert!(
        matches!(i.state, CommandState::Queued | CommandState::Sent),
        "{i:?}"
    );
    assert_eq!(active_tasks(&s, &operator), ["idle", "idle"]);

    // Nor may the operator go around the authority: a DNM's own command key is not theirs.
    let switch = json!({"id": "op-direct", "cmd": "switch", "task": "feed"});
    let answers = ask(&operator, &s.key("dnm/a/cmd"), Some(&switch));
    assert!(answers.is_empty(), "{answers:?}");
    assert_eq!(active_tasks(&s, &operator), ["idle", "idle"]);
}
