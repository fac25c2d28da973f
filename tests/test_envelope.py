"""The update envelope: strict validation, fleet filtering and signatures."""

from __future__ import annotations

import contextlib
import dataclasses

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.envelope import Envelope, peek_robot, unpack
from mapd.errors import EnvelopeError, SignatureError
from mapd.grid import Pose2D
from mapd.identity import Identity, Roster

ALPHA, BETA = Identity.generate("alpha"), Identity.generate("beta")
ROSTER_KEYS = {"alpha": ALPHA.public_key, "beta": BETA.public_key}
ROSTER = Roster(ROSTER_KEYS)


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
    signed = make().signed(ALPHA)
    assert unpack(signed.pack(), roster=ROSTER).sig == signed.sig
    with pytest.raises(SignatureError, match="unsigned"):
        unpack(make().pack(), roster=ROSTER)
    with pytest.raises(SignatureError, match="bad signature"):  # alpha's name, another key
        unpack(make().signed(Identity.generate("alpha")).pack(), roster=ROSTER)
    tampered = msgpack.unpackb(signed.pack())
    tampered["v"] = 4
    with pytest.raises(SignatureError, match="bad signature"):
        unpack(msgpack.packb(tampered), roster=ROSTER)


def test_a_robot_cannot_sign_as_another_and_strangers_are_refused() -> None:
    with pytest.raises(ValueError, match="cannot sign an envelope of 'alpha'"):
        make().signed(BETA)
    # beta holds a valid key of the fleet, yet its signature cannot pass for alpha's
    forged = dataclasses.replace(make(robot="beta").signed(BETA), robot="alpha")
    with pytest.raises(SignatureError, match="bad signature on envelope from 'alpha'"):
        unpack(forged.pack(), roster=ROSTER)
    stranger = Identity.generate("gamma")
    with pytest.raises(SignatureError, match="not on the fleet's roster"):
        unpack(make(robot="gamma").signed(stranger).pack(), roster=ROSTER)
    # a fleet that allows unsigned messages takes them, and still checks the roster's robots
    lax = Roster(ROSTER_KEYS, allow_unsigned=True)
    assert unpack(make().pack(), roster=lax).robot == "alpha"
    with pytest.raises(SignatureError, match="bad signature"):
        unpack(forged.pack(), roster=lax)


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


def test_frame_pose_travels_signed_and_is_checked() -> None:
    env = make(frame_pose=Pose2D(12.5, -3.0, 1.2)).signed(ALPHA)
    back = unpack(env.pack(), roster=ROSTER)
    assert back.frame_pose == Pose2D(12.5, -3.0, 1.2)
    assert unpack(make().pack()).frame_pose is None  # optional: absent when the source does not know
    tampered = msgpack.unpackb(env.pack())
    tampered["fp"] = [0.0, 0.0, 0.0]
    with pytest.raises(SignatureError):
        unpack(msgpack.packb(tampered), roster=ROSTER)
    for bad in ([1.0, 2.0], [1e9, 0.0, 0.0], [0.0, 0.0, float("nan")], ["x", 0, 0]):
        d = msgpack.unpackb(make().pack())
        d["fp"] = bad
        with pytest.raises(EnvelopeError, match="frame pose"):
            unpack(msgpack.packb(d))


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_peek_robot_names_the_robot_and_never_raises(data: bytes) -> None:
    """The inbox sorts untrusted bytes by the robot they name before anything is checked."""
    assert peek_robot(data) is None or isinstance(peek_robot(data), str)
    env = make(robot="beta", fleet="x" * 64).signed(BETA)
    assert peek_robot(env.pack()) == "beta"
    assert peek_robot(env.pack()[:5]) is None
