//! The connection layer when things go wrong, with real processes and real shared memory: a
//! failed apply, a source that went quiet, a hung module, a slow apply beside an emergency
//! switch, a removed module, a recorder that lost its disk, a service (a module's, the DNM's
//! task board) a killed process left half-created.

#![allow(clippy::unwrap_used)] // test helpers: failing loudly is right

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use dnm::admin::Request;
use dnm::{DnmReport, ModuleRunState};
use dnm_module::msg::Tick;

mod support;

use support::system::{System, collect, drain, module_host};

const CHAIN: &str = r#"
[system]
name = "SYSTEM"
default_task = "a"

[[dnm]]
name = "main"

[[module]]
name = "src_a"
kind = "ticker"
rate_hz = 100
params = { origin = 1 }

[[module]]
name = "src_b"
kind = "ticker"
rate_hz = 100
restart = "never"
params = { origin = 2 }

[[module]]
name = "relay"
kind = "relay"
restart = "always"

[task.a]
links = ["src_a.out -> relay.in"]

[task.b]
links = ["src_b.out -> relay.in"]
"#;

fn module<'a>(r: &'a DnmReport, name: &str) -> &'a dnm::ModuleReport {
    r.modules
        .iter()
        .find(|m| m.name == name)
        .unwrap_or_else(|| panic!("no module {name} in {:?}", r.modules))
}

fn signal(pid: u32, sig: i32) {
    // SAFETY: kill(2) on a module process of our test system.
    assert_eq!(unsafe { libc::kill(pid as i32, sig) }, 0);
}

/// Processes of `system` running module `name` (read from /proc, so nothing the DNM says).
fn processes_of(system: &str, name: &str) -> Vec<u32> {
    let needle = format!("\"module\":\"{name}\"");
    let system = format!("\"system\":\"{system}\"");
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|pid| {
            std::fs::read(format!("/proc/{pid}/cmdline")).is_ok_and(|c| {
                let c = String::from_utf8_lossy(&c);
                c.contains(&needle) && c.contains(&system)
            })
        })
        .collect()
}

/// A module executable for tests: describes itself as a ticker of kind `kind`; runs as the
/// built-in ticker once `fixed` exists in its folder, after sleeping `delay_s`; until then
/// it exits with status 3 as soon as it starts.
fn fake_ticker(dir: &Path, kind: &str, delay_s: u32) -> PathBuf {
    let out = Command::new(module_host())
        .arg("describe")
        .output()
        .unwrap();
    let mut kinds: Vec<serde_json::Value> = serde_json::from_slice(&out.stdout).unwrap();
    let mut ticker = kinds.drain(..).find(|k| k["name"] == "ticker").unwrap();
    ticker["name"] = kind.into();
    let spec = dir.join(format!("{kind}.json"));
    std::fs::write(&spec, serde_json::to_vec(&ticker).unwrap()).unwrap();
    let exe = dir.join(kind);
    std::fs::write(
        &exe,
        format!(
            "#!/bin/sh\n\
             if [ \"$1\" = describe ]; then cat '{spec}'; exit 0; fi\n\
             [ -e '{fixed}' ] || exit 3\n\
             sleep {delay_s}\n\
             exec '{host}' run \"$(echo \"$2\" | sed 's/\"kind\":\"{kind}\"/\"kind\":\"ticker\"/')\"\n",
            spec = spec.display(),
            fixed = dir.join("fixed").display(),
            host = module_host().display(),
        ),
    )
    .unwrap();
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).unwrap();
    exe
}

/// [`CHAIN`] with ticker `module` of kind `kind`, run by executable `exe`.
fn chain_with(module: &str, kind: &str, exe: &Path) -> String {
    CHAIN.replace(
        &format!("name = \"{module}\"\nkind = \"ticker\""),
        &format!("name = \"{module}\"\nkind = \"{kind}\""),
    ) + &format!("\n[kind.{kind}]\nexec = \"{}\"\n", exe.display())
}

fn apply(sys: &System, text: &str, file: &str) -> std::process::Output {
    let path = sys.dir.join(file);
    std::fs::write(&path, text.replace("SYSTEM", &sys.name)).unwrap();
    sys.dnm(&["apply", "--system", &sys.name, path.to_str().unwrap()])
}

#[test]
fn a_failed_apply_leaves_the_dnm_as_it_was_and_a_retry_succeeds() {
    let sys = System::start(CHAIN);
    let relay = sys.subscribe::<Tick>("relay", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);
    let before = sys.status();
    assert_eq!(before.revision, 1);

    // A new source and a module whose process exits as soon as it starts.
    let broken = fake_ticker(&sys.dir, "broken", 0);
    let grown = format!(
        "{CHAIN}\n[[module]]\nname = \"src_c\"\nkind = \"ticker\"\nparams = {{ origin = 3 }}\n\n\
         [[module]]\nname = \"bad\"\nkind = \"broken\"\n\n\
         [task.c]\nlinks = [\"src_c.out -> relay.in\"]\n\n\
         [kind.broken]\nexec = \"{}\"\n",
        broken.display()
    );
    let out = apply(&sys, &grown, "grown.toml");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("`bad` exited while preparing"), "{err}");

    // Exactly as it was: revision, tasks, modules and their processes; the module started for
    // the failed revision is gone.
    let after = sys.status();
    assert_eq!(after.revision, before.revision);
    assert_eq!(after.tasks, before.tasks);
    assert_eq!(after.active_task, before.active_task);
    assert_eq!(after.preparing, None);
    let names = |r: &DnmReport| {
        r.modules
            .iter()
            .map(|m| (m.name.clone(), m.pid))
            .collect::<Vec<_>>()
    };
    assert_eq!(names(&after), names(&before));
    support::eventually("src_c's process to be gone", || {
        processes_of(&sys.name, "src_c").is_empty().then_some(())
    });

    // A module restarted now serves the committed revision: its input stays connected.
    let victim = module(&after, "relay").pid.unwrap();
    signal(victim, libc::SIGKILL);
    sys.wait_for("relay restarted", |r| {
        let m = module(&r.dnms[0], "relay");
        m.restarts >= 1 && m.state == ModuleRunState::Running
    });
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(ticks.iter().all(|t| t.origin == 1), "{ticks:?}");

    // The same netlist again, now that the module starts: it applies, under a revision
    // number never used before.
    std::fs::write(sys.dir.join("fixed"), "").unwrap();
    let out = apply(&sys, &grown, "grown.toml");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let now = sys.wait_for("the grown system running", |r| {
        r.dnms[0].modules.len() == 5
            && r.dnms[0]
                .modules
                .iter()
                .all(|m| m.state == ModuleRunState::Running)
    });
    assert!(
        now.dnms[0].revision > 2,
        "revision 2 was burned by the failure"
    );
    let r = sys.ask(&Request::Switch { task: "c".into() });
    assert!(r.ok, "{r:?}");
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 3).count() >= 5);
    assert!(
        ticks.iter().rev().take(5).all(|t| t.origin == 3),
        "{ticks:?}"
    );
}

/// The file of event service `name`'s description in `sys`'s DNM's namespace (named after a
/// hash of the service's name), found by creating the service once and reading descriptions.
fn description_of(sys: &System, name: &str) -> PathBuf {
    let service = dnm_module::event_service(&sys.node, name).unwrap();
    let file = existing_description(sys, name);
    drop(service);
    file
}

/// The description file of service `name`, which exists in `sys`'s DNM's namespace.
fn existing_description(sys: &System, name: &str) -> PathBuf {
    use iceoryx2::prelude::SemanticString;
    let g = &sys.node.config().global;
    let text = |b: &[u8]| String::from_utf8(b.to_vec()).unwrap();
    let dir = Path::new(&text(g.root_path().as_bytes())).join(text(g.service.directory.as_bytes()));
    let prefix = text(g.prefix.as_bytes());
    let says = format!("service_name = \"{name}\"");
    std::fs::read_dir(&dir)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .unwrap()
                .to_string_lossy()
                .starts_with(&prefix)
        })
        .find(|p| std::fs::read_to_string(p).is_ok_and(|t| t.contains(&says)))
        .unwrap_or_else(|| panic!("no description of {name} in {}", dir.display()))
}

/// Leaves at `file` what a process killed while creating a service leaves: the description
/// written but still writable (iceoryx2 makes it read-only once the service is created).
fn abandon(file: &Path) {
    use std::os::unix::fs::PermissionsExt;
    // Made anew: a finished description is read-only, even to its owner.
    let _ = std::fs::remove_file(file);
    std::fs::write(file, "").unwrap();
    std::fs::set_permissions(file, std::fs::Permissions::from_mode(0o600)).unwrap();
}

fn abandoned(file: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    std::fs::metadata(file).is_ok_and(|m| m.permissions().mode() & 0o777 == 0o600)
}

#[test]
fn a_service_a_killed_process_left_half_created_does_not_keep_its_module_from_starting() {
    let sys = System::start(CHAIN);
    // What a process killed while it creates `src_c`'s output event leaves (the relay opening
    // it for a new revision, say): its description written but never made read-only, which
    // iceoryx2 takes for a service still being created, forever.
    let file = description_of(&sys, "src_c/out/ev");
    abandon(&file);

    let grown = format!(
        "{CHAIN}\n[[module]]\nname = \"src_c\"\nkind = \"ticker\"\nparams = {{ origin = 3 }}\n\n\
         [task.c]\nlinks = [\"src_c.out -> relay.in\"]\n"
    );
    let out = apply(&sys, &grown, "grown.toml");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(!abandoned(&file), "the service was created afresh");
    let relay = sys.subscribe::<Tick>("relay", "out");
    let r = sys.ask(&Request::Switch { task: "c".into() });
    assert!(r.ok, "{r:?}");
    let ticks = collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 3).count() >= 5);
    assert!(ticks.iter().any(|t| t.origin == 3), "{ticks:?}");
}

#[test]
fn the_dnm_frees_a_half_created_service_after_a_process_dies_without_anyone_opening_it() {
    let sys = System::start(CHAIN);
    let file = description_of(&sys, "gone/out/ev");
    abandon(&file);
    // A death makes the DNM sweep its shared memory. The description is too young to call
    // abandoned then (it could be one being written), so a sweep the creation timeout later
    // removes it.
    let victim = module(&sys.status(), "relay").pid.unwrap();
    signal(victim, libc::SIGKILL);
    support::eventually("the half-created service to be removed", || {
        (!file.exists()).then_some(())
    });
}

#[test]
fn a_dnm_starts_over_a_task_board_its_killed_predecessor_left_half_created() {
    let mut sys = System::start(CHAIN);
    let board = existing_description(&sys, dnm_module::protocol::TASK_SERVICE);
    // The DNM and its modules killed. The DNM is stopped first, so that it reaps none of them
    // and their pids stay theirs until they are all signalled.
    let modules: Vec<u32> = sys.status().modules.iter().filter_map(|m| m.pid).collect();
    signal(sys.child.id(), libc::SIGSTOP);
    for pid in modules {
        signal(pid, libc::SIGKILL);
    }
    sys.child.kill().unwrap();
    sys.child.wait().unwrap();
    for name in ["src_a", "src_b", "relay"] {
        support::eventually(&format!("{name}'s process gone"), || {
            processes_of(&sys.name, name).is_empty().then_some(())
        });
    }
    // The board left as a DNM killed while it created it leaves it: the description written,
    // never made read-only.
    abandon(&board);
    // Session folders for the seconds the restart may start in, as a run started then would
    // have left them: the restarted DNM must record into a folder of its own.
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs();
    let taken: Vec<PathBuf> = (now.saturating_sub(2)..now + 30)
        .map(|t| {
            let dir = sys.dir.join(dnm::session::session_name(&sys.name, t));
            std::fs::create_dir_all(&dir).unwrap();
            let file = dir.join("rec-main.mcap");
            if !file.exists() {
                std::fs::write(&file, b"another run's").unwrap();
            }
            file
        })
        .collect();
    let before: Vec<Vec<u8>> = taken.iter().map(|f| std::fs::read(f).unwrap()).collect();

    sys.child = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .arg("up")
        .arg(sys.dir.join("netlist.toml"))
        .env("DNM_MODULE_HOST", module_host())
        .env("DNM_RECORD_DIR", &sys.dir)
        .env("RUST_LOG", "warn")
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    sys.wait_for("the DNM started again, its modules running", |r| {
        r.dnms.iter().all(|d| {
            d.modules.len() == 3 && d.modules.iter().all(|m| m.state == ModuleRunState::Running)
        })
    });
    assert!(
        std::fs::metadata(&board).is_ok_and(|m| {
            use std::os::unix::fs::PermissionsExt;
            m.permissions().mode() & 0o777 == 0o400
        }),
        "the board was created afresh"
    );
    let relay = sys.subscribe::<Tick>("relay", "out");
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 5);
    assert!(ticks.iter().all(|t| t.origin == 1), "{ticks:?}");
    // It records, into a session folder of its own: the one named after the second it started
    // in was taken, so its name carries `-2`; the earlier run's files are untouched.
    let recording = sys.wait_for("the restarted DNM recording", |r| {
        let rec = r.dnms[0].recording.as_ref();
        assert!(rec.is_some_and(|x| x.error.is_none()), "{rec:?}");
        rec.is_some_and(|x| x.messages > 0)
    });
    let file = PathBuf::from(&recording.dnms[0].recording.as_ref().unwrap().file);
    let folder = file
        .parent()
        .unwrap()
        .file_name()
        .unwrap()
        .to_string_lossy();
    assert!(
        file.ends_with("rec-main.mcap") && folder.starts_with(&sys.name) && folder.ends_with("-2"),
        "{}",
        file.display()
    );
    let after: Vec<Vec<u8>> = taken.iter().map(|f| std::fs::read(f).unwrap()).collect();
    assert!(before == after, "an earlier run's file was written to");
}

#[test]
fn a_replacement_whose_executable_cannot_run_is_refused_before_the_commit() {
    let sys = System::start(CHAIN);
    let relay = sys.subscribe::<Tick>("relay", "out");
    let before = sys.status();
    // An executable that describes itself (the DNM checks the netlist) and then loses its
    // execute permission, so starting it fails.
    let broken = fake_ticker(&sys.dir, "vanishing", 0);
    let script =
        std::fs::read_to_string(&broken)
            .unwrap()
            .replacen("cat '", "chmod -x \"$0\"; cat '", 1);
    std::fs::write(&broken, script).unwrap();
    let replaced = chain_with("src_a", "vanishing", &broken);
    let out = apply(&sys, &replaced, "replaced.toml");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("cannot start module `src_a`"), "{err}");
    // Nothing changed: the revision, the module and its process, the data it feeds.
    let after = sys.status();
    assert_eq!(after.revision, before.revision);
    let (a0, a1) = (module(&before, "src_a"), module(&after, "src_a"));
    assert_eq!((a1.kind.as_str(), a1.pid), (a0.kind.as_str(), a0.pid));
    assert_eq!(a1.state, ModuleRunState::Running);
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(ticks.iter().all(|t| t.origin == 1));
}

#[test]
fn what_a_module_starts_goes_with_it_when_it_dies_or_is_replaced() {
    let sys = System::start(CHAIN);
    let relay = sys.subscribe::<Tick>("relay", "out");
    // src_a becomes a module that starts a helper process of its own (as a wrapper script or a
    // Python module's workers do), then runs as the ticker.
    std::fs::write(sys.dir.join("fixed"), "").unwrap();
    let forking = fake_ticker(&sys.dir, "forking", 0);
    let helpers = sys.dir.join("helpers");
    std::fs::create_dir_all(&helpers).unwrap();
    let script = std::fs::read_to_string(&forking).unwrap().replacen(
        "exec '",
        &format!("sleep 600 & echo $! > '{}/'$$\nexec '", helpers.display()),
        1,
    );
    std::fs::write(&forking, script).unwrap();
    let with_helper = chain_with("src_a", "forking", &forking);
    let out = apply(&sys, &with_helper, "forking.toml");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    // The helper of the module process now running.
    let helper_of = |pid: u32| -> u32 {
        support::eventually("the module's helper started", || {
            std::fs::read_to_string(helpers.join(pid.to_string()))
                .ok()?
                .trim()
                .parse()
                .ok()
        })
    };
    let alive = |pid: u32| {
        std::fs::read_to_string(format!("/proc/{pid}/stat")).is_ok_and(|s| {
            !s.rsplit(')')
                .next()
                .unwrap_or("")
                .trim_start()
                .starts_with('Z')
        })
    };
    sys.wait_for("src_a running as the forking kind", |r| {
        let m = module(&r.dnms[0], "src_a");
        m.kind == "forking" && m.state == ModuleRunState::Running
    });
    let first = module(&sys.status(), "src_a").pid.unwrap();
    let helper = helper_of(first);
    assert!(alive(helper));
    // The module dies (killed from outside): its helper goes with it, and it is restarted.
    signal(first, libc::SIGKILL);
    support::eventually("the dead module's helper gone", || {
        (!alive(helper)).then_some(())
    });
    sys.wait_for("src_a restarted", |r| {
        let m = module(&r.dnms[0], "src_a");
        m.restarts >= 1 && m.state == ModuleRunState::Running
    });
    let second = module(&sys.status(), "src_a").pid.unwrap();
    let helper = helper_of(second);
    assert!(alive(helper));
    // Replaced by the plain ticker: the stopped module's helper goes too, and data flows.
    let out = apply(&sys, CHAIN, "plain.toml");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    support::eventually("the replaced module's helper gone", || {
        (!alive(helper)).then_some(())
    });
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(ticks.iter().all(|t| t.origin == 1), "{ticks:?}");
}

#[test]
fn a_replacement_that_cannot_start_still_commits_routes_and_recording() {
    let sys = System::start(CHAIN);
    let before = sys.status();
    let files_before = before.recording.as_ref().unwrap().files;
    // src_b becomes a module whose process exits at once (it is not restarted: "never").
    let broken = fake_ticker(&sys.dir, "broken", 0);
    let replaced = chain_with("src_b", "broken", &broken);
    let out = apply(&sys, &replaced, "replaced.toml");
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = sys.wait_for("src_b replaced and given up", |r| {
        let m = module(&r.dnms[0], "src_b");
        m.kind == "broken" && m.state == ModuleRunState::Stopped
    });
    let d = &r.dnms[0];
    assert_eq!(d.revision, before.revision + 1);
    // The recorder followed the new revision: a new file with its netlist.
    assert!(
        d.recording.as_ref().unwrap().files > files_before,
        "{:?}",
        d.recording
    );
    assert!(
        d.events
            .iter()
            .any(|e| e.module == "src_b" && e.what == "gave_up")
    );
}

#[test]
fn switching_back_to_a_quiet_source_delivers_nothing_old() {
    let sys = System::start(CHAIN);
    let relay = sys.subscribe::<Tick>("relay", "out");
    // b, then a: src_b's samples queue up in the relay while a is active.
    assert!(sys.ask(&Request::Switch { task: "b".into() }).ok);
    drain(&relay);
    collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 2).count() >= 5);
    assert!(sys.ask(&Request::Switch { task: "a".into() }).ok);
    drain(&relay);
    collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 1).count() >= 5);
    // src_b goes quiet (stopped), after having sent into the relay's queue.
    let quiet = module(&sys.status(), "src_b").pid.unwrap();
    std::thread::sleep(Duration::from_millis(100));
    signal(quiet, libc::SIGSTOP);
    std::thread::sleep(Duration::from_millis(300));

    // Back to b: nothing src_b sent before the switch may come through.
    assert!(sys.ask(&Request::Switch { task: "b".into() }).ok);
    let mut stale = Vec::new();
    let until = Instant::now() + Duration::from_secs(1);
    while Instant::now() < until {
        while let Some(s) = relay.receive().unwrap() {
            let t: Tick = bytemuck::pod_read_unaligned(s.payload());
            if t.origin == 2 {
                stale.push(t);
            }
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    assert!(
        stale.is_empty(),
        "old samples delivered after the switch: {stale:?}"
    );

    // When it speaks again, its new samples flow.
    signal(quiet, libc::SIGCONT);
    let ticks = collect::<Tick>(&relay, |t| t.iter().filter(|x| x.origin == 2).count() >= 5);
    assert!(ticks.iter().any(|t| t.origin == 2));
}

#[test]
fn a_stopped_module_is_reported_hung_and_handled_by_its_restart_policy() {
    // src_a: restarted on failure, hung after 3 s without stepping; src_b: never restarted,
    // hung after 1 s; the relay waits for input and must not look hung while idle.
    let netlist = CHAIN
        .replace(
            "params = { origin = 1 }",
            "hung_after = \"3s\"\nparams = { origin = 1 }",
        )
        .replace(
            "restart = \"never\"\n",
            "restart = \"never\"\nhung_after = \"1s\"\n",
        );
    let sys = System::start(&netlist);
    let before = sys.status();
    let a_pid = module(&before, "src_a").pid.unwrap();
    let b_pid = module(&before, "src_b").pid.unwrap();
    signal(a_pid, libc::SIGSTOP);
    signal(b_pid, libc::SIGSTOP);

    // src_b: reported hung, left alone (its policy is never), running again when it steps.
    let r = sys.wait_for("src_b hung", |r| {
        module(&r.dnms[0], "src_b").state == ModuleRunState::Hung
    });
    assert_eq!(module(&r.dnms[0], "src_b").pid, Some(b_pid));
    signal(b_pid, libc::SIGCONT);
    sys.wait_for("src_b recovered", |r| {
        module(&r.dnms[0], "src_b").state == ModuleRunState::Running
    });

    // src_a: hung, killed, restarted; the relay idled meanwhile without being taken for hung.
    let r = sys.wait_for("src_a restarted after hanging", |r| {
        let m = module(&r.dnms[0], "src_a");
        m.hangs >= 1 && m.restarts >= 1 && m.state == ModuleRunState::Running
    });
    let d = &r.dnms[0];
    let a = module(d, "src_a");
    assert_ne!(a.pid, Some(a_pid));
    assert!(
        a.last_exit.as_deref().unwrap_or("").contains("hung"),
        "{a:?}"
    );
    assert_eq!(
        module(d, "relay").hangs,
        0,
        "an idle module was taken for hung"
    );
    assert_eq!(module(d, "relay").restarts, 0);
    let what: Vec<(&str, &str)> = d
        .events
        .iter()
        .map(|e| (e.module.as_str(), e.what.as_str()))
        .collect();
    for expected in [
        ("src_b", "hung"),
        ("src_b", "recovered"),
        ("src_a", "hung"),
        ("src_a", "restarting"),
    ] {
        assert!(what.contains(&expected), "{expected:?} not in {what:?}");
    }

    // The hang is in the recording.
    let recorded = support::eventually("the hang recorded", || {
        let events = mcap_json(&sys.dir, "/main/_events");
        events
            .iter()
            .any(|e| e["module"] == "src_a" && e["what"] == "hung")
            .then_some(events)
    });
    assert!(
        recorded
            .iter()
            .any(|e| e["module"] == "src_b" && e["what"] == "recovered")
    );
}

/// The JSON messages of `topic` in every recording in `dir` (open files included).
fn mcap_json(dir: &Path, topic: &str) -> Vec<serde_json::Value> {
    let mut out = Vec::new();
    for f in support::mcap_files(dir) {
        let bytes = std::fs::read(&f).unwrap();
        let options = enumset::enum_set!(mcap::read::Options::IgnoreEndMagic);
        let Ok(stream) = mcap::MessageStream::new_with_options(&bytes, options) else {
            continue;
        };
        for m in stream {
            let Ok(m) = m else { break };
            if m.channel.topic == topic {
                out.extend(serde_json::from_slice(&m.data).ok());
            }
        }
    }
    out
}

#[test]
fn a_switch_never_waits_for_an_apply_in_progress() {
    let sys = System::start(CHAIN);
    // A new module that takes 3 s to start: the apply is pending that long.
    let slow = fake_ticker(&sys.dir, "slow", 3);
    std::fs::write(sys.dir.join("fixed"), "").unwrap();
    let grown = format!(
        "{CHAIN}\n[[module]]\nname = \"late\"\nkind = \"slow\"\nparams = {{ origin = 4 }}\n\n\
         [kind.slow]\nexec = \"{}\"\n",
        slow.display()
    );
    let path = sys.dir.join("grown.toml");
    std::fs::write(&path, grown.replace("SYSTEM", &sys.name)).unwrap();
    let mut applying = Command::new(env!("CARGO_BIN_EXE_dnm"))
        .args(["apply", "--system", &sys.name, path.to_str().unwrap()])
        .stdout(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // The apply is under way once the new module's process runs (it sleeps before starting).
    support::eventually("the new module starting", || {
        (!processes_of(&sys.name, "late").is_empty()).then_some(())
    });

    // Switches are served meanwhile, under the committed revision.
    for task in ["b", "a", "b"] {
        let r = sys.ask(&Request::Switch { task: task.into() });
        assert!(r.ok, "{r:?}");
        assert_eq!(r.switches[0].revision, 1);
    }
    assert!(
        applying.try_wait().unwrap().is_none(),
        "the switches waited for the apply to finish"
    );
    let during = sys.status();
    assert!(during.preparing.is_some(), "{during:?}");
    assert_eq!(during.active_task.as_deref(), Some("b"));

    // The apply commits afterwards, keeping the task the operator chose.
    assert!(applying.wait().unwrap().success());
    let after = sys.status();
    assert_eq!(after.revision, 2);
    assert_eq!(after.active_task.as_deref(), Some("b"));
    assert!(after.modules.iter().any(|m| m.name == "late"));
}

#[test]
fn a_removed_module_releases_its_port_services() {
    let sys = System::start(CHAIN);
    let exists = || {
        let config =
            dnm_module::protocol::dnm_config(&dnm_module::protocol::dnm_prefix(&sys.name, "main"))
                .unwrap();
        let name: iceoryx2::prelude::ServiceName = "src_b/out".try_into().unwrap();
        <iceoryx2::prelude::ipc::Service as iceoryx2::service::Service>::does_exist(
            &name,
            &config,
            iceoryx2::prelude::MessagingPattern::PublishSubscribe,
        )
        .unwrap()
    };
    assert!(exists());
    let out = sys.dnm(&["module", "remove", "--system", &sys.name, "--name", "src_b"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    support::eventually("src_b/out released", || (!exists()).then_some(()));
    assert!(sys.status().modules.iter().all(|m| m.name != "src_b"));
}

#[test]
fn a_recorder_that_lost_its_disk_counts_what_it_drops() {
    let sys = System::start(CHAIN);
    let before = sys.status();
    assert!(before.recording.as_ref().unwrap().error.is_none());
    // The recordings folder goes away; the next revision needs a new file.
    let netlists = std::env::temp_dir().join(format!("{}-netlists", sys.name));
    std::fs::create_dir_all(&netlists).unwrap();
    let recordings = sys.dir.clone();
    let path = netlists.join("next.toml");
    std::fs::write(
        &path,
        CHAIN
            .replace("SYSTEM", &sys.name)
            .replace("origin = 1", "origin = 5"),
    )
    .unwrap();
    // The system folder holds the recordings: make it unusable for new files.
    let kept = recordings.with_extension("kept");
    std::fs::rename(&recordings, &kept).unwrap();
    std::fs::write(&recordings, "not a folder").unwrap();
    let out = sys.dnm(&["apply", "--system", &sys.name, path.to_str().unwrap()]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let r = sys.wait_for("the recorder's failure reported with drops", |r| {
        let rec = r.dnms[0].recording.as_ref().unwrap();
        rec.error.is_some() && rec.dropped > 100
    });
    let rec = r.dnms[0].recording.clone().unwrap();
    // The running system is untouched: the new revision is in force, and its modules (the
    // replaced one may still be starting) all run.
    assert_eq!(r.dnms[0].revision, before.revision + 1);
    let r = sys.wait_for("every module running", |r| {
        r.dnms[0]
            .modules
            .iter()
            .all(|m| m.state == ModuleRunState::Running)
    });
    assert!(
        r.dnms[0].modules.iter().all(|m| m.restarts == 0),
        "{:?}",
        r.dnms[0].modules
    );
    std::fs::remove_file(&recordings).unwrap();
    std::fs::rename(&kept, &recordings).unwrap();
    let _ = std::fs::remove_dir_all(&netlists);
    let error = rec.error.unwrap();
    assert!(
        error.contains(&sys.name),
        "the error names the file: {error}"
    );
}

/// Sends one command over Zenoh as `client` and returns the DNM's answer.
fn zenoh_command(
    session: &zenoh::Session,
    system: &str,
    body: serde_json::Value,
) -> Result<dnm::proto::Response, String> {
    use zenoh::Wait;
    let replies = session
        .get(dnm::keys::cmd(system, "main"))
        .payload(serde_json::to_vec(&body).unwrap())
        .timeout(Duration::from_secs(10))
        .wait()
        .map_err(|e| e.to_string())?;
    let reply = replies.recv().map_err(|e| e.to_string())?;
    let bytes = match reply.result() {
        Ok(s) => s.payload().to_bytes().into_owned(),
        Err(e) => e.payload().to_bytes().into_owned(),
    };
    serde_json::from_slice(&bytes).map_err(|e| format!("{e}: {}", String::from_utf8_lossy(&bytes)))
}

/// Resident memory of a process, KiB.
fn rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .unwrap()
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.split_whitespace().next()?.parse().ok())
        .unwrap()
}

#[test]
fn a_flood_of_queries_delays_neither_switches_nor_supervision() {
    use std::sync::Arc;
    use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
    use zenoh::Wait;
    let port = support::free_port();
    let endpoint = support::endpoint(port);
    let sys = System::start_with(CHAIN, &["--no-multicast", "--listen", &endpoint]);
    let session = support::zenoh_client(port);
    let system = sys.name.clone();
    support::eventually("the DNM on Zenoh", || {
        zenoh_command(&session, &system, serde_json::json!({"cmd": "status"}))
            .ok()
            .filter(|r| r.ok)
    });
    let rss_before = rss_kib(sys.child.id());

    // 100,000 queries paced at 10,000 a second (10 every millisecond) over every queryable of
    // the DNM: reports, modules with their last values, ports, the netlist.
    const QUERIES: u64 = 100_000;
    let done = Arc::new(AtomicBool::new(false));
    let sent = Arc::new(AtomicU64::new(0));
    let replies = Arc::new(AtomicU64::new(0));
    let flood = {
        let (session, done, sent, replies) =
            (session.clone(), done.clone(), sent.clone(), replies.clone());
        let keys = [
            dnm::keys::dnm(&system, "main"),
            dnm::keys::module(&system, "main", "*"),
            dnm::keys::port(&system, "main", "*", "*"),
            dnm::keys::netlist(&system, "main"),
        ];
        std::thread::spawn(move || {
            let start = Instant::now();
            let mut n = 0u64;
            while n < QUERIES {
                for _ in 0..10 {
                    let replies = replies.clone();
                    let _ = session
                        .get(&keys[(n % 4) as usize])
                        .callback(move |_| {
                            replies.fetch_add(1, Ordering::Relaxed);
                        })
                        .timeout(Duration::from_secs(1))
                        .wait();
                    n += 1;
                }
                sent.store(n, Ordering::Relaxed);
                let next = start + Duration::from_micros(n * 100);
                if let Some(wait) = next.checked_duration_since(Instant::now()) {
                    std::thread::sleep(wait);
                }
            }
            done.store(true, Ordering::Relaxed);
            start.elapsed()
        })
    };

    // A switch every 100 ms while the flood lasts: every one is served.
    let mut switches = 0u32;
    let start = Instant::now();
    while !done.load(Ordering::Relaxed) {
        let task = if switches.is_multiple_of(2) { "b" } else { "a" };
        let r = zenoh_command(
            &session,
            &system,
            serde_json::json!({"client": "flood-test", "id": format!("s{switches}"), "cmd": "switch", "task": task}),
        )
        .unwrap_or_else(|e| panic!("switch {switches} not served during the flood: {e}"));
        assert!(r.ok, "switch {switches}: {r:?}");
        assert_eq!(r.switches[0].to, task);
        switches += 1;
        let next = start + Duration::from_millis(100 * u64::from(switches));
        if let Some(wait) = next.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
    }
    let took = flood.join().unwrap();
    let after = sys.status();
    let rss_after = rss_kib(sys.child.id());
    eprintln!(
        "flood: {} queries in {:.1} s ({:.0}/s), {} replies; {switches} switches; DNM answered {}, \
         refused {}; supervision: {} passes, longest gap {} ms (period {} ms); RSS {} -> {} KiB",
        sent.load(Ordering::Relaxed),
        took.as_secs_f64(),
        QUERIES as f64 / took.as_secs_f64(),
        replies.load(Ordering::Relaxed),
        after.routes.queries_answered,
        after.routes.queries_refused,
        after.supervision.passes,
        after.supervision.max_gap_ms,
        after.supervision.period_ms,
        rss_before,
        rss_after,
    );
    assert!(switches >= 10, "the flood ended before it began");
    // Supervision was never starved: no pass came more than ten periods after the last one.
    assert!(
        after.supervision.max_gap_ms <= 10 * after.supervision.period_ms,
        "{:?}",
        after.supervision
    );
    // Memory stays bounded: the queries did not pile up in the DNM.
    assert!(
        rss_after < rss_before + 64 * 1024,
        "RSS grew from {rss_before} to {rss_after} KiB"
    );
    assert!(
        after
            .modules
            .iter()
            .all(|m| m.state == ModuleRunState::Running)
    );
}

#[test]
fn command_ids_belong_to_their_client() {
    let port = support::free_port();
    let endpoint = support::endpoint(port);
    let sys = System::start_with(CHAIN, &["--no-multicast", "--listen", &endpoint]);
    let session = support::zenoh_client(port);
    let system = sys.name.clone();
    let send = |client: &str, task: &str| {
        support::eventually("a command answered", || {
            zenoh_command(
                &session,
                &system,
                serde_json::json!({"client": client, "id": "1", "cmd": "switch", "task": task}),
            )
            .ok()
        })
    };
    // Two clients, one id: both commands are applied.
    let x = send("station-x", "b");
    assert!(x.ok && x.switches[0].to == "b", "{x:?}");
    let y = send("station-y", "a");
    assert!(y.ok && y.switches[0].to == "a", "{y:?}");
    assert_eq!(sys.status().active_task.as_deref(), Some("a"));
    // A retry of x's command gets x's first answer and changes nothing.
    let again = send("station-x", "b");
    assert_eq!(again.switches[0].at_ns, x.switches[0].at_ns);
    assert_eq!(sys.status().active_task.as_deref(), Some("a"));
}

#[test]
fn a_plan_a_module_cannot_prepare_is_refused_and_the_module_keeps_running() {
    // One output read by more inputs than its port was made for (its subscriber slots are
    // fixed when it is made): the revision cannot be prepared.
    let sys = System::start(CHAIN);
    let relay = sys.subscribe::<Tick>("relay", "out");
    collect::<Tick>(&relay, |t| t.len() >= 5);
    let before = sys.status();
    let mut crowded = CHAIN.to_string();
    let mut links = Vec::new();
    for i in 0..dnm_module::protocol::MAX_PORT_SUBSCRIBERS {
        crowded += &format!("\n[[module]]\nname = \"fan{i}\"\nkind = \"relay\"\n");
        links.push(format!("\"src_a.out -> fan{i}.in\""));
    }
    crowded = crowded.replace(
        "links = [\"src_a.out -> relay.in\"]",
        &format!("links = [\"src_a.out -> relay.in\", {}]", links.join(", ")),
    );
    let out = apply(&sys, &crowded, "crowded.toml");
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("was made for 16 subscribers"), "{err}");
    let after = sys.status();
    assert_eq!(after.revision, before.revision);
    assert_eq!(after.modules.len(), before.modules.len());
    for m in &after.modules {
        let was = module(&before, &m.name);
        assert_eq!(
            (m.pid, m.restarts, m.state),
            (was.pid, was.restarts, ModuleRunState::Running)
        );
    }
    support::eventually("the fan modules gone", || {
        (0..dnm_module::protocol::MAX_PORT_SUBSCRIBERS)
            .all(|i| processes_of(&sys.name, &format!("fan{i}")).is_empty())
            .then_some(())
    });
    drain(&relay);
    let ticks = collect::<Tick>(&relay, |t| t.len() >= 10);
    assert!(ticks.iter().all(|t| t.origin == 1));
}

#[test]
fn a_process_can_host_dnms_again_after_stopping_them() {
    // The library use: start a machine's DNMs in this process, stop them, start them again.
    let name = format!("t{}again", std::process::id());
    let dir = std::env::temp_dir().join(format!("dnm-test-{name}"));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("netlist.toml");
    std::fs::write(&path, CHAIN.replace("SYSTEM", &name)).unwrap();
    let mut zenoh = zenoh::Config::default();
    zenoh
        .insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    for round in 0..2 {
        let netlist = dnm::load_netlist(&path).unwrap();
        let mut options = dnm::HostOptions::standard().unwrap();
        options.dnm.module_host = module_host();
        let host =
            dnm::host::Host::start(netlist, &["main".into()], options, zenoh.clone()).unwrap();
        support::eventually(&format!("round {round}: every module running"), || {
            dnm::admin::request(&name, &Request::Status)
                .ok()
                .filter(|r| {
                    r.dnms.len() == 1
                        && r.dnms[0]
                            .modules
                            .iter()
                            .all(|m| m.state == ModuleRunState::Running)
                })
        });
        host.stop();
    }
    let _ = std::fs::remove_dir_all(&dir);
}
