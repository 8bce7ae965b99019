"""Message types in Python, without a DNM: declared with `@dnm.message`, encoded as the Rust
layout, and errors that name the field."""

import pytest

import dnm
from dnm.msg import Scalar, Tick


@dnm.message("test_msgs/Gains")
class Gains:
    gain: "float64" = 1.5
    count: "uint32"
    weights: "float32[2]" = (0.25, 0.75)


def test_a_declared_message_has_its_defaults_and_the_c_layout():
    g = Gains(count=3)
    assert (g.gain, g.count, g.weights) == (1.5, 3, [0.25, 0.75])
    # float64 at 0, uint32 at 8, float32[2] at 12: 20 bytes, padded to 24 (8-aligned).
    data = g.encode()
    assert len(data) == 24
    assert Gains.decode(data) == g
    assert Gains.message_type()["payload"] == {"layout": "fixed", "size_bytes": 24}


def test_a_default_that_does_not_fit_its_field_is_refused_where_it_is_declared():
    with pytest.raises(TypeError, match=r"field `x` \(uint8\) cannot hold -1"):

        @dnm.message("test_msgs/Bad")
        class Bad:
            x: "uint8" = -1


def test_a_value_that_does_not_fit_names_its_field():
    with pytest.raises(TypeError, match=r"Tick: field `origin` \(uint64\) cannot hold -1"):
        Tick(origin=-1).encode()
    with pytest.raises(TypeError, match=r"Scalar: field `value` \(float64\) cannot hold 'x'"):
        Scalar(value="x").encode()
    with pytest.raises(TypeError, match="has no field speed"):
        Tick(speed=1)


def test_a_kind_with_a_name_a_netlist_refuses_is_refused_where_it_is_declared():
    with pytest.raises(ValueError, match=r"kind `bad name!`: kind name `bad name!` must start"):
        dnm.Kind("bad name!", "").output("out", Tick).spec()
    with pytest.raises(ValueError, match=r"output name `out port` must start"):
        dnm.Kind("good", "").output("out port", Tick).spec()
