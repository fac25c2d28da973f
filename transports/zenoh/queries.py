"""Keyframe queries of the zenoh transport, signed by the robot that asks.

A query of ``mapd/<fleet>/<robot>/latest`` is answered with ``<robot>``'s latest keyframe whoever
asks: the keyframe is signed by its origin and holds no secret. But a query that names its asker
also makes the answering daemon forget the asker's acked delta base and publish its next map whole
(``KeyframeNeeded``), which costs every robot on the bus a keyframe's bytes. Anyone who can reach a
zenoh router could otherwise force that on the fleet over and over by naming a robot on the roster.
So the name must be the asker's own, and the query fresh::

    mapd/<fleet>/<robot>/latest?from=<asker>;n=<nonce>;sig=<128 hex digits>

``sig`` is the asker's Ed25519 signature over the fleet, the asker, the robot asked and ``n``.
``n`` grows with every query the asker sends (:class:`NonceClock`: nanoseconds of its wall clock,
or one more than the last when the clock stands still or steps back), and the robot asked heeds a
query only when ``n`` is above the last it heeded from that asker, so a recorded query played
back is refused. In a fleet whose config allows unsigned messages, ``sig`` is left out.

A query refused for any of these reasons is still answered (within the ration every query is
answered by, :meth:`~transports.zenoh.core.ZenohCore.may_reply`): only the ``KeyframeNeeded`` is
withheld.
"""

from __future__ import annotations

import struct

from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import SIG_LEN, Identity, Roster

_NONCE = struct.Struct(">Q")
_MAX_NONCE = 1 << 63
_NONCE_DIGITS = len(str(_MAX_NONCE))


def _blob(fleet: str, asker: str, robot: str, nonce: int) -> bytes:
    return b"mapd-query/1\0" + "\0".join((fleet, asker, robot)).encode() + b"\0" + _NONCE.pack(nonce)


class NonceClock:
    """The asker's side: a nonce above every one it gave before, from the wall clock passed in.

    Wall-clock nanoseconds keep nonces growing across restarts of the asker (the robot asked
    remembers the last one it heeded for as long as it runs); within one run they grow even when
    the clock stands still or is stepped back.
    """

    def __init__(self) -> None:
        self._last = 0

    def next(self, wall_ns: int) -> int:
        """The nonce for the next query, given the wall clock now in nanoseconds."""
        self._last = min(max(self._last + 1, wall_ns), _MAX_NONCE - 1)
        return self._last


def parameters(identity: Identity | None, *, fleet: str, asker: str, robot: str, nonce: int) -> str:
    """The selector parameters of ``asker``'s query of ``robot``'s latest keyframe."""
    if not 0 < nonce < _MAX_NONCE:
        raise ValueError(f"query nonce {nonce} is out of range")
    params = f"from={asker};n={nonce}"
    if identity is None:
        return params
    if identity.robot != asker:
        raise ValueError(f"robot '{identity.robot}' cannot sign a query of '{asker}'")
    return f"{params};sig={identity.sign(_blob(fleet, asker, robot, nonce)).hex()}"


def verify(roster: Roster, *, fleet: str, asker: str, robot: str, nonce: str | None, sig: str | None) -> int:
    """The nonce of ``asker``'s query of ``robot``, once its signature is checked.

    ``nonce`` and ``sig`` are the query's ``n`` and ``sig`` parameters as they came off the
    network. :class:`~mapd.errors.EnvelopeError` when ``n`` is missing or not a number in range;
    :class:`~mapd.errors.SignatureError` when ``roster`` does not accept the signature (unsigned in
    a signed fleet, another key, not 128 hex digits).
    """
    if nonce is None or not nonce.isdigit() or not nonce.isascii() or len(nonce) > _NONCE_DIGITS:
        raise EnvelopeError(f"keyframe query from '{asker}' has no valid nonce")
    n = int(nonce)
    if not 0 < n < _MAX_NONCE:
        raise EnvelopeError(f"keyframe query from '{asker}' has nonce {n}, out of range")
    raw = b""
    if sig:
        if len(sig) != 2 * SIG_LEN:
            raise SignatureError(f"keyframe query from '{asker}' has a signature of {len(sig)} hex digits")
        try:
            raw = bytes.fromhex(sig)
        except ValueError:
            raise SignatureError(f"keyframe query from '{asker}' has a signature that is not hex") from None
    roster.verify(asker, _blob(fleet, asker, robot, n), raw, "keyframe query")
    return n
