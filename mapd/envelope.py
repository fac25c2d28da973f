"""The update envelope: what every transport carries, msgpack-packed and strictly validated.

An envelope names the fleet, the robot, its map version and the base version a delta was coded
against, the codec and its variant (model id), the grid metadata, and the codec payload. With a
signed fleet (the default), it carries the Ed25519 signature of the robot it names over everything
else, checked against the fleet's roster (:mod:`mapd.identity`), so forged, impersonating or foreign
updates are dropped before anything decodes them.

Wire form: a msgpack map with short keys (see ``_KEYS``). Unpacking bounds every length before
msgpack allocates, rejects unknown or missing keys and wrong types, and checks the signature.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import msgpack

from mapd.errors import EnvelopeError, SignatureError
from mapd.grid import MAX_ORIGIN_M, MAX_ORIGIN_YAW, Pose2D
from mapd.identity import SIG_LEN, Identity, Roster

#: 2: Ed25519 signatures by each robot's own key (1 had a fleet-wide HMAC).
FORMAT = 2
#: Versions, bases, sizes and sequence numbers are whole numbers below this: a signed 64-bit int,
#: what msgpack and every peer's counters hold. The state directory and transports check the same.
COUNT_LIMIT = 1 << 63
#: Signatures cover the fields under this domain, so no other signed mapd message can pass for one.
_DOMAIN = b"mapd-envelope/2\x00"
_KEYS = {
    "f": "format",
    "fl": "fleet",
    "r": "robot",
    "v": "version",
    "b": "base_version",
    "c": "codec",
    "m": "variant",
    "w": "width",
    "h": "height",
    "res": "resolution",
    "o": "origin",
    "fr": "frame_id",
    "t": "stamp",
    "n": "seq",
    "p": "payload",
    "fp": "frame_pose",
    "s": "sig",
}
#: The longest string an envelope field holds (robot, fleet, codec, frame_id), in characters.
MAX_STR = 64


#: Where an envelope names its robot: its packer writes format, fleet (64 bytes at most), then robot
#: (64 bytes at most) first (:meth:`Envelope._fields`), well within this many bytes and fields.
_HEAD_BYTES = 256
_HEAD_FIELDS = 3


def peek_robot(data: bytes) -> str | None:
    """The robot an envelope's bytes name (its ``r`` field), read from their first fields without
    verifying anything, or None when it is not there (not an envelope, or one packed otherwise).

    Only to sort untrusted bytes before they are checked (the daemon's inbox keeps a slot per
    robot); never a reason to trust them. Cheap on the event loop: at most :data:`_HEAD_BYTES`
    bytes are looked at, the payload never.
    """
    head = msgpack.Unpacker(raw=False, max_buffer_size=_HEAD_BYTES)
    head.feed(data[:_HEAD_BYTES])
    try:
        for _ in range(min(head.read_map_header(), _HEAD_FIELDS)):
            if head.unpack() == "r":
                robot = head.unpack()
                return robot if isinstance(robot, str) else None
            head.skip()
    except Exception:  # msgpack raises assorted exceptions on hostile or cut-short bytes
        return None
    return None


@dataclass(frozen=True)
class Envelope:
    """One map update on the wire.

    ``base_version`` is 0 for a keyframe (a whole map), else the version the payload is a delta
    against. Versions carry the robot's incarnation in their high 32 bits (see
    :mod:`mapd.daemon.versions`), so a replayed or older update is never newer than one held.
    ``seq`` counts the envelopes a robot made (for logs and ``mapd status``; versions, not ``seq``,
    refuse replays). ``sig`` is empty in a fleet that allows unsigned messages.
    """

    fleet: str
    robot: str
    version: int
    base_version: int
    codec: str
    width: int
    height: int
    resolution: float
    origin: Pose2D
    payload: bytes
    variant: str = ""
    frame_id: str = "map"
    stamp: float = 0.0
    seq: int = 0
    #: Where the robot's map frame lies in the fleet's world frame, when its source knows (the
    #: start pose of a simulated or logged robot, or ``start_pose`` in its config): receivers place
    #: its map there, as a configured pose, unless their own config says otherwise.
    frame_pose: Pose2D | None = None
    sig: bytes = field(default=b"", repr=False)

    @property
    def is_keyframe(self) -> bool:
        return self.base_version == 0

    def _fields(self) -> dict[str, Any]:
        return {
            "f": FORMAT,
            "fl": self.fleet,
            "r": self.robot,
            "v": self.version,
            "b": self.base_version,
            "c": self.codec,
            "m": self.variant,
            "w": self.width,
            "h": self.height,
            "res": self.resolution,
            "o": list(self.origin),
            "fr": self.frame_id,
            "t": self.stamp,
            "n": self.seq,
            "p": self.payload,
            **({"fp": list(self.frame_pose)} if self.frame_pose is not None else {}),
        }

    def signed(self, identity: Identity) -> Envelope:
        """A copy carrying ``identity``'s signature over all other fields (it must be this robot's)."""
        if identity.robot != self.robot:
            raise ValueError(f"robot '{identity.robot}' cannot sign an envelope of '{self.robot}'")
        return replace(self, sig=identity.sign(_signed_blob(self._fields())))

    def pack(self) -> bytes:
        body = self._fields()
        if self.sig:
            body["s"] = self.sig
        return msgpack.packb(body, use_bin_type=True)


def _signed_blob(fields: dict[str, Any]) -> bytes:
    return _DOMAIN + msgpack.packb(fields, use_bin_type=True)


def _want(d: dict[str, Any], k: str, kind: type | tuple[type, ...]) -> Any:
    v = d[k]
    if isinstance(v, bool) or not isinstance(v, kind):
        raise EnvelopeError(f"envelope field '{_KEYS[k]}' has the wrong type ({type(v).__name__})")
    return v


def unpack(
    data: bytes,
    *,
    max_bytes: int = 8 << 20,
    roster: Roster | None = None,
    fleet: str | None = None,
) -> Envelope:
    """Parse and validate an envelope from untrusted bytes.

    Raises :class:`EnvelopeError` when it is too large, malformed or from another fleet, and
    :class:`SignatureError` when ``roster`` does not accept its signature (unsigned in a signed
    fleet, a robot not on the roster, or signed by another key). Without a roster nothing is
    verified (tools that only read envelopes).
    """
    if len(data) > max_bytes:
        raise EnvelopeError(f"envelope of {len(data)} bytes is over the limit of {max_bytes}")
    try:
        obj = msgpack.unpackb(
            data,
            raw=False,
            strict_map_key=True,
            max_bin_len=max_bytes,
            max_str_len=MAX_STR,
            max_array_len=8,
            max_map_len=len(_KEYS),
            max_ext_len=0,
        )
    except (msgpack.ExtraData, msgpack.FormatError, msgpack.StackError, ValueError, TypeError) as exc:
        raise EnvelopeError(f"malformed envelope: {exc}") from None
    except Exception as exc:  # msgpack raises assorted exceptions on hostile input
        raise EnvelopeError(f"malformed envelope: {type(exc).__name__}") from None
    if not isinstance(obj, dict):
        raise EnvelopeError("malformed envelope: not a map")
    unknown = set(obj) - set(_KEYS)
    if unknown:
        raise EnvelopeError(f"envelope has unknown fields {sorted(map(str, unknown))}")
    missing = set(_KEYS) - {"s", "fp"} - set(obj)
    if missing:
        raise EnvelopeError(f"envelope is missing fields {sorted(_KEYS[k] for k in missing)}")
    if _want(obj, "f", int) != FORMAT:
        raise EnvelopeError(f"envelope format {obj['f']} is not supported (this mapd reads {FORMAT})")
    strs = {k: _want(obj, k, str) for k in ("fl", "r", "c", "m", "fr")}
    ints = {k: _want(obj, k, int) for k in ("v", "b", "w", "h", "n")}
    if any(not 0 <= v < COUNT_LIMIT for v in ints.values()):
        raise EnvelopeError("envelope has a negative or oversized integer field")
    if ints["v"] == 0 or ints["b"] >= ints["v"]:
        raise EnvelopeError(f"envelope version {ints['v']} with base {ints['b']} is inconsistent")
    if not strs["fl"] or not strs["r"] or not strs["c"]:
        raise EnvelopeError("envelope has an empty fleet, robot or codec")
    res = _want(obj, "res", (float, int))
    stamp = _want(obj, "t", (float, int))
    origin = _want(obj, "o", list)
    if len(origin) != 3 or not all(isinstance(x, float | int) and not isinstance(x, bool) for x in origin):
        raise EnvelopeError("envelope origin must be three numbers")
    if not all(math.isfinite(float(x)) for x in (res, stamp, *origin)) or res <= 0:
        raise EnvelopeError("envelope has a non-finite resolution, stamp or origin")
    payload = _want(obj, "p", bytes)
    frame_pose = _frame_pose(obj["fp"]) if "fp" in obj else None
    sig = obj.get("s", b"")
    if not isinstance(sig, bytes) or (sig and len(sig) != SIG_LEN):
        raise SignatureError("envelope signature has the wrong form")
    if fleet is not None and strs["fl"] != fleet:
        raise EnvelopeError(f"envelope is for fleet '{strs['fl']}', not '{fleet}'")
    if roster is not None:
        fields = {k: v for k, v in obj.items() if k != "s"}
        roster.verify(strs["r"], _signed_blob(fields), sig, "envelope")
    return Envelope(
        fleet=strs["fl"],
        robot=strs["r"],
        version=ints["v"],
        base_version=ints["b"],
        codec=strs["c"],
        variant=strs["m"],
        width=ints["w"],
        height=ints["h"],
        resolution=float(res),
        origin=Pose2D(*(float(x) for x in origin)),
        frame_id=strs["fr"],
        stamp=float(stamp),
        seq=ints["n"],
        payload=payload,
        frame_pose=frame_pose,
        sig=sig,
    )


def _frame_pose(v: Any) -> Pose2D:
    if (
        not isinstance(v, list)
        or len(v) != 3
        or not all(isinstance(x, float | int) and not isinstance(x, bool) for x in v)
        or not all(math.isfinite(float(x)) for x in v)
        or max(abs(float(v[0])), abs(float(v[1]))) > MAX_ORIGIN_M  # the bounds of map origins
        or abs(float(v[2])) > MAX_ORIGIN_YAW
    ):
        raise EnvelopeError("envelope frame pose must be [x, y, yaw], finite and within bounds")
    return Pose2D(float(v[0]), float(v[1]), float(v[2]))
