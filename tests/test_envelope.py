"""The update envelope: strict validation, fleet filtering and signatures."""

from __future__ import annotations

import contextlib

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.envelope import Envelope, unpack
from mapd.errors import EnvelopeError
from mapd.grid import Pose2D

KEY = b"k" * 32


def make(**kw: object) -> Envelope:
    base = dict(
        fleet="f1",
        robot="alpha",
        version=3,
        base_version=2,
        codec="lossless",
        width=10,
        height=20,
        resolution=0.05,
        origin=Pose2D(1.0, 2.0, 0.5),
        payload=b"\x01\x02",
        variant="",
        stamp=12.5,
        seq=7,
    )
    base.update(kw)
    return Envelope(**base)  # type: ignore[arg-type]


def test_round_trip() -> None:
    env = make()
    assert unpack(env.pack()) == env
    assert not env.is_keyframe and make(base_version=0).is_keyframe


def test_signature_checked() -> None:
    signed = make().signed(KEY)
    assert unpack(signed.pack(), key=KEY).sig == signed.sig
    with pytest.raises(EnvelopeError, match="unsigned"):
        unpack(make().pack(), key=KEY)
    with pytest.raises(EnvelopeError, match="bad signature"):
        unpack(signed.pack(), key=b"x" * 32)
    tampered = msgpack.unpackb(signed.pack())
    tampered["v"] = 4
    with pytest.raises(EnvelopeError, match="bad signature"):
        unpack(msgpack.packb(tampered), key=KEY)


def test_fleet_and_size_limits() -> None:
    with pytest.raises(EnvelopeError, match="fleet 'f1', not 'f2'"):
        unpack(make().pack(), fleet="f2")
    with pytest.raises(EnvelopeError, match="over the limit"):
        unpack(make(payload=bytes(5000)).pack(), max_bytes=1000)


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("v", "3", "wrong type"),
        ("v", 0, "inconsistent"),
        ("b", 5, "inconsistent"),
        ("res", -1.0, "non-finite"),
        ("o", [1, 2], "three numbers"),
        ("zz", 1, "unknown fields"),
        ("f", 9, "format 9"),
        ("r", "", "empty"),
    ],
)
def test_bad_fields(field: str, value: object, match: str) -> None:
    d = msgpack.unpackb(make().pack())
    d[field] = value
    with pytest.raises(EnvelopeError, match=match):
        unpack(msgpack.packb(d))


def test_missing_field() -> None:
    d = msgpack.unpackb(make().pack())
    del d["p"]
    with pytest.raises(EnvelopeError, match="missing fields"):
        unpack(msgpack.packb(d))


@settings(max_examples=300, deadline=None)
@given(blob=st.binary(max_size=300))
def test_fuzz_unpack_only_raises_envelope_errors(blob: bytes) -> None:
    with contextlib.suppress(EnvelopeError):
        unpack(blob)


@settings(max_examples=100, deadline=None)
@given(
    obj=st.recursive(
        st.none()
        | st.integers(-(2**63), 2**64 - 1)
        | st.text(max_size=5)
        | st.binary(max_size=5)
        | st.floats(),
        lambda c: st.lists(c, max_size=4) | st.dictionaries(st.text(max_size=3), c, max_size=4),
        max_leaves=20,
    )
)
def test_fuzz_structured_garbage(obj: object) -> None:
    with contextlib.suppress(EnvelopeError):
        unpack(msgpack.packb(obj))
