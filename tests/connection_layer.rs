//! The connection layer with real processes and real shared memory: a `dnm up` process hosts
//! module processes; the test reads their output ports from iceoryx2 like any other reader.

#![allow(clippy::unwrap_used)] // test helpers: failing loudly is right

use std::collections::BTreeSet;
use std::process::Command;

use dnm::admin::Request;
use dnm_module::msg::{PairReading, Tick};

mod support;

use support::system::{System, collect, drain};

const PIPELINE: &str = r#"
[system]
name = "SYSTEM"
default_task = "a"

[[dnm]]
name = "main"

[[module]]
name = "src_a"
kind = "ticker"
rate_hz = 200
params = { origin = 1 }

[[module]]
name = "src_b"
kind = "ticker"
rate_hz = 200
params = { origin = 2 }

[[module]]
name = "relay"
kind = "relay"
restart = "always"

[[module]]
name = "pair"
kind = "pair"

[task.a]
links = ["src_a.out -> relay.in", "src_a.out -> pair.a", "src_b.out -> pair.b"]

[task.b]
links = ["src_b.out -> relay.in", "src_b.out -> pair.a", "src_a.out -> pair.b"]
"#;

/// Readings after the last one taken under another slot than `slot`.
fn settled(readings: &[PairReading], slot: u64) -> usize {
    readings
        .iter()
        .rev()
        .take_while(|r| r.task_slot == slot)
        .count()
}

#[test]
fn data_flows_and_task_switches_never_mix_sources() {
    let sys = System::start(PIPELINE);
    let relay = sys.subscribe::<Tick>("relay", "out");
    let pair = sys.subscribe::<PairReading>("pair", "out");

    // Task `a` (slot 0): the relay forwards src_a; pair reads (src_a, src_b).
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 20);
    assert!(ticks.iter().all(|t| t.origin == 1), "{ticks:?}");
    let seqs: Vec<u64> = ticks.iter().map(|t| t.seq).collect();
    assert!(
        seqs.windows(2).all(|w| w[0] < w[1]),
        "relay output out of order: {seqs:?}"
    );

    // Switch back and forth many times while data flows. Every step runs under one task and
    // reads only that task's sources: slot 0 => (1, 2), slot 1 => (2, 1), never a mix.
    drain(&pair);
    let mut readings: Vec<PairReading> = Vec::new();
    for i in 0..20 {
        let task = if i % 2 == 0 { "b" } else { "a" };
        let r = sys.ask(&Request::Switch { task: task.into() });
        assert!(r.ok, "{r:?}");
        assert_eq!(r.switches[0].to, task);
        let slot = if task == "a" { 0 } else { 1 };
        readings.extend(collect::<PairReading>(&pair, |got| settled(got, slot) >= 3));
    }
    let slots: BTreeSet<u64> = readings.iter().map(|r| r.task_slot).collect();
    assert_eq!(slots, BTreeSet::from([0, 1]));
    for r in &readings {
        let expected = if r.task_slot == 0 { (1, 2) } else { (2, 1) };
        assert_eq!((r.a_origin, r.b_origin), expected, "mixed reading {r:?}");
    }

    // After the last switch (to `a`), the relay reads src_a again, and only src_a.
    drain(&relay);
    let after = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(after.iter().skip(1).all(|t| t.origin == 1), "{after:?}");
    let st = sys.status();
    assert_eq!(st.active_task.as_deref(), Some("a"));
    assert_eq!(st.switches.len(), 20);
}

#[test]
fn module_added_at_run_time_joins_a_task() {
    let sys = System::start(PIPELINE);
    let relay = sys.subscribe::<Tick>("relay", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);

    let out = sys.dnm(&[
        "module",
        "add",
        "--system",
        &sys.name,
        "--name",
        "src_c",
        "--kind",
        "ticker",
        "--param",
        "origin=3",
        "--link",
        "a:src_c.out -> relay.in",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let st = sys.status();
    assert_eq!(st.revision, 2);
    assert!(st.modules.iter().any(|m| m.name == "src_c"));

    // The relay now follows src_c in task `a`.
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 3).count() >= 10);
    let last = ticks.iter().rev().take(10);
    assert!(last.clone().all(|t| t.origin == 3), "{ticks:?}");

    // Removing it drops its link; the relay has no source in task `a` then.
    let out = sys.dnm(&["module", "remove", "--system", &sys.name, "--name", "src_c"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let st = sys.status();
    assert_eq!(st.revision, 3);
    assert!(!st.modules.iter().any(|m| m.name == "src_c"));
}

#[test]
fn replaced_module_keeps_its_links() {
    let sys = System::start(PIPELINE);
    let relay = sys.subscribe::<Tick>("relay", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);
    let old_pid = sys
        .status()
        .modules
        .iter()
        .find(|m| m.name == "src_a")
        .unwrap()
        .pid;
    let out = sys.dnm(&[
        "module", "replace", "--system", &sys.name, "--name", "src_a", "--param", "origin=7",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let st = sys.wait_for("src_a replaced", |r| {
        r.dnms[0].modules.iter().any(|m| {
            m.name == "src_a" && m.state == dnm::ModuleRunState::Running && m.pid != old_pid
        })
    });
    assert_eq!(st.dnms[0].revision, 2);
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 7).count() >= 5);
    assert!(
        ticks.iter().rev().take(5).all(|t| t.origin == 7),
        "{ticks:?}"
    );
}

#[test]
fn killed_module_is_reported_and_restarted_while_others_run() {
    let sys = System::start(PIPELINE);
    let relay = sys.subscribe::<Tick>("relay", "out");
    let pair = sys.subscribe::<PairReading>("pair", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);
    let before = sys.status();
    let victim = before
        .modules
        .iter()
        .find(|m| m.name == "relay")
        .unwrap()
        .pid
        .unwrap();
    // SAFETY: kill(2) on a module process of our test system.
    assert_eq!(unsafe { libc::kill(victim as i32, libc::SIGKILL) }, 0);

    // The others keep running while the relay is down.
    drain(&pair);
    collect::<PairReading>(&pair, |p| p.len() >= 20);

    let r = sys.wait_for("relay restarted", |r| {
        r.dnms[0].modules.iter().any(|m| {
            m.name == "relay" && m.restarts >= 1 && m.state == dnm::ModuleRunState::Running
        })
    });
    let d = &r.dnms[0];
    let relay_now = d.modules.iter().find(|m| m.name == "relay").unwrap();
    assert_ne!(relay_now.pid, Some(victim));
    assert!(
        relay_now.last_exit.as_deref().unwrap_or("").contains("9"),
        "exit reported: {:?}",
        relay_now.last_exit
    );
    // The dead process's shared-memory resources are gone (the DNM removes them when it notices
    // the death, unless a starting process of the namespace got there first).
    let config =
        dnm_module::protocol::dnm_config(&dnm_module::protocol::dnm_prefix(&sys.name, "main"))
            .unwrap();
    support::eventually("no dead node left in the DNM's namespace", || {
        let mut dead = 0;
        iceoryx2::prelude::Node::<iceoryx2::prelude::ipc::Service>::list(&config, |n| {
            if matches!(n, iceoryx2::node::NodeState::Dead(_)) {
                dead += 1;
            }
            iceoryx2::prelude::CallbackProgression::Continue
        })
        .unwrap();
        (dead == 0).then_some(())
    });
    for m in &d.modules {
        if m.name != "relay" {
            assert_eq!(m.restarts, 0, "{} restarted", m.name);
            let was = before.modules.iter().find(|b| b.name == m.name).unwrap();
            assert_eq!(m.pid, was.pid);
        }
    }
    // And data flows through the new relay process.
    drain(&relay);
    collect::<Tick>(&relay, |t| t.len() >= 10);
}

#[test]
fn bad_netlist_is_refused_and_the_running_task_continues() {
    let sys = System::start(PIPELINE);
    let relay = sys.subscribe::<Tick>("relay", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);
    let before = sys.status();

    let bad = PIPELINE
        .replace("SYSTEM", &sys.name)
        .replace("\"src_b.out -> relay.in\"", "\"src_x.out -> relay.in\"");
    let path = sys.dir.join("bad.toml");
    std::fs::write(&path, &bad).unwrap();
    let out = sys.dnm(&["apply", "--system", &sys.name, path.to_str().unwrap()]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let line = bad.lines().position(|l| l.contains("src_x")).unwrap() + 1;
    assert!(err.contains(&format!("bad.toml:{line}:")), "{err}");
    assert!(err.contains("unknown module `src_x`"), "{err}");
    assert!(err.contains("nothing changed"), "{err}");

    let after = sys.status();
    assert_eq!(after.revision, before.revision);
    assert_eq!(after.active_task, before.active_task);
    for (a, b) in after.modules.iter().zip(&before.modules) {
        assert_eq!(
            (a.pid, a.restarts),
            (b.pid, b.restarts),
            "{} was disturbed",
            a.name
        );
    }
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(ticks.iter().all(|t| t.origin == 1));

    // Unknown tasks are refused too.
    let r = sys.ask(&Request::Switch { task: "c".into() });
    assert!(!r.ok && r.error.unwrap().contains("unknown task `c`"));
}

/// The shared-memory files of DNM `main` of `system` (iceoryx2's node counter aside, which
/// iceoryx2 keeps by design).
fn shared_memory_of(system: &str) -> Vec<String> {
    let prefix = format!("dnm_{system}_main_");
    std::fs::read_dir("/dev/shm")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|f| f.starts_with(&prefix) && !f.ends_with(".global_mgmt"))
        .collect()
}

/// A DNM builds its report for the Zenoh side when something in it changes or a tool asks,
/// not on every supervision tick; a tool asking over Zenoh still gets the live figures.
#[test]
fn reports_are_made_when_asked_and_carry_the_live_figures() {
    use zenoh::Wait;
    let port = support::free_port();
    let sys = System::start_with(
        PIPELINE,
        &["--no-multicast", "--listen", &support::endpoint(port)],
    );
    let session = support::zenoh_client(port);
    let over_zenoh = || -> Option<dnm::DnmReport> {
        let replies = session
            .get(format!("{}/dnm/main", sys.name))
            .timeout(std::time::Duration::from_secs(5))
            .wait()
            .ok()?;
        let reply = replies.recv().ok()?;
        serde_json::from_slice(&reply.result().ok()?.payload().to_bytes()).ok()
    };
    let steps = |r: &dnm::DnmReport| r.modules.iter().find(|m| m.name == "src_a").unwrap().steps;
    let mut second = support::eventually("the DNM's report over Zenoh", over_zenoh);
    // Four times: the ticker steps forty times more, as the DNM itself counts them (its admin
    // socket), and a tool asking over Zenoh more than a tick later (the bridge's `FRESH`, 100
    // ms) is shown at least what the DNM counted, though the DNM makes a report for the Zenoh
    // side only once a second unless asked.
    for _ in 0..4 {
        let before = steps(&second);
        let direct = sys.wait_for("forty more steps", |r| {
            r.dnms[0]
                .modules
                .iter()
                .any(|m| m.name == "src_a" && m.steps >= before + 40)
        });
        std::thread::sleep(std::time::Duration::from_millis(150));
        second = support::eventually("the DNM's report over Zenoh", over_zenoh);
        assert!(
            steps(&second) >= steps(&direct.dnms[0])
                && second.supervision.passes >= direct.dnms[0].supervision.passes,
            "an old report: {} steps at pass {} over Zenoh after the DNM counted {} at pass {}",
            steps(&second),
            second.supervision.passes,
            steps(&direct.dnms[0]),
            direct.dnms[0].supervision.passes
        );
    }
    // Thirty ticks go by: the DNM made a few reports in them, not one a tick.
    sys.wait_for("thirty ticks", |r| {
        r.dnms[0].supervision.passes >= second.supervision.passes + 30
    });
    let third = support::eventually("the DNM's report over Zenoh", over_zenoh);
    let passes = third.supervision.passes - second.supervision.passes;
    let snapshots = third.supervision.snapshots - second.supervision.snapshots;
    assert!(
        snapshots * 2 < passes,
        "{snapshots} reports made in {passes} ticks"
    );
}

#[test]
fn a_dnm_stopped_cleanly_leaves_no_shared_memory_behind() {
    let mut sys = System::start(PIPELINE);
    // The admin socket served a request: its thread holds the DNM's commanders.
    assert!(sys.ask(&Request::Status).ok);
    assert!(!shared_memory_of(&sys.name).is_empty());
    // SIGTERM, as a service manager stops it (Ctrl-C takes the same path). Looked at while
    // this test's own iceoryx2 node lives: dropped, it would sweep what a dead process left.
    // SAFETY: kill(2) on our own child, not reaped yet.
    unsafe { libc::kill(sys.child.id() as i32, libc::SIGTERM) };
    let exit = sys.child.wait().unwrap();
    assert!(exit.success(), "{exit}");
    let left = shared_memory_of(&sys.name);
    assert!(left.is_empty(), "left in /dev/shm: {left:?}");
}

#[test]
fn watch_prints_an_output_s_values_decoded_and_names_what_exists_when_asked_wrong() {
    let at = support::endpoint(support::free_port());
    let sys = System::start_with(PIPELINE, &["--no-multicast", "--listen", &at]);
    let global = ["--no-multicast", "--connect", at.as_str()];
    let watch =
        |args: &[&str]| sys.dnm(&[&global[..], &["watch", "--system", &sys.name], args].concat());

    // `--timeout`: a hang guard, never reached when it works.
    let out = watch(&[
        "relay.out",
        "--count",
        "3",
        "--json",
        "--rate",
        "full",
        "--timeout",
        "60",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 3, "{lines:?}");
    // Task `a`: the relay forwards src_a's ticks, numbered one after the other.
    assert!(lines.iter().all(|l| l["value"]["origin"] == 1), "{lines:?}");
    let seqs: Vec<u64> = lines
        .iter()
        .map(|l| l["value"]["seq"].as_u64().unwrap())
        .collect();
    assert!(seqs.windows(2).all(|w| w[1] > w[0]), "{seqs:?}");
    assert!(
        lines.iter().all(|l| l["unix_ns"].as_u64().unwrap() > 0),
        "{lines:?}"
    );

    let out = watch(&["relay.nope", "--count", "1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("module `relay` has no output `nope`; its outputs: out"),
        "{err}"
    );
    let out = watch(&["zz.out", "--count", "1"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        err.contains("its modules: src_a, src_b, relay, pair"),
        "{err}"
    );
}

#[test]
fn check_reports_errors_with_location_and_exit_code() {
    let dir = std::env::temp_dir().join(format!("dnm-check-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("good.toml");
    std::fs::write(&good, PIPELINE.replace("SYSTEM", "checked")).unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .arg("check")
        .arg(&good)
        .output()
        .unwrap();
    assert!(out.status.success());
    assert!(String::from_utf8_lossy(&out.stdout).contains("task a (initial): 3 links"));

    let bad = dir.join("bad.toml");
    std::fs::write(
        &bad,
        PIPELINE
            .replace("SYSTEM", "checked")
            .replace("kind = \"relay\"", "kind = \"rely\""),
    )
    .unwrap();
    let out = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(["check", "--json"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!out.status.success());
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let e = &v["errors"][0];
    assert_eq!(e["field"], "module[2].kind");
    assert!(e["line"].as_u64().unwrap() > 0);
    assert!(e["help"].as_str().unwrap().contains("did you mean `relay`"));
    let _ = std::fs::remove_dir_all(&dir);
}
