"""A zenoh ack: the payload a peer publishes to say it applied one of a robot's versions.

8 bytes of big-endian version, plus the acking robot's 64-byte Ed25519 signature in a signed
fleet. The signature covers the fleet, the acker and the robot acked, so an ack cannot be replayed
as another robot's or into another fleet. :class:`~transports.zenoh.core.ZenohCore` turns a valid
ack of one of our own offered versions into ``Delivered``; the daemon's publisher then codes
against it.
"""

from __future__ import annotations

import struct

from mapd.envelope import COUNT_LIMIT
from mapd.errors import EnvelopeError
from mapd.identity import SIG_LEN, Identity, Roster

_ACK = struct.Struct(">Q")


def _ack_blob(fleet: str, peer: str, robot: str, body: bytes) -> bytes:
    return b"mapd-ack/2\0" + "\0".join((fleet, peer, robot)).encode() + b"\0" + body


def pack_ack(version: int, *, identity: Identity | None, fleet: str, peer: str, robot: str) -> bytes:
    """The payload ``peer`` publishes to say it applied ``robot``'s ``version``, signed by ``peer``."""
    if not 0 < version < COUNT_LIMIT:
        raise ValueError(f"ack version {version} is out of range")
    body = _ACK.pack(version)
    if identity is None:
        return body
    if identity.robot != peer:
        raise ValueError(f"robot '{identity.robot}' cannot sign an ack of '{peer}'")
    return body + identity.sign(_ack_blob(fleet, peer, robot, body))


def unpack_ack(data: bytes, *, roster: Roster, fleet: str, peer: str, robot: str) -> int:
    """The version in an ack from ``peer``.

    :class:`~mapd.errors.SignatureError` when ``roster`` does not accept ``peer``'s signature (unsigned
    in a signed fleet, not on the roster, another key), :class:`EnvelopeError` when malformed otherwise.
    """
    if len(data) not in (_ACK.size, _ACK.size + SIG_LEN):
        raise EnvelopeError(
            f"ack from '{peer}' is {len(data)} bytes, expected {_ACK.size} or {_ACK.size + SIG_LEN}"
        )
    (version,) = _ACK.unpack_from(data)
    roster.verify(peer, _ack_blob(fleet, peer, robot, data[: _ACK.size]), data[_ACK.size :], "ack")
    if not 0 < version < COUNT_LIMIT:
        raise EnvelopeError(f"ack from '{peer}' names version {version}")
    return int(version)
