"""Pose messages: packed by hand, signed by the robot they name, strictly parsed, newest wins."""

from __future__ import annotations

import contextlib
import itertools
import math
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import EnvelopeError, SignatureError
from mapd.grid import Pose2D, StampedPose
from mapd.identity import Identity, Roster
from mapd.poses import MAX_AHEAD_S, PoseBook, PoseMessage, unpack_pose

R0, R1 = Identity.generate("robot0"), Identity.generate("robot1")
ROSTER = Roster({"robot0": R0.public_key, "robot1": R1.public_key})


def msg(**kw: object) -> PoseMessage:
    fields: dict[str, object] = {
        "fleet": "demo",
        "robot": "robot0",
        "stamp": 1.8e9,
        "pose": Pose2D(1.5, -2.25, 0.5),
    }
    fields.update(kw)
    return PoseMessage(**fields)  # type: ignore[arg-type]


def test_round_trip_signed_and_small() -> None:
    data = msg().signed(R0).pack()
    got = unpack_pose(data, roster=ROSTER, fleet="demo")
    assert (got.robot, got.fleet, got.stamp) == ("robot0", "demo", 1.8e9)
    assert got.pose == pytest.approx(Pose2D(1.5, -2.25, 0.5))
    assert len(data) < 110  # small enough for a radio: 64 of it is the signature


def test_every_changed_byte_is_refused() -> None:
    data = bytearray(msg().signed(R0).pack())
    for i in range(len(data)):
        bad = bytearray(data)
        bad[i] ^= 0x01
        with pytest.raises(EnvelopeError):  # SignatureError is one
            unpack_pose(bytes(bad), roster=ROSTER, fleet="demo")


def test_a_robot_cannot_speak_for_another() -> None:
    with pytest.raises(ValueError, match="cannot sign"):
        msg().signed(R1)
    forged = msg()._body() + R1.sign(b"mapd-pose/1\x00" + msg()._body())  # robot1's key, robot0's name
    with pytest.raises(SignatureError):
        unpack_pose(forged, roster=ROSTER, fleet="demo")
    with pytest.raises(SignatureError):  # unsigned, in a signed fleet
        unpack_pose(msg().pack(), roster=ROSTER, fleet="demo")
    with pytest.raises(SignatureError):  # a stranger
        unpack_pose(msg(robot="robot9").pack(), roster=ROSTER, fleet="demo")
    with pytest.raises(EnvelopeError, match="fleet"):
        unpack_pose(msg(fleet="other").signed(R0).pack(), roster=ROSTER, fleet="demo")
    # an envelope's signature cannot be replayed as a pose: the domains differ
    assert unpack_pose(msg().pack(), roster=Roster.open()).robot == "robot0"


@pytest.mark.parametrize(
    ("x", "y"),
    [(512345.67, 5412345.67), (687654.32, -9876543.21), (-40000.002, 3.0), (9_999_999.999, 0.5)],
)
def test_far_from_the_origin_a_pose_keeps_its_millimetres(x: float, y: float) -> None:
    """UTM-sized map frames: float32 would round 5,412,345.67 m to 5,412,345.5, so format 2 (float64)."""
    data = msg(pose=Pose2D(x, y, -1.25)).signed(R0).pack()
    assert data[2] == 2
    got = unpack_pose(data, roster=ROSTER, fleet="demo")
    assert abs(got.pose.x - x) < 1e-6 and abs(got.pose.y - y) < 1e-6
    assert got.pose.yaw == pytest.approx(-1.25)
    # A robot walking 10 cm steps there is seen walking 10 cm steps, not half-metre jumps.
    seen = [unpack_pose(msg(pose=Pose2D(x, y + 0.1 * i, 0)).pack()).pose.y for i in range(8)]
    assert [round(b - a, 6) for a, b in itertools.pairwise(seen)] == [0.1] * 7


def test_near_the_origin_the_pose_stays_format_1() -> None:
    """Format 1 where float32 holds x and y within a millimetre: no extra bytes on the radio, and
    robots of earlier releases (which read format 1 only) keep reading it."""
    data = msg(pose=Pose2D(8000.123, -16000.5, 3.0)).signed(R0).pack()
    assert data[2] == 1
    assert len(data) == len(msg(pose=Pose2D(1e6 + 0.3, 0, 0)).signed(R0).pack()) - 8
    got = unpack_pose(data, roster=ROSTER, fleet="demo")
    assert abs(got.pose.x - 8000.123) <= 1e-3 and abs(got.pose.y + 16000.5) <= 1e-3


@pytest.mark.parametrize(
    ("pose", "stamp", "why"),
    [
        (Pose2D(math.nan, 0, 0), 1.0, "non-finite"),
        (Pose2D(0, 0, 0), -1.0, "non-positive"),
        (Pose2D(1e8, 0, 0), 1.0, "extent"),
        (Pose2D(0, 0, 10.0), 1.0, "extent"),
    ],
)
def test_absurd_values_are_refused(pose: Pose2D, stamp: float, why: str) -> None:
    with pytest.raises(EnvelopeError, match=why):
        unpack_pose(msg(pose=pose, stamp=stamp).pack())


def test_structure_errors() -> None:
    good = msg().pack()
    for cut in range(len(good)):
        with pytest.raises(EnvelopeError):
            unpack_pose(good[:cut])
    with pytest.raises(EnvelopeError, match="format"):
        unpack_pose(good[:2] + b"\x09" + good[3:])
    with pytest.raises(EnvelopeError, match="too long"):
        unpack_pose(good + bytes(300))
    with pytest.raises(EnvelopeError, match="signature"):
        unpack_pose(good + bytes(10))
    with pytest.raises(EnvelopeError, match="name"):
        unpack_pose(b"MP\x01\x00" + struct.pack("<dfff", 1, 0, 0, 0))
    far = msg(pose=Pose2D(3e6 + 0.3, 0, 0)).pack()
    for cut in range(len(far)):
        with pytest.raises(EnvelopeError):
            unpack_pose(far[:cut])
    with pytest.raises(EnvelopeError, match="extent"):
        unpack_pose(far.replace(struct.pack("<d", 3e6 + 0.3), struct.pack("<d", 2e7)))


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_only_envelope_errors(data: bytes) -> None:
    with contextlib.suppress(EnvelopeError):
        unpack_pose(b"MP\x01" + data, roster=ROSTER, fleet="demo")
    with contextlib.suppress(EnvelopeError):
        unpack_pose(b"MP\x02" + data, roster=ROSTER, fleet="demo")
    with contextlib.suppress(EnvelopeError):
        unpack_pose(data)


def test_book_takes_only_newer_and_never_the_future() -> None:
    book = PoseBook(max_robots=2)
    now = 1000.0
    assert book.offer("robot0", StampedPose(Pose2D(1, 0, 0), 990.0), now)
    assert not book.offer("robot0", StampedPose(Pose2D(1, 0, 0), 990.0), now)  # sent again: not counted
    assert not book.offer("robot0", StampedPose(Pose2D(2, 0, 0), 980.0), now)  # reordered, older
    assert book.poses["robot0"].pose.x == 1
    # a forged far-future stamp would freeze the robot: refused, and real poses still land
    assert not book.offer("robot0", StampedPose(Pose2D(9, 9, 0), now + MAX_AHEAD_S + 1), now)
    assert book.offer("robot0", StampedPose(Pose2D(3, 0, 0), 995.0), now)
    assert book.offer("robot1", StampedPose(Pose2D(0, 0, 0), 995.0), now)
    assert not book.offer("robot2", StampedPose(Pose2D(0, 0, 0), 995.0), now)  # bounded
    assert book.stats() == {"known": 2, "refused_old": 1, "refused_future": 1, "refused_full": 1}
