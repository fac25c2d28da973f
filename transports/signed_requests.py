"""Requests one robot makes of others, signed by the asker and fresh: what the transports share.

A robot that cannot use a peer's delta asks that peer for a whole map: a zenoh query, or a control
message over UWB. The request makes the asked robot forget the asker's delta base and send its
next map whole, a keyframe's bytes on a shared link, so it must come from the robot it names and
must not be a recording played back. Both transports build it the same way:

* the asker signs ``domain || fleet || asker || robots asked || nonce`` with its Ed25519 key
  (:func:`sign`); each transport has its own ``domain``, so a request seen on one cannot be
  replayed on the other;
* ``nonce`` grows with every request the asker makes (:class:`NonceClock`: nanoseconds of its
  wall clock, or one more than the last when the clock stands still or steps back), so it keeps
  growing across the asker's restarts;
* the robot asked heeds a request only when its signature checks against the roster
  (:func:`verify`) and its nonce is above the last one heeded from that asker (:class:`Freshness`).

Pure: no clock and no I/O; the caller passes the wall clock in.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence

from mapd.identity import Identity, Roster

_NONCE = struct.Struct(">Q")
#: Nonces are positive and below this (they fit a signed 64-bit integer).
MAX_NONCE = 1 << 63


def blob(domain: bytes, *, fleet: str, asker: str, robots: Sequence[str], nonce: int) -> bytes:
    """The bytes the asker signs: ``domain``, fleet, asker and robots asked (NUL-separated), nonce."""
    return domain + b"\0" + "\0".join((fleet, asker, *robots)).encode() + b"\0" + _NONCE.pack(nonce)


def sign(
    identity: Identity | None, domain: bytes, *, fleet: str, asker: str, robots: Sequence[str], nonce: int
) -> bytes:
    """``asker``'s signature of its request (empty where the fleet does not sign: no identity).

    ValueError for a nonce out of range or an identity that is not ``asker``'s: a caller's bug,
    found before anything is on a link.
    """
    if not 0 < nonce < MAX_NONCE:
        raise ValueError(f"request nonce {nonce} is out of range")
    if identity is None:
        return b""
    if identity.robot != asker:
        raise ValueError(f"robot '{identity.robot}' cannot sign a request of '{asker}'")
    return identity.sign(blob(domain, fleet=fleet, asker=asker, robots=robots, nonce=nonce))


def verify(
    roster: Roster,
    domain: bytes,
    *,
    fleet: str,
    asker: str,
    robots: Sequence[str],
    nonce: int,
    sig: bytes,
    what: str,
) -> None:
    """Check ``asker``'s signature of its request; :class:`~mapd.errors.SignatureError` says why not.

    Unsigned (``sig`` empty) passes only in a fleet that allows unsigned messages, as
    :meth:`Roster.verify` decides.
    """
    roster.verify(asker, blob(domain, fleet=fleet, asker=asker, robots=robots, nonce=nonce), sig, what)


class NonceClock:
    """The asker's side: a nonce above every one it gave before, from the wall clock passed in.

    Wall-clock nanoseconds keep nonces growing across restarts of the asker (the robot asked
    remembers the last one it heeded for as long as it runs); within one run they grow even when
    the clock stands still or is stepped back.
    """

    def __init__(self) -> None:
        self._last = 0

    def next(self, wall_ns: int) -> int:
        """The nonce for the next request, given the wall clock now in nanoseconds."""
        self._last = min(max(self._last + 1, wall_ns), MAX_NONCE - 1)
        return self._last


class Freshness:
    """The asked robot's side: the last nonce heeded from each asker, so a replay is refused.

    Only askers whose signature checked (or, in an unsigned fleet, the link's own peers) reach it,
    and it keeps at most ``max_askers``: past that the asker heard longest ago is forgotten, which
    at worst lets one of its old requests through once more.
    """

    def __init__(self, max_askers: int = 1024) -> None:
        self.max_askers = max_askers
        self._last: dict[str, int] = {}

    def fresh(self, asker: str, nonce: int) -> bool:
        """Whether ``nonce`` is above the last heeded from ``asker``; if so it becomes the last."""
        last = self._last.pop(asker, 0)
        if nonce <= last:
            self._last[asker] = last
            return False
        self._last[asker] = nonce  # (re-inserted: the dict keeps askers in order of last use)
        while len(self._last) > self.max_askers:
            del self._last[next(iter(self._last))]
        return True
