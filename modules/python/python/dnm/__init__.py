"""Modules in Python for the DNM middleware, on the Rust module SDK's runtime.

The names are the Rust SDK's, so one page documents both::

    import dnm
    from dnm.msg import Tick

    class Relay(dnm.Module):
        @classmethod
        def kind(cls):
            return dnm.Kind("py_relay", "forwards ticks").input("in", Tick).output("out", Tick).on_input()

        def __init__(self, setup):
            self.inp = setup.input("in")
            self.out = setup.output("out")

        def step(self, io):
            tick = io.read(self.inp)
            if tick is not None:
                io.write(self.out, tick)

    if __name__ == "__main__":
        raise SystemExit(dnm.host_main([Relay]))

A netlist declares the file as a kind's executable (``[kind.py_relay] exec = "relay.py"``, the
file executable with a ``#!/usr/bin/env python3`` line); the DNM starts, supervises, records and
replays it like a Rust module. Inputs of variable-size types are read as numpy arrays that *are*
the producer's shared memory (read-only, valid during the step: ``.copy()`` what you keep);
outputs are loaned in shared memory (``io.loan``), filled in place and sent (``io.send``). An
exception in ``step`` ends the process with its traceback, which the DNM puts in the module's
events before it applies the restart policy.
"""

import json
import sys

from . import _dnm, msg
from .msg import BytesType, Message, message

__all__ = ["Module", "Kind", "Setup", "Io", "Port", "host_main", "message", "msg"]


class Kind:
    """Declares a module kind: its ports, parameters and trigger (10 Hz until told otherwise)."""

    def __init__(self, name, description=""):
        self.name = name
        self.description = description
        self._inputs = []
        self._outputs = []
        self._params = []
        self._trigger = {"mode": "periodic", "rate_hz": 10.0}

    @staticmethod
    def _port(name, type, max_bytes):
        if isinstance(type, BytesType):
            if max_bytes is None:
                raise TypeError(f"port `{name}`: a {type!r} port needs max_bytes=")
            message_type = type.message_type(max_bytes)
        elif isinstance(type, builtins_type) and issubclass(type, Message):
            message_type = type.message_type()
        else:
            raise TypeError(
                f"port `{name}`: {type!r} is not a message type (dnm.msg.*, or a class "
                "declared with @dnm.message)"
            )
        return {"name": name, "message": message_type}

    def _add(self, ports, name, type, max_bytes):
        if any(p["name"] == name for p in ports):
            raise ValueError(f"kind `{self.name}`: two ports named `{name}`")
        ports.append(self._port(name, type, max_bytes))
        return self

    def input(self, name, type, max_bytes=None):
        return self._add(self._inputs, name, type, max_bytes)

    def output(self, name, type, max_bytes=None):
        return self._add(self._outputs, name, type, max_bytes)

    def param(self, name, default, description=""):
        """A parameter and its default, whose type is the parameter's (int, float, bool, str)."""
        kind = {bool: "bool", int: "int", float: "float", str: "string"}.get(builtins_type(default))
        if kind is None:
            raise TypeError(f"parameter `{name}`: a default of type {builtins_type(default).__name__}")
        self._params.append({"name": name, "kind": kind, "default": default, "doc": description})
        return self

    def periodic(self, rate_hz):
        """Step at ``rate_hz`` (the netlist may override it per module)."""
        rate_hz = float(rate_hz)
        if not 0 < rate_hz <= 100_000:
            raise ValueError(f"kind `{self.name}`: a rate of {rate_hz} Hz; give one above 0 and at most 100 kHz")
        self._trigger = {"mode": "periodic", "rate_hz": rate_hz}
        return self

    def on_input(self):
        """Step whenever an input connected in the active task has new data."""
        self._trigger = {"mode": "on_input"}
        return self

    def spec(self):
        """The declaration as the DNM reads it (JSON text), checked."""
        return _dnm.check_kind(
            json.dumps(
                {
                    "name": self.name,
                    "summary": self.description,
                    "inputs": self._inputs,
                    "outputs": self._outputs,
                    "params": self._params,
                    "trigger": self._trigger,
                }
            )
        )


builtins_type = type


class Module:
    """Base class of a Python module: ``kind()``, ``__init__(self, setup)``, ``step(self, io)``."""

    @classmethod
    def kind(cls):
        raise NotImplementedError(f"{cls.__name__}.kind(): return a dnm.Kind")

    def __init__(self, setup):
        pass

    def step(self, io):
        pass


class Port:
    """A port's handle: what ``setup.input``/``setup.output`` give, ``io`` takes."""

    __slots__ = ("name", "index", "input", "type", "message_type", "fixed", "image")

    def __init__(self, name, index, input, message_type):
        self.name = name
        self.index = index
        self.input = input
        self.message_type = message_type
        fixed = message_type["payload"]["layout"] == "fixed"
        self.fixed = fixed
        self.image = message_type["encoding"] == "dnm-image-rgb8"
        known = msg.by_schema(message_type["schema_name"])
        if fixed:
            if known is None or not isinstance(known, builtins_type):
                known = msg._make(
                    message_type["schema_name"].rsplit("/", 1)[-1],
                    message_type["schema_name"],
                    message_type["schema"],
                )
        elif not isinstance(known, BytesType):
            known = BytesType(
                message_type["schema_name"].rsplit("/", 1)[-1],
                message_type["schema_name"],
                message_type["encoding"],
                message_type["schema"],
            )
        self.type = known

    def __repr__(self):
        return f"<{'input' if self.input else 'output'} `{self.name}` ({self.message_type['schema_name']})>"


class Setup:
    """Given to ``__init__``: the module's name, parameters and ports."""

    def __init__(self, raw):
        self._raw = raw

    @property
    def name(self):
        return self._raw.name()

    def param(self, name):
        return self._raw.param(name)

    def _port(self, name, input):
        index, message_type = self._raw.port(name, input)
        port = Port(name, index, input, json.loads(message_type))
        if not port.fixed:
            # Imported now, not in the first step that reads or loans it (a stall of a few
            # hundred milliseconds there).
            _numpy()
        return port

    def input(self, name):
        return self._port(name, True)

    def output(self, name):
        return self._port(name, False)


def _numpy():
    try:
        import numpy
    except ImportError as e:  # pragma: no cover - numpy is a dependency of the package
        raise ImportError("variable-size ports are read as numpy arrays: pip install numpy") from e
    return numpy


class Io:
    """Given to ``step``: reads inputs under the task of this step, writes outputs. Valid only
    during the step."""

    __slots__ = ("_raw", "loan_address", "_loans")

    def __init__(self, raw):
        self._raw = raw
        #: Where the last loan lies in shared memory.
        self.loan_address = None
        # Per output: the array of its loan not sent yet.
        self._loans = {}

    @property
    def now_ns(self):
        """CLOCK_MONOTONIC time at the start of this step, ns."""
        return self._raw.now_ns()

    @property
    def task(self):
        """The task this step runs under."""
        return self._raw.task()

    @staticmethod
    def _check(port, input):
        if port.__class__ is not Port:
            raise TypeError(f"{port!r} is not a port: take it from setup.input/setup.output")
        if port.input is not input:
            raise TypeError(f"{port!r} is not an {'input' if input else 'output'}")

    def read(self, port):
        """The newest value on ``port`` if it arrived since the port was last read (``None``
        otherwise): a message, or a read-only numpy array on the sample's shared memory."""
        # The hot path of every module: one call into the runtime, no frames of its own.
        if port.__class__ is not Port or port.input is not True:
            self._check(port, True)
        if port.fixed:
            view = self._raw.take_view(port.index)
            return None if view is None else port.type.decode(view)
        return self._raw.array(port.index, port.image, False)

    def latest(self, port):
        """The newest value on ``port``, new or not."""
        self._check(port, True)
        if port.fixed:
            got = self._raw.latest(port.index)
            return None if got is None else port.type.decode(got[0])
        return self._raw.array(port.index, port.image, True)

    def header(self, port):
        """(send stamp ns, sequence number, address of the bytes) of the newest sample."""
        self._check(port, True)
        got = self._raw.latest(port.index)
        return None if got is None else got[1:]

    def write(self, port, value):
        """Sends ``value`` on ``port``: a message of the port's type, or (variable-size ports)
        bytes or a numpy array, copied once into shared memory."""
        self._check(port, False)
        if port.fixed:
            if not isinstance(value, port.type):
                raise TypeError(
                    f"output `{port.name}` carries {port.type.SCHEMA_NAME}, not "
                    f"{type(value).__name__}"
                )
            self._raw.write(port.index, value.encode())
            return
        if isinstance(value, Message):
            raise TypeError(f"output `{port.name}` carries bytes ({port.type!r}), not {value!r}")
        data = memoryview(value).cast("B")
        buf = self.loan(port, len(data))
        buf[:] = _numpy().frombuffer(data, dtype="u1")
        self.send(port)

    def loan(self, port, shape, dtype="u1"):
        """A writable numpy array of ``shape`` in shared memory on ``port``, zeroed, to fill in
        place and send with :meth:`send` in this step. It turns read-only when it is sent, when
        the step ends, or when the same output is loaned again (the first loan is given
        back): views taken of it are not to be kept."""
        self._check(port, False)
        if port.fixed:
            raise TypeError(
                f"output `{port.name}` carries {port.type.SCHEMA_NAME}, a fixed-size message: "
                "write it with io.write"
            )
        np = _numpy()
        dtype = np.dtype(dtype)
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
        self._close(port.index)
        view, self.loan_address = self._raw.loan(port.index, nbytes)
        array = self._loans[port.index] = np.ndarray(shape, dtype=dtype, buffer=view)
        return array

    def loan_image(self, port, height, width):
        """A writable ``(height, width, 3)`` rgb8 image in shared memory on ``port``, its header
        written, to fill and send."""
        self._check(port, False)
        if not port.image:
            raise TypeError(f"output `{port.name}` carries {port.message_type['schema_name']}, not an rgb8 image")
        np = _numpy()
        step = width * 3
        self._close(port.index)
        view, self.loan_address = self._raw.loan(port.index, msg.IMAGE_HEADER + step * height)
        np.frombuffer(view, dtype="<u4", count=3)[:] = (width, height, step)
        array = self._loans[port.index] = np.ndarray(
            (height, width, 3), dtype=np.uint8, buffer=view, offset=msg.IMAGE_HEADER
        )
        return array

    def send(self, port):
        """Sends what was loaned on ``port``. The loaned array turns read-only: the sample is
        the readers' now."""
        self._check(port, False)
        # Locked first, so nothing runs between the send and the readers' wake-up.
        self._close(port.index)
        self._raw.send(port.index)

    def _close(self, index):
        """Makes the array loaned on output ``index`` read-only: it was sent, given back (a
        new loan on the same output), or its step ended."""
        array = self._loans.pop(index, None)
        if array is not None:
            array.flags.writeable = False

    def _end_step(self):
        for index in list(self._loans):
            self._close(index)


class _Stepped:
    """The runtime's handle on a module object: the runtime calls ``step(io)`` itself, with
    one `Io` for all the steps, pointing at each step's inputs and outputs while it runs."""

    __slots__ = ("module", "io", "step")

    def __init__(self, module):
        self.module = module
        self.io = None
        self.step = module.step

    def _bind(self, raw_io):
        self.io = Io(raw_io)


def _traceback(e):
    import traceback

    return "".join(traceback.format_exception(type(e), e, e.__traceback__)).rstrip()


def _build(cls, raw):
    try:
        return _Stepped(cls(Setup(raw)))
    except BaseException as e:
        e.__dnm_traceback__ = _traceback(e)
        raise


def _spec_of(cls):
    k = cls.kind()
    if not isinstance(k, Kind):
        raise TypeError(f"{cls.__name__}.kind() returned {k!r}, not a dnm.Kind")
    return k


def host_main(modules, argv=None):
    """The ``main`` of a module executable: ``describe`` prints its kind, ``run '<launch>'``
    (what the DNM runs) runs it, ``offline '<launch>'`` steps it for ``dnm replay --check``.
    One kind per executable file (``modules`` is a list of one class). Returns the exit code."""
    argv = sys.argv[1:] if argv is None else argv
    kinds = {}
    for cls in modules:
        k = _spec_of(cls)
        kinds[k.name] = (cls, k)
    if argv[:1] in (["describe"], ["--describe"]):
        if len(kinds) != 1:
            print(
                f"{sys.argv[0]}: {len(kinds)} kinds; a module executable is one kind (a netlist's "
                "[kind.NAME] exec = FILE): give host_main one class per file",
                file=sys.stderr,
            )
            return 2
        (_, k), = kinds.values()
        print(json.dumps(json.loads(k.spec()), indent=2))
        return 0
    if len(argv) == 2 and argv[0] in ("run", "offline"):
        launch = json.loads(argv[1])
        entry = kinds.get(launch.get("kind"))
        if entry is None:
            print(f"this executable has no kind `{launch.get('kind')}`", file=sys.stderr)
            return 2
        cls, k = entry
        if argv[0] == "offline":
            # The determinism check speaks on standard output: what the module prints goes to
            # standard error.
            sys.stdout = sys.stderr
            _dnm.offline(argv[1], k.spec(), lambda raw: _build(cls, raw))
            return 0
        try:
            _dnm.run(argv[1], k.spec(), lambda raw: _build(cls, raw))
        except RuntimeError as e:
            print(f"module `{launch.get('module')}` failed: {e}", file=sys.stderr)
            return 1
        return 0
    print(
        f"usage: {sys.argv[0]} describe | run '<launch json>' | offline '<launch json>'\n"
        "(module processes are started by a DNM)",
        file=sys.stderr,
    )
    return 2
