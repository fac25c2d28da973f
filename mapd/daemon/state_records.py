"""What the state directory holds, as values: ``state.json``'s records and what a map's YAML keeps.

``state.json`` holds the versions (own: incarnation and number; each peer's applied version), the
acks and the envelope sequence (:class:`StateData`). It is read back strictly: the counters must be
right or the state starts afresh (a new incarnation from the clock), while a record or ack that is
not right is left out, costing one whole map on the link. It names each map by version and digest
(:class:`MapRecord`), which is all that maps saved before versions were kept in their YAML have.
Its counters change only through :class:`StateCounters` (the store's methods), under the store's
lock: the event loop and worker threads both touch them.

A peer map's YAML also holds what came with it (:class:`SavedPeer`): the pose of its map frame its
robot reported (``mapd_frame_pose``), fused again after a restart, and the roster key it was taken
under (``mapd_key``): a robot given a new key while the daemon was down has the maps its old key
signed left out, as a reload would have.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapd.daemon.versions import incarnation_at, make, next_version
from mapd.envelope import COUNT_LIMIT
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.save import committed_record

# Said as the store's lines are: one logger for everything the state directory says.
log = logging.getLogger("mapd.daemon.state")
#: state.json's largest size read: its records are some 100 bytes a peer, and peers are capped.
MAX_STATE_JSON = 16 << 20


@dataclass
class MapRecord:
    version: int
    digest: str


@dataclass(frozen=True)
class SavedPeer:
    """A peer's map as the state directory holds it, with what was saved beside it."""

    grid: OccupancyGrid
    #: Wall time it was saved (its YAML's modification time): when this robot took that version,
    #: from which the bound on the peer's next version counts (:func:`~mapd.daemon.versions.check_step`).
    saved_at: float
    #: Where the peer's map frame lies in the fleet frame, as its map reported it (its source's
    #: start pose), or None: fused again as the live map's pose was.
    frame_pose: Pose2D | None = None
    #: The roster key it was taken under (``mapd_key``), or None (unsigned, or saved before keys
    #: were kept): a map its robot's key no longer matches is not restored (the key was replaced).
    key: str | None = None


@dataclass(frozen=True)
class _Held:
    """A peer's map as last saved (or restored), with what was saved beside it: written again
    when the state directory loses it."""

    grid: OccupancyGrid
    frame_pose: Pose2D | None
    key: str | None


@dataclass
class StateData:
    """The small, frequently written part of the state."""

    own_version: int = 0
    own: MapRecord | None = None
    base: MapRecord | None = None
    peers: dict[str, MapRecord] = field(default_factory=dict)
    #: peer -> newest own version that peer acknowledged
    acked: dict[str, int] = field(default_factory=dict)
    seq: int = 0
    #: The versions' incarnation began from a clock the kernel did not say was synchronized: it
    #: may have been behind (see ``Outbound._versions_to_begin_again``).
    began_unsynchronized: bool = False

    def to_json(self) -> dict[str, Any]:
        rec = lambda r: None if r is None else {"version": r.version, "digest": r.digest}  # noqa: E731
        return {
            "own_version": self.own_version,
            "own": rec(self.own),
            "base": rec(self.base),
            "peers": {k: rec(v) for k, v in self.peers.items()},
            "acked": dict(self.acked),
            "seq": self.seq,
            "began_unsynchronized": self.began_unsynchronized,
        }

    @classmethod
    def from_json(cls, d: object) -> StateData:
        """The state a ``to_json`` document holds. A damaged file (it was written whole, but disks
        fail) raises ValueError or TypeError for the counters, which must be right or start afresh;
        a record or ack that is not right is left out, costing one whole map on the link."""

        def rec(x: Any) -> MapRecord | None:
            if isinstance(x, dict) and _is_count(x.get("version")) and isinstance(x.get("digest"), str):
                return MapRecord(x["version"], x["digest"])
            return None

        if not isinstance(d, dict):
            raise TypeError(f"state.json holds a {type(d).__name__}, not an object")
        counters = {k: d.get(k, 0) for k in ("own_version", "seq")}
        for key, value in counters.items():
            if not _is_count(value):
                # Out of range, a new incarnation from the clock is right (versions.py); a version
                # past 2^63 or below 0 would have every map refused by every peer, for ever.
                raise ValueError(f"{key} {value!r:.40} is not a count below 2^63")
        peers, acked = d.get("peers") or {}, d.get("acked") or {}
        if not isinstance(peers, dict) or not isinstance(acked, dict):
            raise TypeError("state.json: peers and acked must be objects")
        return cls(
            own_version=counters["own_version"],
            own=rec(d.get("own")),
            base=rec(d.get("base")),
            peers={str(k): r for k, v in peers.items() if (r := rec(v)) is not None},
            acked={str(k): v for k, v in acked.items() if _is_count(v)},
            seq=counters["seq"],
            began_unsynchronized=d.get("began_unsynchronized") is True,
        )


def _saved_record(extra: dict[str, Any]) -> MapRecord | None:
    """The version and digest a state map's YAML holds, or None (a YAML from before they were kept)."""
    record = committed_record(extra)
    return None if record is None else MapRecord(*record)


def _saved_pose(extra: dict[str, Any], where: Path) -> Pose2D | None:
    """The reported pose a peer map's YAML holds (``mapd_frame_pose``: x, y, yaw), or None."""
    raw = extra.get("mapd_frame_pose")
    if raw is None:
        return None
    if (
        isinstance(raw, list)
        and len(raw) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in raw)
    ):
        with contextlib.suppress(OverflowError):  # an int too large for a float (YAML reads any)
            pose = Pose2D(*(float(v) for v in raw))
            if all(math.isfinite(v) for v in pose):
                return pose
    log.warning("state map %s: ignoring its reported pose %.60r (not three finite numbers)", where, raw)
    return None


def _is_count(x: object) -> bool:
    """Whether ``x`` is a version, sequence number or ack as envelopes carry them: 0 <= x < 2^63."""
    return type(x) is int and 0 <= x < COUNT_LIMIT


class StateCounters:
    """The counters ``state.json`` holds (versions, the envelope sequence, acks), as the store
    changes them: only through these methods, under its lock (no file I/O)."""

    # The store's (StateStore): its records, and the lock that guards them.
    data: StateData
    _lock: threading.Lock

    def new_state(self) -> bool:
        """Whether no own version was ever numbered here: the next starts a new incarnation from
        the wall clock (a new or lost state directory)."""
        with self._lock:
            return self.data.own_version == 0

    def begin_again(self, wall_time: float, *, synchronized: bool) -> None:
        """Number the next own version in a new incarnation from ``wall_time``, if that is newer
        (a state begun from a clock behind: see ``Outbound._versions_to_begin_again``); never lower.
        ``synchronized``: whether the kernel says the clock is, now (saved with the next state)."""
        with self._lock:
            self.data.own_version = max(self.data.own_version, make(incarnation_at(wall_time), 0))
            self.data.began_unsynchronized = not synchronized

    def began_unsynchronized(self) -> bool:
        """Whether this state's versions began from a clock not said to be synchronized."""
        with self._lock:
            return self.data.began_unsynchronized

    def next_own_version(self, wall_time: float) -> int:
        """Reserve the next own map version (see :mod:`mapd.daemon.versions`).

        Versions keep increasing across restarts; a state directory that is new (or lost) starts a
        new incarnation from ``wall_time``, so peers take the robot's next map at once.
        """
        with self._lock:
            self.data.own_version = next_version(self.data.own_version, wall_time)
            return self.data.own_version

    def next_seq(self) -> int:
        """Reserve the next envelope sequence number."""
        with self._lock:
            self.data.seq += 1
            return self.data.seq

    def acked(self) -> dict[str, int]:
        """A copy of peer -> newest own version that peer acknowledged."""
        with self._lock:
            return dict(self.data.acked)

    def set_acked(self, peer: str, version: int) -> bool:
        """Record that ``peer`` holds own ``version``; True when that is newer than what it held."""
        with self._lock:
            if version <= self.data.acked.get(peer, 0):
                return False
            self.data.acked[peer] = version
            return True

    def forget_acked(self, peer: str) -> None:
        """``peer`` may have lost what it acked (it restarted, or asked for a whole map)."""
        with self._lock:
            self.data.acked.pop(peer, None)
