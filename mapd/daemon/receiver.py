"""Peers' maps in: verify, decide, decode, keep. The decisions are plain methods; the daemon runs the CPU work.

For every :class:`~transports.base.Received` the daemon calls, in order:

1. :func:`open_envelope` in a worker thread: size cap, strict parse, signature (a forgery raises
   :class:`~mapd.errors.SignatureError`, other damage :class:`~mapd.errors.EnvelopeError`);
2. :meth:`Receiver.plan` on the loop: another fleet's, our own, or an old version is dropped; a delta
   whose base is not held asks for a keyframe; otherwise the base to decode against;
3. :func:`decode_envelope` in a worker thread;
4. :meth:`Receiver.accept` on the loop: keep the map (and a few recent versions as delta bases) and
   count it; the daemon then saves it, hands it to fusion and acks it.

The receiver keeps, per peer robot, the newest map, up to :data:`KEEP_PEER_VERSIONS` recent
versions (a sender may code a delta against a version it saw acked while newer ones were still in
flight), and what ``mapd status`` shows about it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

from mapd.codec import decode
from mapd.envelope import Envelope, unpack
from mapd.errors import CodecError, SignatureError
from mapd.grid import OccupancyGrid

KEEP_PEER_VERSIONS = 8


@dataclass
class ReceiverCounters:
    """Why updates were taken or dropped, for ``mapd status``."""

    bad_envelopes: int = 0
    foreign_fleet: int = 0
    bad_signature: int = 0
    duplicates: int = 0
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

    def to_json(self) -> dict[str, Any]:
        return {
            k: v for k, v in asdict(self).items() if v is not None and (k not in ("bytes", "updates") or v)
        }


@dataclass(frozen=True)
class Decode:
    """Decode the envelope against ``base`` (None for a keyframe)."""

    base: OccupancyGrid | None


@dataclass(frozen=True)
class AskKeyframe:
    """A delta whose base is not held: ask ``robot`` for a whole map."""

    robot: str


@dataclass(frozen=True)
class Drop:
    """Nothing to do with this envelope (another fleet's, our own, or not newer than what is held)."""

    reason: str


def open_envelope(data: bytes, *, max_bytes: int, key: bytes | None) -> Envelope:
    """Parse and verify untrusted bytes (CPU work: call it from a worker thread)."""
    return unpack(data, max_bytes=max_bytes, key=key)


def decode_envelope(env: Envelope, base: OccupancyGrid | None, *, max_cells: int) -> OccupancyGrid:
    """Decode ``env``'s payload and check it against the envelope (CPU work: a worker thread)."""
    grid = decode(env.payload, base, max_cells=max_cells)
    if (grid.width, grid.height) != (env.width, env.height):
        raise CodecError(
            f"payload decodes to {grid.width} x {grid.height}, the envelope says {env.width} x {env.height}"
        )
    return grid.replace(robot=env.robot, version=env.version, stamp=env.stamp, frame_id=env.frame_id)


@dataclass
class Receiver:
    """Peers' maps held by one robot, and the rules for taking new ones."""

    me: str
    fleet: str
    counters: ReceiverCounters = field(default_factory=ReceiverCounters)
    maps: dict[str, OccupancyGrid] = field(default_factory=dict)
    info: dict[str, PeerInfo] = field(default_factory=dict)
    _history: dict[str, dict[int, OccupancyGrid]] = field(default_factory=dict)

    def restore(self, grid: OccupancyGrid) -> None:
        """A peer's map from the state directory."""
        self.maps[grid.robot] = grid
        self._history[grid.robot] = {grid.version: grid}

    def refused(self, exc: Exception) -> None:
        """:func:`open_envelope` refused the bytes: count why."""
        if isinstance(exc, SignatureError):
            self.counters.bad_signature += 1
        else:
            self.counters.bad_envelopes += 1

    def plan(self, env: Envelope) -> Decode | AskKeyframe | Drop:
        """What to do with a verified envelope."""
        if env.fleet != self.fleet:
            self.counters.foreign_fleet += 1
            return Drop("another fleet")
        if env.robot == self.me:
            return Drop("our own map")
        held = self.maps.get(env.robot)
        if held is not None and env.version <= held.version:
            self.counters.duplicates += 1
            return Drop(f"v{env.version} is not newer than v{held.version}")
        if env.is_keyframe:
            return Decode(None)
        base = self._history.get(env.robot, {}).get(env.base_version)
        if base is None:
            self.counters.keyframe_requests += 1
            return AskKeyframe(env.robot)
        return Decode(base)

    def undecodable(self, env: Envelope, base: OccupancyGrid | None) -> AskKeyframe | None:
        """The payload did not decode; a delta may decode after a keyframe, so ask for one."""
        self.counters.decode_errors += 1
        if base is None:
            return None
        self.counters.keyframe_requests += 1
        return AskKeyframe(env.robot)

    def accept(self, grid: OccupancyGrid, env: Envelope, transport: str, nbytes: int, now: float) -> None:
        """Keep a decoded map (``now``: wall-clock seconds, for the age ``mapd status`` shows)."""
        self.maps[env.robot] = grid
        history = self._history.setdefault(env.robot, {})
        history[env.version] = grid
        for v in sorted(history)[:-KEEP_PEER_VERSIONS]:
            del history[v]
        self.counters.updates_received += 1
        info = self.info.setdefault(env.robot, PeerInfo())
        info.version = env.version
        info.received_at = now
        info.link = transport
        info.present = True
        info.bytes += nbytes
        info.updates += 1
        info.last_kind = "keyframe" if env.is_keyframe else "delta"

    def presence(self, peer: str, transport: str, present: bool) -> None:
        info = self.info.setdefault(peer, PeerInfo())
        info.present = present
        info.link = transport

    def status(self, now: float, acked: dict[str, int]) -> dict[str, dict[str, Any]]:
        """Per peer robot: what ``mapd status`` shows."""
        peers = {}
        for robot in sorted(set(self.info) | set(self.maps)):
            info = self.info.get(robot, PeerInfo()).to_json()
            received_at = info.pop("received_at", None)
            if received_at is not None:
                info["age_s"] = round(now - received_at, 1)
            held = self.maps.get(robot)
            if held is not None:
                # The version we hold, also for a peer restored from the state directory that has
                # sent nothing since this start (its counters are then empty, its map is not).
                info["version"] = held.version
                info["restored"] = "age_s" not in info  # nothing received from it since this start
            info["acked_our_version"] = acked.get(robot, 0)
            peers[robot] = info
        return peers
