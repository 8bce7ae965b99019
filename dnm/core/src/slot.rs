//! What a DNM holds per module and per output port, and the processes it is stopping.

use std::path::PathBuf;
use std::process::Child;
use std::time::{Duration, Instant};

use dnm_module::protocol::*;
use dnm_module::{event_service, plan_service_factory, status_service_factory};
use dnm_netlist::{KindSource, KindSpec, Netlist, Trigger};
use dnm_proto::ModuleRunState;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use iceoryx2::service::port_factory::event::PortFactory as EventFactory;
use iceoryx2::service::port_factory::publish_subscribe::PortFactory as PubSubFactory;

use crate::error::{DnmError, ipc};
use crate::procfs::CpuMeter;

pub(crate) type Svc = ipc::Service;

/// Keeps an output port's services alive while the DNM runs, so they outlive module restarts.
#[allow(dead_code)]
pub(crate) struct PortServices {
    pub(crate) data: PubSubFactory<Svc, [u8], PortHeader>,
    pub(crate) event: EventFactory<Svc>,
}

/// One module as its DNM holds it: its declaration, its control services and its process.
pub(crate) struct ModuleSlot {
    pub(crate) decl: dnm_netlist::Module,
    pub(crate) spec: KindSpec,
    pub(crate) source: KindSource,
    pub(crate) plan_pub: Publisher<Svc, [u8], ()>,
    pub(crate) wake: Notifier<Svc>,
    pub(crate) status_sub: Subscriber<Svc, Status, ()>,
    pub(crate) child: Option<Child>,
    /// When the current process was started.
    pub(crate) spawned_at: Instant,
    pub(crate) state: ModuleRunState,
    pub(crate) restarts: u32,
    /// Restarts in a row, each after a run shorter than a healthy one (the count
    /// `max_restarts` limits).
    pub(crate) streak: u32,
    pub(crate) hangs: u32,
    /// Set when the DNM killed the process because it hung: its exit is reported as such.
    pub(crate) killed_hung: Option<String>,
    /// Start the process at this time (a restart after a back-off, or a replacement once the
    /// old process is gone).
    pub(crate) start_at: Option<Instant>,
    pub(crate) last_exit: Option<String>,
    pub(crate) status: Status,
    pub(crate) rate: (Instant, u64, f64),
    pub(crate) cpu: CpuMeter,
    pub(crate) memory: Option<crate::proto::Memory>,
    /// How long it may go without a sign of life.
    pub(crate) hung_after: Duration,
}

impl ModuleSlot {
    pub(crate) fn pid(&self) -> Option<u32> {
        self.child.as_ref().map(Child::id)
    }

    /// The error its process posted in its last status before it exited (a failed build, a
    /// step's fatal error): the statuses still queued are taken first, and only the exited
    /// process's own counts. Call it before the child is dropped.
    pub(crate) fn last_error(&mut self) -> Option<String> {
        let pid = self.pid();
        while let Ok(Some(s)) = self.status_sub.receive() {
            if Some(s.pid) == pid {
                self.status = *s;
            }
        }
        pid.filter(|p| *p == self.status.pid)
            .and_then(|_| self.status.error())
    }

    /// Opens the module's control services; starts nothing.
    pub(crate) fn open(
        node: &Node<Svc>,
        netlist: &Netlist,
        name: &str,
        on_input_hung_after: Duration,
    ) -> Result<Self, DnmError> {
        let (decl, entry) = declared(netlist, name)?;
        let plan_pub = plan_service_factory(node, name)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .publisher_builder()
            .initial_max_slice_len(MAX_PLAN_BYTES)
            .create()
            .map_err(ipc("plan publisher"))?;
        let wake = event_service(node, &wake_event(name))
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .notifier_builder()
            .create()
            .map_err(ipc("wake notifier"))?;
        let status_sub = status_service_factory(node, name)
            .map_err(|e| DnmError::Ipc(e.to_string()))?
            .subscriber_builder()
            .create()
            .map_err(ipc("status subscriber"))?;
        let hung_after = hung_deadline(&decl, &entry.spec, on_input_hung_after);
        Ok(ModuleSlot {
            decl,
            spec: entry.spec,
            source: entry.source,
            plan_pub,
            wake,
            status_sub,
            child: None,
            spawned_at: Instant::now(),
            state: ModuleRunState::Starting,
            restarts: 0,
            streak: 0,
            hangs: 0,
            killed_hung: None,
            start_at: None,
            last_exit: None,
            status: Status::default(),
            rate: (Instant::now(), 0, 0.0),
            cpu: CpuMeter::default(),
            memory: None,
            hung_after,
        })
    }

    /// Takes a new declaration (a replacement): same name, so the same control services.
    pub(crate) fn redeclare(
        &mut self,
        netlist: &Netlist,
        on_input_hung_after: Duration,
    ) -> Result<(), DnmError> {
        let (decl, entry) = declared(netlist, &self.decl.name)?;
        self.hung_after = hung_deadline(&decl, &entry.spec, on_input_hung_after);
        self.decl = decl;
        self.spec = entry.spec;
        self.source = entry.source;
        self.restarts = 0;
        self.streak = 0;
        self.status = Status::default();
        self.rate = (Instant::now(), 0, 0.0);
        Ok(())
    }

    /// Posts a plan; the module finds the last two plans as history when it (re)starts.
    pub(crate) fn post_plan(&self, plan: &Plan) -> Result<(), DnmError> {
        let bytes = serde_json::to_vec(plan).map_err(|e| DnmError::Ipc(e.to_string()))?;
        if bytes.len() > MAX_PLAN_BYTES {
            return Err(DnmError::Ipc(format!(
                "plan of `{}` is {} bytes, more than {MAX_PLAN_BYTES}",
                self.decl.name,
                bytes.len()
            )));
        }
        let sample = self
            .plan_pub
            .loan_slice_uninit(bytes.len())
            .map_err(ipc("loan plan"))?;
        sample
            .write_from_slice(&bytes)
            .send()
            .map_err(ipc("post plan"))?;
        self.wake.notify().map_err(ipc("wake module"))?;
        Ok(())
    }

    /// The executable that runs this module.
    pub(crate) fn exec(&self, module_host: &std::path::Path) -> PathBuf {
        exec_of(&self.source, module_host)
    }
}

/// The executable that runs modules of a kind from `source`.
pub(crate) fn exec_of(source: &KindSource, module_host: &std::path::Path) -> PathBuf {
    match source {
        KindSource::BuiltIn => module_host.to_path_buf(),
        KindSource::Exec { path } => PathBuf::from(path),
    }
}

/// A module's declaration in `netlist` and its kind's catalogue entry.
fn declared(
    netlist: &Netlist,
    name: &str,
) -> Result<(dnm_netlist::Module, dnm_netlist::CatalogEntry), DnmError> {
    let decl = netlist
        .module(name)
        .ok_or_else(|| DnmError::Ipc(format!("module {name} vanished")))?
        .clone();
    let entry = netlist
        .catalog
        .get(&decl.kind)
        .ok_or_else(|| DnmError::Ipc(format!("kind {} vanished", decl.kind)))?
        .clone();
    Ok((decl, entry))
}

/// How long a module may go without a sign of life: its own `hung_after`, else five periods of
/// a periodic module (at least a second), else the DNM's default for on-input modules. Never
/// less than two heartbeats (two periods for a periodic module) plus slack for supervision,
/// so a healthy module cannot look hung.
fn hung_deadline(decl: &dnm_netlist::Module, spec: &KindSpec, on_input: Duration) -> Duration {
    let slack = Duration::from_millis(250);
    let period = match (spec.trigger, decl.rate_hz) {
        (Trigger::Periodic { .. }, Some(rate_hz)) | (Trigger::Periodic { rate_hz }, None) => {
            Some(Duration::try_from_secs_f64(1.0 / rate_hz).unwrap_or(Duration::MAX))
        }
        (Trigger::OnInput, _) => None,
    };
    let floor = match period {
        Some(p) => p.saturating_mul(2).saturating_add(slack),
        None => HEARTBEAT.saturating_mul(2).saturating_add(slack),
    };
    let chosen = match (decl.hung_after_ms, period) {
        (Some(ms), _) => Duration::from_millis(ms),
        (None, Some(p)) => p.saturating_mul(5).max(Duration::from_secs(1)),
        (None, None) => on_input,
    };
    chosen.max(floor)
}

/// A process on its way out: SIGTERM sent, SIGKILL at `kill_at`, reaped by supervision.
pub(crate) struct Stopping {
    pub(crate) module: String,
    pub(crate) child: Child,
    pub(crate) kill_at: Instant,
    /// The module's control and port services, kept (never read) until the process is gone so
    /// they are not removed while it still uses them, and a new module of the name opens fresh
    /// ones.
    #[allow(dead_code)]
    pub(crate) held_slot: Option<ModuleSlot>,
    #[allow(dead_code)]
    pub(crate) held_ports: Vec<PortServices>,
}
