"""Python modules with real DNMs: between Rust modules, zero-copy images, exceptions and the
restart policy, live replacement, recording."""

import struct

from conftest import eventually

RELAY = '''
import dnm
from dnm.msg import Tick

class Relay(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_relay", "forwards ticks, adding `add` to their origin") \\
            .input("in", Tick).output("out", Tick).param("add", 0).on_input()

    def __init__(self, setup):
        self.inp = setup.input("in")
        self.out = setup.output("out")
        self.add = setup.param("add")

    def step(self, io):
        t = io.read(self.inp)
        if t is not None:
            io.write(self.out, Tick(origin=t.origin + self.add, seq=t.seq))

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Relay]))
'''

TICKS = '''
import dnm
from dnm.msg import Tick

class Ticks(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_ticks", "numbered ticks").output("out", Tick).param("origin", 0).periodic(50)

    def __init__(self, setup):
        self.out = setup.output("out")
        self.origin = setup.param("origin")
        self.seq = 0

    def step(self, io):
        io.write(self.out, Tick(origin=self.origin, seq=self.seq))
        self.seq += 1

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Ticks]))
'''


def ticks(payloads):
    """(origin, seq) of recorded ticks: CDR, a 4-byte header then the fields."""
    return [struct.unpack_from("<QQ", data, 4) for _, data in payloads]


def test_a_python_relay_between_two_rust_modules(system):
    system.module("relay.py", RELAY)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_relay]
exec = "relay.py"

[[module]]
name = "src"
kind = "ticker"
rate_hz = 50
params = { origin = 5 }

[[module]]
name = "py"
kind = "py_relay"
params = { add = 100 }

[[module]]
name = "sink"
kind = "relay"

[task.a]
links = ["src.out -> py.in", "py.out -> sink.in"]
''')
    system.up(n)
    system.running("src", "py", "sink")
    eventually("ticks through the Python relay", lambda: system.modules()["sink"]["sent"] > 50)
    kinds = system.cmd("kinds", "--netlist", str(n)).stdout
    assert "py_relay" in kinds and "in [in: dnm_msgs/Tick] out [out: dnm_msgs/Tick]" in kinds, kinds
    system.stop()
    got = ticks(system.messages("/main/sink/out"))
    assert len(got) > 50
    assert all(origin == 105 for origin, _ in got), got[:5]
    seqs = [s for _, s in got]
    assert seqs == sorted(seqs)


def test_a_python_module_feeds_a_rust_one_and_the_reverse(system):
    system.module("ticks.py", TICKS)
    system.module("relay.py", RELAY)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_ticks]
exec = "ticks.py"

[kind.py_relay]
exec = "relay.py"

[[module]]
name = "pysrc"
kind = "py_ticks"
params = { origin = 7 }

[[module]]
name = "rust"
kind = "relay"

[[module]]
name = "py"
kind = "py_relay"
params = { add = 1 }

[task.a]
links = ["pysrc.out -> rust.in", "rust.out -> py.in"]
''')
    system.up(n)
    system.running("pysrc", "rust", "py")
    eventually("Python -> Rust -> Python", lambda: system.modules()["py"]["sent"] > 30)
    system.stop()
    assert {o for o, _ in ticks(system.messages("/main/rust/out"))} == {7}
    assert {o for o, _ in ticks(system.messages("/main/py/out"))} == {8}


FAILING = '''
import dnm
from dnm.msg import Tick

class Failing(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_failing", "fails on its fifth tick").input("in", Tick).on_input()

    def __init__(self, setup):
        self.inp = setup.input("in")
        self.n = 0

    def step(self, io):
        if io.read(self.inp) is not None:
            self.n += 1
            if self.n == 5:
                self.check_rock({"size": None})

    def check_rock(self, rock):
        return rock["size"] * 2

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Failing]))
'''


def test_an_exception_in_step_restarts_the_module_with_its_traceback_in_the_events(system):
    system.module("failing.py", FAILING)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_failing]
exec = "failing.py"

[[module]]
name = "src"
kind = "ticker"
rate_hz = 50

[[module]]
name = "bad"
kind = "py_failing"

[task.a]
links = ["src.out -> bad.in"]
''')
    system.up(n, record=False)
    exited = eventually(
        "the module's exit in the events",
        lambda: [e for e in system.events() if e["module"] == "bad" and e["what"] == "exited"],
    )
    detail = exited[0]["detail"]
    assert "Traceback (most recent call last)" in detail, detail
    assert "check_rock" in detail, detail
    assert "TypeError: unsupported operand type(s)" in detail, detail
    # Restarted by its policy, and failing again the same way.
    eventually("restarted", lambda: system.modules()["bad"]["restarts"] >= 2)


TYPO = '''
import dnm
from dnm.msg import Tick, Scalar

class Wrong(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_wrong", "writes the wrong message").output("out", Tick).periodic(20)

    def __init__(self, setup):
        self.out = setup.output("out")

    def step(self, io):
        io.write(self.out, Scalar(value=1.0))

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Wrong]))
'''


def test_writing_the_wrong_message_is_a_clear_python_error(system):
    system.module("wrong.py", TYPO)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_wrong]
exec = "wrong.py"

[[module]]
name = "w"
kind = "py_wrong"

[task.a]
links = []
''')
    system.up(n, record=False)
    exited = eventually(
        "the module's exit in the events",
        lambda: [e for e in system.events() if e["module"] == "w" and e["what"] in ("exited", "gave_up")],
    )
    detail = exited[0]["detail"]
    assert "TypeError: output `out` carries dnm_msgs/Tick, not Scalar" in detail, detail


ZERO_COPY = '''
import dnm
import numpy as np
from dnm.msg import Blob, Image, Tick

MIB = 1 << 20

class ZeroCopy(dnm.Module):
    @classmethod
    def kind(cls):
        return (dnm.Kind("py_zero_copy", "reads a 1 MiB blob and an image in place, writes one in place")
                .input("blob", Blob, max_bytes=MIB).input("image", Image, max_bytes=230412)
                .output("copy", Blob, max_bytes=MIB).output("verdict", Tick).on_input())

    def __init__(self, setup):
        self.blob = setup.input("blob")
        self.image = setup.input("image")
        self.copy = setup.output("copy")
        self.verdict = setup.output("verdict")
        self.n = 0

    def step(self, io):
        a = io.read(self.blob)
        if a is None:
            return
        _stamp, _seq, address = io.header(self.blob)
        # The array is the producer's shared-memory sample: same address, no copy, read-only.
        assert a.nbytes == MIB and a.dtype == np.uint8, (a.nbytes, a.dtype)
        assert a.__array_interface__["data"][0] == address, "the input was copied"
        assert not a.flags.writeable
        # Nor can it be made writable: the sample is its producer's and every reader's.
        try:
            a.flags.writeable = True
            raise AssertionError("an input was made writable")
        except ValueError:
            pass
        out = io.loan(self.copy, MIB)
        assert out.__array_interface__["data"][0] == io.loan_address, "the output is not the loan"
        out[:] = a
        out[8:16] = 0xAB
        io.send(self.copy)
        # Sent: the sample is its readers' now.
        assert not out.flags.writeable, "a sent loan stays writable"
        # A port sends at most its max_bytes.
        try:
            io.loan(self.copy, MIB + 1)
            raise AssertionError("a loan beyond max_bytes was given")
        except RuntimeError as e:
            assert "port `copy`" in str(e) and "max_bytes (1048576)" in str(e), e
        img = io.latest(self.image)
        # Shaped from its header, on the sample's pixels (after the 12 bytes of the header).
        pixels = io.header(self.image)[2] + 12 if img is not None else None
        shaped = (
            img is not None
            and img.shape == (240, 320, 3)
            and img.__array_interface__["data"][0] == pixels
            and not img.flags.writeable
        )
        self.n += 1
        io.write(self.verdict, Tick(origin=int(shaped), seq=self.n))

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([ZeroCopy]))
'''


POSE = '''
import dnm
from dnm.msg import WorldState

class Pose(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_pose", "a rover standing still").output("world", WorldState).periodic(10)

    def __init__(self, setup):
        self.out = setup.output("world")

    def step(self, io):
        io.write(self.out, WorldState(x=1.0, y=0.5, yaw=0.3))

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Pose]))
'''


def test_a_1_mib_sample_is_read_as_numpy_without_a_copy_and_one_written_in_place(system):
    system.module("zero_copy.py", ZERO_COPY)
    system.module("pose.py", POSE)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_zero_copy]
exec = "zero_copy.py"

[kind.py_pose]
exec = "pose.py"

[[module]]
name = "pose"
kind = "py_pose"

[[module]]
name = "blobs"
kind = "blob_source"
rate_hz = 20
params = { bytes = 1048576, origin = 9 }

[[module]]
name = "camera"
kind = "camera"

[[module]]
name = "zc"
kind = "py_zero_copy"

[task.a]
links = ["blobs.out -> zc.blob", "camera.image -> zc.image", "pose.world -> camera.world"]
''')
    system.up(n)
    system.running("blobs", "camera", "zc", "pose")
    eventually("1 MiB samples checked", lambda: system.modules()["zc"]["sent"] > 40)
    assert not [e for e in system.events() if e["module"] == "zc"], system.events()
    system.stop()
    verdicts = ticks(system.messages("/main/zc/verdict"))
    assert verdicts and verdicts[-1][0] == 1, "the image was read shaped (240, 320, 3)"
    copies = system.messages("/main/zc/copy")
    assert copies
    # CDR `uint8[] data`: the 4-byte encapsulation, the length, then the bytes.
    _, data = copies[-1]
    (length,) = struct.unpack_from("<I", data, 4)
    body = data[8 : 8 + length]
    assert length == 1 << 20
    assert struct.unpack_from("<Q", body, 0)[0] == 9, "the producer's tag, copied"
    assert body[8:16] == b"\xab" * 8, "written in place"


def test_a_python_module_replaced_live_under_traffic(system):
    system.module("relay.py", RELAY)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_relay]
exec = "relay.py"

[[module]]
name = "src"
kind = "ticker"
rate_hz = 50
params = { origin = 5 }

[[module]]
name = "py"
kind = "py_relay"
params = { add = 100 }

[[module]]
name = "sink"
kind = "relay"

[task.a]
links = ["src.out -> py.in", "py.out -> sink.in"]
''')
    system.up(n)
    system.running("src", "py", "sink")
    eventually("traffic", lambda: system.modules()["sink"]["sent"] > 50)
    system.cmd("module", "replace", "--system", system.system, "--name", "py", "--param", "add=200")
    before = system.modules()["sink"]["sent"]
    eventually("traffic after the replacement", lambda: system.modules()["sink"]["sent"] > before + 50)
    system.stop()
    origins = [o for o, _ in ticks(system.messages("/main/sink/out"))]
    switched = origins.index(205)
    assert set(origins[:switched]) == {105} and set(origins[switched:]) == {205}, origins


def test_replay_check_steps_a_python_module_on_its_recorded_inputs(system):
    relay = system.module("relay.py", RELAY)
    source = system.module("ticks.py", TICKS)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_relay]
exec = "relay.py"

[kind.py_ticks]
exec = "ticks.py"

[[module]]
name = "src"
kind = "py_ticks"
params = { origin = 5 }

[[module]]
name = "py"
kind = "py_relay"
params = { add = 100 }

[task.a]
links = ["src.out -> py.in"]
''')
    system.up(n)
    system.running("src", "py")
    eventually("traffic", lambda: system.modules()["py"]["sent"] > 50)
    system.stop()
    session = str(system.session())
    # A recording alone runs nothing: the module's executable must be named.
    r = system.cmd("replay", "--check", "py", session, check=False)
    assert r.returncode != 0 and "is not run for a recording" in r.stderr, r.stderr
    # Every kind this build does not hold is named; only the checked one steps.
    r = system.cmd("replay", "--check", "py", "--exec", str(relay), session, check=False)
    assert r.returncode != 0 and "name it with --exec too" in r.stderr, r.stderr
    execs = ["--exec", str(relay), "--exec", str(source)]
    r = system.cmd("replay", "--check", "py", *execs, "--json", session, check=False)
    assert r.returncode == 0, r.stdout + r.stderr
    report = __import__("json").loads(r.stdout)
    assert report["ok"], report
    assert report["outputs"]["out"]["recorded"] > 50
    assert report["outputs"]["out"]["identical"] == report["outputs"]["out"]["recorded"]
    # Its code changed: the check finds where it diverges.
    r = system.cmd("replay", "--check", "py", *execs, "--set", "add=101", session, check=False)
    assert r.returncode == 1, r.stdout + r.stderr
    assert "origin" in r.stdout, r.stdout


def test_the_rock_detector_example_runs_on_beetle_one(system, tmp_path):
    """examples/python: Beetle-One's mission with the Python rock detector on its camera board,
    its detections recorded and decoded, the detector checked on its recorded frames."""
    import json
    import os
    import subprocess
    from pathlib import Path

    example = Path(__file__).resolve().parents[3] / "examples" / "python"
    env = dict(
        os.environ,
        PATH=f"{Path(os.sys.executable).parent}:{os.environ['PATH']}",
        DNM_MODULE_DIR=str(example),
        DNM_RECORD_DIR=str(tmp_path / "recordings"),
        RUST_LOG="warn",
    )
    netlist = (example / "beetle-rocks.toml").read_text().replace('name = "beetle"', f'name = "{system.system}"', 1)
    mine = example / f"test-{system.system}.toml"
    mine.write_text(netlist)
    try:
        r = subprocess.run(
            [str(system.dnm), "--no-multicast", "demo", "--json", "--teleop-seconds", "2", "--netlist", str(mine)],
            capture_output=True, text=True, env=env, timeout=600,
        )
    finally:
        mine.unlink()
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    assert json.loads(r.stdout)["ok"], r.stdout
    rows = [struct.unpack_from("<Qddd", data, 4) for _, data in system.messages("/vision/rocks/detections")]
    assert len(rows) > 50
    assert max(count for count, *_ in rows) >= 1, "rocks seen on the way"
    assert all(0.0 <= coverage <= 1.0 for *_, coverage in rows)
    r = system.cmd("replay", "--check", "rocks", "--exec", str(example / "rocks.py"), str(system.session()), check=False)
    assert r.returncode == 0, r.stdout + r.stderr


BROKEN_INIT = '''
import dnm
from dnm.msg import Tick

class Broken(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_broken", "fails to build").input("in", Tick).on_input()

    def __init__(self, setup):
        self.gain = setup.param("gain")

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([Broken]))
'''


def test_an_exception_in_init_is_reported_with_its_traceback(system):
    system.module("broken.py", BROKEN_INIT)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_broken]
exec = "broken.py"

[[module]]
name = "src"
kind = "ticker"

[[module]]
name = "b"
kind = "py_broken"

[task.a]
links = ["src.out -> b.in"]
''')
    system.up(n, record=False)
    system.proc.wait(timeout=120)
    log = system.log.read_text()
    assert "exited while preparing revision 1" in log, log[-3000:]
    assert "its last error: Traceback (most recent call last)" in log, log[-3000:]
    assert "parameter `gain`: not declared by kind `py_broken`" in log, log[-3000:]


BAD_KIND = '''
import dnm

class BadKind(dnm.Module):
    @classmethod
    def kind(cls):
        return dnm.Kind("py_bad_kind", "declares a port of no message type").input("in", int).on_input()

if __name__ == "__main__":
    raise SystemExit(dnm.host_main([BadKind]))
'''


def test_a_kind_that_cannot_describe_itself_is_refused_with_its_python_error(system):
    system.module("bad_kind.py", BAD_KIND)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_bad_kind]
exec = "bad_kind.py"

[[module]]
name = "b"
kind = "py_bad_kind"

[task.a]
links = []
''')
    r = system.cmd("check", str(n), check=False)
    assert r.returncode != 0, r.stdout
    out = r.stdout + r.stderr
    assert "kind.py_bad_kind.exec" in out, out
    assert "TypeError: port `in`" in out, out


def test_ctrl_c_in_a_terminal_stops_the_modules_in_order(system):
    """A terminal's Ctrl-C signals its whole foreground process group: the DNM stops its
    modules itself, and none of them is seen exiting on its own behind its back."""
    import os
    import signal as sig
    import subprocess

    system.module("relay.py", RELAY)
    n = system.netlist('''
default_task = "a"

[[dnm]]
name = "main"

[kind.py_relay]
exec = "relay.py"

[[module]]
name = "src"
kind = "ticker"
rate_hz = 50

[[module]]
name = "py"
kind = "py_relay"

[task.a]
links = ["src.out -> py.in"]
''')
    args = [str(system.dnm), "--no-multicast", "up", str(n),
            "--state-dir", str(system.dir / "state"),
            "--record-dir", str(system.dir / "recordings")]
    from conftest import env
    system.proc = subprocess.Popen(args, stdout=open(system.log, "w"), stderr=subprocess.STDOUT,
                                   env=env(), start_new_session=True)
    system.running("src", "py")
    eventually("traffic", lambda: system.modules()["py"]["sent"] > 20)
    # Out of the terminal's reach: each module in a process group of its own.
    for name, m in system.modules().items():
        assert os.getpgid(m["pid"]) != os.getpgid(system.proc.pid), name
    os.killpg(system.proc.pid, sig.SIGINT)
    assert system.proc.wait(timeout=60) == 0, system.log.read_text()[-3000:]
    system.proc = None
    log = system.log.read_text()
    assert "module exited" not in log and "gave_up" not in log, log[-3000:]
    events = [data for _, data in system.messages("/main/_events")]
    bad = [e for e in events if b"gave_up" in e or b"\"exited\"" in e]
    assert not bad, bad
