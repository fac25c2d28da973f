"""Robots the roster takes out of the fusion worker's global map: revoked now, or since the last run.

A robot whose key is removed from the roster, or replaced (a key is replaced because it leaked),
must leave the global map, and so must what rests on its map:

* while the daemon runs, :meth:`RosterSide.forget` drops its map, placement and reported pose, and
  the map is merged again without it. Robots placed against its map, or along a chain through it,
  are estimated afresh (it may have been forged to misplace them). A global map restored from
  before the restart goes too if the robot is in it (its cells cannot be told from the others').
  When its map frame was the fleet frame, the fleet frame stays where it is: the robots placed in
  it are held there as known poses;
* at start, what a previous run left in the state directory is restored without the robots off
  the roster or given a new key since (:meth:`RosterSide._load_state`): their placements go, and a
  global map built with their maps is not restored.

:class:`RosterSide` is a mixin: :class:`~mapd.fusion.worker.FusionWorker` owns the state declared
here.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable

from mapd.errors import FusionError
from mapd.fusion.merge import Bounds
from mapd.fusion.placement import Placement, derived_from
from mapd.fusion.placer import Placer
from mapd.fusion.store import GLOBAL_YAML, FusionStore
from mapd.grid import OccupancyGrid

#: The worker's logger, one for all its parts.
log = logging.getLogger("mapd.fusion.worker")


class RosterSide:
    """Taking robots out of the global map, and restoring a previous run's state without them (a
    mixin: :class:`~mapd.fusion.worker.FusionWorker` owns the state declared here)."""

    robot: str
    store: FusionStore | None
    placer: Placer
    forgotten: int
    _latest: dict[str, OccupancyGrid]
    _wake: asyncio.Event
    _global: OccupancyGrid | None
    _placements: dict[str, Placement]
    _bounds: Bounds | None
    _resolution: float | None
    _restored: OccupancyGrid | None
    _restored_robots: set[str]
    _merges: int
    _merging: bool
    _forget_later: list[str]
    _admits: Callable[[str], bool]
    _key_of: Callable[[str], str | None]

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
