//! A real headless Chromium driven over W3C WebDriver (Debian's `chromium` and
//! `chromium-driver`; `.ci/run` installs them).
#![allow(clippy::unwrap_used, clippy::expect_used)] // test helpers: failing loudly is right

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::Duration;

use base64::Engine;
use serde_json::{Value, json};

const ELEMENT: &str = "element-6066-11e4-a52e-4f735466cecf";

/// A browser session; the browser and its driver end when it is dropped.
pub struct Browser {
    driver: Child,
    base: String,
    session: String,
    _profile: PathBuf,
}

fn agent() -> ureq::Agent {
    ureq::Agent::new_with_config(
        ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(120)))
            .build(),
    )
}

fn find(names: &[&str]) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .flat_map(|d| names.iter().map(move |n| d.join(n)))
        .find(|p| p.is_file())
}

impl Browser {
    /// Starts chromedriver and a headless Chromium with a fresh profile, `width`×`height`.
    pub fn start(dir: &Path, width: u32, height: u32) -> Self {
        let driver = find(&["chromedriver"]).expect(
            "no chromedriver on the PATH: install Debian's `chromium` and `chromium-driver` \
             (`.ci/run` does)",
        );
        let chromium = find(&["chromium", "chromium-browser", "google-chrome"])
            .expect("no Chromium on the PATH: install Debian's `chromium` (`.ci/run` does)");
        let port = super::free_port();
        let log = std::fs::File::create(dir.join("chromedriver.log")).unwrap();
        let mut child = Command::new(driver)
            .arg(format!("--port={port}"))
            .stdin(Stdio::null())
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .unwrap();
        let base = format!("http://127.0.0.1:{port}");
        super::eventually("chromedriver ready", || {
            if let Ok(Some(status)) = child.try_wait() {
                panic!("chromedriver exited: {status}");
            }
            let mut r = agent().get(format!("{base}/status")).call().ok()?;
            let v: Value = serde_json::from_str(&r.body_mut().read_to_string().ok()?).ok()?;
            v["value"]["ready"].as_bool().filter(|r| *r)
        });
        let profile = dir.join("chromium-profile");
        let caps = json!({"capabilities": {"alwaysMatch": {
            "browserName": "chrome",
            "goog:chromeOptions": {
                "binary": chromium.display().to_string(),
                "args": [
                    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                    "--no-first-run", "--disable-background-networking",
                    "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage",
                    format!("--user-data-dir={}", profile.display()),
                    format!("--window-size={width},{height}"),
                ],
            },
        }}});
        let mut r = agent()
            .post(format!("{base}/session"))
            .content_type("application/json")
            .send(caps.to_string().as_bytes())
            .unwrap();
        let v: Value = serde_json::from_str(&r.body_mut().read_to_string().unwrap()).unwrap();
        let session = v["value"]["sessionId"]
            .as_str()
            .unwrap_or_else(|| panic!("no browser session: {v}"))
            .to_string();
        Self {
            driver: child,
            base,
            session,
            _profile: profile,
        }
    }

    fn call(&self, method: &str, path: &str, body: Option<Value>) -> Value {
        let url = format!("{}/session/{}{path}", self.base, self.session);
        let mut r = match method {
            "GET" => agent().get(&url).call().unwrap(),
            "DELETE" => agent().delete(&url).call().unwrap(),
            _ => agent()
                .post(&url)
                .content_type("application/json")
                .send(body.unwrap_or_else(|| json!({})).to_string().as_bytes())
                .unwrap(),
        };
        let status = r.status().as_u16();
        let v: Value = serde_json::from_str(&r.body_mut().read_to_string().unwrap()).unwrap();
        assert!(status < 400, "WebDriver {method} {path}: {status} {v}");
        v["value"].clone()
    }

    pub fn goto(&self, url: &str) {
        self.call("POST", "/url", Some(json!({ "url": url })));
    }

    /// Runs `script` (a function body; `arguments` holds `args`) and returns its value.
    pub fn js(&self, script: &str, args: Value) -> Value {
        self.call(
            "POST",
            "/execute/sync",
            Some(json!({ "script": script, "args": args })),
        )
    }

    /// Runs an async script: it calls `arguments[arguments.length - 1](value)` when done.
    pub fn js_async(&self, script: &str, args: Value) -> Value {
        self.call(
            "POST",
            "/execute/async",
            Some(json!({ "script": script, "args": args })),
        )
    }

    /// The first element matching `css`, if any.
    pub fn try_element(&self, css: &str) -> Option<String> {
        let url = format!("{}/session/{}/element", self.base, self.session);
        let mut r = agent()
            .post(&url)
            .content_type("application/json")
            .send(
                json!({"using": "css selector", "value": css})
                    .to_string()
                    .as_bytes(),
            )
            .unwrap();
        let v: Value = serde_json::from_str(&r.body_mut().read_to_string().unwrap()).unwrap();
        v["value"][ELEMENT].as_str().map(str::to_string)
    }

    /// The first element matching `css`, waiting for it to appear.
    pub fn element(&self, css: &str) -> String {
        super::eventually(&format!("an element `{css}` in the page"), || {
            self.try_element(css)
        })
    }

    pub fn click(&self, css: &str) {
        let e = self.element(css);
        self.call("POST", &format!("/element/{e}/click"), None);
    }

    pub fn type_into(&self, css: &str, text: &str) {
        let e = self.element(css);
        self.call("POST", &format!("/element/{e}/clear"), None);
        self.call(
            "POST",
            &format!("/element/{e}/value"),
            Some(json!({ "text": text })),
        );
    }

    /// Types `text` after what a field holds (a field not focused takes it at its end).
    pub fn type_after(&self, css: &str, text: &str) {
        let e = self.element(css);
        self.call(
            "POST",
            &format!("/element/{e}/value"),
            Some(json!({ "text": text })),
        );
    }

    /// Chooses `file` in a file input, as an operator picking it would.
    pub fn choose_file(&self, css: &str, file: &Path) {
        self.type_after(css, &file.display().to_string());
    }

    /// Types `text` over a field's current value (selected first, so the field never
    /// passes through empty as a clear would).
    pub fn retype(&self, css: &str, text: &str) {
        let e = self.element(css);
        self.js(
            "arguments[0].focus(); arguments[0].select();",
            json!([{ ELEMENT: e }]),
        );
        self.call(
            "POST",
            &format!("/element/{e}/value"),
            Some(json!({ "text": text })),
        );
    }

    pub fn text(&self, css: &str) -> String {
        let e = self.element(css);
        self.call("GET", &format!("/element/{e}/text"), None)
            .as_str()
            .unwrap_or_default()
            .to_string()
    }

    /// The centre of the element matching `css`, in viewport pixels, scrolled into view.
    fn centre(&self, css: &str) -> (i64, i64) {
        self.element(css);
        let v = self.js(
            "const e = document.querySelector(arguments[0]);\
             e.scrollIntoView({block: 'nearest', inline: 'nearest'});\
             const r = e.getBoundingClientRect();\
             return [Math.round(r.left + r.width / 2), Math.round(r.top + r.height / 2)];",
            json!([css]),
        );
        (v[0].as_i64().unwrap(), v[1].as_i64().unwrap())
    }

    /// Presses the mouse on `from`, moves it to `to` in steps and releases it: what an
    /// operator's drag does, as real pointer events.
    pub fn drag(&self, from: &str, to: &str) {
        let pointer = |actions: Value| {
            json!({"actions": [{
                "type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"},
                "actions": actions,
            }]})
        };
        let (ax, ay) = self.centre(from);
        self.call(
            "POST",
            "/actions",
            Some(pointer(json!([
                {"type": "pointerMove", "origin": "viewport", "x": ax, "y": ay, "duration": 0},
                {"type": "pointerDown", "button": 0},
                {"type": "pointerMove", "origin": "viewport", "x": ax + 12, "y": ay + 6, "duration": 50},
            ]))),
        );
        // The drop point is taken once the page has reacted to the press.
        let (bx, by) = self.centre(to);
        self.call(
            "POST",
            "/actions",
            Some(pointer(json!([
                {"type": "pointerMove", "origin": "viewport", "x": bx, "y": by, "duration": 150},
                {"type": "pointerUp", "button": 0},
            ]))),
        );
        self.call("DELETE", "/actions", None);
    }

    /// A PNG of the window, written to `path`.
    pub fn screenshot(&self, path: &Path) {
        self.save_png(&self.call("GET", "/screenshot", None), path);
    }

    /// A PNG of the element `css` alone, written to `path`.
    pub fn screenshot_element(&self, css: &str, path: &Path) {
        let e = self.element(css);
        self.save_png(
            &self.call("GET", &format!("/element/{e}/screenshot"), None),
            path,
        );
    }

    fn save_png(&self, b64: &Value, path: &Path) {
        let png = base64::engine::general_purpose::STANDARD
            .decode(b64.as_str().unwrap())
            .unwrap();
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).unwrap();
        }
        std::fs::write(path, png).unwrap();
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = agent()
            .delete(format!("{}/session/{}", self.base, self.session))
            .call();
        let _ = self.driver.kill();
        let _ = self.driver.wait();
    }
}
