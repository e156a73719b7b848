"""Register-map profiles: shipped tables, decode of every type and order, clear errors."""

import struct

import numpy as np
import pytest
import tomllib
from hypothesis import given
from hypothesis import strategies as st

from torchcontact.drivers.profiles import (
    ProfileError,
    available_profiles,
    decode_value,
    encode_value,
    load_profile,
    parse_profile,
)

FMT = {"int16": "h", "uint16": "H", "int32": "i", "uint32": "I", "float32": "f"}


def registers_from_bytes(value, type_, word_order, byte_order):
    """Reference: pack big-endian with struct, then reorder words and bytes by hand."""
    raw = struct.pack(">" + FMT[type_], value)
    words = [raw[i : i + 2] for i in range(0, len(raw), 2)]
    if word_order == "little":
        words = words[::-1]
    if byte_order == "little":
        words = [w[::-1] for w in words]
    return [int.from_bytes(w, "big") for w in words]


@pytest.mark.parametrize("word_order", ["big", "little"])
@pytest.mark.parametrize("byte_order", ["big", "little"])
@pytest.mark.parametrize(
    ("type_", "value"),
    [
        ("int16", -12345),
        ("uint16", 54321),
        ("int32", -123456789),
        ("uint32", 3_000_000_000),
        ("float32", -1234.5),
    ],
)
def test_decode_every_type_and_order(type_, value, word_order, byte_order):
    regs = registers_from_bytes(value, type_, word_order, byte_order)
    assert decode_value(regs, type_, word_order, byte_order) == value
    assert encode_value(value, type_, word_order, byte_order) == regs


def test_orders_differ():
    # guards against an implementation ignoring the order: the four layouts are distinct
    layouts = {
        tuple(registers_from_bytes(1.5, "float32", w, b))
        for w in ("big", "little")
        for b in ("big", "little")
    }
    assert len(layouts) == 4


@given(
    st.floats(-1e6, 1e6, width=32),
    st.sampled_from(["big", "little"]),
    st.sampled_from(["big", "little"]),
)
def test_float32_roundtrip(x, w, b):
    assert decode_value(encode_value(x, "float32", w, b), "float32", w, b) == x


def test_shipped_profiles():
    assert {"robotiq-ft300", "generic-float32"} <= set(available_profiles())
    ft = load_profile("robotiq-ft300")
    assert (ft.device_id, ft.baudrate, ft.parity, ft.span) == (9, 19200, "N", (180, 6))
    assert [c.scale for c in ft.channels] == [0.01] * 3 + [0.001] * 3
    assert ft.stream.start_address == 410 and ft.stream.start_value == 0x0200
    assert ft.identity == {"firmware": (500, 3), "serial": (510, 4), "year": (514, 1)}
    g = load_profile("generic-float32")
    assert g.verified is False and "Unofficial" in g.note


def test_ft300_decode_scaling():
    ft = load_profile("robotiq-ft300")
    regs = [20000, 0xFFFF, 150, 1000, 0x8000, 7]  # int16 two's complement on the wire
    np.testing.assert_allclose(ft.decode(regs), [200.0, -0.01, 1.5, 1.0, -32.768, 0.007])


def test_generic_float32_encode_decode():
    g = load_profile("generic-float32")
    w = np.array([1.5, -2.25, 100.0, 0.125, -0.5, 3.0])
    regs = g.encode(w)
    block = [regs[a] for a in range(12)]
    np.testing.assert_array_equal(g.decode(block), w)


BASE = tomllib.loads(
    (
        __import__("pathlib").Path(__file__).parents[2]
        / "torchcontact/data/profiles/generic-float32.toml"
    ).read_text()
)


def edited(**changes):
    import copy

    data = copy.deepcopy(BASE)
    for key, value in changes.items():
        *path, last = key.split("__")
        t = data
        for p in path:
            t = t[p]
        if value is None:
            del t[last]
        else:
            t[last] = value
    return data


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"colour": "red"}, "unknown key(s) ['colour'] in the top level"),
        ({"device__baud": 9600}, "unknown key(s) ['baud'] in [device]"),
        ({"map__word_order": "middle"}, "[map].word_order = 'middle'"),
        ({"note": None}, "verified = false needs a 'note'"),
        ({"device": None}, "missing key 'device'"),
        ({"device__device_id": 300}, "device_id = 300 is not in 0..247"),
    ],
)
def test_profile_errors_name_the_problem(changes, message):
    with pytest.raises(ProfileError) as info:
        parse_profile(edited(**changes), "x.toml")
    assert message in str(info.value) and str(info.value).startswith("x.toml")


def test_channel_errors():
    data = edited()
    data["channels"][0]["type"] = "int8"
    with pytest.raises(ProfileError, match=r"\[\[channels\]\] #0.type = 'int8'"):
        parse_profile(data, "x.toml")
    data = edited()
    data["channels"][1]["address"] = 1  # overlaps fx (0-1)
    with pytest.raises(ProfileError, match="overlap at 1"):
        parse_profile(data, "x.toml")
    data = edited()
    data["channels"] = data["channels"][:5]
    with pytest.raises(ProfileError, match="channels must be exactly"):
        parse_profile(data, "x.toml")


def test_unknown_profile_lists_shipped(tmp_path):
    with pytest.raises(ProfileError, match="unknown profile 'nope'.*robotiq-ft300"):
        load_profile("nope")
    with pytest.raises(ProfileError, match="does not exist"):
        load_profile(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("name = ")
    with pytest.raises(ProfileError, match="not valid TOML"):
        load_profile(bad)
