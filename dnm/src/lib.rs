//! The `dnm` command's library: runs a machine's DNMs ([`host::Host`]: each DNM on its own
//! thread, with its Zenoh bridge, its recorder and the machine's admin socket), reads netlists
//! against the built-in kinds, and the Beetle-One demo. The layers it puts together live in
//! their own crates: [`dnm_core`] (the DNM), [`dnm_zenoh`] (DNMs on Zenoh), [`dnm_record`]
//! (MCAP), [`dnm_proto`] (what they say to each other).
//!
//! ```no_run
//! # fn main() -> anyhow::Result<()> {
//! let netlist = dnm::load_netlist("configs/pipeline.toml".as_ref())?;
//! let options = dnm::HostOptions::standard()?;
//! let host = dnm::host::Host::start(netlist, &["main".into()], options, zenoh::Config::default())?;
//! let status = dnm::admin::request("pipeline", &dnm::proto::Request::Status)?;
//! host.stop();
//! # Ok(()) }
//! ```

pub use dnm_core::{
    Command, Commander, Dnm, DnmError, DnmOptions, DnmReport, ModuleReport, ModuleRunState,
    SwitchRecord, crossing_links,
};
pub use dnm_proto as proto;
pub use dnm_proto::keys;
pub use dnm_record::{check, playback, record, replay, session, stats};
pub use dnm_router::{ZenohOptions, init_logging};
pub use dnm_zenoh::remote;

pub mod admin;
pub mod allocator;
pub mod host;

pub use host::HostOptions;

use std::path::Path;

use dnm_netlist::{DescribeError, KindSpec, Netlist, NetlistError};

/// Where durable state goes by default: `$DNM_STATE_DIR`, else `$XDG_STATE_HOME/dnm`, else
/// `~/.local/state/dnm`. Never the temporary directory: an authority whose store is lost at a
/// reboot forgets which commands it ran.
pub fn default_state_dir() -> Option<std::path::PathBuf> {
    if let Some(d) = std::env::var_os("DNM_STATE_DIR") {
        return Some(d.into());
    }
    if let Some(d) = std::env::var_os("XDG_STATE_HOME") {
        return Some(std::path::PathBuf::from(d).join("dnm"));
    }
    std::env::var_os("HOME").map(|h| std::path::PathBuf::from(h).join(".local/state/dnm"))
}

/// The message for a durable store with no folder to live in.
pub const NO_STATE_DIR: &str = "no folder for durable state: set --state-dir, $DNM_STATE_DIR, \
     $XDG_STATE_HOME or $HOME (never the temporary directory: a store lost at a reboot forgets \
     which commands ran)";

/// Whether a system is commanded through its authority: it names one, or it has DNMs across
/// a radio link. Its DNMs then start empty and take what the authority decided.
pub fn commanded_by_authority(netlist: &Netlist) -> bool {
    netlist.authority_dnm.is_some() || netlist.dnms.iter().any(|d| d.radio)
}

/// How long a module executable may take to describe itself.
const DESCRIBE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(5);
/// How much it may print doing so.
const DESCRIBE_MAX_BYTES: u64 = 1 << 20;

/// Asks a module executable for its kind (`EXEC describe`), within [`DESCRIBE_TIMEOUT`] and
/// [`DESCRIBE_MAX_BYTES`] of output.
pub fn describe_exec(path: &Path) -> Result<KindSpec, DescribeError> {
    use std::io::Read;
    use std::os::unix::process::CommandExt;
    use std::time::Instant;
    // A group of its own: whatever it starts goes with it.
    let mut child = std::process::Command::new(path)
        .arg("describe")
        .stdin(std::process::Stdio::null())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .process_group(0)
        .spawn()?;
    let mut stdout = child.stdout.take().ok_or("no output")?;
    let mut stderr = child.stderr.take().ok_or("no error output")?;
    let (out_tx, out_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut out = Vec::new();
        let r = (&mut stdout)
            .take(DESCRIBE_MAX_BYTES + 1)
            .read_to_end(&mut out);
        let _ = out_tx.send(r.map(|_| out));
    });
    let (err_tx, err_rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut err = Vec::new();
        let _ = (&mut stderr).take(DESCRIBE_MAX_BYTES).read_to_end(&mut err);
        let _ = err_tx.send(err);
    });
    let deadline = Instant::now() + DESCRIBE_TIMEOUT;
    let timeout = || DescribeError::Timeout(DESCRIBE_TIMEOUT.as_secs());
    let status = loop {
        // Exited: what it left running (holding its output open) is killed, then it is reaped.
        if dnm_core::group::kill_leftovers(child.id()) {
            break child.wait()?;
        }
        if Instant::now() >= deadline {
            dnm_core::group::signal(child.id(), libc::SIGKILL);
            let _ = child.wait();
            return Err(timeout());
        }
        std::thread::sleep(std::time::Duration::from_millis(10));
    };
    // (A process of its that left its group may still hold the output: waited for until the
    // deadline, then taken for a describe that did not finish; a moment is left to read what
    // one that finished just before it printed.)
    let left = || {
        deadline
            .saturating_duration_since(Instant::now())
            .max(std::time::Duration::from_millis(500))
    };
    let out = out_rx
        .recv_timeout(left())
        .map_err(|_| timeout())?
        .map_err(DescribeError::from)?;
    if out.len() as u64 > DESCRIBE_MAX_BYTES {
        return Err(DescribeError::TooMuchOutput(DESCRIBE_MAX_BYTES));
    }
    if !status.success() {
        let err = err_rx.recv_timeout(left()).unwrap_or_default();
        return Err(DescribeError::Failed {
            status,
            stderr: last_lines(&String::from_utf8_lossy(&err), DESCRIBE_ERROR_LINES),
        });
    }
    serde_json::from_slice(&out).map_err(DescribeError::NoKind)
}

/// How many of its last lines of standard error a failed `describe` is quoted with.
const DESCRIBE_ERROR_LINES: usize = 12;

/// The last `n` non-empty lines of `text`, each indented for a diagnostic.
fn last_lines(text: &str, n: usize) -> String {
    let lines: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
    lines[lines.len().saturating_sub(n)..]
        .iter()
        .map(|l| format!("        {}", l.trim_end()))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The folder of module executables installed on this computer (`$DNM_MODULE_DIR`): the only
/// place a netlist from the network may take external kinds from.
pub fn module_dir() -> Option<std::path::PathBuf> {
    std::env::var_os("DNM_MODULE_DIR").map(Into::into)
}

/// Validates a netlist that came over the network (an operator's apply, the authority's
/// decisions): its external kinds are looked up by file name in [`module_dir`] and nothing
/// outside it is ever run or described.
pub fn parse_remote_netlist(path: &Path, text: &str) -> Result<Netlist, NetlistError> {
    let dir = module_dir();
    let name = path
        .file_name()
        .map_or_else(|| "remote.toml".into(), |n| n.to_os_string());
    // Relative `exec` paths resolve against the module folder, not the sender's.
    let file = dir
        .as_ref()
        .map_or_else(|| Path::new("/nonexistent").join(&name), |d| d.join(&name));
    let installed = dir.as_ref().and_then(|d| d.canonicalize().ok());
    let mut describe = |exec: &Path| -> Result<KindSpec, DescribeError> {
        let Some(root) = &installed else {
            return Err(DescribeError::NotRun(format!(
                "`{}` is not run: a netlist from the network may only use kinds installed on this \
                 computer; set DNM_MODULE_DIR to the folder of installed module executables",
                exec.display()
            )));
        };
        match exec.canonicalize() {
            Ok(p) if p.starts_with(root) && p.is_file() => describe_exec(&p),
            _ => Err(DescribeError::NotRun(format!(
                "`{}` is not an installed module: a netlist from the network may only name \
                 executables in {} (DNM_MODULE_DIR), by file name",
                exec.display(),
                root.display()
            ))),
        }
    };
    Netlist::parse(&file, text, &catalog(), &mut describe)
}

/// The door of `system` for netlists that come over the network: validated by
/// [`parse_remote_netlist`], for this system only. A DNM's bridge, its joining and the authority
/// take netlists through it, and through nothing else.
pub fn remote_door(system: &str) -> dnm_netlist::NetlistDoor {
    dnm_netlist::NetlistDoor::new(system, std::sync::Arc::new(parse_remote_netlist))
}

/// The door of `system` for netlists given on this machine (the admin socket, whose user may
/// run any executable here anyway): validated by [`parse_netlist`], for this system only.
pub fn local_door(system: &str) -> dnm_netlist::NetlistDoor {
    dnm_netlist::NetlistDoor::new(system, std::sync::Arc::new(parse_netlist))
}

/// Validates a netlist stored in a recording without running anything: its external kinds
/// stay unknown.
pub fn parse_recorded_netlist(path: &Path, text: &str) -> Result<Netlist, NetlistError> {
    let mut refuse = |exec: &Path| -> Result<KindSpec, DescribeError> {
        Err(DescribeError::NotRun(format!(
            "`{}` is not run for a recording: analyse it where the module is installed",
            exec.display()
        )))
    };
    Netlist::parse(path, text, &catalog(), &mut refuse)
}

/// Every built-in kind: the standard ones and Beetle-One's. `dnm-module-host` runs them.
pub fn registry() -> dnm_module::Registry {
    dnm_module_host::registry()
}

/// The built-in kinds as a netlist catalog.
pub fn catalog() -> dnm_netlist::Catalog {
    let mut c = dnm_netlist::Catalog::new();
    for spec in registry().specs() {
        c.insert(spec, dnm_netlist::KindSource::BuiltIn);
    }
    c
}

/// Loads and validates a netlist against the built-in kinds and the executables it declares.
pub fn load_netlist(path: &Path) -> Result<Netlist, NetlistError> {
    Netlist::load(path, &catalog(), &mut describe_exec)
}

/// Validates netlist text (e.g. sent by an operator) the same way.
pub fn parse_netlist(path: &Path, text: &str) -> Result<Netlist, NetlistError> {
    Netlist::parse(path, text, &catalog(), &mut describe_exec)
}

/// Why a placement could not be written into a netlist's text.
#[derive(Debug, thiserror::Error)]
pub enum PlacedTextError {
    #[error("parsing the netlist: {0}")]
    Parse(#[from] toml::de::Error),
    /// The text is not the shape a netlist has (`what` says where).
    #[error("the netlist {what}")]
    Shape { what: &'static str },
    #[error("writing the placed netlist: {0}")]
    Write(#[from] toml::ser::Error),
}

/// `text` (a netlist) with each module on the DNM `assignment` gives it and `new_dnms`
/// declared; `unpin` also drops `pinned` flags (for placements that moved pinned modules).
pub fn placed_text(
    text: &str,
    assignment: &std::collections::BTreeMap<String, String>,
    new_dnms: &[(String, Option<String>)],
    unpin: bool,
) -> Result<String, PlacedTextError> {
    let mut doc: toml::Table = text.parse()?;
    if !new_dnms.is_empty() {
        let dnms = doc
            .entry("dnm")
            .or_insert_with(|| toml::Value::Array(Vec::new()))
            .as_array_mut()
            .ok_or(PlacedTextError::Shape {
                what: "has a `dnm` that is not an array",
            })?;
        for (name, parent) in new_dnms {
            let mut t = toml::Table::new();
            t.insert("name".into(), name.clone().into());
            if let Some(p) = parent {
                t.insert("parent".into(), p.clone().into());
            }
            dnms.push(t.into());
        }
    }
    let modules =
        doc.get_mut("module")
            .and_then(|m| m.as_array_mut())
            .ok_or(PlacedTextError::Shape {
                what: "has no modules",
            })?;
    for m in modules.iter_mut().filter_map(|m| m.as_table_mut()) {
        let name = m.get("name").and_then(|n| n.as_str()).unwrap_or_default();
        if let Some(d) = assignment.get(name) {
            m.insert("dnm".into(), d.clone().into());
        }
        if unpin {
            m.remove("pinned");
        }
    }
    Ok(toml::to_string(&doc)?)
}

#[cfg(test)]
mod describe_tests {
    use super::*;

    fn script(name: &str, body: &str) -> std::path::PathBuf {
        use std::os::unix::fs::PermissionsExt;
        let dir = std::env::temp_dir().join(format!("dnm-describe-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join(name);
        std::fs::write(&p, format!("#!/bin/sh\n{body}\n")).unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o755)).unwrap();
        p
    }

    #[test]
    fn a_module_that_hangs_or_floods_when_asked_to_describe_itself_is_refused() {
        let hang = script("hang", "sleep 60");
        let e = describe_exec(&hang).unwrap_err();
        assert!(matches!(e, DescribeError::Timeout(_)), "{e}");
        assert!(e.to_string().contains("did not finish"), "{e}");
        // Its kind printed and gone, a process of its left holding the output open: answered
        // at once, and what it left is gone too.
        let spec = serde_json::to_string(&dnm_netlist::KindSpec {
            name: "lingering".into(),
            summary: String::new(),
            inputs: Vec::new(),
            outputs: Vec::new(),
            params: Vec::new(),
            trigger: dnm_netlist::Trigger::OnInput,
        })
        .unwrap();
        let pids = std::env::temp_dir().join(format!("dnm-describe-left-{}", std::process::id()));
        let lingering = script(
            "lingering",
            &format!(
                "sleep 100000 &\necho $! > '{}'\necho '{spec}'",
                pids.display()
            ),
        );
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(describe_exec(&lingering));
        });
        // (A hang guard: a describe that waits for what it left would wait for a day.)
        let kind = rx
            .recv_timeout(std::time::Duration::from_secs(60))
            .expect("describe waited for the process it left")
            .unwrap();
        assert_eq!(kind.name, "lingering");
        let left: u32 = std::fs::read_to_string(&pids)
            .unwrap()
            .trim()
            .parse()
            .unwrap();
        let _ = std::fs::remove_file(&pids);
        let gone = (0..6000).any(|_| {
            std::thread::sleep(std::time::Duration::from_millis(10));
            std::fs::read_to_string(format!("/proc/{left}/stat"))
                .map_or(true, |s| s.contains(") Z "))
        });
        assert!(gone, "the process it left runs on");
        let flood = script("flood", "yes");
        let e = describe_exec(&flood).unwrap_err();
        assert!(
            matches!(
                e,
                DescribeError::Timeout(_) | DescribeError::TooMuchOutput(_)
            ),
            "{e}"
        );
    }

    #[test]
    fn a_remote_netlist_names_only_installed_executables_and_a_recording_none() {
        let text = "[system]\nname = \"s\"\n[[module]]\nname = \"x\"\nkind = \"evil\"\n[kind.evil]\nexec = \"/bin/sh\"\n";
        let e = parse_remote_netlist(Path::new("evil.toml"), text).unwrap_err();
        assert!(e.to_string().contains("/bin/sh"), "{e}");
        // Through the door every network path takes.
        let e = remote_door("s").accept("evil.toml", text).unwrap_err();
        assert!(e.to_string().contains("/bin/sh"), "{e}");
        let e = parse_recorded_netlist(Path::new("evil.toml"), text).unwrap_err();
        assert!(e.to_string().contains("not run for a recording"), "{e}");
    }
}

#[cfg(test)]
mod sequence_tests {
    #![allow(clippy::unwrap_used)]
    use dnm_netlist::sequence::{OnTimeout, Step};
    use dnm_netlist::{NetlistError, Sequence};

    fn beetle() -> dnm_netlist::Netlist {
        super::load_netlist(std::path::Path::new("../configs/beetle.toml")).unwrap()
    }

    fn errors(text: &str) -> NetlistError {
        Sequence::parse("bad.toml".as_ref(), text, &beetle()).unwrap_err()
    }

    /// The one diagnostic a sequence gives: (line, column, field, message).
    fn only(e: &NetlistError) -> (usize, usize, &str, &str) {
        assert_eq!(e.diagnostics.len(), 1, "{e}");
        let d = &e.diagnostics[0];
        let (line, col) = d.location.unwrap();
        (line, col, d.field.as_str(), d.message.as_str())
    }

    const HEAD: &str = "[sequence]\nname = \"s\"\n";

    #[test]
    fn beetle_explores_by_sequence() {
        let s = Sequence::load("../configs/sequences/explore.toml".as_ref(), &beetle()).unwrap();
        assert_eq!(s.name, "explore");
        assert_eq!(s.guards.len(), 1);
        assert_eq!(s.steps.len(), 5);
        assert!(matches!(
            &s.steps[1],
            Step::WaitUntil {
                timeout_ms: 180_000,
                on_timeout: OnTimeout::Safe,
                ..
            }
        ));
    }

    #[test]
    fn an_unknown_field_is_named_with_the_fields_there_are() {
        let e = errors(&format!(
            "{HEAD}[[step]]\nwait_until = \"odometry.odom.speed > 1\"\ntimeout = \"1m\"\n"
        ));
        let (line, col, field, message) = only(&e);
        assert_eq!((line, col, field), (4, 15, "step[0].wait_until"));
        assert!(message.contains("has no field `speed`"), "{message}");
        assert!(
            e.diagnostics[0]
                .help
                .as_deref()
                .unwrap()
                .contains("distance")
        );
    }

    #[test]
    fn a_comparison_with_the_wrong_type_is_refused() {
        let e = errors(&format!(
            "{HEAD}[[step]]\nend_if = \"battery.state.charge == true\"\n"
        ));
        assert!(only(&e).3.contains("is a number"), "{e}");
        let e = errors(&format!(
            "{HEAD}[[step]]\nend_if = \"camera.image.width > 3\"\n"
        ));
        assert!(only(&e).3.contains("not a fixed-size message"), "{e}");
    }

    #[test]
    fn an_unknown_task_module_or_port_is_refused() {
        let e = errors(&format!("{HEAD}[[step]]\nswitch = \"nowhere\"\n"));
        assert_eq!(only(&e).3, "unknown task `nowhere`");
        let e = errors(&format!("{HEAD}[[step]]\nend_if = \"ghost.odom.x > 1\"\n"));
        assert_eq!(only(&e).3, "unknown module `ghost`");
        let e = errors(&format!(
            "{HEAD}[[step]]\nend_if = \"odometry.pose.x > 1\"\n"
        ));
        assert!(only(&e).3.contains("has no output `pose`"), "{e}");
        let e = errors(&format!(
            "{HEAD}[[step]]\nedit = {{ remove = \"ghost\" }}\n"
        ));
        assert_eq!(only(&e).3, "unknown module `ghost`");
    }

    #[test]
    fn a_step_after_an_unconditional_end_never_runs() {
        let e = errors(&format!(
            "{HEAD}[[step]]\nend = true\n\n[[step]]\nswitch = \"auto\"\n"
        ));
        let (line, _, field, message) = only(&e);
        assert_eq!((line, field), (6, "step[1]"));
        assert!(
            message.contains("ends unconditionally at step[0]"),
            "{message}"
        );
        // A conditional end is not the end.
        let ok = format!(
            "{HEAD}[[step]]\nend_if = \"odometry.odom.distance > 2\"\n\n[[step]]\nswitch = \"auto\"\n"
        );
        Sequence::parse("ok.toml".as_ref(), &ok, &beetle()).unwrap();
    }

    #[test]
    fn a_condition_in_a_multi_line_or_escaped_string_is_located_at_its_start() {
        let e = errors(&format!("{HEAD}[[step]]\nend_if = \"\"\"'é'?\"\"\"\n"));
        let (line, col, _, _) = only(&e);
        assert_eq!((line, col), (4, 10));
        let e = errors(&format!("{HEAD}[[step]]\nend_if = \"\\t\\t'é'?\"\n"));
        assert_eq!(only(&e).0, 4);
    }

    #[test]
    fn an_edit_names_only_what_it_uses() {
        let e = errors(&format!(
            "{HEAD}[[step]]\nedit = {{ remove = \"camera\", params = [\"fov_deg=40\"] }}\n"
        ));
        assert_eq!(only(&e).3, "this edit does not use params");
    }

    #[test]
    fn a_wait_until_needs_a_timeout_and_a_step_does_one_thing() {
        let e = errors(&format!(
            "{HEAD}[[step]]\nwait_until = \"odometry.odom.distance > 2\"\n"
        ));
        assert!(only(&e).3.contains("needs a `timeout`"), "{e}");
        let e = errors(&format!(
            "{HEAD}[[step]]\nswitch = \"auto\"\nwait = \"1s\"\n"
        ));
        assert_eq!(only(&e).3, "a step does exactly one thing");
        let e = errors(&format!(
            "{HEAD}[[step]]\nswitch = \"auto\"\nsay = \"hi\"\n"
        ));
        assert_eq!(only(&e).2, "toml");
        assert!(e.to_string().contains("1 error in sequence"), "{e}");
    }
}
