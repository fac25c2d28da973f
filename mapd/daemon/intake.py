"""A peer's map on its way in, step by step: the CPU steps, the plan's answers between them, and
what ``mapd status`` counts of them. :class:`~mapd.daemon.receiver.Receiver` holds the rules; the
daemon (:mod:`~mapd.daemon.inbound`) runs the steps, the CPU ones in worker threads, off the loop.

For every :class:`~transports.base.Received` the daemon calls, in order:

1. :func:`open_envelope` in a worker thread: size cap, strict parse, signature (a forgery raises
   :class:`~mapd.errors.SignatureError`, other damage :class:`~mapd.errors.EnvelopeError`);
2. :meth:`~mapd.daemon.receiver.Receiver.plan` on the loop: another fleet's, our own, an old
   version, a version that jumps too far (:func:`~mapd.daemon.versions.check_step`), a map larger
   than the limits allow, an unsigned map that names another robot than the link it came on, or a
   robot beyond ``max_peers`` is dropped (:class:`Drop`); a delta whose base is not held asks for a
   keyframe (:class:`AskKeyframe`); otherwise the base to decode against (:class:`Decode`);
3. :func:`decode_envelope` in a worker thread;
4. :meth:`~mapd.daemon.receiver.Receiver.accept` on the loop: keep the map (and a few recent
   versions as delta bases) and count it (:class:`ReceiverCounters`); the daemon then saves it,
   hands it to fusion and acks it.

Per peer robot, what ``mapd status`` shows (its link, version, bytes, updates) is a
:class:`PeerInfo`.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

from mapd.codec import decode
from mapd.codec.base import CodecOptions
from mapd.envelope import Envelope, unpack
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid
from mapd.identity import Roster


@dataclass
class ReceiverCounters:
    """Why updates were taken or dropped, for ``mapd status``."""

    bad_envelopes: int = 0
    foreign_fleet: int = 0
    bad_signature: int = 0
    duplicates: int = 0
    refused_versions: int = 0
    refused_sizes: int = 0
    wrong_link: int = 0
    too_many_robots: int = 0
    new_incarnations: int = 0
    decode_errors: int = 0
    keyframe_requests: int = 0
    updates_received: int = 0


@dataclass
class PeerInfo:
    """What ``mapd status`` shows about one peer robot (None: not known yet)."""

    present: bool | None = None
    link: str | None = None
    version: int | None = None
    received_at: float | None = None
    bytes: int = 0
    updates: int = 0
    last_kind: str | None = None
    #: The robot whose link sent its newest map, when not the map's own robot (a uwb relay).
    relayed_by: str | None = None

    def to_json(self) -> dict[str, Any]:
        return {
            k: v for k, v in asdict(self).items() if v is not None and (k not in ("bytes", "updates") or v)
        }


@dataclass(frozen=True)
class Decode:
    """Decode the envelope against ``base`` (None for a keyframe)."""

    base: OccupancyGrid | None
    #: The robot started a new incarnation (it lost its state): it holds none of our maps either.
    new_incarnation: bool = False


@dataclass(frozen=True)
class AskKeyframe:
    """A delta whose base is not held: ask ``robot`` for a whole map."""

    robot: str
    #: As :attr:`Decode.new_incarnation`.
    new_incarnation: bool = False


@dataclass(frozen=True)
class Drop:
    """Nothing to do with this envelope; ``routine`` for echoes and duplicates, else a refusal worth a log line."""

    reason: str
    routine: bool = False
    #: The link may now hold this version as the robot's newest (zenoh's core does): ask it to
    #: forget, so the robot's real next versions are not taken for stale ones.
    forget: bool = False
    #: Worth a warning, not an info line: something an operator has to act on.
    warning: bool = False
    #: This very version is the one held: ack it again. Its robot offers it again after a restart
    #: whose state lost our ack (a full disk, a kill), and waited out its in-flight timeout (30 s)
    #: for an ack that a dropped duplicate never got.
    held: bool = False
    #: ``reason`` is a :class:`~mapd.daemon.refusals.Refusal`'s whole line (it names the robot and
    #: the fix): said as it is.
    refusal: bool = False


def open_envelope(data: bytes, *, max_bytes: int, roster: Roster) -> Envelope:
    """Parse and verify untrusted bytes (CPU work: call it from a worker thread)."""
    return unpack(data, max_bytes=max_bytes, roster=roster)


def decode_envelope(
    env: Envelope, base: OccupancyGrid | None, *, max_cells: int, options: CodecOptions | None = None
) -> OccupancyGrid:
    """Decode ``env``'s payload and check it against the envelope (CPU work: a worker thread).

    The decoder may allocate no more cells than the envelope claims (which
    :meth:`~mapd.daemon.receiver.Receiver.plan` has bounded), so a payload cannot claim more than
    its signed envelope does. ``options``: this robot's own codec's (``[codec.<use>]``), for a map
    in that codec: a fleet on a paper model other than the default one coded with it, and every
    receiver decoded with the default.
    """
    grid = decode(
        env.payload, base, max_cells=min(max_cells, max(1, env.width * env.height)), options=options
    )
    if (grid.width, grid.height) != (env.width, env.height):
        raise CodecError(
            f"payload decodes to {grid.width} x {grid.height}, the envelope says {env.width} x {env.height}"
        )
    return grid.replace(robot=env.robot, version=env.version, stamp=env.stamp, frame_id=env.frame_id)
