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
