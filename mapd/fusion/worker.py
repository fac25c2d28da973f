"""The fusion worker: the asyncio task that owns the global map.

API for the daemon::

    worker = FusionWorker(robot, cfg.fusion, state_dir, on_global=[callback])
    task = asyncio.create_task(worker.run())
    worker.submit(grid)          # own map or a peer's decoded map; grid.robot names it
    worker.status()              # JSON-able dict for `mapd status`
    worker.global_map            # latest OccupancyGrid, or None
    task.cancel()                # stops; a pending update is merged with the held placements first

* ``submit`` never blocks and never queues: the latest map of each robot wins.
* ``run`` loads the previous global map and ``transforms.json`` from the state directory (so a
  restart loses neither the map nor the accepted placements), then waits for submissions. After the
  first new map it waits ``cfg.debounce_s`` (collecting whatever else arrives), places every map with
  a :class:`~mapd.fusion.placer.Placer` and merges them in a worker thread (a large merge never
  stalls the event loop), leaving out maps the global map cannot hold (:mod:`~mapd.fusion.limits`),
  writes ``global.yaml`` + ``global-<version>.pgm``, ``transforms.json`` and ``owner.npy`` + ``owner.json``
  into the state directory (:mod:`~mapd.fusion.store`), and calls every ``on_global`` callback with
  the new grid on the event loop's thread.
* A stop (``task.cancel()``) during a merge gives up its placement search within a fraction of a
  second (:class:`~mapd.fusion.estimate.SearchStopped`, between the search's stages): that merge
  goes on with the placements found and held so far, which is cheap, and is saved; the robots it did
  not place keep what they held and are searched again at the next start, whose daemon submits their
  maps again from its state directory. (A search of a large map takes seconds: a stop waited 10 s
  and more for it, and saved nothing of that merge.)
* The **fleet frame** is the frame the configured poses are given in, or this robot's own map frame
  when no pose is configured (``cfg.poses``: robot -> ``[x m, y m, yaw rad]`` of that robot's map
  frame in the fleet frame, or ``"estimate"``). The global map's origin lies on the fleet frame's
  cell lattice and only grows outward in blocks of 64 cells (:mod:`mapd.fusion.merge`).
* ``transforms.json`` and ``status()["robots"]`` give, per robot, the "fleet frame -> robot map"
  transform (x, y in meters, yaw in radians, such that ``p_fleet = R(yaw) p_robot_map + (x, y)``),
  its source, confidence, agreement, whether it is merged, and the reason when it is not; for one
  found against another robot's map, where that map was placed then (``against_at``), so that a
  restored placement follows that map when it is placed anew, as a live one does.
* Until every robot named in a restored ``transforms.json`` has sent a map again, the restored global
  map fills the cells no current map knows, so a restart never shows a half-empty map.

This module is the event loop's side: the API, the debounce and the merge task, a stop's flush. One
merge on its worker thread is :class:`~mapd.fusion.worker_merge.MergeSide`'s; taking a revoked
robot out, and restoring a previous run's state without the robots revoked since, is
:class:`~mapd.fusion.worker_roster.RosterSide`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from mapd.config import FusionSection
from mapd.errors import FusionError, MapdError
from mapd.files.outage import WRITE_RETRY_S, WriteOutage
from mapd.fusion.estimate import EstimateOptions
from mapd.fusion.merge import Bounds
from mapd.fusion.placement import Placement
from mapd.fusion.placer import Placer
from mapd.fusion.store import FusionStore
from mapd.fusion.worker_merge import MergeSide, _Fused, _Unsaved
from mapd.fusion.worker_roster import RosterSide
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D, geometry_problem

#: The worker's logger, one for all its parts.
log = logging.getLogger("mapd.fusion.worker")


class FusionWorker(MergeSide, RosterSide):
    """Owns the global map: re-places and re-merges on every new map version, debounced."""

    def __init__(
        self,
        robot: str,
        cfg: FusionSection,
        state_dir: Path | None,
        on_global: Sequence[Callable[[OccupancyGrid], None]] | None = None,
        *,
        max_cells: int = DEFAULT_MAX_CELLS,
        max_robots: int = 64,
        anchor: str | None = "",
        options: EstimateOptions | None = None,
        admits: Callable[[str], bool] | None = None,
        key_of: Callable[[str], str | None] | None = None,
    ) -> None:
        self.robot = robot
        self.cfg = cfg
        self.store = None if state_dir is None else FusionStore(state_dir, robot=robot, max_cells=max_cells)
        self.on_global: list[Callable[[OccupancyGrid], None]] = list(on_global or [])
        self.max_cells = max_cells
        self.max_robots = max_robots
        poses = {r: (Pose2D(*p) if isinstance(p, list) else None) for r, p in cfg.poses.items()}
        self.placer = Placer(
            poses,
            anchor=robot if anchor == "" else anchor,  # "": this robot's map frame; None: the first map's
            min_confidence=cfg.min_confidence,
            min_agreement=cfg.min_agreement,
            options=options,
        )
        self._latest: dict[str, OccupancyGrid] = {}
        self._wake = asyncio.Event()
        self._global: OccupancyGrid | None = None
        self._placements: dict[str, Placement] = {}
        self._bounds: Bounds | None = None
        #: Set when the daemon stops during a merge: its thread gives up its search (the placer's
        #: ``stop``, asked between a search's stages) and merges what is placed.
        self._stop_merge = threading.Event()
        #: robot -> why its map is left out, as last said (the merge thread's; merges never overlap)
        self._said_left_out: dict[str, str] = {}
        self._resolution: float | None = None
        self._restored: OccupancyGrid | None = None
        self._restored_robots: set[str] = set()
        self._merges = 0
        self._last_merge: float | None = None
        self._last_seconds: float | None = None
        self._error: str | None = None
        #: The global map could not be written (said once, not at every merge).
        self._saves = WriteOutage(log)
        #: The newest merge whose save failed, tried again every WRITE_RETRY_S (under _save_lock: a
        #: retry must never write an older map over one a merge saved meanwhile).
        self._unsaved: _Unsaved | None = None
        self._save_lock = threading.Lock()
        self._dropped = 0
        self._loaded = False
        #: Whether a robot's map may be in the global map at all (the roster); others found in the
        #: state directory at start are left out, as :meth:`forget` leaves them out later.
        self._admits = admits or (lambda robot: True)
        #: A robot's roster key now (None: none known), saved with the global map for the robots
        #: in it: one given a new key by the next start has it rebuilt without it, as a reload would.
        self._key_of = key_of or (lambda robot: None)
        #: The keys of the maps the merge under way holds (taken on the loop as it began: a key
        #: replaced meanwhile revokes the robot, and the merge's files must not name the new one).
        self._merge_keys: dict[str, str] = {}
        self.forgotten = 0
        self._merging = False  # a merge runs on a worker thread (_merge_once)
        self._forget_later: list[str] = []  # robots revoked meanwhile (forget)

    # -- the daemon's side ------------------------------------------------------------------

    def submit(self, grid: OccupancyGrid) -> None:
        """Hand over a map (own or a peer's); ``grid.robot`` names it. Latest wins; never blocks."""
        robot = grid.robot or ""
        if not robot:
            raise FusionError("a map submitted for fusion must name its robot")
        if robot not in self._latest and len(self._latest) >= self.max_robots:
            self._dropped += 1
            log.warning("fusion: ignoring a map from '%s': already %d robots", robot, self.max_robots)
            return
        self._latest[robot] = grid
        self._wake.set()

    def known_pose(self, robot: str, pose: Pose2D) -> None:
        """``robot`` reports where its map frame lies in the fleet frame (its source's start pose).

        Used as a configured pose, unless ``fusion.poses`` names that robot: the config wins. A pose
        that is not finite or lies beyond the bounds of a map origin is ignored with a warning: a
        NaN in it would make every merge fail, freezing the global map for the whole fleet.
        """
        if robot in self.cfg.poses or self.placer.poses.get(robot) == pose:
            return
        problem = geometry_problem(1.0, (pose.x, pose.y, pose.yaw))
        if problem is not None:
            log.warning("fusion: ignoring the start pose reported for '%s': %s", robot, problem)
            return
        self.placer.poses[robot] = pose
        self.placer.reported.add(robot)
        self._wake.set()

    @property
    def global_map(self) -> OccupancyGrid | None:
        """The latest global map (the restored one until the first merge), or None."""
        return self._global

    @property
    def placements(self) -> dict[str, Placement]:
        return dict(self._placements)

    def status(self) -> dict[str, Any]:
        """JSON-able state for ``mapd status``."""
        g = self._global
        robots: dict[str, Any] = {}
        # A robot revoked while a merge runs keeps its placement until the merge is back; it is
        # gone already for everyone who asks.
        for name in sorted((set(self._latest) | set(self._placements)) - set(self._forget_later)):
            p = self._placements.get(name)
            entry = p.as_dict() if p is not None else Placement(name, reason="not merged yet").as_dict()
            grid = self._latest.get(name)
            entry["version"] = None if grid is None else grid.version
            robots[name] = entry
        return {
            "robot": self.robot,
            "mode": self.cfg.mode,
            "fleet_frame": self.placer.fleet_frame,
            "maps": sum(1 for p in self._placements.values() if p.accepted and p.robot in self._latest),
            "robots": robots,
            "global": None
            if g is None
            else {
                "width": g.width,
                "height": g.height,
                "resolution": g.resolution,
                "origin": {"x": g.origin.x, "y": g.origin.y, "yaw": g.origin.yaw},
                "version": g.version,
            },
            "merges": self._merges,
            "last_merge": self._last_merge,
            "last_merge_s": self._last_seconds,
            "pending": self._wake.is_set(),
            "error": self._error,
            "dropped": self._dropped,
            "revoked": self.forgotten,
            "restored_until": sorted(self._restored_robots - set(self._latest)) if self._restored else [],
        }

    async def run(self) -> None:
        """The worker task: load state, then merge on submissions until cancelled."""
        if not self._loaded:
            await asyncio.to_thread(self._load_state)
            self._loaded = True
        try:
            while True:
                retry = WRITE_RETRY_S if self._unsaved is not None else None
                try:
                    await asyncio.wait_for(self._wake.wait(), retry)
                except TimeoutError:
                    await asyncio.to_thread(self._save_unsaved)
                    continue
                if self.cfg.debounce_s > 0:
                    await asyncio.sleep(self.cfg.debounce_s)
                self._wake.clear()
                await self._merge_once(search=True)
        except asyncio.CancelledError:
            if self._wake.is_set() and self._latest:
                # cheap flush: merge what is pending with the placements already held, no estimation
                with contextlib.suppress(Exception):
                    self._wake.clear()
                    await asyncio.to_thread(self._fuse_and_publish_sync, False)
            raise

    async def merge_now(self) -> None:
        """Merge immediately (no debounce); for tools and tests."""
        if not self._loaded:
            await asyncio.to_thread(self._load_state)
            self._loaded = True
        self._wake.clear()
        await self._merge_once(search=True)

    # -- internals --------------------------------------------------------------------------

    async def _merge_once(self, search: bool) -> None:
        maps = dict(self._latest)
        self._merge_keys = self._keys(maps)
        self._merging = True
        self._stop_merge.clear()
        job = asyncio.ensure_future(asyncio.to_thread(self._fuse, maps, search))
        stopped: asyncio.CancelledError | None = None
        try:
            try:
                fused = await asyncio.shield(job)
            except asyncio.CancelledError as exc:
                # A thread cannot be stopped, but its search gives up at its next stage (a fraction
                # of a second; a search took up to 13 s, and a merge with robots that do not place
                # minutes, past systemd's stop timeout) and the merge goes on with what is placed,
                # which is cheap. Wait for it (once; a second cancel is not waited out), so that the
                # stop's flush (run) never shares the placer with it, and it does not save a map
                # after the flush has saved a newer one.
                self._stop_merge.set()
                stopped = exc
                with contextlib.suppress(BaseException):
                    await asyncio.wait({job})
                if not job.done() or job.cancelled() or job.exception() is not None:
                    raise  # (its error, retrieved, is not news now: the flush reports its own)
                fused = job.result()
        except MapdError as exc:
            self._error = str(exc)
            log.warning("fusion: %s", exc)
            return
        except Exception as exc:  # a bug must not take the daemon down with the global map
            self._error = f"internal error: {type(exc).__name__}: {exc}"
            log.exception("fusion: merge failed")
            return
        finally:
            self._merging = False
            revoked, self._forget_later = self._forget_later, []
            for robot in revoked:
                self._forget_placement(robot)
        if not revoked:  # (one that holds a revoked map is not kept: forget woke the next merge)
            # Saved already; not published on the way out, as the stop's flush is not either.
            self._apply(fused, publish=stopped is None)
        if stopped is not None:
            raise stopped

    def _fuse_and_publish_sync(self, search: bool) -> None:
        maps = dict(self._latest)
        self._merge_keys = self._keys(maps)
        fused = self._fuse(maps, search)
        self._apply(fused, publish=False)

    def _keys(self, maps: dict[str, OccupancyGrid]) -> dict[str, str]:
        return {r: k for r in maps if r != self.robot and (k := self._key_of(r)) is not None}

    def _apply(self, fused: _Fused, publish: bool = True) -> None:
        self._merges = fused.result.grid.version
        self._global = fused.result.grid
        self._bounds = fused.result.bounds
        self._placements = fused.placements
        self._last_merge = fused.result.grid.stamp
        self._last_seconds = fused.seconds
        self._error = None
        if not publish:
            return
        for callback in self.on_global:
            try:
                callback(fused.result.grid)
            except Exception:  # one failing sink must not stop the others or the worker
                log.exception("fusion: an on_global callback failed")


__all__ = ["FusionWorker"]
