"""Message types: what ports carry.

A fixed-size message is a C struct sent as its little-endian in-memory layout (encoding
``dnm-pod``), its fields listed in ROS 2 ``.msg`` syntax so recordings decode without our code:
the same bytes as the Rust SDK's ``#[repr(C)]`` types, so Python and Rust modules link to each
other. The SDK's and Beetle-One's types are here (``dnm.msg.Tick``, ``dnm.msg.Odometry``...);
declare your own with :func:`message`::

    @dnm.message("rocks_msgs/Detection")
    class Detection:
        x: "float64"
        y: "float64"
        size: "float64"
        count: "uint32"

Build one with keyword arguments (``Detection(x=1.0, y=2.0)``; fields not given are 0) and read
its fields as attributes. Variable-size types (``Blob``, ``Image``, ``Telemetry``) are bytes on
the port: inputs of those types are read as numpy arrays (an image shaped ``(height, width, 3)``
from its header).
"""

import json
import struct

from . import _dnm

__all__ = ["Message", "BytesType", "message", "POD_ENCODING"]

POD_ENCODING = "dnm-pod"

# (struct code, size) of each primitive of the ``.msg`` syntax.
_PRIMITIVES = {
    "bool": ("?", 1),
    "int8": ("b", 1),
    "uint8": ("B", 1),
    "byte": ("B", 1),
    "char": ("B", 1),
    "int16": ("h", 2),
    "uint16": ("H", 2),
    "int32": ("i", 4),
    "uint32": ("I", 4),
    "float32": ("f", 4),
    "int64": ("q", 8),
    "uint64": ("Q", 8),
    "float64": ("d", 8),
}


def _layout(fields):
    """The struct format of ``fields`` [(name, type, count)] with C alignment, and its size."""
    fmt = "<"
    offset = 0
    align = 1
    for name, ty, count in fields:
        if ty not in _PRIMITIVES:
            raise TypeError(
                f"field `{name}`: `{ty}` is not a fixed-size primitive "
                f"(one of {', '.join(sorted(_PRIMITIVES))})"
            )
        code, size = _PRIMITIVES[ty]
        pad = (-offset) % size
        if pad:
            fmt += f"{pad}x"
        offset += pad
        n = count or 1
        fmt += f"{n}{code}" if count else code
        offset += size * n
        align = max(align, size)
    pad = (-offset) % align
    if pad:
        fmt += f"{pad}x"
    offset += pad
    return fmt, offset


def _parse_schema(schema):
    """[(name, type, count or None)] of a ``.msg`` field list."""
    fields = []
    for line in schema.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        ty, name = line.split()[:2]
        count = None
        if "[" in ty:
            ty, rest = ty.split("[", 1)
            count = int(rest.rstrip("]"))
        fields.append((name, ty, count))
    return fields


class Message:
    """Base of fixed-size message types: fields as attributes, encoded as their C layout."""

    SCHEMA_NAME = ""
    SCHEMA = ""
    FIELDS = ()
    _struct = struct.Struct("<")
    _standard = None
    # Field defaults a `@message` class gives (zero otherwise).
    _defaults = {}

    __slots__ = ()

    def __init__(self, **fields):
        unknown = set(fields) - {f[0] for f in self.FIELDS}
        if unknown:
            raise TypeError(
                f"{type(self).__name__} has no field {', '.join(sorted(unknown))}; "
                f"its fields: {', '.join(f[0] for f in self.FIELDS)}"
            )
        for name, ty, count in self.FIELDS:
            if name in fields:
                value = fields[name]
            elif name in self._defaults:
                value = self._defaults[name]
                value = list(value) if count else value
            else:
                value = [0] * count if count else (False if ty == "bool" else 0)
            setattr(self, name, value)

    @classmethod
    def message_type(cls):
        """The type as the DNM declares it (a dict of its JSON form)."""
        t = {
            "schema_name": cls.SCHEMA_NAME,
            "encoding": POD_ENCODING,
            "schema": cls.SCHEMA,
            "payload": {"layout": "fixed", "size_bytes": cls._struct.size},
        }
        if cls._standard is not None:
            t["standard"] = cls._standard
        return t

    def encode(self):
        values = []
        for name, _ty, count in self.FIELDS:
            v = getattr(self, name)
            if count:
                v = list(v)
                if len(v) != count:
                    raise ValueError(f"field `{name}` holds {count} values, not {len(v)}")
                values.extend(v)
            else:
                values.append(v)
        try:
            return self._struct.pack(*values)
        except struct.error as e:
            raise TypeError(f"{type(self).__name__}: {self._bad_field() or e}") from None

    def _bad_field(self):
        """Which field does not fit its type, and why (for an encoding error)."""
        for name, ty, count in self.FIELDS:
            code = _PRIMITIVES[ty][0]
            v = getattr(self, name)
            for x in list(v) if count else [v]:
                try:
                    struct.pack("<" + code, x)
                except struct.error as e:
                    return f"field `{name}` ({ty}) cannot hold {x!r}: {e}"
        return None

    @classmethod
    def decode(cls, data):
        flat = cls._struct.unpack(data)
        m = cls.__new__(cls)
        i = 0
        for name, _ty, count in cls.FIELDS:
            if count:
                setattr(m, name, list(flat[i : i + count]))
                i += count
            else:
                setattr(m, name, flat[i])
                i += 1
        return m

    def __eq__(self, other):
        return type(self) is type(other) and all(
            getattr(self, f[0]) == getattr(other, f[0]) for f in self.FIELDS
        )

    def __repr__(self):
        inner = ", ".join(f"{f[0]}={getattr(self, f[0])!r}" for f in self.FIELDS)
        return f"{type(self).__name__}({inner})"


def _make(class_name, schema_name, schema, standard=None, base=Message, namespace=None):
    fields = _parse_schema(schema)
    fmt, _size = _layout(fields)
    attrs = dict(namespace or {})
    attrs.update(
        {
            "SCHEMA_NAME": schema_name,
            "SCHEMA": schema,
            "FIELDS": tuple(fields),
            "_struct": struct.Struct(fmt),
            "_standard": standard,
            "__slots__": tuple(f[0] for f in fields),
        }
    )
    attrs.pop("__dict__", None)
    attrs.pop("__weakref__", None)
    return type(class_name, (base,), attrs)


def message(schema_name):
    """Declares a fixed-size message type from a class whose annotations are field types
    (``x: "float64"``, an array ``corners: "float32[4]"``): the same layout as a Rust
    ``#[repr(C)]`` struct of those fields."""

    def wrap(cls):
        lines = []
        for name, ty in getattr(cls, "__annotations__", {}).items():
            ty = ty if isinstance(ty, str) else getattr(ty, "__name__", str(ty))
            lines.append(f"{ty} {name}")
        if not lines:
            raise TypeError(f"{cls.__name__}: declare its fields as annotations (x: \"float64\")")
        schema = "\n".join(lines) + "\n"
        fields = cls.__annotations__
        # `x: "float64" = 1.0`: a default, not a class attribute (the fields are slots).
        ns = {k: v for k, v in vars(cls).items() if k != "__annotations__" and k not in fields}
        ns["_defaults"] = {k: v for k, v in vars(cls).items() if k in fields}
        made = _make(cls.__name__, schema_name, schema, namespace=ns)
        try:
            made().encode()
        except (TypeError, ValueError) as e:
            raise TypeError(f"{cls.__name__}: a default does not fit its field: {e}") from None
        return made

    return wrap


class BytesType:
    """A variable-size message type: bytes on the port (read as a numpy array)."""

    def __init__(self, name, schema_name, encoding, schema):
        self.__name__ = name
        self.SCHEMA_NAME = schema_name
        self.ENCODING = encoding
        self.SCHEMA = schema

    def message_type(self, max_bytes):
        return {
            "schema_name": self.SCHEMA_NAME,
            "encoding": self.ENCODING,
            "schema": self.SCHEMA,
            "payload": {"layout": "bytes", "max_bytes": int(max_bytes)},
        }

    def __repr__(self):
        return f"dnm.msg.{self.__name__}"


# An image's header: width, height, row step (uint32 each), then rgb8 rows.
IMAGE_HEADER = 12

_builtin = {}
for _name, _t in json.loads(_dnm.message_types()).items():
    if _t["payload"]["layout"] == "fixed":
        _builtin[_name] = _make(_name, _t["schema_name"], _t["schema"], _t.get("standard"))
    else:
        _builtin[_name] = BytesType(_name, _t["schema_name"], _t["encoding"], _t["schema"])
globals().update(_builtin)
__all__ += sorted(_builtin)


def by_schema(schema_name):
    """The known type of a schema name (built in or declared), if any."""
    for t in list(_builtin.values()) + _declared():
        if t.SCHEMA_NAME == schema_name:
            return t
    return None


def _declared():
    out = []
    stack = list(Message.__subclasses__())
    while stack:
        t = stack.pop()
        out.append(t)
        stack.extend(t.__subclasses__())
    return out
