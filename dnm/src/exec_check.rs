//! A module of another language under the determinism check (`dnm replay --check MODULE
//! --exec FILE`): its executable, run as `FILE offline '<launch>'`, steps the module without a
//! DNM on what this process hands it over a pipe. Each step: the inputs new since the last
//! one (and those cleared by a task switch) and the task go out; what the module wrote comes
//! back and is written to the check's outputs, so the check sees it as it sees a Rust module.
//!
//! Frames, both ways: a 4-byte little-endian length, a JSON header of that length, then the
//! payloads it lists (`payload_bytes` in all), back to back. Only an executable the operator
//! names runs: a recording never makes this process run a program.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};

use dnm_module::protocol::Launch;
use dnm_module::{Io, ModuleError, Setup, Stepper};
use serde_json::{Value, json};

/// Largest frame taken from the module: what a few large samples need.
const MAX_FRAME: u64 = 1 << 30;

/// The module's executable, stepping it.
pub struct ExecStepper {
    child: Child,
    stdin: ChildStdin,
    stdout: ChildStdout,
    inputs: usize,
    exec: PathBuf,
}

impl ExecStepper {
    /// Starts `exec` in its offline mode for the module `setup` describes.
    pub fn spawn(exec: &Path, kind: &str, setup: &Setup<'_>) -> Result<Self, ModuleError> {
        let spec = setup.spec();
        let launch = Launch {
            system: String::new(),
            dnm: String::new(),
            prefix: String::new(),
            module: setup.name().to_string(),
            kind: kind.to_string(),
            params: setup.params().clone(),
            trigger: spec.trigger,
        };
        let launch =
            serde_json::to_string(&launch).map_err(|e| ModuleError::Launch(e.to_string()))?;
        let mut child = Command::new(exec)
            .arg("offline")
            .arg(launch)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .map_err(|e| ModuleError::Launch(format!("running {}: {e}", exec.display())))?;
        let (Some(stdin), Some(stdout)) = (child.stdin.take(), child.stdout.take()) else {
            return Err(ModuleError::Launch("no pipes to the module".into()));
        };
        Ok(Self {
            child,
            stdin,
            stdout,
            inputs: spec.inputs.len(),
            exec: exec.to_path_buf(),
        })
    }

    fn pipe(&self, e: std::io::Error) -> ModuleError {
        ModuleError::Step(format!("{} (offline): {e}", self.exec.display()))
    }

    fn exchange(&mut self, head: &Value, body: &[u8]) -> Result<(Value, Vec<u8>), ModuleError> {
        let h = serde_json::to_vec(head).map_err(|e| ModuleError::Step(e.to_string()))?;
        let sent = self
            .stdin
            .write_all(&(h.len() as u32).to_le_bytes())
            .and_then(|_| self.stdin.write_all(&h))
            .and_then(|_| self.stdin.write_all(body))
            .and_then(|_| self.stdin.flush());
        sent.map_err(|e| self.pipe(e))?;
        let mut len = [0u8; 4];
        self.stdout.read_exact(&mut len).map_err(|e| self.pipe(e))?;
        let mut h = vec![0u8; u32::from_le_bytes(len) as usize];
        self.stdout.read_exact(&mut h).map_err(|e| self.pipe(e))?;
        let head: Value =
            serde_json::from_slice(&h).map_err(|e| ModuleError::Step(e.to_string()))?;
        let total = head["payload_bytes"].as_u64().unwrap_or(0);
        if total > MAX_FRAME {
            return Err(ModuleError::Step(format!("{} bytes in one answer", total)));
        }
        let mut body = vec![0u8; total as usize];
        self.stdout
            .read_exact(&mut body)
            .map_err(|e| self.pipe(e))?;
        Ok((head, body))
    }
}

impl Stepper for ExecStepper {
    fn step_io(&mut self, io: &mut Io<'_>) -> Result<(), ModuleError> {
        let (mut set, mut clear, mut body) = (Vec::new(), Vec::new(), Vec::new());
        for i in 0..self.inputs {
            let new = io.take_raw(i).map(|(h, bytes)| {
                body.extend_from_slice(bytes);
                json!([i, h.stamp_ns, h.seq, bytes.len()])
            });
            match new {
                Some(s) => set.push(s),
                None if io.latest_raw(i).is_none() => clear.push(i),
                None => {}
            }
        }
        let head = json!({
            "now_ns": io.now_ns(),
            "task": io.task(),
            "set": set,
            "clear": clear,
            "payload_bytes": body.len(),
        });
        let (answer, out) = self.exchange(&head, &body)?;
        if answer["ok"] != true {
            return Err(ModuleError::Step(
                answer["error"]
                    .as_str()
                    .unwrap_or("the module failed")
                    .to_string(),
            ));
        }
        let mut at = 0usize;
        for o in answer["outputs"].as_array().into_iter().flatten() {
            let index = o[0].as_u64().unwrap_or(u64::MAX) as usize;
            let len = o[1].as_u64().unwrap_or(0) as usize;
            let bytes = out.get(at..at + len).unwrap_or_default();
            at += len;
            io.write_raw(index, bytes)?;
        }
        Ok(())
    }
}

impl Drop for ExecStepper {
    fn drop(&mut self) {
        // Its standard input closed, the module's offline loop ends.
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
