//! Joining Zenoh. Every process of the system (DNM hosts, the `dnm` command, the router) builds
//! its Zenoh configuration with [`ZenohOptions`]: a Zenoh JSON5 file (ours are in
//! `configs/zenoh/`) or Zenoh's defaults (peer mode, multicast scouting), with endpoints and mode
//! given on the command line on top. [`run_router`] runs a Zenoh router: the process that joins
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
