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
version and digest (:mod:`mapd.daemon.state_records`: what it holds, and what a peer map's YAML
keeps beside the map). A revoked robot's map files are removed, not only its record.

One daemon holds the directory (:mod:`mapd.daemon.state_lock`). The directory may go while the
daemon runs (emptied, removed, unmounted, remounted read-only): the store looks at it before each
save and makes it whole again from memory once it can be written (:mod:`mapd.daemon.state_watch`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from mapd.daemon.state_records import (
    MAX_STATE_JSON,
    MapRecord,
    SavedPeer,
    StateCounters,
    StateData,
    _Held,
    _saved_pose,
    _saved_record,
)
from mapd.daemon.state_watch import LAYOUT, StateDirWatch
from mapd.errors import MapdError, StateError
from mapd.files import atomic_write_json, make_dir, remove_stale_temps
from mapd.files.folders import file_id, mount_point
from mapd.files.outage import WriteOutage
from mapd.files.reading import read_json_capped
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D
from mapd.grid.load import map_from_yaml_fields, read_map_yaml
from mapd.grid.save import save_committed
from mapd.imaging.pixels import one_line

log = logging.getLogger(__name__)
_SAFE = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-")


class StateStore(StateCounters, StateDirWatch):
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
        StateDirWatch.__init__(self)  # what a directory lost under it needs

    # ------------------------------------------------------------------ setup
    def open(self) -> StateData:
        """Create the layout (checking it is writable) and load what a previous run left."""
        try:
            for sub in LAYOUT:
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
            else:
                self._remember("state.json", path)
        self._mount = mount_point(self.root)
        with contextlib.suppress(OSError):  # (taken by lock_state_dir before, where the daemon runs)
            self._lock_id = file_id(self.root / "lock")
        self._opened = True
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

    # ------------------------------------------------------------------ peers' records and folders
    def forget_peer(self, robot: str) -> None:
        """Drop the record of ``robot``'s map (its files are unreadable or gone)."""
        with self._lock:
            self.data.peers.pop(robot, None)
            self._peers_held.pop(robot, None)  # (revoked: never written back either)
            self._ids.pop(f"peers/{robot}", None)

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
        path = self.root / "own" / "map.yaml"
        grid = self._load(path, self.data.own)
        if grid is not None:
            with self._lock:
                self.data.own = MapRecord(grid.version, grid.digest().hex())
                self.data.own_version = max(self.data.own_version, grid.version)
                self._own_held = grid
            self._remember_map("own", path, grid)
        return grid

    def base_map(self) -> OccupancyGrid | None:
        path = self.root / "own" / "base.yaml"
        grid = self._load(path, self.data.base)
        if grid is not None:
            with self._lock:
                self.data.base = MapRecord(grid.version, grid.digest().hex())
                self._base_held = grid
            self._remember_map("base", path, grid)
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
        key = extra.get("mapd_key")
        saved = SavedPeer(
            grid.replace(robot=robot),
            saved_at,
            _saved_pose(extra, path),
            key if isinstance(key, str) else None,
        )
        with self._lock:
            self.data.peers[robot] = MapRecord(grid.version, grid.digest().hex())
            self._peers_held[robot] = _Held(saved.grid, saved.frame_pose, saved.key)
        self._remember_map(f"peers/{robot}", path, grid)
        return saved

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
    def _counted(self, peer: str | None = None, *, ends: bool = True) -> Iterator[None]:
        """Count the write in the block in :attr:`outage` (a StateError out of it: failed). One
        that goes through ends the outage only when no peer's map is left held unsaved (``peer``:
        the block saved that robot's map, which is not any more), and ``ends``: a look that wrote
        nothing new ends none (the own map a full disk refused is still unsaved)."""
        try:
            yield
        except StateError as exc:
            self.outage.failed(str(exc))
            raise
        if not ends:
            return
        with self._lock:
            if peer is not None:
                self._unsaved_peers -= {peer}
            unsaved = bool(self._unsaved_peers)
        if not unsaved:
            self.outage.recovered("")

    def health(self) -> dict[str, Any]:
        """The state directory's writes for ``mapd status --json``: its ``dir``, ``writing`` (False
        while saves fail: a full disk, or a directory gone, unmounted or read-only), ``failures``
        (saves failed in all), ``failing_s`` and ``error`` (see
        :meth:`~mapd.files.outage.WriteOutage.status`). Writes fail until every peer's map held
        unsaved is saved (:meth:`set_unsaved_peers`), though others go through meanwhile."""
        return {"dir": str(self.root), **self.outage.status()}

    def save_own(self, grid: OccupancyGrid) -> None:
        """Save the robot's map, then ``state.json``; :class:`StateError` when it cannot be."""
        with self._io, self._counted():
            self._ready()
            self._save_own(grid)
            self._write_state()

    def _save_own(self, grid: OccupancyGrid) -> None:
        path = self.root / "own" / "map.yaml"
        record = self._save(grid, path)
        with self._lock:
            self.data.own = record
            self.data.own_version = max(self.data.own_version, grid.version)
            self._own_held = grid
        self._remember_map("own", path, grid)

    def save_base(self, grid: OccupancyGrid) -> None:
        """Save the delta base, then ``state.json``; :class:`StateError` when it cannot be."""
        with self._io, self._counted():
            self._ready()
            self._save_base(grid)
            self._write_state()

    def _save_base(self, grid: OccupancyGrid) -> None:
        path = self.root / "own" / "base.yaml"
        record = self._save(grid, path)
        with self._lock:
            self.data.base = record
            self._base_held = grid
        self._remember_map("base", path, grid)

    def save_peer(
        self, grid: OccupancyGrid, frame_pose: Pose2D | None = None, key: str | None = None
    ) -> None:
        """Save a peer's map, with the pose of its map frame its envelope reported and the roster
        key it was taken under (``key``), if any."""
        self._peer_dir(grid.robot)  # (a name no folder may have: refused before anything)
        with self._io, self._counted(grid.robot):
            self._ready()
            self._save_peer(_Held(grid, frame_pose, key))
            self._write_state()

    def _save_peer(self, held: _Held) -> None:
        grid = held.grid
        d = self._peer_dir(grid.robot)
        try:
            make_dir(d)
        except OSError as exc:
            # A full disk (ENOSPC), a file in its place: a save that failed, said as one line
            # (the daemon says it once and uses the map all the same), never a traceback.
            raise StateError(f"{d}: cannot create the folder: {exc.strerror or one_line(exc)}") from None
        extra: dict[str, Any] = {}
        if held.frame_pose is not None:
            extra["mapd_frame_pose"] = [float(v) for v in held.frame_pose]
        if held.key is not None:
            extra["mapd_key"] = held.key
        record = self._save(grid, d / "map.yaml", extra)
        with self._lock:
            self.data.peers[grid.robot] = record
            self._peers_held[grid.robot] = held
        self._remember_map(f"peers/{grid.robot}", d / "map.yaml", grid)

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
            self._ready()
            self._write_state()

    def _write_state(self) -> None:
        with self._lock:
            doc = self.data.to_json()
        path = self.root / "state.json"
        try:
            atomic_write_json(path, doc)
        except OSError as exc:
            raise StateError(f"cannot write {path}: {exc.strerror}") from None
        self._remember("state.json", path)
