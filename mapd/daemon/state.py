"""Crash-safe persistence of what a daemon must not lose (the systemd ``StateDirectory``).

Layout::

    <state>/state.json          versions: own (incarnation and number), each peer's applied version,
                                acks, envelope seq
    <state>/own/map.yaml+pgm    the robot's latest map
    <state>/own/base.yaml+pgm   the newest own version every peer acknowledged (the delta base)
    <state>/peers/<robot>/map.yaml+pgm   the last applied version of each peer's map
    <state>/global/...          written by the fusion worker

Every file is replaced atomically (temp file, fsync, rename), map files first and ``state.json``
last; the temp files a crash mid-write left anywhere in the directory are removed at start-up.

A map's YAML is its commit: it names an image written before it under a name of its own
(``map-<version>.pgm``; the old image is removed only once the new YAML is in place), and it holds
the map's version and digest (``mapd_version``, ``mapd_digest``). So a crash at any point leaves the
old map or the new one whole, and a map saved just before a crash that ``state.json`` had not yet
recorded is restored with its version rather than lost. An image that does not match its YAML's
digest is treated as absent, never as the wrong version. ``state.json`` also names each map by
version and digest, which is all that maps saved before versions were kept in the YAML have.

A peer map's YAML also holds what came with it: the pose of its map frame its robot reported
(``mapd_frame_pose``), fused again after a restart, and the roster key it was taken under
(``mapd_key``): a robot given a new key while the daemon was down has the maps its old key signed
left out, as a reload would have. A revoked robot's map files are removed, not only its record.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import math
import os
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapd.daemon.versions import incarnation_at, make, next_version
from mapd.envelope import COUNT_LIMIT
from mapd.errors import MapdError, StateError
from mapd.files import WriteOutage, atomic_write_json, make_dir, read_json_capped, remove_stale_temps
from mapd.grid import (
    DEFAULT_MAX_CELLS,
    OccupancyGrid,
    Pose2D,
    committed_record,
    map_from_yaml_fields,
    read_map_yaml,
    save_committed,
)
from mapd.imaging.pixels import one_line

log = logging.getLogger(__name__)
#: state.json's largest size read: its records are some 100 bytes a peer, and peers are capped.
MAX_STATE_JSON = 16 << 20
_SAFE = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")


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


def lock_state_dir(root: Path) -> int:
    """Hold ``root/lock`` (flock, exclusive) for the life of the process; returns its descriptor.

    Two daemons on one state directory (a second started by mistake, or two configs with the same
    ``state.dir``) numbered maps from the same counter, swept each other's in-flight temp files and
    wrote each other's state.json. The lock is the kernel's: a daemon killed with -9 releases it.
    """
    try:
        root.mkdir(parents=True, exist_ok=True)
        fd = os.open(root / "lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise StateError(f"state directory {root} is not writable: {exc.strerror or exc}") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode("ascii", "replace").strip()
        os.close(fd)
        raise StateError(
            f"state directory {root} is in use by another mapd{f' (pid {holder})' if holder.isdigit() else ''}"
        ) from None
    except OSError as exc:
        os.close(fd)
        raise StateError(f"state directory {root}: cannot lock it: {exc.strerror or exc}") from None
    with contextlib.suppress(OSError):  # the holder's pid, for the message above (a hint only)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    return fd


class StateStore:
    """Reads and writes the state directory, and owns the counters in it.

    Versions, the envelope sequence and the acks change only through this class's methods, under
    its lock: the event loop and worker threads both touch them. ``data`` may be read anywhere (a
    snapshot is :meth:`acked`), never written. Methods that write files block: call them from a
    worker thread.
    """

    def __init__(self, root: Path, *, max_cells: int = DEFAULT_MAX_CELLS) -> None:
        self.root = root
        self.max_cells = max_cells
        self.data = StateData()
        # Two locks, so the event loop never waits on the disk: ``_lock`` guards the records and
        # counters and is held for microseconds; ``_io`` lets one worker write files at a time
        # (state.json written last, from a copy of the records taken under ``_lock``).
        self._lock = threading.Lock()
        self._io = threading.Lock()
        #: The writes of the state directory that fail now (a full disk), for ``mapd status``. Not
        #: logged here: whoever saved says it once (its line says what the failure costs).
        self.outage = WriteOutage(None)
        #: Peers whose newest map the daemon holds unsaved (its save failed; it tries again): the
        #: outage lasts while any is, though other writes go through (a restart would lose it).
        self._unsaved_peers: frozenset[str] = frozenset()

    # ------------------------------------------------------------------ setup
    def open(self) -> StateData:
        """Create the layout (checking it is writable) and load what a previous run left."""
        try:
            for sub in ("own", "peers", "global"):
                (self.root / sub).mkdir(parents=True, exist_ok=True)
            probe = self.root / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise StateError(f"state directory {self.root} is not writable: {exc.strerror}") from None
        self._remove_stale_temps()
        path = self.root / "state.json"
        if path.exists():
            try:
                self.data = StateData.from_json(read_json_capped(path, MAX_STATE_JSON))
            except (OSError, ValueError, TypeError, RecursionError) as exc:
                log.warning("state.json unreadable (%s); starting with empty state", exc)
                self.data = StateData()
        return self.data

    def _remove_stale_temps(self) -> None:
        """Remove what writers killed mid-write (``kill -9``, power loss) left in the state directory.

        Each is as large as the map it was to replace and bears its dead writer's pid, so no later
        write reuses it: without this a robot that crashes now and then fills its disk. The whole
        tree is swept (own, peers, global, the transports' ``links``), before anything writes.
        """
        removed = 0
        for here, _dirs, _files in os.walk(self.root):  # symlinks not followed: only our own tree
            removed += len(remove_stale_temps(Path(here)))
        if removed:
            log.info("removed %d temp file(s) an interrupted write left in %s", removed, self.root)

    # ------------------------------------------------------------------ counters (no file I/O)
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

    def forget_peer(self, robot: str) -> None:
        """Drop the record of ``robot``'s map (its files are unreadable or gone)."""
        with self._lock:
            self.data.peers.pop(robot, None)

    def remove_peer(self, robot: str) -> None:
        """Drop ``robot``'s map: its record and its files (blocking). It was revoked, and a key that
        had to be revoked may have signed it: no restart may bring it back. :class:`StateError`
        when a file cannot be removed."""
        d = self._peer_dir(robot)
        with self._io:  # after a save of it that is under way, never half-way through one
            self.forget_peer(robot)  # (here: such a save has just put its record back)
            try:
                if not d.is_dir():
                    return
                # The YAML first: it commits the map, so a kill part-way leaves no map behind.
                (d / "map.yaml").unlink(missing_ok=True)
                for image in d.glob("map*.pgm"):
                    image.unlink(missing_ok=True)
                with contextlib.suppress(OSError):  # not empty: something else is kept there
                    d.rmdir()
            except OSError as exc:
                raise StateError(
                    f"{d}: cannot remove the revoked map: {exc.strerror or one_line(exc)}"
                ) from None

    @staticmethod
    def savable(robot: str) -> bool:
        """Whether a map of ``robot`` can be saved here at all: a name a folder may have (others,
        which only a fleet without a roster lets in, are refused by every save, not only now)."""
        return bool(robot) and set(robot) <= _SAFE

    def _peer_dir(self, robot: str) -> Path:
        if not self.savable(robot):
            raise StateError(f"refusing unsafe robot name {robot!r} for a state path")
        return self.root / "peers" / robot

    # ------------------------------------------------------------------ maps
    def _load(self, yaml_path: Path, rec: MapRecord | None) -> OccupancyGrid | None:
        """The map at ``yaml_path`` with its version, or None when it is absent, unreadable or not
        the map its YAML (or, for a YAML without a version, ``state.json``) says it is."""
        loaded = self._load_with_extra(yaml_path, rec)
        return None if loaded is None else loaded[0]

    def _load_with_extra(
        self, yaml_path: Path, rec: MapRecord | None
    ) -> tuple[OccupancyGrid, dict[str, Any]] | None:
        """As :meth:`_load`, with the YAML's extra fields."""
        try:
            if not yaml_path.exists():
                return None
            meta = read_map_yaml(yaml_path)
            grid = map_from_yaml_fields(meta, yaml_path, max_cells=self.max_cells)
        except MapdError as exc:
            log.warning("state map %s unreadable: %s", yaml_path, exc)
            return None
        except OSError as exc:  # a folder that cannot be looked at: as unreadable
            log.warning("state map %s unreadable: %s", yaml_path, exc.strerror or one_line(exc))
            return None
        digest = grid.digest().hex()
        saved = _saved_record(meta["extra"])
        if saved is None:  # saved before the YAML held its version: state.json alone says which it is
            if rec is None or digest != rec.digest:
                log.warning(
                    "state map %s does not match state.json (interrupted write); ignoring it", yaml_path
                )
                return None
            return grid.replace(version=rec.version), meta["extra"]
        if saved.digest != digest:
            log.warning(
                "state map %s does not match the digest in its YAML (damaged); ignoring it", yaml_path
            )
            return None
        if rec is None or rec.version != saved.version:
            log.info(
                "state map %s is v%d, which state.json had not recorded (a crash between the two "
                "writes): restored",
                yaml_path,
                saved.version,
            )
        return grid.replace(version=saved.version), meta["extra"]

    def own_map(self) -> OccupancyGrid | None:
        """The robot's latest saved map (its record and version counter follow it: never reused)."""
        grid = self._load(self.root / "own" / "map.yaml", self.data.own)
        if grid is not None:
            with self._lock:
                self.data.own = MapRecord(grid.version, grid.digest().hex())
                self.data.own_version = max(self.data.own_version, grid.version)
        return grid

    def base_map(self) -> OccupancyGrid | None:
        grid = self._load(self.root / "own" / "base.yaml", self.data.base)
        if grid is not None:
            with self._lock:
                self.data.base = MapRecord(grid.version, grid.digest().hex())
        return grid

    def peer_map(self, robot: str) -> OccupancyGrid | None:
        saved = self.saved_peer(robot)
        return None if saved is None else saved.grid

    def saved_peer(self, robot: str) -> SavedPeer | None:
        """``robot``'s last saved map, with when it was saved and the pose it reported, or None.

        Also a map ``state.json`` does not name (a kill between the map's save and state.json's):
        then its YAML's own version and digest are all that is trusted, as for a newer version.
        """
        path = self._peer_dir(robot) / "map.yaml"
        loaded = self._load_with_extra(path, self.data.peers.get(robot))
        if loaded is None:
            return None
        grid, extra = loaded
        try:
            saved_at = path.stat().st_mtime
        except OSError:  # gone since it was read: nothing says when, so count from now
            saved_at = time.time()
        with self._lock:
            self.data.peers[robot] = MapRecord(grid.version, grid.digest().hex())
        key = extra.get("mapd_key")
        return SavedPeer(
            grid.replace(robot=robot),
            saved_at,
            _saved_pose(extra, path),
            key if isinstance(key, str) else None,
        )

    def unrecorded_peers(self) -> list[str]:
        """The robots (safe names only) whose folder holds a map that ``state.json`` does not name:
        saved just before a kill that came before ``state.json`` named it, or left by a revocation
        of a release that kept the files."""
        try:
            names = sorted(p.name for p in (self.root / "peers").iterdir())
        except OSError:
            return []
        found = []
        for robot in names:
            if robot in self.data.peers or not set(robot) <= _SAFE:
                continue
            with contextlib.suppress(OSError):
                if (self.root / "peers" / robot / "map.yaml").is_file():
                    found.append(robot)
        return found

    def set_unsaved_peers(self, robots: Iterable[str]) -> None:
        """The peers whose newest map is held unsaved now (see :meth:`health`)."""
        with self._lock:
            self._unsaved_peers = frozenset(robots)

    @contextlib.contextmanager
    def _counted(self, peer: str | None = None) -> Iterator[None]:
        """Count the write in the block in :attr:`outage` (a StateError out of it: failed). One
        that goes through ends the outage only when no peer's map is left held unsaved (``peer``:
        the block saved that robot's map, which is not any more)."""
        try:
            yield
        except StateError as exc:
            self.outage.failed(str(exc))
            raise
        with self._lock:
            if peer is not None:
                self._unsaved_peers -= {peer}
            unsaved = bool(self._unsaved_peers)
        if not unsaved:
            self.outage.recovered("")

    def health(self) -> dict[str, Any]:
        """The state directory's writes for ``mapd status --json``: its ``dir``, ``writing`` (False
        while saves fail: a full disk), ``failures`` (saves failed in all), ``failing_s`` and
        ``error`` (see :meth:`~mapd.files.WriteOutage.status`). Writes fail until every peer's map
        held unsaved is saved (:meth:`set_unsaved_peers`), though others go through meanwhile."""
        return {"dir": str(self.root), **self.outage.status()}

    def save_own(self, grid: OccupancyGrid) -> None:
        with self._io, self._counted():
            record = self._save(grid, self.root / "own" / "map.yaml")
            with self._lock:
                self.data.own = record
                self.data.own_version = max(self.data.own_version, grid.version)
            self._write_state()

    def save_base(self, grid: OccupancyGrid) -> None:
        with self._io, self._counted():
            record = self._save(grid, self.root / "own" / "base.yaml")
            with self._lock:
                self.data.base = record
            self._write_state()

    def save_peer(
        self, grid: OccupancyGrid, frame_pose: Pose2D | None = None, key: str | None = None
    ) -> None:
        """Save a peer's map, with the pose of its map frame its envelope reported and the roster
        key it was taken under (``key``), if any."""
        d = self._peer_dir(grid.robot)
        with self._io, self._counted(grid.robot):
            try:
                make_dir(d)
            except OSError as exc:
                # A full disk (ENOSPC), a file in its place: a save that failed, said as one line
                # (the daemon says it once and uses the map all the same), never a traceback.
                raise StateError(f"{d}: cannot create the folder: {exc.strerror or one_line(exc)}") from None
            extra: dict[str, Any] = {}
            if frame_pose is not None:
                extra["mapd_frame_pose"] = [float(v) for v in frame_pose]
            if key is not None:
                extra["mapd_key"] = key
            record = self._save(grid, d / "map.yaml", extra)
            with self._lock:
                self.data.peers[grid.robot] = record
            self._write_state()

    def _save(self, grid: OccupancyGrid, path: Path, extra: dict[str, Any] | None = None) -> MapRecord:
        """Write ``grid`` at ``path``, committed by its YAML with ``extra`` fields
        (:func:`~mapd.grid.save_committed`)."""
        try:
            return MapRecord(grid.version, save_committed(grid, path, extra))
        except MapdError as exc:
            raise StateError(str(exc)) from None

    def flush(self) -> None:
        """Write ``state.json`` now (blocking)."""
        with self._io, self._counted():
            self._write_state()

    def _write_state(self) -> None:
        with self._lock:
            doc = self.data.to_json()
        try:
            atomic_write_json(self.root / "state.json", doc)
        except OSError as exc:
            raise StateError(f"cannot write {self.root / 'state.json'}: {exc.strerror}") from None
