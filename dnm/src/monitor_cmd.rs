//! `dnm monitor`, `dnm demo --rerun` and `dnm ground serve --monitor` start `dnm-monitor`, a
//! separate executable: the Rerun SDK stays out of the DNM, the module host and this command.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, ExitCode, Stdio};

use anyhow::Context;

/// Where `dnm-monitor` is: `$DNM_MONITOR`, next to this executable, else on the PATH.
pub fn monitor_path() -> PathBuf {
    if let Some(p) = std::env::var_os("DNM_MONITOR") {
        return PathBuf::from(p);
    }
    if let Ok(exe) = std::env::current_exe() {
        let dir = exe.parent().unwrap_or(Path::new("."));
        for candidate in [dir.join("dnm-monitor"), dir.join("../dnm-monitor")] {
            if candidate.exists() {
                return candidate;
            }
        }
    }
    PathBuf::from("dnm-monitor")
}

/// Whether a Rerun viewer (`rerun`) can be started: on the PATH, with a display to open on.
pub fn viewer_available() -> bool {
    let display = ["DISPLAY", "WAYLAND_DISPLAY"]
        .iter()
        .any(|v| std::env::var_os(v).is_some_and(|d| !d.is_empty()));
    display
        && std::env::var_os("PATH").is_some_and(|paths| {
            std::env::split_paths(&paths).any(|d| {
                let p = d.join("rerun");
                std::fs::metadata(&p).is_ok_and(|m| m.is_file())
            })
        })
}

/// The Zenoh flags a monitor needs to join the same network as `z`.
pub fn zenoh_flags(z: &dnm::ZenohOptions) -> Vec<String> {
    let mut out = Vec::new();
    if let Some(c) = &z.config {
        out.extend(["--zenoh-config".into(), c.display().to_string()]);
    }
    if let Some(m) = &z.mode {
        out.extend(["--zenoh-mode".into(), m.clone()]);
    }
    for e in &z.connect {
        out.extend(["--connect".into(), e.clone()]);
    }
    if z.no_multicast {
        out.push("--no-multicast".into());
    }
    out
}

/// The monitor executable with `args`, and what to say if it cannot start.
fn command(args: &[String]) -> (Command, String) {
    let path = monitor_path();
    let mut c = Command::new(&path);
    c.args(args);
    let why = format!(
        "starting {} (build it with `cargo build --release -p dnm-monitor`, or set DNM_MONITOR)",
        path.display()
    );
    (c, why)
}

/// Starts a monitor with `args`, its standard input a pipe to write to.
pub fn start_piped(args: &[String]) -> anyhow::Result<Child> {
    let (mut c, why) = command(args);
    c.stdin(Stdio::piped()).spawn().context(why)
}

/// Starts a monitor with `args`.
pub fn start(args: &[String]) -> anyhow::Result<Child> {
    let (mut c, why) = command(args);
    c.stdin(Stdio::null()).spawn().context(why)
}

/// Asks a monitor to finish its file and waits for it.
pub fn stop(mut child: Child) {
    // SAFETY: kill(2) on a child we started and have not reaped.
    unsafe {
        libc::kill(child.id() as libc::pid_t, libc::SIGTERM);
    }
    let _ = child.wait();
}

/// `dnm monitor ARGS`: runs the monitor in the foreground.
pub fn run(z: &dnm::ZenohOptions, args: &[String]) -> anyhow::Result<ExitCode> {
    let mut all = zenoh_flags(z);
    all.extend(args.iter().cloned());
    let (mut c, why) = command(&all);
    let status = c.status().context(why)?;
    Ok(if status.success() {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    })
}
