"""Keyframe queries of the zenoh transport, signed by the robot that asks.

A query of ``mapd/<fleet>/<robot>/latest`` is answered with ``<robot>``'s latest keyframe whoever
asks: the keyframe is signed by its origin and holds no secret. But a query that names its asker
also makes the answering daemon forget the asker's acked delta base and publish its next map whole
(``KeyframeNeeded``), which costs every robot on the bus a keyframe's bytes. Anyone who can reach a
zenoh router could otherwise force that on the fleet over and over by naming a robot on the roster.
So the name must be the asker's own, and the query fresh::

    mapd/<fleet>/<robot>/latest?from=<asker>;n=<nonce>;sig=<128 hex digits>

``sig`` is the asker's Ed25519 signature over the fleet, the asker, the robot asked and ``n``.
``n`` grows with every query the asker sends (:class:`~transports.signed_requests.NonceClock`:
nanoseconds of its wall clock, or one more than the last when the clock stands still or steps
back), and the robot asked heeds a query only when ``n`` is above the last it heeded from that
asker, so a recorded query played back is refused. In a fleet whose config allows unsigned
messages, ``sig`` is left out.

A query refused for any of these reasons is still answered (within the ration every query is
answered by, :meth:`~transports.zenoh.answers.AnswerSide.may_reply`): only the ``KeyframeNeeded`` is
withheld.
"""

from __future__ import annotations

from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import SIG_LEN, Identity, Roster
from transports import signed_requests

#: What a zenoh query's signature starts with (:func:`transports.signed_requests.blob`).
DOMAIN = b"mapd-query/1"
_NONCE_DIGITS = len(str(signed_requests.MAX_NONCE))


def parameters(identity: Identity | None, *, fleet: str, asker: str, robot: str, nonce: int) -> str:
    """The selector parameters of ``asker``'s query of ``robot``'s latest keyframe."""
    sig = signed_requests.sign(identity, DOMAIN, fleet=fleet, asker=asker, robots=[robot], nonce=nonce)
    params = f"from={asker};n={nonce}"
    return f"{params};sig={sig.hex()}" if sig else params


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
    if not 0 < n < signed_requests.MAX_NONCE:
        raise EnvelopeError(f"keyframe query from '{asker}' has nonce {n}, out of range")
    raw = b""
    if sig:
        if len(sig) != 2 * SIG_LEN:
            raise SignatureError(f"keyframe query from '{asker}' has a signature of {len(sig)} hex digits")
        try:
            raw = bytes.fromhex(sig)
        except ValueError:
            raise SignatureError(f"keyframe query from '{asker}' has a signature that is not hex") from None
    signed_requests.verify(
        roster, DOMAIN, fleet=fleet, asker=asker, robots=[robot], nonce=n, sig=raw, what="keyframe query"
    )
    return n
