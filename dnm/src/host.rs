//! A machine's DNMs in one process: each DNM on its own thread with its Zenoh bridge and its
//! recorder, the system's authority when it lives here, and the admin socket in front of them
//! ([`crate::admin`]). Stopping, on any path (a failed start, [`Host::stop`], a dropped host),
//! is written once: [`Hosted`]'s and [`Host`]'s `Drop`.

use std::os::fd::AsRawFd as _;
use std::os::unix::net::{UnixListener, UnixStream};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, SyncSender};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use anyhow::Context as _;
use dnm_core::{Commander, Dnm, DnmOptions};
use dnm_netlist::Netlist;
use zenoh::Wait;

use crate::admin::{private_dir, serve, socket_path};

/// How a host runs its DNMs: the DNMs' own options and what they record.
#[derive(Debug, Clone)]
pub struct HostOptions {
    pub dnm: DnmOptions,
    /// Record every output port to MCAP; `None`: no recording (and no downlink to the
    /// ground, which is served from the recording).
    pub record: Option<crate::record::RecordOptions>,
    /// How much of each downlinked channel its publisher keeps for the ground to recover
    /// (longer gaps are filled from the recording).
    pub downlink_cache: Duration,
    /// Where durable state lives (the authority's database); `None`: nowhere lasting is
    /// known, and a host that needs one refuses to start.
    pub state_dir: Option<PathBuf>,
}

impl HostOptions {
    /// [`DnmOptions::standard`], no recording.
    pub fn standard() -> std::io::Result<Self> {
        Ok(Self {
            dnm: DnmOptions::standard()?,
            record: None,
            downlink_cache: Duration::from_secs(dnm_downlink::CACHE_SECONDS),
            state_dir: crate::default_state_dir(),
        })
    }
}

/// Runs the given DNMs of a netlist in this process, one thread each, each in its own
/// shared-memory namespace, with the system's admin socket. Returns when all DNMs stopped
/// (SIGINT/SIGTERM).
pub fn run_host(
    netlist: Netlist,
    dnms: &[String],
    options: HostOptions,
    zenoh: zenoh::Config,
) -> anyhow::Result<()> {
    Host::start(netlist, dnms, options, zenoh)?.wait();
    Ok(())
}

/// A machine's DNMs running in this process (see [`run_host`]), for programs that drive them
/// from the same process, such as `dnm demo`. Dropped, it stops them.
pub struct Host {
    authority: Option<dnm_authority::Authority>,
    session: zenoh::Session,
    system: String,
    hosted: Hosted,
    socket: PathBuf,
    /// The socket file as bound: removed at the end only if it is still ours.
    socket_id: Option<(u64, u64)>,
    admin: Option<Admin>,
}

/// The admin socket's thread, and how to stop it.
struct Admin {
    listener: Arc<UnixListener>,
    stop: Arc<AtomicBool>,
    /// Ends with the connections still being served.
    thread: JoinHandle<Vec<JoinHandle<()>>>,
}

impl Admin {
    /// Stops taking connections: the flag, then the listening socket shut down under its
    /// accept (which wakes it: on Linux a shut-down listener's accept returns). Returns the
    /// threads of the connections still being served, to join once the DNMs no longer answer
    /// slowly.
    fn stop(self) -> Vec<JoinHandle<()>> {
        self.stop.store(true, Ordering::Release);
        // SAFETY: shutdown(2) on the listener's descriptor, which `self.listener` keeps open.
        unsafe { libc::shutdown(self.listener.as_raw_fd(), libc::SHUT_RDWR) };
        self.thread.join().unwrap_or_default()
    }
}

/// Identifies a file: its device and inode.
fn file_id(path: &std::path::Path) -> Option<(u64, u64)> {
    use std::os::unix::fs::MetadataExt as _;
    std::fs::symlink_metadata(path)
        .ok()
        .map(|m| (m.dev(), m.ino()))
}

impl std::fmt::Debug for Host {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Host")
            .field("system", &self.system)
            .field("socket", &self.socket)
            .finish_non_exhaustive()
    }
}

impl Host {
    /// The process's Zenoh session (the DNMs' own): queries and commands sent on it reach the
    /// hosted DNMs and every other DNM of the system.
    pub fn session(&self) -> &zenoh::Session {
        &self.session
    }

    pub fn system(&self) -> &str {
        &self.system
    }

    /// Waits until the DNMs stop (SIGINT/SIGTERM or [`Host::stop`]); the authority stops with
    /// them.
    pub fn wait(mut self) {
        self.hosted.join();
    }

    /// Stops every DNM of the process (their modules first) and waits for them.
    pub fn stop(self) {
        drop(self);
    }

    /// Starts DNMs `dnms` of `netlist` in this process, one thread each, with the admin socket.
    /// On error, whatever had started is stopped again.
    pub fn start(
        netlist: Netlist,
        dnms: &[String],
        options: HostOptions,
        zenoh: zenoh::Config,
    ) -> anyhow::Result<Host> {
        if !dnm_core::clear_stop_if_idle() {
            anyhow::bail!(
                "DNMs of this process are still stopping; wait for them before starting again"
            );
        }
        let session = zenoh::open(zenoh)
            .wait()
            .map_err(|e| anyhow::anyhow!("opening the Zenoh session: {e}"))?;
        tracing::info!(zid = %session.zid(), "on Zenoh");
        let follow = crate::commanded_by_authority(&netlist);
        let (netlist, joined) = join_running(&session, netlist, dnms, follow);
        let mut hosted = Hosted(Vec::new());
        // The authority's sequence events go to its DNM's recorder, once it runs.
        let sequences: SequenceSlot = Arc::default();
        for name in dnms {
            let start = DnmStart {
                netlist: netlist.clone(),
                name: name.clone(),
                options: options.clone(),
                session: session.clone(),
                joined: joined.clone(),
                follow,
                sequences: (netlist.authority() == Some(name.as_str())).then(|| sequences.clone()),
            };
            hosted.0.push(start.spawn()?);
        }
        let (socket, listener) = bind_socket(&netlist.system, dnms)?;
        let authority = start_authority(&session, &netlist, dnms, follow, &options, sequences)?;
        let commanders: Vec<Commander> = hosted.0.iter().map(|h| h.commander.clone()).collect();
        let system = netlist.system.clone();
        let follows = follow
            .then(|| netlist.authority().map(str::to_string))
            .flatten();
        let socket_id = file_id(&socket);
        let listener = Arc::new(listener);
        let stop = Arc::new(AtomicBool::new(false));
        let (served, stopped) = (listener.clone(), stop.clone());
        let thread = std::thread::Builder::new()
            .name("dnm-admin".into())
            .spawn(move || serve(&served, &system, follows.as_deref(), &commanders, &stopped))
            .context("spawning admin thread")?;
        Ok(Host {
            authority,
            session,
            system: netlist.system.clone(),
            hosted,
            socket,
            socket_id,
            admin: Some(Admin {
                listener,
                stop,
                thread,
            }),
        })
    }
}

impl Drop for Host {
    fn drop(&mut self) {
        // No command comes in while the DNMs stop; those being served are answered (a DNM
        // stopping refuses what it has not started) and their threads let go of the DNMs'
        // commanders, each a port of its DNM's wake-up event in shared memory.
        let serving = self.admin.take().map(Admin::stop).unwrap_or_default();
        self.hosted.stop_and_join();
        for t in serving {
            let _ = t.join();
        }
        if let Some(a) = self.authority.take() {
            a.stop();
        }
        // Not another process's, bound in its place; the system's folder stays (another
        // process of the system may be binding in it).
        if self.socket_id.is_some() && file_id(&self.socket) == self.socket_id {
            let _ = std::fs::remove_file(&self.socket);
        }
    }
}

/// A hosted DNM's thread and the way to command it.
struct DnmHandle {
    commander: Commander,
    thread: JoinHandle<()>,
}

/// The DNM threads started so far. Dropped, they are stopped and joined.
struct Hosted(Vec<DnmHandle>);

impl Hosted {
    /// Waits for every DNM thread to end.
    fn join(&mut self) {
        for h in self.0.drain(..) {
            let _ = h.thread.join();
        }
    }

    /// Stops every DNM still running (their modules first) and waits for them. Their bridges
    /// hold commanders too: dropping ours first leaves nothing here keeping a DNM busy.
    fn stop_and_join(&mut self) {
        if self.0.is_empty() {
            return;
        }
        dnm_core::request_stop();
        for h in self.0.drain(..) {
            drop(h.commander);
            let _ = h.thread.join();
        }
    }
}

impl Drop for Hosted {
    fn drop(&mut self) {
        self.stop_and_join();
    }
}

/// How long a starting DNM asks the running ones for the netlist in force.
const JOIN_TIMEOUT: Duration = Duration::from_secs(1);

/// Joining a running system: the netlist, revision and task in force there, when they still
/// have all of `dnms`. A system with an authority needs none of it: its DNMs start empty and
/// the authority has them adopt what it decided.
fn join_running(
    session: &zenoh::Session,
    netlist: Netlist,
    dnms: &[String],
    follow: bool,
) -> (Netlist, Option<(u64, Option<String>)>) {
    if follow {
        tracing::info!(authority = ?netlist.authority(), "the DNMs take what the authority decides");
        return (netlist, None);
    }
    if let Some(state) = dnm_zenoh::newest_netlist(session, &netlist.system, JOIN_TIMEOUT)
        && let Some((newer, revision, task)) = adopt(&state, &netlist, dnms)
    {
        tracing::info!(revision, task = ?task, "joining the running system");
        return (newer, Some((revision, task)));
    }
    (netlist, None)
}

/// The netlist, revision and task joining DNMs take over, if the running system's netlist is
/// valid here and still has all of them.
fn adopt(
    state: &dnm_proto::NetlistState,
    local: &Netlist,
    dnms: &[String],
) -> Option<(Netlist, u64, Option<String>)> {
    let text = state.text.as_ref()?;
    // It came over the network: external kinds only from this computer's module folder.
    let door = crate::remote_door(&local.system);
    match door.accept(&local.file.to_string_lossy(), text) {
        Ok(n) if dnms.iter().all(|d| n.dnm(d).is_some()) => {
            Some((n, state.revision, state.active_task.clone()))
        }
        Ok(_) => None,
        Err(e) => {
            tracing::warn!("the running system's netlist does not validate here: {e}");
            None
        }
    }
}

/// The admin socket of `dnms` of `system`, refused when they already run on this machine.
fn bind_socket(system: &str, dnms: &[String]) -> anyhow::Result<(PathBuf, UnixListener)> {
    let path = socket_path(system, dnms);
    if let Some(dir) = path.parent() {
        private_dir(dir).context("the admin socket folder")?;
    }
    if UnixStream::connect(&path).is_ok() {
        anyhow::bail!(
            "DNMs {} of system `{system}` are already running on this machine ({})",
            dnms.join(", "),
            path.display()
        );
    }
    let _ = std::fs::remove_file(&path);
    let listener =
        UnixListener::bind(&path).with_context(|| format!("binding {}", path.display()))?;
    tracing::info!(socket = %path.display(), "admin socket ready");
    Ok((path, listener))
}

/// The system's authority, when this process hosts its DNM and the DNMs follow it.
fn start_authority(
    session: &zenoh::Session,
    netlist: &Netlist,
    dnms: &[String],
    follow: bool,
    options: &HostOptions,
    sequences: SequenceSlot,
) -> anyhow::Result<Option<dnm_authority::Authority>> {
    if netlist
        .authority()
        .filter(|a| follow && dnms.iter().any(|d| d == a))
        .is_none()
    {
        return Ok(None);
    }
    let Some(dir) = options.state_dir.as_ref() else {
        anyhow::bail!("the authority did not start: {}", crate::NO_STATE_DIR);
    };
    let db = dir.join(format!("{}-authority.redb", netlist.system));
    let mut authority_options = dnm_authority::AuthorityOptions::new(db);
    authority_options.sequence_log = Some(dnm_authority::SequenceLog(Arc::new(move |e| {
        if let (Ok(slot), Ok(json)) = (sequences.lock(), serde_json::to_string(e))
            && let Some(r) = slot.as_ref()
        {
            r.record(json);
        }
    })));
    let authority = dnm_authority::Authority::start(
        session.clone(),
        netlist,
        crate::remote_door(&netlist.system),
        authority_options,
    )
    .map_err(|e| anyhow::anyhow!("the authority did not start: {e}"))?;
    Ok(Some(authority))
}

/// Where the authority's sequence events are recorded: its DNM's recorder, once it runs.
type SequenceSlot = Arc<Mutex<Option<crate::record::SequenceRecorder>>>;

/// What a DNM thread starts from.
struct DnmStart {
    netlist: Netlist,
    name: String,
    options: HostOptions,
    session: zenoh::Session,
    /// The revision and task of the running system it joins.
    joined: Option<(u64, Option<String>)>,
    /// It takes what the authority decides instead of applying the netlist.
    follow: bool,
    /// Set for the authority's DNM: its recorder records the sequence events.
    sequences: Option<SequenceSlot>,
}

impl DnmStart {
    /// Starts the DNM's thread and waits until the DNM runs (or failed to start).
    fn spawn(self) -> anyhow::Result<DnmHandle> {
        let (ready_tx, ready_rx) = mpsc::sync_channel::<Result<Commander, String>>(1);
        let name = self.name.clone();
        let thread = std::thread::Builder::new()
            .name(format!("dnm-{name}"))
            .spawn(move || self.run(&ready_tx))
            .context("spawning DNM thread")?;
        match ready_rx.recv() {
            Ok(Ok(commander)) => Ok(DnmHandle { commander, thread }),
            Ok(Err(e)) => {
                let _ = thread.join();
                anyhow::bail!("DNM `{name}` did not start: {e}");
            }
            Err(_) => anyhow::bail!("DNM `{name}` stopped while starting"),
        }
    }

    /// The DNM's thread: sets it up, says so on `ready`, and runs it until it stops.
    fn run(self, ready: &SyncSender<Result<Commander, String>>) {
        let name = self.name.clone();
        // The recording answers the ground while the DNM runs.
        let (mut dnm, _history) = match self.set_up() {
            Ok((dnm, commander, history)) => {
                let _ = ready.send(Ok(commander));
                (dnm, history)
            }
            Err(e) => {
                let _ = ready.send(Err(e.to_string()));
                return;
            }
        };
        if let Err(e) = dnm.run() {
            tracing::error!(dnm = %name, "DNM loop failed: {e}");
        }
        dnm.shutdown();
    }

    /// The DNM with its bridge and recorder (and its recording answering the ground), on the
    /// netlist (or waiting for its authority).
    fn set_up(self) -> anyhow::Result<(Dnm, Commander, Option<dnm_downlink::HistoryServer>)> {
        let (netlist, name) = (&self.netlist, self.name.as_str());
        let mut dnm = Dnm::new(&netlist.system, name, self.options.dnm)?;
        // What the recorder writes of the downlink plan (and every switch and event) goes
        // to the ground too.
        let tap = dnm_downlink::DownlinkTap::new(
            self.session.clone(),
            &netlist.system,
            name,
            self.options.downlink_cache,
        );
        let session = self.session.clone();
        let bridge = dnm_zenoh::Bridge::new(
            self.session,
            &netlist.system,
            name,
            dnm.prefix(),
            dnm.commander()?,
            crate::remote_door(&netlist.system),
        )?;
        let bridge = match netlist.authority().filter(|_| self.follow) {
            Some(a) => bridge.follow_authority(a)?,
            None => bridge,
        };
        dnm.add_plugin(Box::new(bridge));
        let mut history = None;
        if let Some(mut r) = self.options.record {
            r.tap = Some(Arc::new(tap));
            history = Some(dnm_downlink::HistoryServer::start(
                &session,
                &netlist.system,
                name,
                &r.dir,
            )?);
            let recorder = crate::record::Recorder::start(name, dnm.prefix(), r)?;
            if let Some(slot) = &self.sequences
                && let Ok(mut slot) = slot.lock()
            {
                *slot = Some(recorder.sequence_recorder());
            }
            dnm.add_plugin(Box::new(recorder));
        }
        // A DNM joining a running system continues from the netlist and task in force there.
        if let Some((revision, task)) = &self.joined {
            dnm.continue_from(revision.saturating_sub(1), task.as_deref());
        }
        if !self.follow {
            dnm.apply(netlist)?;
        }
        let commander = dnm.commander()?;
        Ok((dnm, commander, history))
    }
}
