"""One merge of the fusion worker, on a worker thread: place, merge, save.

Every map is placed with the worker's :class:`~mapd.fusion.placer.Placer` (within
``search_budget_s``, and given up at the search's next stage when the daemon stops), the global
map's resolution is chosen (the config's, else this robot's own map's, else the median of the maps
placed), maps the global map cannot hold are left out with the reason (:mod:`~mapd.fusion.limits`),
the rest are merged on the previous global map's cell lattice (:mod:`mapd.fusion.merge`), and
until every robot of a restored global map has sent a map again, the restored map fills the cells
no current map knows, so a restart never shows a half-empty map.

The result is saved to the state directory (:mod:`~mapd.fusion.store`). A save that fails (a full
disk) does not freeze the fleet's global map: the new one still goes out, and the newest unsaved
one is saved again every ``WRITE_RETRY_S``. :class:`MergeSide` is a mixin:
:class:`~mapd.fusion.worker.FusionWorker` owns the state declared here, and takes the result on
the event loop's thread.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass

from mapd.config import FusionSection
from mapd.errors import MapdError
from mapd.files.outage import WRITE_RETRY_S, WriteOutage
from mapd.fusion.limits import leave_out, say_left_out, within_cell_limit, within_extent, within_merge_limits
from mapd.fusion.merge import Bounds, MergeResult, extent, merge_with_owner
from mapd.fusion.placement import Placement
from mapd.fusion.placer import Placer
from mapd.fusion.store import FusionStore
from mapd.grid import UNKNOWN, OccupancyGrid

#: The worker's logger, one for all its parts.
log = logging.getLogger("mapd.fusion.worker")
#: How many times the area its maps now cover the global map may keep (see MergeSide._kept_bounds).
SHRINK_AREA = 4
#: A merge not saved yet: its result, placements, stamp, the keys of its maps, the robots in it.
_Unsaved = tuple[MergeResult, dict[str, Placement], float, dict[str, str], list[str]]


@dataclass(frozen=True)
class _Fused:
    """One merge's outcome, handed from the worker thread to the event loop's (``_apply``)."""

    result: MergeResult
    placements: dict[str, Placement]
    seconds: float
    versions: dict[str, int]


class MergeSide:
    """Placing, merging and saving, on a worker thread (a mixin:
    :class:`~mapd.fusion.worker.FusionWorker` owns the state declared here)."""

    robot: str
    cfg: FusionSection
    store: FusionStore | None
    max_cells: int
    placer: Placer
    _said_left_out: dict[str, str]
    _resolution: float | None
    _bounds: Bounds | None
    _restored: OccupancyGrid | None
    _restored_robots: set[str]
    _merges: int
    _stop_merge: threading.Event
    _merge_keys: dict[str, str]
    _saves: WriteOutage
    _unsaved: _Unsaved | None
    _save_lock: threading.Lock

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
