//! A `dnm up` process hosting a test system, read and driven like an operator would.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

use dnm::admin::{Request, Response, request};
use dnm_module::port_service;
use dnm_module::protocol::{PortHeader, dnm_config, dnm_prefix, output_service};
use dnm_netlist::Payload;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;

/// Waits for conditions in tests; generous so a loaded machine does not fail them.
pub const PATIENCE: Duration = Duration::from_secs(30);

static NEXT: AtomicU32 = AtomicU32::new(0);

/// The module host built beside the `dnm` executable.
pub fn module_host() -> PathBuf {
    let host = std::path::Path::new(env!("CARGO_BIN_EXE_dnm")).with_file_name("dnm-module-host");
    assert!(
        host.exists(),
        "no {}: run the tests with `cargo test --workspace`, which builds it",
        host.display()
    );
    host
}

/// A running `dnm up` with a unique system name; stopped with SIGTERM when dropped.
pub struct System {
    pub name: String,
    pub dir: PathBuf,
    pub child: Child,
    pub node: Node<ipc::Service>,
}

impl System {
    pub fn start(template: &str) -> Self {
        Self::start_with(template, &[])
    }

    /// Starts `dnm [global] up NETLIST`, e.g. with `--listen` to reach it over Zenoh.
    pub fn start_with(template: &str, global: &[&str]) -> Self {
        let name = format!(
            "t{}x{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        );
        let dir = std::env::temp_dir().join(format!("dnm-test-{name}"));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("netlist.toml");
        std::fs::write(&path, template.replace("SYSTEM", &name)).unwrap();
        let child = Command::new(env!("CARGO_BIN_EXE_dnm"))
            .args(global)
            .arg("up")
            .arg(&path)
            .env("DNM_MODULE_HOST", module_host())
            .env("DNM_RECORD_DIR", &dir)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .unwrap();
        let config = dnm_config(&dnm_prefix(&name, "main")).unwrap();
        let node = NodeBuilder::new()
            .config(&config)
            .create::<ipc::Service>()
            .unwrap();
        let sys = System {
            name,
            dir,
            child,
            node,
        };
        sys.wait_for("all modules running", |r| {
            r.dnms.iter().all(|d| {
                d.modules
                    .iter()
                    .all(|m| m.state == dnm::ModuleRunState::Running)
            })
        });
        sys
    }

    pub fn ask(&self, req: &Request) -> Response {
        request(&self.name, req).unwrap()
    }

    pub fn status(&self) -> dnm::DnmReport {
        self.ask(&Request::Status).dnms.remove(0)
    }

    pub fn wait_for(&self, what: &str, ok: impl Fn(&Response) -> bool) -> Response {
        let deadline = Instant::now() + PATIENCE;
        loop {
            if let Ok(r) = request(&self.name, &Request::Status)
                && ok(&r)
            {
                return r;
            }
            assert!(Instant::now() < deadline, "gave up waiting for {what}");
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    pub fn subscribe<M>(
        &self,
        module: &str,
        port: &str,
    ) -> Subscriber<ipc::Service, [u8], PortHeader> {
        let payload = Payload::Fixed {
            size_bytes: size_of::<M>(),
        };
        port_service(&self.node, &output_service(module, port), &payload)
            .unwrap()
            .subscriber_builder()
            .create()
            .unwrap()
    }

    pub fn dnm(&self, args: &[&str]) -> std::process::Output {
        Command::new(env!("CARGO_BIN_EXE_dnm"))
            .args(args)
            .output()
            .unwrap()
    }
}

impl Drop for System {
    fn drop(&mut self) {
        // Not one a test has stopped and reaped already (its pid may be another's now).
        if matches!(self.child.try_wait(), Ok(None)) {
            // SAFETY: kill(2) on our own child, not reaped yet.
            unsafe { libc::kill(self.child.id() as i32, libc::SIGTERM) };
        }
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// Collects values from a subscriber until `enough` says so (or patience runs out).
pub fn collect<M: bytemuck::Pod>(
    sub: &Subscriber<ipc::Service, [u8], PortHeader>,
    mut enough: impl FnMut(&[M]) -> bool,
) -> Vec<M> {
    let mut got = Vec::new();
    let deadline = Instant::now() + PATIENCE;
    while !enough(&got) {
        assert!(
            Instant::now() < deadline,
            "gave up collecting samples ({} so far)",
            got.len()
        );
        while let Some(s) = sub.receive().unwrap() {
            got.push(bytemuck::pod_read_unaligned::<M>(s.payload()));
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    got
}

pub fn drain(sub: &Subscriber<ipc::Service, [u8], PortHeader>) {
    while sub.receive().unwrap().is_some() {}
}
