//! Fault protection, end to end with real processes killed: the rover makes itself safe
//! whatever fails (the station with a rover computer, the station with the authority's
//! computer), safing holds (nothing taken before it runs after it), the station recovers from
//! an authority that lost its store, and stations' commands run in the order they arrived.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

mod support;

use std::sync::Mutex;
use std::time::{Duration, Instant};

use dnm_ground::CommandState;
use dnm_proto::station::RoverState;
use dnm_proto::station::{Fate, Order};
use support::ground::{Api, ROVER, Rig, report, wait_in_step};
use support::{eventually, free_port, zenoh_client};

/// One of these tests at a time: each runs a whole rover on a small machine.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

const LOSS: &str = r#"on_link_loss = { after = "2s", task = "c" }"#;

fn switch(task: &str) -> Order {
    Order::Switch {
        task: task.into(),
        at_unix_ns: None,
        late_by_ms: None,
    }
}

/// Waits until every DNM named is on `task`; returns how long that took from `since`.
fn wait_task(session: &zenoh::Session, system: &str, dnms: &[&str], task: &str) -> Duration {
    let since = Instant::now();
    eventually(&format!("DNMs {dnms:?} on `{task}`"), || {
        dnms.iter()
            .all(|d| {
                report(session, system, d).is_some_and(|r| r.active_task.as_deref() == Some(task))
            })
            .then_some(())
    });
    since.elapsed()
}

/// Switches the rover to `task` through the station and waits until every DNM is on it;
/// returns the revision.
fn command(session: &zenoh::Session, rig: &Rig, api: &Api, task: &str) -> u64 {
    let e = api.submit(&switch(task));
    assert_eq!(api.entry(e.seq, 60).state, CommandState::Applied, "{e:?}");
    wait_in_step(session, &rig.system, &ROVER, task)
}

/// The station hears the rover again and shows it safe on `c`; a command given after that
/// takes the rover out of it, for good (nothing of the safing comes back).
fn leaves_safe_on_a_new_command(session: &zenoh::Session, rig: &Rig, api: &Api) -> RoverState {
    let rover = eventually("the station sees the rover safe", || {
        let l = api.link();
        l.rover.filter(|r| l.up && r.safe)
    });
    assert_eq!(rover.task.as_deref(), Some("c"));
    command(session, rig, api, "a");
    std::thread::sleep(Duration::from_millis(1500));
    for d in ROVER {
        let r = report(session, &rig.system, d).unwrap();
        assert_eq!(r.active_task.as_deref(), Some("a"), "{d} went back to safe");
        assert_eq!(r.safed, None, "{d}");
    }
    rover
}

fn refused_reason(e: &dnm_ground::Entry) -> String {
    match &e.fate {
        Some(Fate::Refused { reason }) => reason.clone(),
        other => panic!("command {} not refused: {other:?}", e.seq),
    }
}

#[test]
fn the_station_and_a_rover_computer_die_together_and_the_others_go_safe() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fsv", LOSS);
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (station, api) = rig.station();
    let _rover = rig.up(&["rover"], false);
    let _drive = rig.up(&["drive"], false);
    let vision = rig.up(&["vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let revision = command(&session, &rig, &api, "b");

    // The station and the vision computer die together (a power cut on the ground, a crash on
    // the rover): the authority cannot reach `vision`, and safes the others without it.
    station.kill();
    vision.kill();
    let took = wait_task(&session, &rig.system, &["rover", "drive"], "c");
    eprintln!(
        "rover and drive safe {:.2} s after the failure",
        took.as_secs_f64()
    );
    let drive = report(&session, &rig.system, "drive").unwrap();
    let safed = drive.safed.expect("drive says why it is safe");
    assert_eq!(safed.task, "c");
    assert!(
        safed.epoch.is_some(),
        "drive followed the authority's safing: {safed:?}"
    );
    assert_eq!(drive.revision, revision);

    // The computer comes back: it adopts the decided state, the safe task, and nothing else.
    let _vision = rig.up(&["vision"], false);
    wait_in_step(&session, &rig.system, &ROVER, "c");
    let (_station, api) = rig.station();
    let rover = leaves_safe_on_a_new_command(&session, &rig, &api);
    let safing = rover.last_safing.unwrap();
    assert_eq!(safing.task, "c");
    // Whichever the authority noticed first: the station gone, or `vision`.
    assert!(
        safing.reason.contains("no ground station") || safing.reason.contains("DNM `vision`"),
        "{safing:?}"
    );
}

#[test]
fn the_station_and_the_authority_die_together_and_the_rover_goes_safe_by_itself() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fsa", LOSS);
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (station, api) = rig.station();
    let authority = rig.up(&["rover"], false);
    let _others = rig.up(&["drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let revision = command(&session, &rig, &api, "b");

    // The station and the authority's computer die together: nobody is left to decide, and
    // each DNM makes itself safe by its lease on the authority.
    station.kill();
    authority.kill();
    let took = wait_task(&session, &rig.system, &["drive", "vision"], "c");
    eprintln!(
        "drive and vision safe {:.2} s after the failure",
        took.as_secs_f64()
    );
    for d in ["drive", "vision"] {
        let r = report(&session, &rig.system, d).unwrap();
        let safed = r.safed.unwrap_or_else(|| panic!("{d} says why it is safe"));
        assert_eq!(safed.epoch, None, "{d} went safe on its own");
        assert!(
            safed.reason.contains("no word from the authority"),
            "{safed:?}"
        );
        assert_eq!(r.revision, revision);
        assert!(
            r.events.iter().any(|e| e.what == "safed"),
            "{d} recorded it"
        );
    }

    // The authority comes back: it adopts the rover's state, safe, and has its own DNM
    // adopt that, never the task it had decided before it died.
    let _authority = rig.up(&["rover"], false);
    wait_in_step(&session, &rig.system, &ROVER, "c");
    let (_station, api) = rig.station();
    // It adopted the DNMs' own safing, or (having heard no station since before it died)
    // made the rover safe itself at once.
    let rover = leaves_safe_on_a_new_command(&session, &rig, &api);
    assert!(
        rover.events.iter().any(|e| {
            (e.what == "safed" && e.detail.contains("made itself safe")) || e.what == "link_loss"
        }),
        "{:?}",
        rover.events
    );
}

#[test]
fn safing_holds_nothing_taken_before_it_runs_after_it() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fhold", LOSS);
    let _routers = rig.routers();
    let radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive"], false);
    let vision = rig.up(&["vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");

    // A time tag that falls due during the outage to come.
    let tag = api.submit(&Order::Switch {
        task: "b".into(),
        at_unix_ns: Some(dnm_ground::now_unix_ns() + 8_000_000_000),
        late_by_ms: None,
    });
    eventually("the tag scheduled", || {
        (api.entry(tag.seq, 0).state == CommandState::Scheduled).then_some(())
    });
    // `vision` dies: the authority holds the next commands until every DNM can take them, so
    // they are acknowledged and not run.
    vision.kill();
    let held: Vec<u64> = ["b", "a"]
        .iter()
        .map(|t| api.submit(&switch(t)).seq)
        .collect();
    for seq in &held {
        eventually("acknowledged", || {
            (api.entry(*seq, 0).state == CommandState::Acknowledged).then_some(())
        });
    }

    // The radio goes dead for longer than the loss-of-signal time.
    radio.kill();
    wait_task(&session, &rig.system, &["rover", "drive"], "c");
    // Given during the outage, before the station could see the safing.
    let blind = api.submit(&switch("b")).seq;
    // Past the tag's time.
    std::thread::sleep(Duration::from_millis(
        (tag.order_at_ns().saturating_sub(dnm_ground::now_unix_ns()) / 1_000_000) + 1000,
    ));
    let _vision = rig.up(&["vision"], false);
    let _radio = rig.linksim(&["--delay", "20ms"]);

    // Every one of them is refused, the safing named as the reason; the rover stays safe.
    for seq in [tag.seq, held[0], held[1], blind] {
        let e = eventually("the command's fate", || {
            Some(api.entry(seq, 0)).filter(|e| e.state.is_final())
        });
        assert_eq!(e.state, CommandState::Refused, "{e:?}");
        let reason = refused_reason(&e);
        assert!(reason.contains("made itself safe"), "{seq}: {reason}");
        assert!(reason.contains("on `c`"), "{seq}: {reason}");
    }
    wait_in_step(&session, &rig.system, &ROVER, "c");
    std::thread::sleep(Duration::from_secs(2));
    for d in ROVER {
        let r = report(&session, &rig.system, d).unwrap();
        assert_eq!(r.active_task.as_deref(), Some("c"), "{d} left safe");
    }
    // The station shows why; a command given after it saw the safing runs.
    leaves_safe_on_a_new_command(&session, &rig, &api);
}

/// The rover time of a time-tagged switch.
trait TagTime {
    fn order_at_ns(&self) -> u64;
}

impl TagTime for dnm_ground::Entry {
    fn order_at_ns(&self) -> u64 {
        match &self.order {
            Order::Switch {
                at_unix_ns: Some(at),
                ..
            } => *at,
            _ => 0,
        }
    }
}

#[test]
fn a_station_goes_on_after_the_authority_lost_its_store() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fstore", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let authority = rig.up(&["rover"], false);
    let _others = rig.up(&["drive", "vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    for t in ["b", "c"] {
        let e = api.submit(&switch(t));
        assert_eq!(api.entry(e.seq, 60).state, CommandState::Applied);
    }
    // A time tag far ahead: acknowledged by the rover, not final at the station.
    let tag = api.submit(&Order::Switch {
        task: "b".into(),
        at_unix_ns: Some(dnm_ground::now_unix_ns() + 600_000_000_000),
        late_by_ms: None,
    });
    eventually("the tag scheduled", || {
        (api.entry(tag.seq, 0).state == CommandState::Scheduled).then_some(())
    });

    // The authority's computer restarts with its store gone.
    authority.kill();
    let db = rig
        .dir
        .join("state")
        .join(format!("{}-authority.redb", rig.system));
    std::fs::remove_file(&db).unwrap();
    let _authority = rig.up(&["rover"], false);
    wait_in_step(&session, &rig.system, &ROVER, "c");

    // The station's later commands are applied, in order, none twice; the tag the rover
    // forgot is sent again and can still be cancelled.
    let later = ["a", "b", "a", "c"];
    let seqs: Vec<u64> = later.iter().map(|t| api.submit(&switch(t)).seq).collect();
    for seq in &seqs {
        assert_eq!(api.entry(*seq, 120).state, CommandState::Applied, "{seq}");
    }
    assert_eq!(api.entry(tag.seq, 0).state, CommandState::Scheduled);
    let cancel = api.submit(&Order::Cancel { seq: tag.seq });
    assert_eq!(api.entry(cancel.seq, 60).state, CommandState::Applied);
    assert_eq!(api.entry(tag.seq, 0).state, CommandState::Cancelled);
    let drive = report(&session, &rig.system, "drive").unwrap();
    let tail: Vec<&str> = drive
        .switches
        .iter()
        .rev()
        .take(later.len())
        .rev()
        .map(|s| s.to.as_str())
        .collect();
    assert_eq!(tail, later, "each later command switched exactly once");
}

#[test]
fn two_stations_commands_run_in_the_order_they_arrived() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("forder", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    // `zulu` sorts after `alpha`: by name it would wait for all of alpha's commands.
    let (_a, alpha) = rig.station_named("alpha", &format!("127.0.0.1:{}", free_port()));
    let (_z, zulu) = rig.station_named("zulu", &format!("127.0.0.1:{}", free_port()));
    let _rover = rig.up(&["rover", "vision"], false);
    let drive = rig.up(&["drive"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");

    // `drive` hangs: the authority takes the commands but runs none until it is back.
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(drive.pid() as i32, libc::SIGSTOP) };
    let mut given = Vec::new();
    for (i, task) in ["b", "c", "a", "b", "c", "a"].iter().enumerate() {
        let (name, api) = if i % 2 == 0 {
            ("zulu", &zulu)
        } else {
            ("alpha", &alpha)
        };
        let e = api.submit(&switch(task));
        eventually("acknowledged", || {
            (api.entry(e.seq, 0).state == CommandState::Acknowledged).then_some(())
        });
        given.push((name, e.seq));
    }
    // SAFETY: as above.
    unsafe { libc::kill(drive.pid() as i32, libc::SIGCONT) };
    let mut ran = Vec::new();
    for (name, seq) in &given {
        let api = if *name == "zulu" { &zulu } else { &alpha };
        let e = api.entry(*seq, 120);
        let Some(Fate::Applied { at_unix_ns, .. }) = e.fate else {
            panic!("{name} {seq}: {e:?}");
        };
        ran.push((at_unix_ns, *name, *seq));
    }
    let mut by_time = ran.clone();
    by_time.sort();
    assert_eq!(by_time, ran, "run in the order they arrived");
}

/// libfaketime (Debian's `faketime`), which `.ci/run` installs: it sets a process's wall clock
/// apart from the machine's.
const FAKETIME: &str = "/usr/lib/x86_64-linux-gnu/faketime/libfaketime.so.1";

#[test]
fn a_dnm_whose_clock_is_two_minutes_off_refuses_transactions_by_name() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    assert!(
        std::path::Path::new(FAKETIME).exists(),
        "{FAKETIME} missing: apt-get install faketime (.ci/run does)"
    );
    let rig = Rig::new("fclock", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "vision"], false);
    // `drive`'s computer has a wall clock two minutes behind (its monotonic clock is right).
    let drive = rig.up_env(
        &["drive"],
        false,
        &[
            ("LD_PRELOAD", FAKETIME),
            ("FAKETIME", "-120s"),
            ("FAKETIME_DONT_FAKE_MONOTONIC", "1"),
            ("FAKETIME_DONT_RESET", "1"),
        ],
    );
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let offset = eventually("drive measures its clock", || {
        report(&session, &rig.system, "drive")?
            .lease?
            .clock_offset_ms
    });
    assert!((offset - 120_000.0).abs() < 5_000.0, "offset {offset} ms");

    // Refused by name, with the offset; nothing held anywhere afterwards.
    let e = api.submit(&switch("b"));
    let e = api.entry(e.seq, 120);
    let reason = refused_reason(&e);
    assert!(reason.contains("DNM `drive`'s clock is 1"), "{reason}");
    assert!(reason.contains("behind"), "{reason}");
    for d in ROVER {
        let r = report(&session, &rig.system, d).unwrap();
        assert_eq!(r.holding, None, "{d} holds a transaction");
        assert_eq!(r.active_task.as_deref(), Some("a"));
    }
    // Its clock set right (the computer restarted with NTP), later transactions go through.
    drop(drive);
    let _drive = rig.up(&["drive"], false);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let e = api.submit(&switch("b"));
    assert_eq!(api.entry(e.seq, 120).state, CommandState::Applied);
    wait_in_step(&session, &rig.system, &ROVER, "b");
}

#[test]
fn a_dnm_an_apply_removes_stops_its_modules() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fremove", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive"], false);
    let _vision = rig.up(&["vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    // The same system without `vision` and its relay.
    let text = support::ground::text(&rig.system, "", 2)
        .replace("[[dnm]]\nname = \"vision\"\nparent = \"rover\"\n\n", "")
        .replace(
            "[[module]]\nname = \"relay\"\nkind = \"relay\"\ndnm = \"vision\"\n\n",
            "",
        )
        .replace("\"src_a.out -> relay.in\", ", "")
        .replace("\"src_b.out -> relay.in\", ", "")
        .replace(", \"relay.out -> watch.in\"", "");
    assert!(
        !text.contains("vision") && !text.contains("relay."),
        "{text}"
    );
    let e = api.submit(&Order::Apply {
        file: "without-vision.toml".into(),
        text,
    });
    assert_eq!(api.entry(e.seq, 120).state, CommandState::Applied, "{e:?}");
    let r = eventually("vision's modules stopped", || {
        report(&session, &rig.system, "vision").filter(|r| {
            r.modules
                .iter()
                .all(|m| m.state == dnm::ModuleRunState::Stopped && m.pid.is_none())
        })
    });
    assert!(
        r.events.iter().any(|e| e.what == "retired"),
        "{:?}",
        r.events
    );
    wait_in_step(&session, &rig.system, &["rover", "drive"], "a");
}

#[test]
fn a_dnm_an_aborted_apply_added_takes_the_next_apply() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fadd", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "vision"], false);
    let drive = rig.up(&["drive"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    // The system with a fourth computer, `arm`, and a module on it; the computer is up (it
    // waits for the authority) before the apply that adds it.
    let text = support::ground::text(&rig.system, "", 2).replace(
        "[[module]]\nname = \"src_a\"",
        "[[dnm]]\nname = \"arm\"\nparent = \"rover\"\n\n[[module]]\nname = \"src_c\"\nkind = \"ticker\"\ndnm = \"arm\"\nrate_hz = 20\n\n[[module]]\nname = \"src_a\"",
    );
    assert!(text.contains("name = \"arm\""), "{text}");
    let with_arm = rig.dir.join("with-arm.toml");
    std::fs::write(&with_arm, &text).unwrap();
    let _arm = rig.up_from(&with_arm, &["arm"], false, &[]);
    eventually("arm up", || report(&session, &rig.system, "arm"));

    // `drive` hangs through the apply: it is aborted everywhere, `arm` included.
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(drive.pid() as i32, libc::SIGSTOP) };
    let e = api.submit(&Order::Apply {
        file: "with-arm.toml".into(),
        text: text.clone(),
    });
    let e = api.entry(e.seq, 120);
    let reason = refused_reason(&e);
    assert!(reason.contains("drive"), "{reason}");
    // SAFETY: as above.
    unsafe { libc::kill(drive.pid() as i32, libc::SIGCONT) };
    eventually("arm holds nothing", || {
        report(&session, &rig.system, "arm").filter(|r| r.holding.is_none())
    });
    // `drive`, stopped for longer than its Zenoh lease, may need a moment to be back on the
    // network: the next apply is for a rover whose computers all answer.
    eventually("drive answers again", || {
        report(&session, &rig.system, "drive").filter(|r| r.holding.is_none())
    });

    // The next apply takes `arm` in like any DNM.
    let e = api.submit(&Order::Apply {
        file: "with-arm.toml".into(),
        text,
    });
    let e = api.entry(e.seq, 120);
    assert_eq!(e.state, CommandState::Applied, "{:?}", e.fate);
    wait_in_step(
        &session,
        &rig.system,
        &["rover", "drive", "vision", "arm"],
        "a",
    );
    let arm = report(&session, &rig.system, "arm").unwrap();
    assert_eq!(arm.modules.len(), 1);
    assert_eq!(arm.modules[0].name, "src_c");
}

#[test]
fn a_computer_that_comes_up_late_does_not_make_a_starting_rover_safe() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("flate", LOSS);
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive"], false);
    let session = zenoh_client(rig.rover_port);
    eventually("the authority decides its first revision", || {
        report(&session, &rig.system, "drive").filter(|r| r.revision > 0)
    });
    // `vision` boots twice the loss-of-signal time after the others: a rover starting up
    // waits for it.
    std::thread::sleep(Duration::from_secs(4));
    let _vision = rig.up(&["vision"], false);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    for d in ROVER {
        let r = report(&session, &rig.system, d).unwrap();
        assert_eq!(r.safed, None, "{d} is not safe");
    }
    let rover = eventually("the station hears the rover", || api.link().rover);
    assert!(!rover.safe, "{:?}", rover.last_safing);
}

#[test]
fn a_rover_computer_that_stops_answering_makes_the_rover_safe_with_the_station_in_contact() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("fhang", LOSS);
    let _routers = rig.routers();
    let _radio = rig.linksim(&["--delay", "20ms"]);
    let (_station, api) = rig.station();
    let _rover = rig.up(&["rover", "drive"], false);
    let vision = rig.up(&["vision"], false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    command(&session, &rig, &api, "b");

    // `vision` hangs (alive, cut off): it makes itself safe by its lease, and the others must
    // not go on without it.
    // SAFETY: kill(2) on our own child.
    unsafe { libc::kill(vision.pid() as i32, libc::SIGSTOP) };
    wait_task(&session, &rig.system, &["rover", "drive"], "c");
    let rover = eventually("the station sees why", || {
        api.link().rover.filter(|r| r.safe)
    });
    let safing = rover.last_safing.unwrap();
    assert!(
        safing.reason.contains("DNM `vision` has not answered"),
        "{safing:?}"
    );
    // SAFETY: as above.
    unsafe { libc::kill(vision.pid() as i32, libc::SIGCONT) };
    wait_in_step(&session, &rig.system, &ROVER, "c");
    leaves_safe_on_a_new_command(&session, &rig, &api);
}

#[test]
fn the_authority_does_not_start_without_a_lasting_folder_for_its_store() {
    let rig = Rig::new("fnostate", "");
    // No --state-dir, no $DNM_STATE_DIR, $XDG_STATE_HOME or $HOME: it would be the temporary
    // directory, lost at a reboot.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_dnm"))
        .env_clear()
        .env("PATH", std::env::var_os("PATH").unwrap_or_default())
        .env("DNM_MODULE_HOST", support::system::module_host())
        .args(["--no-multicast", "up"])
        .arg(&rig.netlist)
        .args(["--dnm", "rover", "--no-record"])
        .output()
        .unwrap();
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no folder for durable state"), "{err}");
}
