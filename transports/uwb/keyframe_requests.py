"""Control messages of the ``uwb`` transport: keyframe requests, carried by the ARQ core on stream 255.

A receiver that gets a delta whose base it does not hold (it restarted and lost a version, or the
update it missed was superseded) asks the map's robot for a whole map. Over zenoh that is a query;
over UWB it is this small message, sent reliably like any other, to the link ids of the robots
named::

    b"MKFR" | version 2 (one byte) | nonce (u64, big-endian) | signature length (one byte: 0 or 64)
           | signature | robot names, UTF-8, separated by b"\\n"

A request makes each robot it names forget the asker's delta base and send its next map whole, a
keyframe's bytes on the shared channel. The frame's link tag proves only that the sender holds the
fleet's link key, and the link id in the frame is the sender's word. So the asker signs the
request with its own key and a nonce that always grows (:mod:`transports.signed_requests`, domain
:data:`DOMAIN`), and a robot heeds it only when the signature is that of the robot the link id
names and the nonce is above the last one heeded from it: no holder of the link key can speak for
another robot or play a request back. In a fleet that allows unsigned messages the signature is
left out (length 0). Version 1 (before signatures: no nonce, no signature) is still read, and
heeded only in such a fleet.

The ARQ core keeps the latest message per stream, so one message names every robot still wanted
(requested within ``hold_s``); a later request supersedes an earlier one without losing a name.
Requests are throttled per robot, so a flood of undecodable deltas costs one request per ``hold_s``.
Everything here is sans-I/O: the caller passes ``now``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from mapd.errors import ProtocolError
from mapd.identity import SIG_LEN

#: The ARQ stream reserved for control messages; maps use 0..252 (253 relay summaries, 254 poses).
CONTROL_STREAM = 255
MAGIC = b"MKFR"
VERSION = 2
#: Keyframe requests of this version have neither nonce nor signature.
UNSIGNED_VERSION = 1
#: What a request's signature starts with (:func:`transports.signed_requests.blob`).
DOMAIN = b"mapd-uwb-kfr/1"
#: Longest control message we build or accept (a few robot names, not a map).
MAX_CONTROL_BYTES = 1024
_HEAD = struct.Struct(">4sBQB")


@dataclass(frozen=True)
class Request:
    """A keyframe request as it came off the link: who is asked, and the asker's nonce and signature.

    ``nonce`` is None for a version-1 request (no nonce, no signature).
    """

    robots: list[str]
    nonce: int | None = None
    sig: bytes = b""


def names(robots: list[str]) -> list[str]:
    """The robots a request built for ``robots`` names, in the order they are signed and sent."""
    return sorted(set(robots))


def pack_request(robots: list[str], *, nonce: int, sig: bytes = b"") -> bytes:
    """The keyframe request naming ``robots`` (at least one); ValueError when it cannot be built.

    ``sig`` is the asker's signature over :func:`names` of ``robots`` (empty: unsigned). Too many
    (or too long) names to fit :data:`MAX_CONTROL_BYTES` is the caller's problem, not a protocol
    fault: nothing has been on a link yet.
    """
    if not robots:
        raise ValueError("a keyframe request names at least one robot")
    if len(sig) not in (0, SIG_LEN):
        raise ValueError(f"a keyframe request's signature is {SIG_LEN} bytes, not {len(sig)}")
    body = _HEAD.pack(MAGIC, VERSION, nonce, len(sig)) + sig + "\n".join(names(robots)).encode()
    if len(body) > MAX_CONTROL_BYTES:
        raise ValueError(f"uwb: keyframe request of {len(body)} bytes is over {MAX_CONTROL_BYTES}")
    return body


def _names(data: bytes) -> list[str]:
    try:
        out = data.decode().split("\n")
    except UnicodeDecodeError:
        raise ProtocolError("uwb: keyframe request with a robot name that is not UTF-8") from None
    if any(not n for n in out):
        raise ProtocolError("uwb: keyframe request with an empty robot name")
    return out


def parse_request(data: bytes) -> Request:
    """The keyframe request in ``data``; :class:`ProtocolError` for anything else.

    Only the form is checked here; whether the asker signed it is the caller's to check (it knows
    who the asker is and whom the fleet trusts).
    """
    if len(data) > MAX_CONTROL_BYTES:
        raise ProtocolError(f"uwb: control message of {len(data)} bytes is over {MAX_CONTROL_BYTES}")
    if data[:4] != MAGIC:
        raise ProtocolError("uwb: control message without the keyframe-request magic")
    if len(data) >= 6 and data[4] == UNSIGNED_VERSION:
        return Request(_names(data[5:]))
    if len(data) < _HEAD.size + 1 or data[4] != VERSION:
        raise ProtocolError("uwb: keyframe request of an unknown version or with no robot")
    _, _, nonce, sig_len = _HEAD.unpack_from(data)
    if sig_len not in (0, SIG_LEN) or len(data) < _HEAD.size + sig_len + 1:
        raise ProtocolError(f"uwb: keyframe request with a signature of {sig_len} bytes")
    return Request(_names(data[_HEAD.size + sig_len :]), nonce, data[_HEAD.size : _HEAD.size + sig_len])


@dataclass
class ControlCounters:
    """Control messages a ``uwb`` transport sent, took and refused (its ``stats()`` shows these names)."""

    keyframe_requests_tx: int = 0
    keyframe_requests_rx: int = 0
    bad_control: int = 0
    #: Requests not heeded: not signed by the robot the link id names (or unsigned in a signed fleet).
    keyframe_requests_forged: int = 0
    #: Requests not heeded: a nonce no higher than the last one heeded from that robot.
    keyframe_requests_replayed: int = 0


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
