//! The ground station's web interface in a real headless Chromium (over WebDriver), against a
//! running system and a real station: an operator composes a task by drawing links, applies
//! it and switches to it through the outbox; a link between mismatched types is refused in the
//! page; a killed module shows failed and then running again; an output is watched; an onboard
//! sequence is written (the task editor adding its switches), uploaded, started, paused, resumed
//! and seen to finish, and one naming a task the rover lacks is refused with the rover's
//! located reason. And the page's responsiveness with a system of 200 modules, measured in the
//! browser.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod support;

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde_json::{Value, json};
use support::eventually;
use support::ground::{Api, Proc, report, wait_in_step, zenoh_args};
use support::webdriver::Browser;

/// One browser test at a time: each runs a whole system and a browser, and this machine may
/// have two cores.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn exclusive() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// Where the screenshots go (`target/tmp/web/`).
fn shots() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR")).join("web")
}

/// A Zenoh router listening on `port` (loopback), once it listens.
fn router(dir: &Path, port: u16) -> Proc {
    let p = Proc::dnm(
        dir,
        "router",
        &[
            "--no-multicast".into(),
            "--listen".into(),
            support::endpoint(port),
            "router".into(),
        ],
    );
    eventually("the router listening", || {
        std::net::TcpStream::connect(("127.0.0.1", port)).ok()
    });
    p
}

/// A router, the system's DNMs (one `dnm up`) and a ground station, on loopback.
struct Rig {
    system: String,
    dir: PathBuf,
    port: u16,
    http: String,
    _procs: Vec<Proc>,
}

impl Drop for Rig {
    fn drop(&mut self) {
        self._procs.clear();
        support::remove_unless_failed(&self.dir);
    }
}

impl Rig {
    fn start(tag: &str, netlist: &str) -> Self {
        let system = format!("w{tag}{}", std::process::id());
        let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        let file = dir.join("netlist.toml");
        std::fs::write(&file, netlist.replace("SYSTEM", &system)).unwrap();
        let port = support::free_port();
        let http = format!("127.0.0.1:{}", support::free_port());
        let router = router(&dir, port);
        let mut up = zenoh_args("peer", port);
        up.extend([
            "up".into(),
            file.display().to_string(),
            // Recording: the station's record of the rover is filled from it.
            "--record-dir".into(),
            dir.join("rec").display().to_string(),
            "--state-dir".into(),
            dir.join("state").display().to_string(),
        ]);
        let up = Proc::dnm(&dir, "up", &up);
        let mut st = zenoh_args("client", port);
        st.extend([
            "ground".into(),
            "serve".into(),
            "--system".into(),
            system.clone(),
            "--db".into(),
            dir.join("ground.redb").display().to_string(),
            "--http".into(),
            http.clone(),
        ]);
        let station = Proc::dnm(&dir, "station", &st);
        let api = Api(format!("http://{http}"));
        eventually("the station's API", || api.up().then_some(()));
        // The page opens on a running system: the station has the netlist in force from the
        // rover (starting a system's module processes can take long on a loaded machine).
        support::eventually_within(
            "the station holding the rover's netlist",
            Duration::from_secs(600),
            || (api.status("/api/netlist") == 200).then_some(()),
        );
        Self {
            system,
            dir,
            port,
            http,
            _procs: vec![station, up, router],
        }
    }

    fn url(&self, hash: &str) -> String {
        format!("http://{}/{hash}", self.http)
    }

    fn api(&self) -> Api {
        Api(format!("http://{}", self.http))
    }
}

/// Waits until `js` (an expression) is truthy in the page and returns its value. If it never
/// is, the failure says what the page showed (and `target/tmp/web/failed.png` shows it).
fn until(b: &Browser, what: &str, js: &str) -> Value {
    let script = format!("try {{ return ({js}); }} catch (e) {{ return null; }}");
    let deadline = std::time::Instant::now() + Duration::from_secs(60);
    loop {
        let v = b.js(&script, json!([]));
        let truthy = match &v {
            Value::Null => false,
            Value::Bool(x) => *x,
            Value::String(s) => !s.is_empty(),
            Value::Number(n) => n.as_f64() != Some(0.0),
            _ => true,
        };
        if truthy {
            return v;
        }
        if std::time::Instant::now() > deadline {
            b.screenshot(&shots().join("failed.png"));
            let page = b.js(
                "const t = (id) => (document.getElementById(id) || {}).textContent; \
                 const S = window.__dnm || {}; \
                 return { message: t('message'), link: t('link-status'), check: t('check-state'), \
                 problems: t('problems'), draft_base: t('draft-base'), task: S.task, \
                 sequences: t('sequences'), sequence_commands: t('seq-commands'), \
                 modules: S.draft && S.draft.module && S.draft.module.length, \
                 kinds: S.kinds && Object.keys(S.kinds).length };",
                json!([]),
            );
            panic!("gave up waiting: {what}; the page showed {page}");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The drawing's geometry, from the page itself: link segments that cross a module's box (a
/// segment touching a box's edge, at its port, does not), link labels that overlap, links not
/// drawn as straight runs, and how many links, labels and radio links there are.
fn layout_faults(b: &Browser) -> Value {
    b.js(
        r#"const boxes = [...document.querySelectorAll('g.module > rect.box')].map(r => ({
             m: r.parentNode.dataset.module, x: +r.getAttribute('x'), y: +r.getAttribute('y'),
             w: +r.getAttribute('width'), h: +r.getAttribute('height') }));
           const crossings = [], curved = [];
           const paths = [...document.querySelectorAll('path.link')];
           for (const p of paths) {
             const d = p.getAttribute('d'), name = p.dataset.activeLink || p.dataset.link;
             if (/[CQSAcqsa]/.test(d)) curved.push(name);
             const pts = (d.match(/-?[\d.]+,-?[\d.]+/g) || []).map(s => s.split(',').map(Number));
             for (let i = 0; i + 1 < pts.length; i++) {
               const [a, c] = [pts[i], pts[i + 1]];
               const x0 = Math.min(a[0], c[0]), x1 = Math.max(a[0], c[0]);
               const y0 = Math.min(a[1], c[1]), y1 = Math.max(a[1], c[1]);
               for (const r of boxes) {
                 if (x1 > r.x + 0.5 && x0 < r.x + r.w - 0.5 && y1 > r.y + 0.5 && y0 < r.y + r.h - 0.5)
                   crossings.push(`${name} crosses ${r.m}`);
               }
             }
           }
           const labels = [...document.querySelectorAll('text.link-label')].map(t => ({ t: t.textContent, b: t.getBBox() }));
           const overlaps = [];
           for (let i = 0; i < labels.length; i++) for (let j = i + 1; j < labels.length; j++) {
             const [p, q] = [labels[i].b, labels[j].b];
             if (p.x < q.x + q.width && q.x < p.x + p.width && p.y < q.y + q.height && q.y < p.y + p.height)
               overlaps.push(`${labels[i].t} / ${labels[j].t}`);
           }
           return { crossings, overlaps, curved, links: paths.length, labels: labels.length,
                    radio: paths.filter(p => p.classList.contains('radio')).length };"#,
        json!([]),
    )
}

/// No link crosses a box, no two labels overlap, every link is drawn in straight runs.
fn assert_readable(b: &Browser, view: &str) -> Value {
    let g = layout_faults(b);
    for fault in ["crossings", "overlaps", "curved"] {
        assert_eq!(g[fault], json!([]), "{view} view: {fault}: {g:#}");
    }
    assert!(
        g["links"].as_u64().unwrap() > 0,
        "{view} view: no links drawn: {g:#}"
    );
    g
}

fn port(p: &str, dir: &str) -> String {
    format!("circle.port[data-port=\"{p}\"][data-dir=\"{dir}\"]")
}

/// The links of the task shown in the editor.
fn draft_links(b: &Browser) -> Vec<String> {
    serde_json::from_value(b.js(
        "const S = window.__dnm; return (S.draft.task[S.task].links || []);",
        json!([]),
    ))
    .unwrap()
}

const CREEP: [(&str, &str); 8] = [
    ("watchdog.twist", "mixer.twist"),
    ("mixer.left", "motor_left.command"),
    ("mixer.right", "motor_right.command"),
    ("motor_left.state", "world.left"),
    ("motor_right.state", "world.right"),
    ("world.state", "encoders.world"),
    ("encoders.ticks", "odometry.ticks"),
    ("world.state", "range.world"),
];

#[test]
fn an_operator_composes_a_task_in_the_browser_applies_it_switches_to_it_watches_a_module_fail_and_runs_a_sequence()
 {
    let _one = exclusive();
    let beetle = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/beetle.toml"),
    )
    .unwrap()
    .replace("name = \"beetle\"", "name = \"SYSTEM\"");
    let rig = Rig::start("ui", &beetle);
    let dnms = ["rover", "drive", "vision", "ground"];
    let z = support::zenoh_client(rig.port);
    let b = Browser::start(&rig.dir, 1600, 1000);
    b.goto(&rig.url(""));
    until(
        &b,
        "the draft loaded from the netlist in force and checked valid",
        "window.__dnm.check && window.__dnm.check.ok && window.__dnm.draft.module.length === 15",
    );

    // Beetle-One's teleop task, drawn by data flow: no link through a box, no label on
    // another, in the task view and in the connection view (rates measured, the joystick's
    // links across the radio drawn as such).
    assert_readable(&b, "task");
    // By data flow: the joystick (the one source) before what it feeds, both motors in one
    // column, the world they drive after them.
    let x: Value = b.js(
        "return Object.fromEntries([...document.querySelectorAll('g.module')].map(g => [g.dataset.module, +g.querySelector('rect.box').getAttribute('x')]))",
        json!([]),
    );
    let col = |m: &str| x[m].as_f64().unwrap();
    assert!(col("joystick") < col("obstacle_stop"), "{x}");
    assert!(col("obstacle_stop") < col("watchdog"), "{x}");
    assert_eq!(col("motor_left"), col("motor_right"), "{x}");
    assert!(col("motor_left") < col("world"), "{x}");
    b.click("#tab-connections");
    until(
        &b,
        "the connection view with every module running and its rates",
        "document.querySelectorAll('g.module[data-state=running]').length === 15 && [...document.querySelectorAll('text.link-label')].some(t => !t.textContent.startsWith('0 Hz'))",
    );
    let g = assert_readable(&b, "connection");
    assert!(g["radio"].as_u64().unwrap() >= 1, "no radio link: {g:#}");
    assert!(g["labels"].as_u64().unwrap() >= 5, "rate labels: {g:#}");
    b.screenshot(&shots().join("connections-teleop.png"));
    b.click("#tab-tasks");

    // A link between mismatched types is refused in the page, with the reason.
    let before = draft_links(&b);
    b.drag(&port("odometry.odom", "out"), &port("mixer.twist", "in"));
    let msg = b.text("#message");
    assert_eq!(
        b.js(
            "return document.getElementById('message').dataset.kind",
            json!([])
        ),
        "refused",
        "{msg}"
    );
    assert!(
        msg.contains("beetle_msgs/Odometry") && msg.contains("mixer.twist takes"),
        "the reason names both types: {msg}"
    );
    assert_eq!(draft_links(&b), before, "nothing was linked");

    // A new task, drawn link by link.
    b.type_into("#task-name", "creep");
    b.click("#task-new");
    until(&b, "task creep selected", "window.__dnm.task === 'creep'");
    assert!(draft_links(&b).is_empty());
    for (from, to) in CREEP {
        b.drag(&port(from, "out"), &port(to, "in"));
        let msg = b.text("#message");
        assert!(msg.starts_with("linked"), "{from} -> {to}: {msg}");
    }
    // A parameter edited in the inspector: the watchdog stops the rover sooner.
    b.js(
        "document.querySelector('g.module[data-module=watchdog] rect.head').scrollIntoView({block: 'center', inline: 'center'}); return null;",
        json!([]),
    );
    b.click("g.module[data-module=watchdog] rect.head");
    b.retype("input[data-param=timeout]", "0.4");
    b.click("#task-name"); // leaving the field commits the edit
    until(
        &b,
        "the watchdog's timeout in the draft",
        "window.__dnm.draft.module.find(m => m.name === 'watchdog').params.timeout === 0.4",
    );
    let drawn = draft_links(&b);
    let want: Vec<String> = CREEP.iter().map(|(f, t)| format!("{f} -> {t}")).collect();
    assert_eq!(drawn, want);
    // The check of this very draft (the edit above started a new one; until it answers, the
    // previous check is still the page's and the apply button is disabled).
    until(
        &b,
        "the draft checked valid",
        "document.getElementById('check-state').textContent === 'valid' && !document.getElementById('draft-apply').disabled && window.__dnm.check.ok && window.__dnm.check.toml.includes('[task.creep]') && window.__dnm.check.toml.includes('timeout = 0.4')",
    );
    assert_readable(&b, "task");
    // From the sources on the left (drawing links scrolled the view).
    b.js(
        "document.getElementById('canvas-wrap').scrollTo(0, 0); return null;",
        json!([]),
    );
    b.screenshot(&shots().join("tasks.png"));

    // The exported netlist is what is applied.
    b.click("#draft-export");
    let exported = b.text("#export-text");
    assert!(
        exported.contains("[task.creep]") && exported.contains("encoders.ticks -> odometry.ticks"),
        "{exported}"
    );
    b.click("#export-close");

    // Applied through the outbox, then switched to; the page shows each command's state.
    b.click("#draft-apply");
    let applied = until(
        &b,
        "the apply applied (outbox in the page)",
        "[...document.querySelectorAll('#outbox li')].find(li => li.textContent.includes('apply') && li.dataset.state === 'applied')?.dataset.seq",
    );
    let seq: u64 = applied.as_str().unwrap().parse().unwrap();
    let entry = rig.api().entry(seq, 0);
    assert_eq!(entry.state, dnm_ground::CommandState::Applied, "{entry:?}");
    let in_force: Value = serde_json::from_str(
        &ureq::get(format!("http://{}/api/netlist", rig.http))
            .call()
            .unwrap()
            .body_mut()
            .read_to_string()
            .unwrap(),
    )
    .unwrap();
    let watchdog = in_force["doc"]["module"]
        .as_array()
        .unwrap()
        .iter()
        .find(|m| m["name"] == "watchdog")
        .unwrap();
    assert_eq!(watchdog["params"]["timeout"], 0.4, "{watchdog}");
    b.click("#task-switch");
    until(
        &b,
        "the switch applied (outbox in the page)",
        "[...document.querySelectorAll('#outbox li')].some(li => li.textContent.includes('switch to creep') && li.dataset.state === 'applied')",
    );
    // Every DNM reports it.
    let revision = wait_in_step(&z, &rig.system, &dnms, "creep");
    for d in dnms {
        let r = report(&z, &rig.system, d).unwrap();
        assert_eq!(r.active_task.as_deref(), Some("creep"), "{d}");
        assert_eq!(r.revision, revision, "{d}");
    }

    // The connection view: the task in force, every module running.
    b.click("#tab-connections");
    until(
        &b,
        "the connection view on task creep",
        "document.getElementById('conn-summary').textContent.includes('task creep') && document.querySelectorAll('g.module[data-state=running]').length === 15",
    );
    assert_readable(&b, "connection");
    let active: Vec<String> = serde_json::from_value(b.js(
        "return [...document.querySelectorAll('[data-active-link]')].map(e => e.dataset.activeLink)",
        json!([]),
    ))
    .unwrap();
    let mut want_sorted = want.clone();
    want_sorted.sort();
    let mut active_sorted = active.clone();
    active_sorted.sort();
    assert_eq!(
        active_sorted, want_sorted,
        "the links in force are highlighted"
    );

    // Killing a module: failed in the view, then running after its restart.
    let pid = report(&z, &rig.system, "rover")
        .unwrap()
        .modules
        .iter()
        .find(|m| m.name == "range")
        .and_then(|m| m.pid)
        .unwrap();
    // SAFETY: kill(2) on a module process this test's system started.
    unsafe { libc::kill(pid as i32, libc::SIGKILL) };
    until(
        &b,
        "range shown failed",
        "document.querySelector('g.module[data-module=range]').dataset.state === 'failed'",
    );
    until(
        &b,
        "range running again after its restart",
        "(g => g.dataset.state === 'running' && Number(g.dataset.restarts) >= 1)(document.querySelector('g.module[data-module=range]'))",
    );
    let events = b.text("#history");
    assert!(events.contains("range exited"), "{events}");

    // Watching an output: its values through the on-demand feed.
    b.click(&port("odometry.odom", "out"));
    until(
        &b,
        "odometry.odom's values in the watch panel",
        "window.__dnm.watch && window.__dnm.watch.samples.length >= 3 && document.querySelector('#watch-values')",
    );
    let values = b.text("#watch-values");
    assert!(values.contains('x') && values.contains("yaw"), "{values}");
    // From the sources on the left (drawing links scrolled the view).
    b.js(
        "document.getElementById('canvas-wrap').scrollTo(0, 0); return null;",
        json!([]),
    );
    b.screenshot(&shots().join("connections.png"));

    // The ground's record of the rover: Beetle-One's downlink plan, what the station missed
    // before it heard the rover filled in from the rover's recording.
    until(
        &b,
        "the record panel showing the pose and the battery complete",
        "['/rover/odometry/odom', '/rover/battery/state'].every((t) => { \
           const r = document.querySelector(`#record tbody tr[data-topic=\"${t}\"]`); \
           return r && r.classList.contains('whole') && +r.children[3].textContent.split(' / ')[0] > 5; })",
    );
    b.screenshot(&shots().join("record.png"));

    run_a_sequence_from_the_page(&b, &rig, &z, &dnms);
    eprintln!("screenshots in {}", shots().display());
}

/// The sequence panel's card of sequence `name` shows `js` (an expression of its element `q`).
fn card(b: &Browser, name: &str, what: &str, js: &str) -> Value {
    until(
        b,
        &format!("sequence {name}: {what}"),
        &format!("(q => q && ({js}))(document.querySelector('.seq[data-seq=\"{name}\"]'))"),
    )
}

/// Picks `task` in the task editor's selector, as an operator choosing it does.
fn pick_task(b: &Browser, task: &str) {
    b.js(
        "const s = document.getElementById('task-select'); s.value = arguments[0]; \
         s.dispatchEvent(new Event('change'));",
        json!([task]),
    );
    until(
        b,
        &format!("task {task} in the editor"),
        &format!("window.__dnm.task === {}", json!(task)),
    );
}

/// An onboard sequence written in the page (its switches added from the task editor), uploaded,
/// started, paused, resumed and seen to finish, every DNM through its tasks; a sequence file
/// chosen and uploaded; a sequence naming a task the rover lacks refused with the rover's
/// located reason.
fn run_a_sequence_from_the_page(b: &Browser, rig: &Rig, z: &zenoh::Session, dnms: &[&str]) {
    b.click("#tab-tasks");
    b.type_into("#seq-text", "[sequence]\nname = \"tour\"\n");
    pick_task(b, "auto");
    b.click("#task-step");
    b.type_after("#seq-text", "\n[[step]]\nwait = \"10s\"\n");
    pick_task(b, "creep");
    b.click("#task-step");
    let written = b.js(
        "return document.getElementById('seq-text').value",
        json!([]),
    );
    assert_eq!(
        written,
        "[sequence]\nname = \"tour\"\n\n[[step]]\nswitch = \"auto\"\n\n[[step]]\nwait = \"10s\"\n\n[[step]]\nswitch = \"creep\"\n",
        "the steps the task editor added"
    );
    b.click("#seq-upload");
    card(b, "tour", "stored", "q.dataset.state === 'stored'");
    let steps = b.text(".seq[data-seq=tour] .seq-step");
    assert!(steps.starts_with("3 steps"), "{steps}");

    b.click(".seq[data-seq=tour] button[data-seq-act=start]");
    card(
        b,
        "tour",
        "running, on its wait",
        "q.dataset.state === 'running' && q.querySelector('.seq-step').textContent.startsWith('step 2/3: wait')",
    );
    b.screenshot(&shots().join("sequence-running.png"));
    b.click(".seq[data-seq=tour] button[data-seq-act=pause]");
    card(
        b,
        "tour",
        "paused, saying so",
        "q.dataset.state === 'paused' && q.querySelector('.seq-why').textContent.includes('paused') && q.querySelector('button[data-seq-act=resume]')",
    );
    b.click(".seq[data-seq=tour] button[data-seq-act=resume]");
    card(
        b,
        "tour",
        "finished",
        "q.dataset.state === 'finished' && q.querySelector('.seq-step').textContent === 'went through its 3 steps'",
    );
    let history = b.text(".seq[data-seq=tour] .seq-history");
    for what in ["finished", "resumed", "paused"] {
        assert!(history.contains(what), "{what}: {history}");
    }
    assert!(
        b.try_element(".seq[data-seq=tour] button[data-seq-act=start]")
            .is_some(),
        "a finished sequence may be started again"
    );
    // Every DNM went to `auto` and back to `creep`.
    wait_in_step(z, &rig.system, dnms, "creep");
    for d in dnms {
        let tasks: Vec<String> = report(z, &rig.system, d)
            .unwrap()
            .switches
            .into_iter()
            .map(|s| s.to)
            .collect();
        assert!(
            tasks.ends_with(&["auto".to_string(), "creep".to_string()]),
            "{d}: {tasks:?}"
        );
    }

    // A sequence file chosen in the page is uploaded under the name it gives itself.
    let explore = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../configs/sequences/explore.toml")
        .canonicalize()
        .unwrap();
    b.choose_file("#seq-file", &explore);
    until(
        b,
        "explore.toml read into the page",
        "document.getElementById('seq-text').value.includes('name = \"explore\"')",
    );
    b.click("#seq-upload");
    card(b, "explore", "stored", "q.dataset.state === 'stored'");
    let head = b.text(".seq[data-seq=explore] .seq-head");
    assert!(head.contains("explore.toml"), "{head}");
    let steps = b.text(".seq[data-seq=explore] .seq-step");
    assert!(steps.starts_with("5 steps"), "{steps}");

    // A task the rover does not have: refused, with the rover's located reason in the page.
    b.type_into(
        "#seq-text",
        "[sequence]\nname = \"lost\"\n\n[[step]]\nswitch = \"nowhere\"\n",
    );
    b.click("#seq-upload");
    let reason = until(
        b,
        "the upload of lost refused in the sequence panel",
        "[...document.querySelectorAll('#seq-commands li')].find(li => li.textContent.includes('upload sequence lost') && li.dataset.state === 'refused')?.textContent",
    );
    let reason = reason.as_str().unwrap();
    assert!(
        reason.contains("nowhere") && reason.contains("lost.toml:5:"),
        "the reason names the task and where: {reason}"
    );
    let outbox = b.text("#outbox");
    assert!(outbox.contains("upload sequence lost"), "{outbox}");
    assert!(
        b.try_element(".seq[data-seq=lost]").is_none(),
        "nothing stored"
    );
    b.screenshot(&shots().join("sequences.png"));
}

/// 200 modules on 4 DNMs: 100 tickers, each feeding a relay; task `u` shifts every link.
fn big_netlist() -> String {
    let mut s = String::from(
        "[system]\nname = \"SYSTEM\"\ndefault_task = \"t\"\n\n[[dnm]]\nname = \"main\"\n\n[[dnm]]\nname = \"a\"\nparent = \"main\"\n\n[[dnm]]\nname = \"b\"\nparent = \"main\"\n\n[[dnm]]\nname = \"c\"\nparent = \"main\"\n",
    );
    let dnm = |i: usize| ["main", "a", "b", "c"][i % 4];
    for i in 0..100 {
        s += &format!(
            "\n[[module]]\nname = \"src{i}\"\nkind = \"ticker\"\ndnm = \"{}\"\nrate_hz = 2\nparams = {{ origin = {i} }}\n",
            dnm(i)
        );
        s += &format!(
            "\n[[module]]\nname = \"relay{i}\"\nkind = \"relay\"\ndnm = \"{}\"\n",
            dnm(i + 1)
        );
    }
    let links = |shift: usize| {
        (0..100)
            .map(|i| format!("\"src{i}.out -> relay{}.in\"", (i + shift) % 100))
            .collect::<Vec<_>>()
            .join(", ")
    };
    s += &format!("\n[task.t]\nlinks = [{}]\n", links(0));
    s += &format!("\n[task.u]\nlinks = [{}]\n", links(1));
    s
}

#[test]
fn the_page_stays_responsive_with_a_system_of_200_modules() {
    let _one = exclusive();
    let rig = Rig::start("big", &big_netlist());
    let z = support::zenoh_client(rig.port);
    // Starting 200 module processes takes a while on a small machine (a hang guard only).
    let starting = std::time::Instant::now();
    support::eventually_within("200 modules running", Duration::from_secs(600), || {
        let all = ["main", "a", "b", "c"].iter().all(|d| {
            report(&z, &rig.system, d).is_some_and(|r| {
                r.revision > 0
                    && r.modules.len() == 50
                    && r.modules
                        .iter()
                        .all(|m| m.state == dnm::ModuleRunState::Running)
            })
        });
        all.then_some(())
    });
    let start_s = starting.elapsed().as_secs_f64();
    let b = Browser::start(&rig.dir, 1600, 1000);
    b.goto(&rig.url(""));
    let loaded = until(
        &b,
        "the 200-module draft rendered and checked",
        "window.__dnm.draft && window.__dnm.draft.module.length === 200 && window.__dnm.check && window.__dnm.check.ok && window.__dnm.perf.firstDraftMs",
    );

    // An edit: a new task and one drawn link, until the check of the changed draft is back.
    b.type_into("#task-name", "probe");
    b.click("#task-new");
    until(&b, "task probe selected", "window.__dnm.task === 'probe'");
    until(
        &b,
        "the new task checked",
        "window.__dnm.check && window.__dnm.check.ok && window.__dnm.check.toml.includes('[task.probe]')",
    );
    b.js(
        "window.__dnm.perf.checks = []; window.__dnm.perf.renders = [];",
        json!([]),
    );
    b.drag(&port("src99.out", "out"), &port("relay0.in", "in"));
    let msg = b.text("#message");
    assert!(msg.starts_with("linked"), "{msg}");
    until(
        &b,
        "the drawn link checked",
        "window.__dnm.check.ok && window.__dnm.check.toml.includes('src99.out -> relay0.in') && window.__dnm.perf.checks.length",
    );
    let edit: Value = b.js(
        "const p = window.__dnm.perf; return {render_ms: p.renders.filter(r => r.view === 'tasks').map(r => r.ms), check_ms: p.checks};",
        json!([]),
    );

    // The live view, redrawn at every poll for a while.
    b.click("#tab-connections");
    until(
        &b,
        "200 modules running in the connection view",
        "document.querySelectorAll('g.module[data-state=running]').length === 200",
    );
    assert_readable(&b, "connection (200 modules)");
    b.js("window.__dnm.perf.renders = []; window.__dnm.perf.events = []; window.__dnm.perf.longTasks = [];", json!([]));
    std::thread::sleep(Duration::from_secs(12));
    // Clicks while it redraws: how long the page takes to answer them.
    for _ in 0..5 {
        b.click("#tab-tasks");
        b.click("#tab-connections");
    }
    std::thread::sleep(Duration::from_secs(2));
    let live: Value = b.js(
        "const p = window.__dnm.perf; return {render_ms: p.renders.filter(r => r.view === 'connections').map(r => r.ms), long_tasks_ms: p.longTasks, event_ms: p.events};",
        json!([]),
    );
    b.screenshot(&shots().join("connections-200.png"));

    let stats = |v: &Value| {
        let mut xs: Vec<f64> = v
            .as_array()
            .unwrap()
            .iter()
            .filter_map(Value::as_f64)
            .collect();
        xs.sort_by(f64::total_cmp);
        if xs.is_empty() {
            return json!({"n": 0});
        }
        let q = |f: f64| xs[((xs.len() - 1) as f64 * f).round() as usize];
        json!({"n": xs.len(), "median": q(0.5), "max": q(1.0)})
    };
    let result = json!({
        "modules": 200,
        "system_start_s": start_s,
        "first_render_after_load_ms": loaded,
        "tasks_view_render_ms": stats(&edit["render_ms"]),
        "check_round_trip_ms": stats(&edit["check_ms"]),
        "connection_view_render_ms": stats(&live["render_ms"]),
        "long_tasks_ms": stats(&live["long_tasks_ms"]),
        "input_event_duration_ms": stats(&live["event_ms"]),
    });
    eprintln!(
        "web interface with 200 modules:\n{}",
        serde_json::to_string_pretty(&result).unwrap()
    );
    std::fs::create_dir_all(shots()).unwrap();
    std::fs::write(
        shots().join("responsiveness.json"),
        serde_json::to_vec_pretty(&result).unwrap(),
    )
    .unwrap();
    // The measurement happened: renders at every poll and the clicks answered.
    assert!(
        result["connection_view_render_ms"]["n"].as_u64().unwrap() >= 8,
        "{result}"
    );
    assert!(
        b.js("return document.body.className", json!([])) == "view-connections",
        "the last click was answered"
    );
}

/// One HTTP/1.1 request as written (any `Host`, any header): (status, head, body).
fn raw_http(addr: &str, request: &str) -> (u16, String, String) {
    use std::io::{Read, Write};
    let mut c = std::net::TcpStream::connect(addr).unwrap();
    c.write_all(request.as_bytes()).unwrap();
    let mut out = String::new();
    c.read_to_string(&mut out).unwrap();
    let (head, body) = out.split_once("\r\n\r\n").unwrap_or((&out, ""));
    let status = head
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(0);
    (status, head.to_string(), body.to_string())
}

fn get(addr: &str, path: &str, host: &str, extra: &str) -> (u16, String, String) {
    raw_http(
        addr,
        &format!("GET {path} HTTP/1.1\r\nHost: {host}\r\n{extra}Connection: close\r\n\r\n"),
    )
}

#[test]
fn the_station_answers_only_its_own_page_and_a_token_guards_it_on_the_network() {
    let system = format!("wacl{}", std::process::id());
    let dir = std::env::temp_dir().join(format!("dnm-test-{system}"));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let _folder = support::Folder(dir.clone());
    let port = support::free_port();
    let _router = router(&dir, port);
    let station = |name: &str, http: &str, token: Option<&str>| {
        let mut a = zenoh_args("client", port);
        a.extend([
            "ground".into(),
            "serve".into(),
            "--system".into(),
            system.clone(),
            "--station".into(),
            name.into(),
            "--db".into(),
            dir.join(format!("{name}.redb")).display().to_string(),
            "--http".into(),
            http.into(),
        ]);
        if let Some(t) = token {
            a.extend(["--token".into(), t.into()]);
        }
        Proc::dnm(&dir, name, &a)
    };

    // On loopback: only requests naming the station's host, only from its own page.
    let local = format!("127.0.0.1:{}", support::free_port());
    let _s1 = station("local", &local, None);
    eventually("the station's API", || {
        std::net::TcpStream::connect(&local).ok()?;
        (get(&local, "/link", &local, "").0 == 200).then_some(())
    });
    let (status, head, _) = get(&local, "/", &local, "");
    assert_eq!(status, 200);
    assert!(head.contains("Content-Security-Policy"), "{head}");
    assert_eq!(
        get(&local, "/api/live", "evil.example", "").0,
        403,
        "a rebound name"
    );
    assert_eq!(
        get(
            &local,
            "/api/watch?module=a&port=b",
            &local,
            "Sec-Fetch-Site: cross-site\r\n"
        )
        .0,
        403,
        "another site's page"
    );
    assert_eq!(
        get(
            &local,
            "/api/live",
            &local,
            "Sec-Fetch-Site: same-origin\r\n"
        )
        .0,
        200,
        "the station's own page"
    );
    // A command posted with `headers` (each ending in CRLF): (status, answer).
    let post = |headers: &str| {
        let body = r#"{"cmd":"switch","task":"t"}"#;
        let (status, _, answer) = raw_http(
            &local,
            &format!(
                "POST /commands HTTP/1.1\r\nHost: {local}\r\n{headers}Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            ),
        );
        (status, answer)
    };
    let (status, answer) =
        post("Origin: http://evil.example\r\nContent-Type: application/json\r\n");
    assert_eq!(status, 403, "{answer}");
    // An old browser's form says neither where it comes from nor JSON: refused as well.
    let (status, answer) = post("Content-Type: text/plain\r\n");
    assert_eq!(status, 415, "{answer}");
    assert!(answer.contains("application/json"), "{answer}");
    assert!(rig_entries(&local).is_empty(), "nothing was queued");

    // On the network: refused without a token; with one, a bearer or the login's cookie.
    let open = format!("0.0.0.0:{}", support::free_port());
    let mut refused = station("open", &open, None);
    let exit = eventually("a station on the network without a token exits", || {
        refused.child.try_wait().unwrap()
    });
    assert!(!exit.success());
    let log = std::fs::read_to_string(&refused.log).unwrap();
    assert!(log.contains("token"), "{log}");

    let token = "0123456789abcdef0123";
    let _s2 = station("guarded", &open, Some(token));
    let at = open.replace("0.0.0.0", "127.0.0.1");
    eventually("the guarded station's API", || {
        std::net::TcpStream::connect(&at).ok()?;
        (get(&at, "/link", &at, "").0 == 401).then_some(())
    });
    assert_eq!(get(&at, "/api/live", &at, "").0, 401);
    assert_eq!(
        get(
            &at,
            "/api/live",
            &at,
            "Authorization: Bearer wrong-wrong-wrong-wrong\r\n"
        )
        .0,
        401
    );
    assert_eq!(
        get(
            &at,
            "/api/live",
            &at,
            &format!("Authorization: Bearer {token}\r\n")
        )
        .0,
        200
    );
    let (status, head, _) = get(&at, &format!("/?token={token}"), &at, "");
    assert_eq!(status, 303, "{head}");
    let cookie = head
        .lines()
        .find_map(|l| l.strip_prefix("Set-Cookie: "))
        .unwrap()
        .split(';')
        .next()
        .unwrap()
        .to_string();
    assert!(
        head.contains("HttpOnly") && head.contains("SameSite=Strict"),
        "{head}"
    );
    assert_eq!(get(&at, "/", &at, &format!("Cookie: {cookie}\r\n")).0, 200);
    assert_eq!(get(&at, "/?token=nope", &at, "").0, 401);
}

fn rig_entries(addr: &str) -> Vec<Value> {
    let (status, _, body) = get(addr, "/commands", addr, "");
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}
