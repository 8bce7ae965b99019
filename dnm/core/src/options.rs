//! How a DNM runs its modules.

use std::path::{Path, PathBuf};
use std::time::Duration;

/// How a DNM runs its modules.
#[derive(Debug, Clone)]
pub struct DnmOptions {
    /// Executable that runs built-in kinds (`dnm-module-host`).
    pub module_host: PathBuf,
    /// How long modules get to prepare a new revision.
    pub prepare_timeout: Duration,
    /// Supervision period: exits, hangs, restarts, CPU readings.
    pub tick: Duration,
    /// How long a module that is not periodic may go without a sign of life before it is
    /// reported hung (a module's `hung_after` overrides it).
    pub on_input_hung_after: Duration,
    /// How long a stopped module gets to exit after SIGTERM before SIGKILL.
    pub stop_grace: Duration,
}

impl DnmOptions {
    /// The module host next to the running executable (or `$DNM_MODULE_HOST`), 5 s to prepare
    /// a revision, a 100 ms supervision tick, 2 s without a sign of life for on-input modules.
    pub fn standard() -> std::io::Result<Self> {
        Ok(Self {
            module_host: module_host_path()?,
            prepare_timeout: Duration::from_secs(5),
            tick: Duration::from_millis(100),
            on_input_hung_after: Duration::from_secs(2),
            stop_grace: Duration::from_secs(2),
        })
    }
}

/// Where the standard module host executable is.
pub fn module_host_path() -> std::io::Result<PathBuf> {
    if let Some(p) = std::env::var_os("DNM_MODULE_HOST") {
        return Ok(PathBuf::from(p));
    }
    let exe = std::env::current_exe()?;
    let dir = exe.parent().unwrap_or(Path::new("."));
    // Test and bench executables live one level down, in `deps/`.
    for candidate in [dir.join("dnm-module-host"), dir.join("../dnm-module-host")] {
        if candidate.exists() {
            return Ok(candidate);
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::NotFound,
        format!(
            "dnm-module-host not found next to {}; build it with `cargo build --workspace` or set DNM_MODULE_HOST",
            exe.display()
        ),
    ))
}
