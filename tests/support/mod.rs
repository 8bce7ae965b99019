//! What the multi-process system tests share.

#![allow(dead_code)] // each test file uses its own subset

pub mod ground;
mod port;
pub mod system;
pub mod webdriver;

pub use port::free_port;

use std::time::{Duration, Instant};

/// `tcp/127.0.0.1:<port>`.
pub fn endpoint(port: u16) -> String {
    format!("tcp/127.0.0.1:{port}")
}

/// Polls `f` until it returns `Some`, failing with `what` if that takes unreasonably long (a
/// hang guard, not a performance limit).
pub fn eventually<T>(what: &str, f: impl FnMut() -> Option<T>) -> T {
    eventually_within(what, Duration::from_secs(60), f)
}

/// [`eventually`] with a hang guard of `guard`, for what legitimately takes long (a lossy radio
/// link whose TCP retransmissions back off across outages).
pub fn eventually_within<T>(what: &str, guard: Duration, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + guard;
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "gave up waiting: {what}");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Polls `f` until it returns `Ok`, failing with `what` and the last state `f` reported
/// (`Err((progress, state))`) once `progress` has not grown for `idle`: a hang guard for what
/// advances in bursts at its own pace (a backfill through a link that is down two thirds of the
/// time), so a loaded machine that is slower, but still advancing, is not taken for a hang.
pub fn eventually_progressing<T>(
    what: &str,
    idle: Duration,
    mut f: impl FnMut() -> Result<T, (u64, String)>,
) -> T {
    let mut best = None;
    let mut deadline = Instant::now() + idle;
    loop {
        match f() {
            Ok(v) => return v,
            Err((progress, state)) => {
                if best.is_none_or(|b| progress > b) {
                    best = Some(progress);
                    deadline = Instant::now() + idle;
                }
                assert!(
                    Instant::now() < deadline,
                    "gave up waiting: {what}: no progress for {idle:?}; {state}"
                );
            }
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// Removes a test's folder once the test has passed; a failing test's is kept for a look, and
/// its path printed.
pub fn remove_unless_failed(dir: &std::path::Path) {
    if std::thread::panicking() {
        eprintln!("kept for a look: {}", dir.display());
    } else {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// A test's folder, removed as [`remove_unless_failed`] says when dropped: declared before the
/// test's processes, it goes after them.
pub struct Folder(pub std::path::PathBuf);

impl Drop for Folder {
    fn drop(&mut self) {
        remove_unless_failed(&self.0);
    }
}

/// The MCAP files in `dir` and in its session folders (`<system>-<time>/`), by path.
pub fn mcap_files(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    let Ok(entries) = std::fs::read_dir(dir) else {
        return out;
    };
    for p in entries.flatten().map(|e| e.path()) {
        if p.is_dir() {
            out.extend(mcap_files(&p));
        } else if p.extension().is_some_and(|e| e == "mcap") {
            out.push(p);
        }
    }
    out.sort();
    out
}

/// A Zenoh client session connected to `port` on loopback, without scouting.
pub fn zenoh_client(port: u16) -> zenoh::Session {
    use zenoh::Wait;
    let mut c = zenoh::Config::default();
    c.insert_json5("mode", "\"client\"").unwrap();
    c.insert_json5("connect/endpoints", &format!("[\"{}\"]", endpoint(port)))
        .unwrap();
    c.insert_json5("scouting/multicast/enabled", "false")
        .unwrap();
    eventually("a Zenoh client session", || {
        zenoh::open(c.clone()).wait().ok()
    })
}

/// Two DNMs: `src` (a ticker, origin 1) on `a` feeds `relay` on `b` in task `feed`; `idle` links
/// nothing. `SYSTEM` and `RATE` are replaced.
pub const FEED_NETLIST: &str = r#"
[system]
name = "SYSTEM"
default_task = "feed"

[[dnm]]
name = "a"

[[dnm]]
name = "b"
parent = "a"

[[module]]
name = "src"
kind = "ticker"
dnm = "a"
rate_hz = RATE
params = { origin = 1 }

[[module]]
name = "relay"
kind = "relay"
dnm = "b"

[task.feed]
links = ["src.out -> relay.in"]

[task.idle]
links = []
"#;
