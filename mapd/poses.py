"""Robot poses between robots: a small, signed, latest-wins message, and the rule that keeps them.

A pose message says where robot ``robot``'s ``base_link`` was, in that robot's own map frame, at
``stamp`` (its wall clock). It is sent a few times a second over Wi-Fi and every few seconds over
the radio, so it is packed by hand rather than as a msgpack envelope (about 100 bytes signed, 64 of
them the signature)::

    "MP" | u8 format (1) | u8 len | fleet | u8 len | robot | f64 stamp | f32 x | f32 y | f32 yaw | sig
    "MP" | u8 format (2) | u8 len | fleet | u8 len | robot | f64 stamp | f64 x | f64 y | f32 yaw | sig

Format 1 holds x and y as float32, whose step is a quarter metre beyond 2,100 km and half a metre
beyond 4,200 km: a map frame in UTM coordinates (which maps may use, up to ``MAX_ORIGIN_M``) would
move peers' robots in half-metre jumps. So a pose whose x or y float32 cannot carry within a
millimetre goes as format 2, with float64 x and y (8 bytes more); every other pose still goes as
format 1, so radios pay nothing extra and robots of earlier releases keep reading them.

``sig`` is the Ed25519 signature of the robot it names over everything before it, under its own
domain (so no other signed mapd message can pass for a pose); it is absent in a fleet that allows
unsigned messages. Receivers check it against the roster, like envelopes.

:class:`PoseBook` is the sans-I/O rule on the receiving side: per robot, only a pose newer than the
one held is taken (a replayed or reordered pose is older), and a stamp far in the receiver's future
is refused, so a forged far-future pose cannot freeze a robot's position. ``now`` is passed in.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from mapd.errors import EnvelopeError
from mapd.grid import MAX_ORIGIN_M, MAX_ORIGIN_YAW, Pose2D, StampedPose
from mapd.identity import SIG_LEN, Identity, Roster

MAGIC = b"MP"
#: The formats this mapd reads; it writes the smallest one that holds the pose (see above).
FORMATS = (1, 2)
_DOMAIN = b"mapd-pose/1\x00"
_MAX_NAME = 64
_TAILS = {1: struct.Struct("<dfff"), 2: struct.Struct("<dddf")}
#: Format 1 is used while float32 keeps x and y within this many metres.
_F32_TOLERANCE_M = 1e-3
#: A pose stamped further than this ahead of the receiver's clock is refused (clocks differ a little).
MAX_AHEAD_S = 60.0


@dataclass(frozen=True)
class PoseMessage:
    """One robot's pose (its ``base_link`` in its own map frame) at ``stamp``."""

    fleet: str
    robot: str
    stamp: float
    pose: Pose2D
    sig: bytes = field(default=b"", repr=False)

    @property
    def format(self) -> int:
        """1 when float32 holds x and y within a millimetre, else 2 (float64 x and y)."""
        fits = all(
            abs(struct.unpack("<f", struct.pack("<f", v))[0] - v) <= _F32_TOLERANCE_M
            for v in (self.pose.x, self.pose.y)
        )
        return 1 if fits else 2

    def _body(self) -> bytes:
        fleet, robot = self.fleet.encode(), self.robot.encode()
        fmt = self.format
        return (
            MAGIC
            + bytes([fmt, len(fleet)])
            + fleet
            + bytes([len(robot)])
            + robot
            + _TAILS[fmt].pack(self.stamp, self.pose.x, self.pose.y, self.pose.yaw)
        )

    def signed(self, identity: Identity) -> PoseMessage:
        """A copy signed by ``identity`` (it must be this robot's)."""
        if identity.robot != self.robot:
            raise ValueError(f"robot '{identity.robot}' cannot sign a pose of '{self.robot}'")
        return PoseMessage(
            self.fleet, self.robot, self.stamp, self.pose, identity.sign(_DOMAIN + self._body())
        )

    def pack(self) -> bytes:
        return self._body() + self.sig

    @property
    def stamped(self) -> StampedPose:
        return StampedPose(self.pose, self.stamp)


def _name(data: bytes, at: int, what: str) -> tuple[str, int]:
    if at >= len(data):
        raise EnvelopeError("pose message is truncated")
    n = data[at]
    raw = data[at + 1 : at + 1 + n]
    if n == 0 or n > _MAX_NAME or len(raw) != n:
        raise EnvelopeError(f"pose message has a bad {what} name")
    try:
        return raw.decode(), at + 1 + n
    except UnicodeDecodeError:
        raise EnvelopeError(f"pose message has a bad {what} name") from None


def unpack_pose(data: bytes, *, roster: Roster | None = None, fleet: str | None = None) -> PoseMessage:
    """Parse and check a pose message from untrusted bytes.

    :class:`EnvelopeError` when it is malformed, absurd or from another fleet;
    :class:`~mapd.errors.SignatureError` when ``roster`` does not accept its signature. Without a
    roster nothing is verified (tools).
    """
    if len(data) > 4 + 2 * (_MAX_NAME + 1) + _TAILS[2].size + SIG_LEN:
        raise EnvelopeError(f"pose message of {len(data)} bytes is too long")
    if data[:2] != MAGIC or len(data) < 3:
        raise EnvelopeError("not a pose message")
    tail = _TAILS.get(data[2])
    if tail is None:
        raise EnvelopeError(f"pose format {data[2]} is not supported (this mapd reads 1 and 2)")
    fleet_name, at = _name(data, 3, "fleet")
    robot, at = _name(data, at, "robot")
    if len(data) < at + tail.size:
        raise EnvelopeError("pose message is truncated")
    stamp, x, y, yaw = tail.unpack_from(data, at)
    at += tail.size
    sig = data[at:]
    if sig and len(sig) != SIG_LEN:
        raise EnvelopeError("pose signature has the wrong length")
    if not all(math.isfinite(v) for v in (stamp, x, y, yaw)) or stamp <= 0:
        raise EnvelopeError("pose message has a non-finite or non-positive field")
    if abs(x) > MAX_ORIGIN_M or abs(y) > MAX_ORIGIN_M or abs(yaw) > MAX_ORIGIN_YAW:
        raise EnvelopeError("pose message is beyond the world's extent")
    if fleet is not None and fleet_name != fleet:
        raise EnvelopeError(f"pose is for fleet '{fleet_name}', not '{fleet}'")
    if roster is not None:
        roster.verify(robot, _DOMAIN + data[:at], sig, "pose")
    return PoseMessage(fleet_name, robot, stamp, Pose2D(x, y, yaw), sig)


@dataclass
class PoseBook:
    """The latest pose of each robot, taking only newer ones; bounded by ``max_robots``."""

    max_robots: int = 64
    poses: dict[str, StampedPose] = field(default_factory=dict)
    refused_old: int = 0
    refused_future: int = 0
    refused_full: int = 0

    def offer(self, robot: str, pose: StampedPose, now: float) -> bool:
        """Keep ``pose`` if it is newer than the one held and not from the future; say whether it was."""
        if pose.stamp > now + MAX_AHEAD_S:
            self.refused_future += 1
            return False
        held = self.poses.get(robot)
        if held is not None and pose.stamp <= held.stamp:
            if pose.stamp < held.stamp:  # equal: the same pose sent again (robots repeat their last)
                self.refused_old += 1
            return False
        if held is None and len(self.poses) >= self.max_robots:
            self.refused_full += 1
            return False
        self.poses[robot] = pose
        return True

    def stats(self) -> dict[str, int]:
        return {
            "known": len(self.poses),
            "refused_old": self.refused_old,
            "refused_future": self.refused_future,
            "refused_full": self.refused_full,
        }
