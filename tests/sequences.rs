//! Onboard sequences, end to end with real processes: uploaded through a station, run by the
//! rover's authority with the radio cut, stopped by a guard on a real output, carried on
//! (never a step twice) by an authority killed and restarted, and refused with located errors
//! when they do not check.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

mod support;

use std::collections::BTreeMap;
use std::sync::Mutex;
use std::time::Duration;

use dnm_ground::CommandState;
use dnm_proto::station::{Fate, Order, SequenceAction, SequenceState, SequenceStatus};
use support::ground::{Api, ROVER, Rig, report, wait_in_step};
use support::{eventually, zenoh_client};

/// One of these tests at a time: each runs a whole rover on a small machine.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

fn upload(name: &str, text: &str) -> Order {
    Order::Sequence {
        name: name.into(),
        action: SequenceAction::Upload {
            file: format!("{name}.toml"),
            text: text.into(),
            netlists: BTreeMap::new(),
        },
    }
}

fn order(name: &str, action: SequenceAction) -> Order {
    Order::Sequence {
        name: name.into(),
        action,
    }
}

/// Submits `order` and waits for its final fate.
fn run(api: &Api, o: &Order) -> dnm_ground::Entry {
    let e = api.submit(o);
    eventually("the command's fate", || {
        Some(api.entry(e.seq, 5)).filter(|e| e.state.is_final())
    })
}

fn done(api: &Api, o: &Order) {
    let e = run(api, o);
    assert!(
        matches!(e.fate, Some(Fate::Done { .. })),
        "{:?}: {:?}",
        e.order,
        e.fate
    );
}

/// The sequence as the station last heard of it.
fn status(api: &Api, name: &str) -> Option<SequenceStatus> {
    api.link()
        .rover?
        .sequences
        .into_iter()
        .find(|q| q.name == name)
}

/// The tasks DNM `dnm` switched to, oldest first.
fn switches(session: &zenoh::Session, system: &str, dnm: &str) -> Vec<String> {
    report(session, system, dnm)
        .unwrap()
        .switches
        .into_iter()
        .map(|s| s.to)
        .collect()
}

/// How many times each step ended (`step_done`, `condition_met`) in run `run`.
fn steps_done(q: &SequenceStatus, run: u64) -> BTreeMap<usize, usize> {
    let mut n = BTreeMap::new();
    for e in &q.history {
        if e.run == run && matches!(e.what.as_str(), "step_done" | "condition_met") {
            *n.entry(e.step.unwrap()).or_default() += 1;
        }
    }
    n
}

const TRIP: &str = r#"
[sequence]
name = "trip"

[[step]]
wait = "3s"

[[step]]
switch = "b"

[[step]]
edit = { replace = "src_b", params = ["origin=7"] }

# The replaced source says so on its output.
[[step]]
wait_until = "src_b.out.origin == 7"
timeout = "30s"
on_timeout = "abort"

[[step]]
wait = "2s"

[[step]]
switch = "a"
"#;

#[test]
fn a_sequence_runs_on_board_with_the_radio_cut_and_the_station_sees_it_after() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("sqcut", r#"on_link_loss = { after = "2s", task = "c" }"#);
    let _routers = rig.routers();
    let radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    let revision = wait_in_step(&session, &rig.system, &ROVER, "a");
    done(&api, &upload("trip", TRIP));
    done(&api, &order("trip", SequenceAction::Start));
    let before = switches(&session, &rig.system, "drive").len();

    // The radio dies for the whole run (and longer than the loss-of-signal time).
    radio.kill();
    let ended = eventually("the sequence's last switch, then the safing", || {
        let seen = switches(&session, &rig.system, "drive");
        (seen.len() >= before + 3).then_some(seen)
    });
    // Through the silence the rover went through every step: `b`, the edit (a new revision,
    // checked below), `a`; then, the sequence over and no station heard, loss of signal made
    // it safe.
    assert_eq!(ended[before..], ["b", "a", "c"], "{ended:?}");
    wait_in_step(&session, &rig.system, &ROVER, "c");
    for d in ROVER {
        let r = report(&session, &rig.system, d).unwrap();
        assert!(r.revision > revision, "{d}: the edit is in force");
        assert!(
            r.safed.as_ref().is_none_or(|s| s.epoch.is_some()),
            "{d} followed the authority, it did not go safe on its own: {:?}",
            r.safed
        );
    }

    // The radio is back: the station shows the whole history.
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let q = eventually("the station hears the sequence's end", || {
        status(&api, "trip").filter(|q| q.state == SequenceState::Finished)
    });
    let whats: Vec<&str> = q.history.iter().map(|e| e.what.as_str()).collect();
    for w in [
        "stored",
        "started",
        "step_started",
        "condition_met",
        "finished",
    ] {
        assert!(whats.contains(&w), "{w} missing from {whats:?}");
    }
    let met = q
        .history
        .iter()
        .find(|e| e.what == "condition_met")
        .unwrap();
    assert!(
        met.detail.contains("src_b.out.origin = 7"),
        "the condition was met on the output's value: {}",
        met.detail
    );
    assert_eq!(
        steps_done(&q, 1),
        (0..6).map(|s| (s, 1)).collect(),
        "{:#?}",
        q.history
    );
    let rover = api.link().rover.unwrap();
    assert!(rover.safe, "made safe once the sequence was over");
    assert!(
        rover
            .last_safing
            .unwrap()
            .reason
            .contains("no ground station"),
        "safe for loss of signal"
    );
}

#[test]
fn a_guard_on_a_real_output_stops_the_sequence_on_its_task() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("sqguard", "");
    // A battery on `drive`, publishing its state at 10 Hz.
    let mut text = std::fs::read_to_string(&rig.netlist).unwrap();
    text.push_str(
        "\n[[module]]\nname = \"battery\"\nkind = \"battery\"\ndnm = \"drive\"\nparams = { charge = 0.9 }\n",
    );
    std::fs::write(&rig.netlist, text).unwrap();
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let guarded = r#"
[sequence]
name = "guarded"

[[guard]]
abort_if = "battery.state.charge < 0.2"
task = "c"

[[step]]
switch = "b"

[[step]]
wait = "10m"

[[step]]
switch = "a"
"#;
    done(&api, &upload("guarded", guarded));
    done(&api, &order("guarded", SequenceAction::Start));
    wait_in_step(&session, &rig.system, &ROVER, "b");

    // The battery is found low: its charge forced by a parameter.
    let e = run(
        &api,
        &Order::Module {
            edit: dnm_proto::station::ModuleEdit::Replace {
                name: "battery".into(),
                kind: None,
                params: vec!["charge=0.1".into()],
            },
        },
    );
    assert_eq!(e.state, CommandState::Applied, "{e:?}");
    wait_in_step(&session, &rig.system, &ROVER, "c");
    let q = eventually("the station sees the sequence aborted", || {
        status(&api, "guarded").filter(|q| q.state == SequenceState::Aborted)
    });
    assert!(
        q.why.contains("guard `battery.state.charge < 0.2` fired"),
        "{}",
        q.why
    );
    assert!(q.why.contains("switched to `c`"), "{}", q.why);
    // From the sample that crossed the limit to the switch in force.
    let fired = q.history.iter().find(|e| e.what == "guard_fired").unwrap();
    let sent = fired.sample_unix_ns.unwrap();
    let aborted = q.history.iter().find(|e| e.what == "aborted").unwrap();
    let in_force = aborted.in_force.as_ref().unwrap();
    assert_eq!(in_force.task.as_deref(), Some("c"));
    let in_force = in_force.at_unix_ns;
    eprintln!(
        "guard: sample sent at {sent}, switch in force {:.1} ms later",
        (in_force as f64 - sent as f64) / 1e6
    );
    assert!(in_force > sent, "{fired:?} / {}", q.why);
    assert!(
        q.history
            .iter()
            .all(|e| e.step != Some(2) || e.what != "step_started"),
        "no step ran after the guard: {:#?}",
        q.history
    );
}

#[test]
fn an_authority_killed_mid_sequence_resumes_it_and_runs_no_step_twice() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    // Loss of signal well beyond the authority's restart: its DNMs do not go safe meanwhile.
    let rig = Rig::new("sqkill", r#"on_link_loss = { after = "30s", task = "c" }"#);
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let authority = rig.up(&["rover"], false);
    let _others = rig.up(&["drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let steps = r#"
[sequence]
name = "steps"

[[step]]
switch = "b"

[[step]]
wait = "8s"

[[step]]
switch = "c"

[[step]]
wait = "1s"

[[step]]
switch = "a"
"#;
    done(&api, &upload("steps", steps));
    let before = switches(&session, &rig.system, "drive").len();
    done(&api, &order("steps", SequenceAction::Start));
    wait_in_step(&session, &rig.system, &ROVER, "b");

    // The authority's computer dies in the 8 s wait, and comes back.
    authority.kill();
    std::thread::sleep(Duration::from_secs(1));
    let _authority = rig.up(&["rover"], false);
    let q = eventually("the sequence finished", || {
        status(&api, "steps").filter(|q| q.state == SequenceState::Finished)
    });
    wait_in_step(&session, &rig.system, &ROVER, "a");
    // `drive` lived through it all: it switched to `b` once, then `c`, then `a`.
    let seen = switches(&session, &rig.system, "drive");
    assert_eq!(seen[before..], ["b", "c", "a"], "{seen:?}");
    assert!(
        q.history
            .iter()
            .any(|e| e.what == "resumed_after_restart" && e.step == Some(1)),
        "{:#?}",
        q.history
    );
    assert_eq!(
        steps_done(&q, 1),
        (0..5).map(|s| (s, 1)).collect(),
        "every step ended once: {:#?}",
        q.history
    );
}

#[test]
fn bad_sequences_are_refused_with_located_errors_and_change_nothing() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("sqbad", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    let revision = wait_in_step(&session, &rig.system, &ROVER, "a");
    let head = "[sequence]\nname = \"bad\"\n";
    let cases = [
        (
            "[[step]]\nwait_until = \"src_a.out.nope > 1\"\ntimeout = \"1s\"\non_timeout = \"abort\"\n",
            "has no field `nope`",
        ),
        (
            "[[step]]\nwait_until = \"src_a.out.seq > true\"\ntimeout = \"1s\"\non_timeout = \"abort\"\n",
            "src_a.out.seq",
        ),
        ("[[step]]\nswitch = \"nowhere\"\n", "nowhere"),
        (
            "[[step]]\nend = true\n\n[[step]]\nswitch = \"b\"\n",
            "never runs",
        ),
        ("[[step]]\nswitch = \"b\"\nbogus = 1\n", "bogus"),
        ("not toml [", "bad.toml"),
    ];
    for (body, says) in cases {
        let e = run(&api, &upload("bad", &format!("{head}{body}")));
        let Some(Fate::Refused { reason }) = &e.fate else {
            panic!("{body}: not refused: {e:?}");
        };
        assert!(reason.contains(says), "{body}: {reason}");
        assert!(reason.contains("bad.toml:"), "located: {reason}");
    }
    // Starting what was never stored is refused too; nothing ran.
    let e = run(&api, &order("bad", SequenceAction::Start));
    assert!(
        matches!(&e.fate, Some(Fate::Refused { reason }) if reason.contains("no sequence `bad`")),
        "{e:?}"
    );
    assert!(status(&api, "bad").is_none());
    for d in ROVER {
        let r = report(&session, &rig.system, d).unwrap();
        assert_eq!(r.revision, revision, "{d}");
        assert_eq!(r.active_task.as_deref(), Some("a"), "{d}");
    }

    // A good one: a module replaced, a condition on its new output (its samples only, not the
    // old module's), a module added, then a wait and a switch: every step after an edit runs as
    // the sequence was started.
    let good = r#"
[sequence]
name = "good"

[[step]]
edit = { replace = "src_b", params = ["origin=9"] }

[[step]]
wait_until = "src_b.out.origin == 9 and src_b.out.seq <= 3"
timeout = "30s"
on_timeout = "abort"

[[step]]
edit = { add = "src_x", kind = "ticker", dnm = "drive", params = ["origin=4"] }

[[step]]
wait = "1s"

[[step]]
switch = "b"
"#;
    done(&api, &upload("good", good));
    done(&api, &order("good", SequenceAction::Start));
    let q = eventually("the good sequence ends", || {
        status(&api, "good")
            .filter(|q| matches!(q.state, SequenceState::Finished | SequenceState::Aborted))
    });
    assert_eq!(q.state, SequenceState::Finished, "{:#?}", q.history);
    let met = q
        .history
        .iter()
        .find(|e| e.what == "condition_met")
        .unwrap();
    assert!(
        met.detail.contains("src_b.out.origin = 9"),
        "{}",
        met.detail
    );
    wait_in_step(&session, &rig.system, &ROVER, "b");
}
