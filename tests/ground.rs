//! The ground station and the rover's authority, end to end with real processes: commands
//! through an emulated radio link (delay, bandwidth, loss, outages), the ground station and the
//! authority killed mid-run, loss of signal, bad commands.
#![allow(clippy::unwrap_used, clippy::expect_used)] // tests: failing loudly is right

mod support;

use std::sync::Mutex;
use std::time::Duration;

use dnm_ground::CommandState;
use dnm_ground::Entry;
use dnm_proto::station::{Fate, ModuleEdit, Order};
use support::ground::{Poller, ROVER, Rig, TASKS, report, slot, text, wait_in_step};
use support::{eventually, eventually_within, zenoh_client};

/// One of these tests at a time: each runs a whole rover on a small machine.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

#[test]
fn a_hundred_commands_over_a_bad_radio_apply_once_in_order_on_every_dnm() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("hundred", "");
    let _routers = rig.routers();
    let mut authority = Some(rig.up(&["rover"], false));
    let _others = rig.up(&["drive", "vision"], false);
    // 300 ms each way, 256 kbit/s, a fifth of the packets lost each way, 10 s out every 30 s.
    let _radio = rig.linksim(&[
        "--delay", "300ms", "--rate", "256kbit", "--loss", "0.2", "--outage", "10s/30s", "--seed",
        "7",
    ]);
    let _ground_dnm = rig.up(&["ground"], true);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let poller = Poller::start(&rig.system, &ROVER);
    let (station, api) = rig.station();
    let mut station = Some(station);

    let mut sent = Vec::new();
    let mut cancelled_target = None;
    // When the authority was down and catching up (wall clock, ns).
    let mut restart = (0u64, 0u64);
    for i in 0..100u64 {
        let order = match i {
            // A time tag far enough ahead to be cancelled, and its cancel.
            58 => Order::Switch {
                task: "b".into(),
                // Far enough ahead that its cancel arrives first, whatever the radio does.
                at_unix_ns: Some(dnm_ground::now_unix_ns() + 300_000_000_000),
                late_by_ms: None,
            },
            60 => Order::Cancel {
                seq: cancelled_target.unwrap(),
            },
            _ if i % 10 == 3 => {
                let origin = 2 + (i / 10) % 2 * 5;
                Order::Apply {
                    file: format!("variant-{origin}.toml"),
                    text: text(&rig.system, "", origin as u32),
                }
            }
            _ if i % 10 == 7 => Order::Module {
                edit: ModuleEdit::Replace {
                    name: "src_a".into(),
                    kind: None,
                    params: vec![format!("origin={}", 10 + i)],
                },
            },
            _ if i % 10 == 5 => Order::Switch {
                task: TASKS[(i as usize / 10) % 3].into(),
                at_unix_ns: Some(dnm_ground::now_unix_ns() + 2_000_000_000 + i * 30_000_000),
                late_by_ms: None,
            },
            _ => Order::Switch {
                task: TASKS[i as usize % 3].into(),
                at_unix_ns: None,
                late_by_ms: None,
            },
        };
        let e = api.submit(&order);
        assert_eq!(e.seq, i + 1);
        if i == 58 {
            cancelled_target = Some(e.seq);
        }
        sent.push(order);
        if i == 30 {
            // The ground station dies (power cut) and comes back: its outbox is on disk.
            station.take().unwrap().kill();
            let (p, _) = rig.station();
            station = Some(p);
        }
        if i == 70 {
            // The authority dies with its DNM, mid-run, and comes back.
            restart.0 = dnm_ground::now_unix_ns();
            poller.set_down("rover", true);
            authority.take().unwrap().kill();
            std::thread::sleep(Duration::from_secs(1));
            let p = rig.up(&["rover"], false);
            let pid = p.pid();
            authority = Some(p);
            eventually("the authority's DNM back", || {
                report(&session, &rig.system, "rover").filter(|r| r.pid == pid)
            });
            poller.set_down("rover", false);
            restart.1 = dnm_ground::now_unix_ns();
        }
        std::thread::sleep(Duration::from_millis(350));
    }
    let entries = api.all_final();
    let (seen, splits) = poller.finish();
    assert_eq!(entries.len(), 100);
    // A page polling the outbox gets the last few, in order, as the whole list has them.
    let last: Vec<Entry> =
        serde_json::from_value(api.get_json("/commands?since=40&last=3&brief")).unwrap();
    let seqs: Vec<u64> = last.iter().map(|e| e.seq).collect();
    assert_eq!(seqs, [98, 99, 100]);
    let early: Vec<Entry> =
        serde_json::from_value(api.get_json("/commands?since=99&last=30")).unwrap();
    assert_eq!(early.iter().map(|e| e.seq).collect::<Vec<_>>(), [99, 100]);

    // Every command has the fate it should: applied, or the cancel and what it cancelled.
    let mut decided: Vec<(u64, u64, String)> = Vec::new();
    for e in &entries {
        match &e.fate {
            Some(Fate::Applied {
                revision,
                task,
                at_unix_ns,
            }) => decided.push((*at_unix_ns, *revision, task.clone().unwrap())),
            Some(Fate::CancelledBy { by }) => {
                assert_eq!((e.seq, *by), (59, 61), "{e:?}");
            }
            Some(Fate::Cancelled { target }) => assert_eq!((e.seq, *target), (61, 59)),
            other => panic!("command {} ended {other:?}: {e:?}", e.seq),
        }
    }
    // A time tag the rover held before its time ran at exactly that rover time (unless it fell
    // due while the authority was restarting and its DNMs catching up).
    let mut on_time = 0;
    for e in &entries {
        if let (
            Order::Switch {
                at_unix_ns: Some(tag),
                ..
            },
            Some(Fate::Applied { at_unix_ns, .. }),
            Some(acked),
        ) = (&e.order, &e.fate, e.acknowledged_unix_ns)
            && acked + 500_000_000 < *tag
            && !(restart.0..restart.1 + 10_000_000_000).contains(tag)
        {
            assert_eq!(at_unix_ns, tag, "{e:?}");
            on_time += 1;
        }
    }
    println!("{on_time} time-tagged switches held by the rover ran at their tag");
    // In the station's order (time tags run at their time).
    let immediate: Vec<(u64, u64)> = entries
        .iter()
        .filter(|e| {
            !matches!(
                e.order,
                Order::Switch {
                    at_unix_ns: Some(_),
                    ..
                } | Order::Cancel { .. }
            )
        })
        .filter_map(|e| match e.fate {
            Some(Fate::Applied {
                revision,
                at_unix_ns,
                ..
            }) => Some((at_unix_ns, revision)),
            _ => None,
        })
        .collect();
    assert!(
        immediate
            .windows(2)
            .all(|w| w[0].0 < w[1].0 && w[0].1 <= w[1].1),
        "{immediate:?}"
    );

    // What every rover DNM went through is exactly what was decided, in order, once each.
    decided.sort();
    // Revision 1 in task `a` is where the authority started; each decision after it.
    let mut expected: Vec<(u64, u16)> = vec![(1, 0)];
    for (_, rev, task) in &decided {
        let s = (*rev, slot(task));
        if expected.last() != Some(&s) {
            expected.push(s);
        }
    }
    for d in ROVER {
        let states: Vec<(u64, u16)> = seen[d].states.iter().map(|s| (s.0, s.1)).collect();
        if d == "rover" {
            // It died once: what it went through is a part of the decisions, in order.
            let mut it = expected.iter();
            for s in &states {
                assert!(
                    it.any(|w| w == s),
                    "{d} went to {s:?}, not next in {expected:?}"
                );
            }
        } else {
            assert_eq!(states, expected, "{d}");
        }
    }

    // Never two rover DNMs on different revisions or tasks, except at a commanded instant.
    let worst = splits.iter().map(|s| s.since_switch_ns).max().unwrap_or(0);
    println!(
        "{} samples with DNMs apart, the longest {:.2} ms after a switch",
        splits.len(),
        worst as f64 / 1e6
    );
    let late: Vec<_> = splits
        .iter()
        .filter(|s| s.since_switch_ns > 20_000_000)
        .collect();
    assert!(late.is_empty(), "DNMs apart outside a switch: {late:?}");

    // The ground's DNM follows across the radio (asked on the ground's side, as an operator
    // would). This link can stall for over a minute: a segment lost again and again while
    // TCP's retransmission timeout doubles across outages, or a session whose lease ran out
    // being set up again, so the hang guard is generous.
    let last = decided.last().unwrap();
    let ground = zenoh_client(rig.ground_port);
    let since = std::time::Instant::now();
    eventually_within("the ground's DNM follows", Duration::from_secs(300), || {
        report(&ground, &rig.system, "ground")
            .filter(|r| r.revision == last.1 && r.active_task.as_deref() == Some(&last.2))
    });
    println!(
        "the ground's DNM in step {:.1} s after every command was final",
        since.elapsed().as_secs_f64()
    );
    drop(authority);
}

#[test]
fn the_rover_goes_safe_when_the_ground_is_lost_and_the_station_shows_it() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("los", r#"on_link_loss = { after = "2s", task = "c" }"#);
    let _routers = rig.routers();
    let radio = rig.linksim(&["--delay", "50ms"]);
    // The station is heard from the start (else the rover would go safe 2 s after it starts).
    let (_station, api) = rig.station();
    let _rover = rig.up(&ROVER, false);
    let session = zenoh_client(rig.rover_port);
    wait_in_step(&session, &rig.system, &ROVER, "a");
    let e = api.submit(&Order::Switch {
        task: "b".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    assert_eq!(api.entry(e.seq, 60).state, CommandState::Applied);
    wait_in_step(&session, &rig.system, &ROVER, "b");

    // The radio goes dead: the rover stops on its own, every DNM together.
    radio.kill();
    let cut = std::time::Instant::now();
    let revision = wait_in_step(&session, &rig.system, &ROVER, "c");
    assert!(
        cut.elapsed() >= Duration::from_secs(2),
        "switched before the deadline"
    );
    eventually("the station sees the link down", || {
        (!api.link().up).then_some(())
    });

    // The radio comes back: the station shows what the rover did, and why.
    let _radio = rig.linksim(&["--delay", "50ms"]);
    let rover = eventually("the station hears the rover again", || {
        let l = api.link();
        l.rover
            .filter(|r| l.up && r.events.iter().any(|e| e.what == "link_back"))
    });
    assert_eq!(rover.task.as_deref(), Some("c"));
    assert_eq!(rover.revision, revision);
    let loss = rover.events.iter().find(|e| e.what == "link_loss").unwrap();
    assert!(loss.detail.contains("switching to `c`"), "{loss:?}");
    assert_eq!(loss.task.as_deref(), Some("c"));
    // The rover stays safe until an operator says otherwise.
    std::thread::sleep(Duration::from_secs(1));
    wait_in_step(&session, &rig.system, &ROVER, "c");
}

#[test]
fn bad_commands_are_refused_with_their_reason_and_change_nothing() {
    use zenoh::Wait;
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("bad", "");
    let _routers = rig.routers();
    let _radio = rig.linksim(&[]);
    let _rover = rig.up(&ROVER, false);
    let session = zenoh_client(rig.rover_port);
    let revision = wait_in_step(&session, &rig.system, &ROVER, "a");
    let running = |session: &zenoh::Session| {
        ROVER
            .iter()
            .map(|d| {
                let r = report(session, &rig.system, d).unwrap();
                let pids: Vec<Option<u32>> = r.modules.iter().map(|m| m.pid).collect();
                (r.revision, r.active_task, r.netlist_digest, pids)
            })
            .collect::<Vec<_>>()
    };
    let before = running(&session);
    let (station, api) = rig.station();

    // The netlists among them come in through the authority's `NetlistDoor::accept`
    // (`dnm/netlist/src/door.rs`), as every netlist from outside does.
    let bad = [
        (
            Order::Switch {
                task: "nope".into(),
                at_unix_ns: None,
                late_by_ms: None,
            },
            "unknown task `nope`; the tasks are a, b, c",
        ),
        (
            Order::Apply {
                file: "broken.toml".into(),
                text: text(&rig.system, "", 2).replace("kind = \"pair\"", "kind = \"pear\""),
            },
            "netlist refused, nothing changed",
        ),
        (
            Order::Apply {
                file: "other.toml".into(),
                text: text("elsewhere", "", 2),
            },
            "netlist is for system `elsewhere`",
        ),
        (
            Order::Module {
                edit: ModuleEdit::Replace {
                    name: "ghost".into(),
                    kind: None,
                    params: vec![],
                },
            },
            "no module `ghost`",
        ),
        (
            Order::Module {
                edit: ModuleEdit::Replace {
                    name: "src_a".into(),
                    kind: Some("no_such_kind".into()),
                    params: vec![],
                },
            },
            "would not validate",
        ),
        (Order::Cancel { seq: 1 }, "nothing to cancel"),
        (Order::Cancel { seq: 99 }, "comes after this cancel"),
    ];
    for (order, why) in &bad {
        let e = api.submit(order);
        let done = api.entry(e.seq, 120);
        match &done.fate {
            Some(Fate::Refused { reason }) => assert!(reason.contains(why), "{reason}"),
            other => panic!("{order:?} ended {other:?}"),
        }
    }
    // Malformed input from the operator or the network is refused at the door.
    let (status, body) = api.post_raw(b"{not json");
    assert_eq!(status, 400, "{body}");
    assert!(
        body["error"]
            .as_str()
            .unwrap()
            .contains("unreadable command"),
        "{body}"
    );
    let (status, body) = api.post_raw(br#"{"cmd":"switch"}"#);
    assert_eq!(status, 400, "{body}");
    let reply_as = |station: &str, payload: &[u8]| -> dnm_proto::station::Downlink {
        let replies = session
            .get(dnm_proto::keys::authority_station(&rig.system, station))
            .payload(payload.to_vec())
            .timeout(Duration::from_secs(10))
            .wait()
            .unwrap();
        let r = replies.recv().unwrap();
        serde_json::from_slice(&r.result().unwrap().payload().to_bytes()).unwrap()
    };
    let reply = |payload: &[u8]| reply_as("late", payload);
    let d = reply(b"\xff garbage");
    assert!(d.error.unwrap().contains("unreadable uplink"));
    let d = reply(br#"{"station":"a/b","commands":[]}"#);
    assert!(d.error.unwrap().contains("not usable"));
    let gap = dnm_proto::station::Uplink {
        station: "late".into(),
        commands: vec![dnm_proto::station::Sent {
            seq: 5,
            id: "late-5".into(),
            order: Order::Switch {
                task: "b".into(),
                at_unix_ns: None,
                late_by_ms: None,
            },
            safings_seen: 0,
            given_unix_ns: None,
        }],
        pending_from: 1,
        waiting: vec![],
        sequence_events: Default::default(),
    };
    let d = reply(&serde_json::to_vec(&gap).unwrap());
    assert_eq!(d.outcomes[0].fate, Fate::OutOfOrder { expected: 1 });
    // A station speaks only for itself: the name in its uplink is the one in its key.
    let d = reply_as("ground-1", &serde_json::to_vec(&gap).unwrap());
    assert!(
        d.error.as_deref().unwrap().contains("a station sends on"),
        "{:?}",
        d.error
    );
    assert!(d.outcomes.is_empty());

    // Nothing running changed: same revision, task, netlist, processes.
    assert_eq!(running(&session), before);
    assert_eq!(before[0].0, revision);

    // A cancel of a command that already ran is refused too, and says when it ran.
    let e = api.submit(&Order::Switch {
        task: "b".into(),
        at_unix_ns: None,
        late_by_ms: None,
    });
    assert_eq!(api.entry(e.seq, 120).state, CommandState::Applied);
    let c = api.submit(&Order::Cancel { seq: e.seq });
    match api.entry(c.seq, 120).fate {
        Some(Fate::Refused { reason }) => assert!(reason.contains("already ran"), "{reason}"),
        other => panic!("{other:?}"),
    }

    // The refusals are stored with the commands: a restarted station still shows them.
    station.kill();
    let (_station, api) = rig.station();
    let entries = api.entries();
    assert_eq!(entries.len(), bad.len() + 2);
    for (e, (_, why)) in entries.iter().zip(&bad) {
        match &e.fate {
            Some(Fate::Refused { reason }) => assert!(reason.contains(why), "{reason}"),
            other => panic!("{other:?}"),
        }
    }
    exit_codes_tell_the_fate(&api);
}

/// `dnm ground ... --wait N` exits with the fate it waited for: 0 applied, 3 refused (the
/// reason printed), 4 not final within N seconds (the state printed).
fn exit_codes_tell_the_fate(api: &support::ground::Api) {
    let run = |args: &[&str]| {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_dnm"))
            .arg("ground")
            .args(args)
            .args(["--url", &api.0])
            .output()
            .unwrap();
        let text = format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        (out.status.code(), text)
    };
    let (code, out) = run(&["switch", "nope", "--wait", "120"]);
    assert_eq!(code, Some(3), "{out}");
    assert!(out.contains("refused: unknown task `nope`"), "{out}");
    let (code, out) = run(&["switch", "c", "--wait", "120"]);
    assert_eq!(code, Some(0), "{out}");
    assert!(out.contains("applied: revision"), "{out}");
    let (code, out) = run(&["switch", "a", "--at", "+1h", "--wait", "1"]);
    assert_eq!(code, Some(4), "{out}");
    assert!(out.contains("not final after 1 s: still"), "{out}");
}

/// The messages of `topic` in the MCAP files under `dir`: (log time, sequence, bytes), by time.
fn recorded(dir: &std::path::Path, topic: &str) -> Vec<(u64, u32, Vec<u8>)> {
    let mut out = Vec::new();
    for f in support::mcap_files(dir) {
        let bytes = std::fs::read(&f).unwrap();
        // Files still being written end with their last whole chunk.
        for m in dnm_record::messages(&bytes).map_while(Result::ok) {
            if m.channel.topic == topic {
                out.push((m.log_time, m.sequence, m.data.into_owned()));
            }
        }
    }
    out.sort();
    out.dedup();
    out
}

#[test]
fn the_ground_keeps_its_own_record_of_beetle_one_through_loss_a_minute_long_outage_and_a_restart() {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner());
    let rig = Rig::new("downlink", "");
    // Beetle-One, with its downlink plan: the pose twice a second, the battery each second.
    let beetle = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/beetle.toml"),
    )
    .unwrap()
    .replace("name = \"beetle\"", &format!("name = \"{}\"", rig.system));
    std::fs::write(&rig.netlist, beetle).unwrap();
    let _routers = rig.routers();
    // What the station fills in, as a monitor on the ground hears it: (send time, x).
    let filled = std::sync::Arc::new(std::sync::Mutex::new(Vec::<(u64, f64)>::new()));
    let listener = support::zenoh_client(rig.ground_port);
    let _filled_sub = {
        use zenoh::Wait;
        let filled = filled.clone();
        listener
            .declare_subscriber(dnm_proto::keys::ground_filled(
                &rig.system,
                "rover",
                "odometry",
                "odom",
            ))
            .callback(move |s| {
                let t = s
                    .attachment()
                    .and_then(|a| dnm_proto::keys::decode_downlink(&a.to_bytes()))
                    .map(|(t, _)| t);
                let v: Option<serde_json::Value> =
                    serde_json::from_slice(&s.payload().to_bytes()).ok();
                if let (Some(t), Some(x)) = (t, v.and_then(|v| v["x"].as_f64())) {
                    filled.lock().unwrap().push((t, x));
                }
            })
            .wait()
            .unwrap()
    };
    let rover_rec = rig.dir.join("rover-rec");
    // Recording only what the plan downlinks (the camera's frames would only slow the test).
    let only = ["--record-only", "odometry", "--record-only", "battery"];
    let _rover = rig.up_recording(&ROVER, &rover_rec, &only);
    // A fifth of the packets lost each way, and the link down for a minute (30 s to 90 s).
    let _radio = rig.linksim(&[
        "--delay", "100ms", "--loss", "0.2", "--outage", "60s/90s", "--seed", "3",
    ]);
    let start = std::time::Instant::now();
    let start_unix = dnm_ground::now_unix_ns();
    // The operator's side: the joystick drives the rover across the radio.
    let _ground_dnm = rig.up(&["ground"], true);
    // Each outage leaves a minute to fill in within the next half minute of link, beside what
    // goes live: a budget with room for it (the benchmark holds the downlink to its budget).
    let budget = ["--downlink-budget", "128kbit"];
    let (station, _api) = rig.station_with(&budget);
    // The station dies in the outage and comes back: it resumes its session, and gets the
    // minute it missed from the rover's recording once the link is back.
    std::thread::sleep(Duration::from_secs(50).saturating_sub(start.elapsed()));
    station.kill();
    std::thread::sleep(Duration::from_secs(10));
    let (_station, api) = rig.station_with(&budget);
    // Just past the outage: everything up to its end is asked for, and must arrive.
    std::thread::sleep(Duration::from_secs(93).saturating_sub(start.elapsed()));
    let cut = dnm_ground::now_unix_ns() - 2_000_000_000;

    let ground = rig.dir.join(format!("{}-ground-1-record", rig.system));
    for (topic, rate_hz) in [("/rover/odometry/odom", 2.0), ("/rover/battery/state", 1.0)] {
        // What the plan asks for: the rover's recording, decimated as the rover decimates.
        let mut d = dnm_netlist::Decimator::new((1e9 / rate_hz) as u64);
        let all = recorded(&rover_rec, topic);
        let rover: Vec<_> = all
            .iter()
            .filter(|(t, _, _)| d.keep(*t))
            .filter(|(t, _, _)| *t <= cut)
            .cloned()
            .collect();
        // The rover recorded from before the outage and through it (however long a loaded
        // machine took to start it).
        let s = |secs: u64| start_unix + secs * 1_000_000_000;
        let before = rover.first().is_some_and(|r| r.0 < s(30));
        let through = rover.iter().filter(|r| r.0 > s(35) && r.0 < s(85)).count();
        assert!(
            before && through as f64 >= rate_hz * 45.0,
            "{topic}: the rover's recording does not cover the outage: {} planned samples, \
             the first {} s after the start, {through} in the outage",
            rover.len(),
            rover
                .first()
                .map_or(-1.0, |r| (r.0 as f64 - start_unix as f64) / 1e9)
        );
        // Everything the ground holds is the rover's, byte for byte; it holds at least 99 %
        // of what the plan asks for over the whole run, the outage included.
        // (The link is up a third of the time: the guard is on progress, over two of its
        // periods, not on the total time a loaded machine takes.)
        let held = support::eventually_progressing(
            "the ground caught up",
            Duration::from_secs(200),
            || {
                let ground = recorded(&ground, topic);
                // (What the rover sent since its recording was read is not checked.)
                for g in ground.iter().filter(|g| g.0 <= cut) {
                    assert!(
                        all.contains(g),
                        "{topic}: the ground holds what the rover never sent: {:?}",
                        (g.0, g.1)
                    );
                }
                let held = rover.iter().filter(|r| ground.contains(r)).count();
                if held as f64 >= 0.99 * rover.len() as f64 {
                    Ok(held)
                } else {
                    let missing: Vec<f64> = rover
                        .iter()
                        .filter(|r| !ground.contains(r))
                        .map(|r| (r.0 as f64 - start_unix as f64) / 1e9)
                        .collect();
                    Err((
                        held as u64,
                        format!(
                            "{topic}: the ground holds {held} of {} planned samples; missing at \
                             {:.1?} s after the start",
                            rover.len(),
                            &missing[..missing.len().min(40)]
                        ),
                    ))
                }
            },
        );
        println!(
            "{topic}: the ground holds {held} of {} planned samples",
            rover.len()
        );
    }
    // What was filled in was told to the ground's monitors, decoded, at its send time: the
    // pose of the rover's recording at that time.
    let told = filled.lock().unwrap().clone();
    assert!(told.len() >= 60, "{} filled-in poses told", told.len());
    let odom = recorded(&rover_rec, "/rover/odometry/odom");
    for (t, _) in &told {
        assert!(
            odom.iter().any(|(r, _, _)| r == t),
            "a pose told at {t} the rover never recorded"
        );
    }
    // The station's page shows the minute filled in from the rover's recording.
    let b = support::webdriver::Browser::start(&rig.dir, 1500, 900);
    b.goto(&format!("{}/#connections", api.0));
    // (The link goes down again every 90 s: a later outage may show as a gap meanwhile.)
    let shown = "(() => { const r = document.querySelector('#record tbody tr[data-topic=\"/rover/odometry/odom\"]'); \
                 return r && r.querySelectorAll('rect.tl-back').length > 0 \
                   && document.querySelectorAll('#record tbody tr').length >= 4; })()";
    support::eventually("the record panel showing the outage filled in", || {
        b.js(&format!("return {shown};"), serde_json::json!([]))
            .as_bool()
            .filter(|ok| *ok)
    });
    b.js(
        "document.querySelector('footer').style.maxHeight = '70vh'; \
         document.querySelector('#record-panel').scrollIntoView(); return true;",
        serde_json::json!([]),
    );
    let shots = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("web");
    std::fs::create_dir_all(&shots).unwrap();
    b.screenshot_element("#record-panel", &shots.join("record-outage.png"));
    // The station says how complete its copy is...
    let status: serde_json::Value = api.get_json("/downlink");
    let channels = status["channels"].as_array().unwrap();
    let odom = channels
        .iter()
        .find(|c| c["topic"] == "/rover/odometry/odom")
        .unwrap();
    assert_eq!(odom["dnm"], "rover", "{status}");
    // The station sees no gap up to the first outage's end: any gap left is a later
    // outage's. (A port's `/raw` twin takes its turn with it, and may wait for the next pass.)
    support::eventually("no gap before the first outage's end", || {
        let status: serde_json::Value = api.get_json("/downlink");
        status["channels"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| {
                c["topic"] == "/rover/odometry/odom" || c["topic"] == "/rover/battery/state"
            })
            .all(|c| c["oldest_gap"]["from_ns"].as_u64().is_none_or(|f| f > cut))
            .then_some(())
    });
    assert!(odom["received"].as_u64().unwrap() >= 160, "{status}");
    assert_eq!(status["budget_bytes_per_s"], 16000, "{status}");
    assert!(
        status["request_bytes"].as_u64().unwrap() >= 1024,
        "{status}"
    );
    // ...and its session reads like a rover's.
    let stats = std::process::Command::new(env!("CARGO_BIN_EXE_dnm"))
        .arg("stats")
        .arg(&ground)
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&stats.stdout);
    assert!(
        stats.status.success(),
        "{out}{}",
        String::from_utf8_lossy(&stats.stderr)
    );
    assert!(
        out.contains("/rover/odometry/odom") && out.contains("/rover/battery/state"),
        "{out}"
    );
    // Its channels are the rover's own: the same standard ROS 2 schemas and encodings, as
    // robotics tools (Rerun, Foxglove) read them in a rover's session.
    let channel_of = |dir: &std::path::Path, topic: &str| {
        support::mcap_files(dir).iter().find_map(|f| {
            let bytes = std::fs::read(f).unwrap();
            dnm_record::messages(&bytes)
                .map_while(Result::ok)
                .find(|m| m.channel.topic == topic)
                .map(|m| {
                    let s = m.channel.schema.as_ref().unwrap();
                    let meta = m.channel.metadata.clone();
                    let theirs = |k: &String| !k.starts_with("dnm.downlink.");
                    (
                        s.name.clone(),
                        s.encoding.clone(),
                        s.data.to_vec(),
                        m.channel.message_encoding.clone(),
                        meta.into_iter()
                            .filter(|(k, _)| theirs(k))
                            .collect::<Vec<_>>(),
                    )
                })
        })
    };
    for topic in ["/rover/odometry/odom", "/rover/battery/state"] {
        let (g, r) = (channel_of(&ground, topic), channel_of(&rover_rec, topic));
        assert!(g.is_some() && g == r, "{topic}: {g:?} against {r:?}");
    }
    assert_eq!(
        channel_of(&ground, "/rover/odometry/odom").unwrap().0,
        "nav_msgs/msg/Odometry"
    );
    // Like a rover's session, it keeps the netlist in force (what a replay needs).
    let netlists: Vec<String> = support::mcap_files(&ground)
        .iter()
        .flat_map(|f| {
            let bytes = std::fs::read(f).unwrap();
            let options = enumset::enum_set!(mcap::read::Options::IgnoreEndMagic);
            mcap::read::LinearReader::new_with_options(&bytes, options)
                .unwrap()
                .map_while(Result::ok)
                .filter_map(|r| match r {
                    mcap::records::Record::Attachment { header, data, .. }
                        if header.name.starts_with("netlist-r") =>
                    {
                        Some(String::from_utf8_lossy(&data).into_owned())
                    }
                    _ => None,
                })
                .collect::<Vec<_>>()
        })
        .collect();
    assert!(
        netlists.iter().any(|n| n.contains("[[downlink]]")),
        "no netlist in the ground's session: {netlists:?}"
    );
}
