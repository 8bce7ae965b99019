//! Joining Zenoh. Every process of the system (DNM hosts, the `dnm` command, the router) builds
//! its Zenoh configuration with [`ZenohOptions`]: a Zenoh JSON5 file (ours are in
//! `configs/zenoh/`) or Zenoh's defaults (peer mode, multicast scouting) listening on loopback
//! only, with endpoints and mode given on the command line on top. [`run_router`] runs a Zenoh router: the process that joins
//! the rover's network and the ground's.
//!
//! ```no_run
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let options = dnm_router::ZenohOptions {
//!     listen: vec!["tcp/0.0.0.0:7447".into()],
//!     no_multicast: true,
//!     ..Default::default()
//! };
//! let session = options.open()?;
//! # Ok(()) }
//! ```

use std::path::PathBuf;

use zenoh::Wait;

/// A Zenoh configuration that cannot be built or used.
#[derive(Debug, thiserror::Error)]
pub enum ZenohConfigError {
    #[error("Zenoh configuration {path}: {why}; see configs/zenoh/ for working examples")]
    File { path: String, why: String },
    #[error("Zenoh setting `{key}` = {value}: {why}")]
    Setting {
        key: String,
        value: String,
        why: String,
    },
    #[error("opening the Zenoh session: {0}")]
    Open(String),
}

/// How a process joins Zenoh.
#[derive(Debug, Clone, Default)]
pub struct ZenohOptions {
    /// A Zenoh JSON5 configuration file (see `configs/zenoh/`).
    pub config: Option<PathBuf>,
    /// `peer`, `client` or `router`; overrides the file.
    pub mode: Option<String>,
    /// Endpoints to listen on, e.g. `tcp/127.0.0.1:7447`; override the file.
    pub listen: Vec<String>,
    /// Endpoints to connect to; override the file.
    pub connect: Vec<String>,
    /// Turn multicast scouting off (only the endpoints given are used).
    pub no_multicast: bool,
}

impl ZenohOptions {
    /// The Zenoh configuration these options describe.
    pub fn config(&self) -> Result<zenoh::Config, ZenohConfigError> {
        let mut config = match &self.config {
            Some(path) => zenoh::Config::from_file(path).map_err(|e| ZenohConfigError::File {
                path: path.display().to_string(),
                why: e.to_string(),
            })?,
            None => zenoh::Config::default(),
        };
        let mut set = |key: &str, value: String| {
            config
                .insert_json5(key, &value)
                .map_err(|e| ZenohConfigError::Setting {
                    key: key.into(),
                    value: value.clone(),
                    why: e.to_string(),
                })
        };
        if let Some(mode) = &self.mode {
            set("mode", serde_json::Value::from(mode.as_str()).to_string())?;
        }
        if !self.listen.is_empty() {
            set(
                "listen/endpoints",
                serde_json::Value::from(self.listen.clone()).to_string(),
            )?;
        } else if self.config.is_none() {
            // Without a configuration nothing is reachable from another machine.
            set("listen/endpoints", r#"["tcp/127.0.0.1:0"]"#.into())?;
        }
        if self.config.is_none() {
            // Nor does it look for others beyond this machine: its scouts never leave it, so
            // no one on the network is found and connected to.
            set("scouting/multicast/ttl", "0".into())?;
        }
        if !self.connect.is_empty() {
            set(
                "connect/endpoints",
                serde_json::Value::from(self.connect.clone()).to_string(),
            )?;
        }
        if self.no_multicast {
            set("scouting/multicast/enabled", "false".into())?;
        }
        Ok(config)
    }

    /// Opens a session with this configuration.
    pub fn open(&self) -> Result<zenoh::Session, ZenohConfigError> {
        zenoh::open(self.config()?)
            .wait()
            .map_err(|e| ZenohConfigError::Open(e.to_string()))
    }
}

/// Runs a Zenoh router until SIGINT or SIGTERM. The mode is forced to `router`.
pub fn run_router(options: &ZenohOptions) -> anyhow::Result<()> {
    let mut options = options.clone();
    options.mode = Some("router".into());
    // Before Zenoh starts its threads, so they inherit the mask and the signal waits for us.
    let signals = block_termination_signals();
    let session = options.open()?;
    let listen = options
        .config()?
        .get_json("listen/endpoints")
        .unwrap_or_default();
    tracing::info!(zid = %session.zid(), %listen, "Zenoh router up");
    println!(
        "Zenoh router {} listening on {listen}; Ctrl-C to stop",
        session.zid()
    );
    wait_for(&signals);
    tracing::info!("Zenoh router stopping");
    let _ = session.close().wait();
    Ok(())
}

/// Blocks SIGINT and SIGTERM in this thread (and the threads it starts later) so that
/// [`wait_for`] receives them.
fn block_termination_signals() -> libc::sigset_t {
    // SAFETY: sigset operations on a local, zero-initialised sigset_t, then pthread_sigmask on
    // the calling thread.
    unsafe {
        let mut set: libc::sigset_t = std::mem::zeroed();
        libc::sigemptyset(&mut set);
        libc::sigaddset(&mut set, libc::SIGINT);
        libc::sigaddset(&mut set, libc::SIGTERM);
        libc::pthread_sigmask(libc::SIG_BLOCK, &set, std::ptr::null_mut());
        set
    }
}

/// Waits until one of the signals of `set` arrives.
fn wait_for(set: &libc::sigset_t) {
    let mut sig = 0;
    // SAFETY: `set` is an initialised sigset_t whose signals are blocked in this thread.
    unsafe { libc::sigwait(set, &mut sig) };
}

/// An error and its causes on one line, as the command-line programs print it: each cause
/// added unless the message before it already says it (many errors quote their cause).
pub fn error_report(e: &anyhow::Error) -> String {
    let mut out = e.to_string();
    for cause in e.chain().skip(1) {
        let c = cause.to_string();
        if !out.contains(&c) {
            out.push_str(": ");
            out.push_str(&c);
        }
    }
    out
}

/// Logging for processes that admit others over Zenoh: the usual log on standard error, and
/// every access Zenoh's access control refuses, written as `access refused: …` (at most
/// [`REFUSALS_PER_WINDOW`] lines per ten seconds, then a count of those left out).
pub fn init_logging(default: &str) {
    use tracing_subscriber::layer::SubscriberExt;
    use tracing_subscriber::util::SubscriberInitExt;
    use tracing_subscriber::{EnvFilter, Layer, filter::Targets};
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| {
        EnvFilter::new(format!(
            "{default},zenoh=warn,zenoh_transport=warn,zenoh_link_tcp=warn,zenoh_link_tls=warn,zenoh_link_udp=warn,zenoh_config=warn"
        ))
    });
    let refusals = Refusals::default().with_filter(
        Targets::new()
            .with_target(ACL_TARGET, tracing::Level::TRACE)
            .with_target("zenoh::net::routing::interceptor", tracing::Level::INFO),
    );
    let _ = tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(filter),
        )
        .with(refusals)
        .try_init();
}

const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";

/// Refusal lines written per ten seconds at most.
pub const REFUSALS_PER_WINDOW: u32 = 20;

#[derive(Default)]
struct Refusals {
    /// Start of the window, lines written in it, lines left out since the last one written.
    window: std::sync::Mutex<Option<(std::time::Instant, u32, u64)>>,
}

struct Message(String);

impl tracing::field::Visit for Message {
    fn record_debug(&mut self, field: &tracing::field::Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            use std::fmt::Write;
            let _ = write!(self.0, "{value:?}");
        }
    }
}

impl<S: tracing::Subscriber> tracing_subscriber::Layer<S> for Refusals {
    fn on_event(
        &self,
        event: &tracing::Event<'_>,
        _ctx: tracing_subscriber::layer::Context<'_, S>,
    ) {
        let mut m = Message(String::new());
        event.record(&mut m);
        if !refused(&m.0) {
            return;
        }
        let Ok(mut w) = self.window.lock() else {
            return;
        };
        let now = std::time::Instant::now();
        let (start, written, left_out) = w.get_or_insert((now, 0, 0));
        if now.duration_since(*start) >= std::time::Duration::from_secs(10) {
            (*start, *written) = (now, 0);
        }
        if *written >= REFUSALS_PER_WINDOW {
            *left_out += 1;
            return;
        }
        *written += 1;
        let more = std::mem::take(left_out);
        let more = if more > 0 {
            format!(" ({more} more refused before this one)")
        } else {
            String::new()
        };
        // Straight to standard error: a refusal is recorded whatever the log filter says.
        // Keys come from the remote: one line each, whatever they hold.
        let text = m.0.escape_debug();
        let mut now = String::new();
        let _ = tracing_subscriber::fmt::time::FormatTime::format_time(
            &tracing_subscriber::fmt::time::SystemTime,
            &mut tracing_subscriber::fmt::format::Writer::new(&mut now),
        );
        eprintln!("{now} WARN access refused: {text}{more}");
    }
}

thread_local! {
    /// The key whose permissions Zenoh is computing on this thread (when a key is declared,
    /// before any message on it), if it is.
    static CACHING: std::cell::RefCell<Option<String>> = const { std::cell::RefCell::new(None) };
}

/// Whether a message of Zenoh's access control reports a refusal of something a remote sent
/// or was to receive (not the permissions worked out ahead for a newly declared key).
fn refused(m: &str) -> bool {
    if let Some(rest) = m.split("caching permissions for `").nth(1) {
        let key = rest.split('`').next().unwrap_or_default().to_string();
        CACHING.with(|c| *c.borrow_mut() = Some(key));
        return false;
    }
    if m.contains("did not match any configured ACL") {
        return true;
    }
    let ahead = !m.starts_with("Using cached result")
        && CACHING.with(|c| {
            c.borrow()
                .as_ref()
                .is_some_and(|k| m.ends_with(&format!(" on {k}")))
        });
    if ahead {
        return false;
    }
    CACHING.with(|c| *c.borrow_mut() = None);
    m.contains("is unauthorized")
}

#[cfg(test)]
mod report_tests {
    use super::error_report;

    #[derive(Debug, thiserror::Error)]
    #[error("opening the store: {0}")]
    struct Quoting(#[source] std::io::Error);

    #[test]
    fn a_cause_the_message_already_quotes_is_said_once() {
        let io = || std::io::Error::other("disk full");
        let e = anyhow::Error::new(Quoting(io())).context("starting");
        assert_eq!(error_report(&e), "starting: opening the store: disk full");
        let e = anyhow::Error::new(io()).context("starting");
        assert_eq!(error_report(&e), "starting: disk full");
    }
}
