"""Control messages of the ``uwb`` transport: keyframe requests, carried by the ARQ core on stream 255.

A receiver that gets a delta whose base it does not hold (it restarted and lost a version, or the
update it missed was superseded) asks the map's robot for a whole map. Over zenoh that is a query;
over UWB it is this tiny message, sent reliably like any other, to the link ids of the robots named:

    b"MKFR" | version 1 (one byte) | robot names, UTF-8, separated by b"\\n"

The ARQ core keeps the latest message per stream, so one message names every robot still wanted
(requested within ``hold_s``); a later request supersedes an earlier one without losing a name.
Requests are throttled per robot, so a flood of undecodable deltas costs one request per ``hold_s``.
Everything here is sans-I/O: the caller passes ``now``.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapd.errors import ProtocolError

#: The ARQ stream reserved for control messages; maps use 0..252 (253 relay summaries, 254 poses).
CONTROL_STREAM = 255
MAGIC = b"MKFR"
VERSION = 1
#: Longest control message we build or accept (a few robot names, not a map).
MAX_CONTROL_BYTES = 1024


def pack_request(robots: list[str]) -> bytes:
    """The keyframe request naming ``robots`` (at least one); ValueError when it cannot be built.

    Too many (or too long) names to fit :data:`MAX_CONTROL_BYTES` is the caller's problem, not a
    protocol fault: nothing has been on a link yet.
    """
    if not robots:
        raise ValueError("a keyframe request names at least one robot")
    body = MAGIC + bytes([VERSION]) + "\n".join(sorted(set(robots))).encode()
    if len(body) > MAX_CONTROL_BYTES:
        raise ValueError(f"uwb: keyframe request of {len(body)} bytes is over {MAX_CONTROL_BYTES}")
    return body


def parse_request(data: bytes) -> list[str]:
    """The robots a keyframe request names; :class:`ProtocolError` for anything else."""
    if len(data) > MAX_CONTROL_BYTES:
        raise ProtocolError(f"uwb: control message of {len(data)} bytes is over {MAX_CONTROL_BYTES}")
    if data[:4] != MAGIC:
        raise ProtocolError("uwb: control message without the keyframe-request magic")
    if len(data) < 6 or data[4] != VERSION:
        raise ProtocolError("uwb: keyframe request of an unknown version or with no robot")
    try:
        names = data[5:].decode().split("\n")
    except UnicodeDecodeError:
        raise ProtocolError("uwb: keyframe request with a robot name that is not UTF-8") from None
    if any(not n for n in names):
        raise ProtocolError("uwb: keyframe request with an empty robot name")
    return names


@dataclass
class ControlCounters:
    """Control messages a ``uwb`` transport sent, took and refused (its ``stats()`` shows these names)."""

    keyframe_requests_tx: int = 0
    keyframe_requests_rx: int = 0
    bad_control: int = 0


class KeyframeRequests:
    """Which robots we want whole maps of, throttled per robot (sans-I/O)."""

    def __init__(self, hold_s: float = 5.0) -> None:
        self.hold_s = hold_s
        self._asked: dict[str, float] = {}

    def want(self, robot: str, now: float) -> list[str] | None:
        """Record a request for ``robot``; return every robot to name now, or None if throttled."""
        last = self._asked.get(robot)
        if last is not None and now - last < self.hold_s:
            return None
        self._asked[robot] = now
        for name, t in list(self._asked.items()):
            if now - t >= self.hold_s:
                del self._asked[name]
        return sorted(self._asked)
