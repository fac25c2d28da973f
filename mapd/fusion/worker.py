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
  a :class:`~mapd.fusion.placement.Placer` and merges them in a worker thread (a large merge never
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
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mapd.config import FusionSection
from mapd.errors import FusionError, MapdError
from mapd.files import WRITE_RETRY_S, WriteOutage
from mapd.fusion.estimate import EstimateOptions
from mapd.fusion.limits import leave_out, say_left_out, within_cell_limit, within_extent, within_merge_limits
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult, extent, merge_with_owner
from mapd.fusion.placement import Placement, Placer, derived_from
from mapd.fusion.store import GLOBAL_YAML, TRANSFORMS_JSON, FusionStore
from mapd.grid import DEFAULT_MAX_CELLS, UNKNOWN, OccupancyGrid, Pose2D, geometry_problem

log = logging.getLogger(__name__)
#: How many times the area its maps now cover the global map may keep (see FusionWorker._kept_bounds).
SHRINK_AREA = 4
#: A merge not saved yet: its result, placements, stamp, the keys of its maps, the robots in it.
_Unsaved = tuple[MergeResult, dict[str, Placement], float, dict[str, str], list[str]]


@dataclass(frozen=True)
class _Fused:
    result: MergeResult
    placements: dict[str, Placement]
    seconds: float
    versions: dict[str, int]


class FusionWorker:
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

    def forget(self, robot: str) -> bool:
        """Take ``robot``'s map out of the global map (it was revoked); False if none was held.

        Its map, placement and reported pose go, and the map is merged again without it. The global
        map held from before the restart goes too if the robot is in it (its cells cannot be told
        from the others'), and so do the bounds, which only ever grew: what is left is built from
        the maps held now, and covers what they cover.
        """
        if robot == self.robot:
            raise FusionError("a robot cannot take its own map out of its global map")
        held = robot in self._latest or robot in self._placements or robot in self._restored_robots
        self._latest.pop(robot, None)
        if self._merging:
            # A merge that began with its map runs on a worker thread, with the placer: the robot
            # is forgotten there once it is back, and its result, which still holds the map, is
            # thrown away (_merge_once), so no global map with it goes out after the revocation.
            self._forget_later.append(robot)
        else:
            self._forget_placement(robot)
        if held:
            self.forgotten += 1
            self._bounds = None
            self._wake.set()
        return held

    def _forget_placement(self, robot: str) -> None:
        """The placement half of :meth:`forget`, on the event loop's thread while no merge runs."""
        self._placements.pop(robot, None)
        again = self.placer.forget(robot)
        if robot == self.placer.anchor:
            self._keep_fleet_frame(robot)  # robots placed in its frame are held where they are
        elif again:
            log.warning(
                "fusion: %s placed against %s's map; estimating afresh from the maps left",
                ", ".join(sorted(again)),
                robot,
            )
        if robot in self._restored_robots:
            self._drop_restored()

    def _keep_fleet_frame(self, anchor: str) -> None:
        """The fleet frame was ``anchor``'s map frame (a base station's first robot, or
        ``fusion.anchor``): keep it where it is, holding the robots placed in it so far as known
        poses, rather than leave every map waiting for a robot that will not come back."""
        pinned = []
        for r, p in self._placements.items():
            if p.accepted and p.transform is not None and r not in self.placer.poses:
                self.placer.pin(r, p.transform)
                pinned.append(r)
        if not self.placer.poses:
            self.placer.anchor = None  # nobody placed yet: the next map fixes a new fleet frame
        log.warning(
            "fusion: the fleet frame was %s's map frame; kept, %s",
            anchor,
            f"with {', '.join(sorted(pinned))} held where they are"
            if pinned
            else "no robot placed in it yet",
        )

    def _drop_restored(self) -> None:
        if self._global is self._restored:
            self._global = None
        self._restored = None
        self._restored_robots = set()

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

    def _fuse(self, maps: dict[str, OccupancyGrid], search: bool) -> _Fused:
        """Place, merge and persist (runs in a worker thread)."""
        t0 = time.perf_counter()
        budget = t0 + self.cfg.search_budget_s
        self.placer.update(
            maps,
            estimate=search,
            enough=lambda: time.perf_counter() >= budget,
            stop=self._stop_merge.is_set,
        )
        # every robot the placer knows, also those restored but not heard from since the restart
        placements = dict(self.placer.placements)
        names = sorted(
            r for r, p in placements.items() if p.accepted and p.transform is not None and r in maps
        )
        names = within_extent(maps, placements, names, self.cfg.max_extent_m)
        kept = self._resolution
        if self.cfg.resolution is not None:
            # said by the config: a base station whose first maps came from the odd robot at another
            # resolution kept that one for good
            self._resolution = self.cfg.resolution
        elif self.robot in names:
            # This robot's own map's, whatever set it before: the first placed robot by name once
            # did, and one at 1e-4 m a cell left every normal map out, for good (restored from
            # global.yaml too). A new resolution of its own map is taken the same way.
            self._resolution = maps[self.robot].resolution
        elif self._resolution is None and names:  # a base station: the median of the maps placed
            self._resolution = sorted(maps[r].resolution for r in names)[(len(names) - 1) // 2]
        if kept is not None and self._resolution != kept:
            log.info("fusion: the global map is now at %g m a cell (it was %g m)", self._resolution, kept)
        names = within_merge_limits(maps, placements, names, resolution=self._resolution or 0.05)
        # Bounds on another resolution's lattice mean nothing on this one.
        bounds = self._kept_bounds(maps, placements, names) if self._resolution == kept else None
        names = within_cell_limit(
            maps,
            placements,
            names,
            resolution=self._resolution or 0.05,
            bounds=bounds,
            max_cells=self.max_cells,
        )
        result = merge_with_owner(
            [maps[r] for r in names],
            [placements[r].transform for r in names],
            self.cfg.mode,
            resolution=self._resolution,
            bounds=bounds,
            frame_id="fleet",
            max_cells=self.max_cells,
        )
        for i, why in result.left_out:
            leave_out(placements, names[i], f"the merge could not take it ({why})")
        say_left_out(placements, self._said_left_out)
        result = self._fill_from_restored(result, set(maps))
        stamp = time.time()
        grid = result.grid.replace(robot=self.robot, version=self._merges + 1, stamp=stamp)
        result = MergeResult(grid=grid, bounds=result.bounds, owner=result.owner)
        with self._save_lock:
            try:
                self._save(result, placements, stamp, self._merge_keys)
            except MapdError as exc:
                # A full disk must not freeze the fleet's global map: the outputs and status still
                # get the new one, and the state directory keeps the last one written whole (each
                # file is atomic), which a restart restores.
                self._saves.failed(
                    f"fusion: global map not saved (saving again at each merge, and every "
                    f"{WRITE_RETRY_S:g} s): {exc}"
                )
                self._unsaved = (result, placements, stamp, dict(self._merge_keys), names)
            else:
                self._saves.recovered("fusion: global map saved again")
                self._unsaved = None
            self._save_owner(result, names)
        return _Fused(result, placements, time.perf_counter() - t0, {r: maps[r].version for r in maps})

    def _kept_bounds(
        self, maps: dict[str, OccupancyGrid], placements: dict[str, Placement], names: list[str]
    ) -> Bounds | None:
        """The previous global map's bounds, which the next one keeps (its cells stay where they
        were as maps come and go), unless they are over :data:`SHRINK_AREA` times what the maps
        now cover: one map placed far off by a wrong pose kept the global map 65 M cells large
        after the pose was put right, and across restarts. Kept while a restored global map still
        stands in for robots not heard since the restart (its cells are theirs).
        """
        if self._bounds is None or self._restored is not None or self._resolution is None:
            return self._bounds
        now = extent([maps[r] for r in names], [placements[r].transform for r in names], self._resolution)
        if now is None:
            return self._bounds
        both = now.union(self._bounds)
        if both.width * both.height <= SHRINK_AREA * now.width * now.height:
            return self._bounds
        log.info(
            "fusion: the global map shrinks from %d x %d to the %d x %d cells its maps now cover",
            self._bounds.width,
            self._bounds.height,
            now.width,
            now.height,
        )
        return None

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

    def _fill_from_restored(self, result: MergeResult, present: set[str]) -> MergeResult:
        """Cells no current map knows keep the restored global map's value until its robots return."""
        old = self._restored
        if old is None:
            return result
        if self._restored_robots <= present:
            self._restored = None
            return result
        ob = Bounds.of_grid(old)
        nb = result.bounds
        if ob is None or old.resolution != result.grid.resolution:
            return result
        c0, r0 = max(ob.c0, nb.c0), max(ob.r0, nb.r0)
        c1, r1 = min(ob.c1, nb.c1), min(ob.r1, nb.r1)
        if c1 <= c0 or r1 <= r0:
            return result
        data = result.grid.data.copy()
        dst = data[r0 - nb.r0 : r1 - nb.r0, c0 - nb.c0 : c1 - nb.c0]
        src = old.data[r0 - ob.r0 : r1 - ob.r0, c0 - ob.c0 : c1 - ob.c0]
        hole = dst == UNKNOWN
        dst[hole] = src[hole]
        return MergeResult(grid=result.grid.replace(data=data), bounds=nb, owner=result.owner)

    # -- state directory --------------------------------------------------------------------

    def _load_state(self) -> None:
        """Take what a previous run left (a worker thread): placements, and the global map unless
        a robot since revoked is in it."""
        if self.store is None:
            return
        saved = self.store.load_placements()
        placements = saved.placements
        # Robots off the roster since the last run, or given a new key (a key is replaced because
        # it leaked): their placements go, and a global map built with their maps is not restored
        # (its cells are theirs and the others' alike).
        rekeyed = {r for r, k in saved.keys.items() if self._admits(r) and self._key_of(r) != k}
        revoked = sorted(
            r for r in set(placements) | rekeyed if r != self.robot and (not self._admits(r) or r in rekeyed)
        )
        again = sorted(derived_from(placements, set(revoked)))
        in_global = [r for r in revoked if (p := placements.pop(r, None)) is not None and p.accepted]
        for r in again:  # placed against a revoked robot's map: estimated afresh from the others
            placements.pop(r)
        if revoked:
            self.forgotten += len(revoked)
            log.warning(
                "fusion: leaving out %s, no longer on the roster or given a new key%s%s",
                ", ".join(revoked),
                "; the global map is built afresh" if in_global else "",
                f"; {', '.join(again)}, placed against it, estimated afresh" if again else "",
            )
        self._merges = saved.version
        self.placer.restore(placements)
        self._placements = dict(placements)
        grid = None if in_global else self.store.load_global()
        if grid is None:
            return
        bounds = Bounds.of_grid(grid)
        if bounds is None:
            log.warning(
                "fusion: %s is not on the fleet lattice; starting a new global map",
                self.store.directory / GLOBAL_YAML,
            )
            return
        # The global map saved last may be newer than transforms.json (a kill between the two):
        # numbered on from the newer, so the next map's image never takes the name of this one's.
        self._merges = max(self._merges, grid.version)
        self._global = grid.replace(robot=self.robot, version=self._merges, frame_id="fleet")
        self._bounds = bounds
        self._resolution = grid.resolution
        self._restored = self._global
        self._restored_robots = {r for r, p in placements.items() if p.accepted}

    def _save(
        self, result: MergeResult, placements: dict[str, Placement], stamp: float, keys: dict[str, str]
    ) -> None:
        if self.store is not None:
            self.store.save(
                result,
                placements,
                stamp=stamp,
                fleet_frame=self.placer.fleet_frame,
                mode=self.cfg.mode,
                keys=keys,
            )

    def _save_unsaved(self) -> None:
        """The newest global map again, after its save failed (runs in a worker thread)."""
        with self._save_lock:
            if self._unsaved is None:
                return  # a merge saved a newer one meanwhile
            result, placements, stamp, keys, names = self._unsaved
            try:
                self._save(result, placements, stamp, keys)
            except MapdError:
                return  # (said when the outage began)
            self._unsaved = None
            self._saves.recovered("fusion: global map saved again")
            self._save_owner(result, names)

    def _save_owner(self, result: MergeResult, names: list[str]) -> None:
        if self.store is not None:
            self.store.save_owner(result.owner, names)


__all__ = ["GLOBAL_YAML", "NO_OWNER", "TRANSFORMS_JSON", "FusionWorker"]
