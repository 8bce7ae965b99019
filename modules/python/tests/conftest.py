"""Real DNMs for the Python module tests: `dnm up` of a netlist in a temporary folder, its
Python modules written there as executables, its recording read back with the `mcap` reader."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]


def _binary(name):
    for profile in (os.environ.get("DNM_PROFILE"), "debug", "release"):
        if profile and (ROOT / "target" / profile / name).exists():
            return ROOT / "target" / profile / name
    pytest.fail(f"build the DNM first: cargo build (no target/*/{name})")


def eventually(what, f, timeout=120.0):
    """Polls `f` until it returns something truthy; fails naming `what` (a guard against a
    test that hangs, not a performance limit)."""
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = f()
        except Exception as e:  # noqa: BLE001 - polled: report the last one
            last = e
        else:
            if last:
                return last
        time.sleep(0.2)
    pytest.fail(f"never: {what} (last: {last!r})")


def env(**more):
    """The environment of the DNM: this Python first on the PATH (`#!/usr/bin/env python3`
    modules find `dnm`)."""
    e = dict(os.environ, PATH=f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}")
    e.setdefault("RUST_LOG", "info")
    e.update(more)
    return e


class System:
    """One machine's DNMs of a netlist, run with `dnm up`."""

    def __init__(self, tmp: Path, name: str):
        self.dir = tmp
        self.system = f"{name}{os.getpid()}"
        self.dnm = _binary("dnm")
        self.proc = None
        self.log = tmp / "dnm.log"

    def module(self, file: str, source: str) -> Path:
        """Writes a Python module executable (run by this interpreter, where `dnm` is)."""
        path = self.dir / file
        path.write_text(f"#!{sys.executable}\n{source}")
        path.chmod(0o755)
        return path

    def netlist(self, body: str) -> Path:
        path = self.dir / "netlist.toml"
        path.write_text(f'[system]\nname = "{self.system}"\n{body}')
        return path

    def cmd(self, *args, check=True):
        r = subprocess.run(
            [str(self.dnm), "--no-multicast", *args],
            capture_output=True,
            text=True,
            timeout=120,
            env=env(),
        )
        if check and r.returncode != 0:
            pytest.fail(f"dnm {' '.join(args)}: {r.stdout}\n{r.stderr}")
        return r

    def up(self, netlist: Path, record=True):
        args = [str(self.dnm), "--no-multicast", "up", str(netlist),
                "--state-dir", str(self.dir / "state"),
                "--record-dir", str(self.dir / "recordings")]
        if not record:
            args.append("--no-record")
        self.proc = subprocess.Popen(args, stdout=open(self.log, "w"), stderr=subprocess.STDOUT, env=env())
        return self

    def status(self):
        r = self.cmd("status", "--system", self.system, "--json", check=False)
        if r.returncode != 0:
            return None
        return json.loads(r.stdout)

    def modules(self):
        """Every module of every DNM, by name."""
        s = self.status()
        if not s:
            return {}
        return {m["name"]: m for d in s["dnms"] for m in d["modules"]}

    def events(self):
        s = self.status() or {"dnms": []}
        return [e for d in s["dnms"] for e in d.get("events", [])]

    def running(self, *names):
        def ok():
            if self.proc is not None and self.proc.poll() is not None:
                pytest.fail(f"`dnm up` exited: {self.log.read_text()[-3000:]}")
            ms = self.modules()
            return all(ms.get(n, {}).get("state") == "running" for n in names) and ms
        return eventually(f"modules {names} running", ok)

    def stop(self):
        if self.proc and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.proc = None

    def session(self) -> Path:
        sessions = [p for p in (self.dir / "recordings").iterdir() if p.is_dir()]
        sessions = sessions or [p for p in (self.dir / "recordings").glob("*/") if p.is_dir()]
        assert len(sessions) == 1, sessions
        return sessions[0]

    def messages(self, topic: str):
        """(log time, payload) of every message on `topic` in the session, read with the MCAP
        tools' reader."""
        from mcap.reader import make_reader

        out = []
        for f in sorted(self.session().glob("*.mcap")):
            with open(f, "rb") as fh:
                for _schema, channel, message in make_reader(fh).iter_messages(topics=[topic]):
                    out.append((message.log_time, message.data))
        return sorted(out, key=lambda m: m[0])


@pytest.fixture
def system(tmp_path, request):
    s = System(tmp_path, request.node.name.replace("test_", "py")[:12].replace("_", ""))
    yield s
    s.stop()
    if getattr(request.node, "rep_call", None) and request.node.rep_call.failed and s.log.exists():
        print(s.log.read_text()[-4000:])


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    setattr(item, "rep_" + rep.when, rep)
