"""Placing every robot's map in the fleet frame, and keeping the placements stable over time.

The **fleet frame** is the frame the configured poses are given in (each pose is a robot's *map
frame* in the fleet frame: x, y in meters, yaw in radians; for a SLAM map that starts where the
robot starts, that is the robot's initial pose). When no pose is configured, the fleet frame is
the ``anchor`` robot's map frame (the worker's own robot, or the first map of ``mapd merge``).

:class:`Placer` decides, on every update, where each map goes:

* a robot with a configured pose is placed by it (and its agreement with the maps it overlaps is
  reported, so a pose given in cells instead of meters, or one that forgets a map's origin, shows);
* any other robot is estimated against the maps already placed (so chains work: c is placed
  against b once b is placed against a); the most confident accepted estimate wins;
* **never flip**: once accepted, a robot's placement is *held*, refined from the held value, and
  replaced only by a clearly better one seen on searched updates in a row; a placement estimated
  against another robot's map follows that map when it is placed anew
  (:mod:`mapd.fusion.placer_hold` has the rules);
* an estimate below threshold is never merged; its ``reason`` says why;
* a search can be given up (``stop``: the daemon stops): the robots not placed yet keep what they
  held, as when the time budget is spent, and are searched again at the next update.

This module holds the fleet's side: the fleet frame, known poses, the order robots are placed in,
the time budget, and robots forgotten or pinned. Pure logic over
:func:`~mapd.fusion.estimate.estimate_transform`: no asyncio, no clock, no files.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import replace

from mapd.fusion.estimate import Estimate, SearchStopped, Stop, check_transform
from mapd.fusion.options import EstimateOptions
from mapd.fusion.placement import Placement, derived_from
from mapd.fusion.placer_hold import HoldSide
from mapd.fusion.transforms import IDENTITY, compose, inverse
from mapd.grid import OccupancyGrid, Pose2D

#: The reason of a robot left unestimated because the update's time budget (``enough``) was spent.
SPENT = "not estimated yet (this merge's search time was spent)"
#: ... because the update was stopped (``stop``: the daemon stops); its map is searched next time.
STOPPED = "not estimated yet (the search was stopped; it is searched again at the next merge)"


class Placer(HoldSide):
    """Placements of a fleet's maps in the fleet frame, kept stable across updates (how one robot
    is placed and held is :class:`~mapd.fusion.placer_hold.HoldSide`'s).

    ``poses`` maps a robot to its map frame's pose in the fleet frame, or to None for "estimate"
    (robots not listed are estimated too). ``anchor`` is the robot whose map frame is the fleet frame
    when no pose is configured.
    """

    def __init__(
        self,
        poses: Mapping[str, Pose2D | None],
        anchor: str | None,
        *,
        min_confidence: float = 0.5,
        min_agreement: float = 0.8,
        options: EstimateOptions | None = None,
        switch_margin: float = 0.1,
        switch_after: int = 2,
        research_every: int = 5,
    ) -> None:
        self.poses = {r: p for r, p in poses.items() if p is not None}
        self.anchor = anchor
        self.min_confidence = min_confidence
        self.min_agreement = min_agreement
        self.options = options or EstimateOptions()
        self.switch_margin = switch_margin
        self.switch_after = max(1, switch_after)
        self.research_every = max(1, research_every)
        self.placements: dict[str, Placement] = {}
        self._tracks = {}  # (typed in HoldSide, which keeps them)
        #: Robots whose pose came with their maps (a source's start pose), not from the config.
        self.reported: set[str] = set()
        #: Robots held where they were placed when the robot whose map frame was the fleet frame
        #: was forgotten (see :meth:`pin`).
        self.pinned: set[str] = set()
        #: Robots the last update left unestimated for want of time (``enough``): first next time.
        self._deferred: set[str] = set()
        #: (robot, other) -> (maps' digests and relative pose, the check of a known pose against it)
        self._pose_checks: dict[tuple[str, str], tuple[tuple[bytes, bytes, Pose2D], Estimate]] = {}

    @property
    def fleet_frame(self) -> str:
        """A description of the fleet frame, for status output."""
        if self.poses:
            what = "known" if self.reported else "configured"
            return f"frame of the {what} poses (" + ", ".join(sorted(self.poses)) + ")"
        return f"map frame of robot '{self.anchor}'" if self.anchor else "map frame of the first map"

    def restore(self, placements: Mapping[str, Placement]) -> None:
        """Hold earlier accepted estimates (from ``transforms.json``) so a restart keeps them."""
        for robot, p in placements.items():
            if p.accepted and p.transform is not None and p.source == "estimate" and robot not in self.poses:
                self.placements[robot] = replace(p, reason="restored from the state directory")

    def forget(self, robot: str) -> set[str]:
        """Drop all that is held of ``robot``: its placement, its track, a pose its maps reported
        (a configured pose stays: the config still names it).

        Robots placed by estimate against its map, or along a chain through it, are estimated
        afresh from the maps left (its map may have been forged to misplace them); returns them.
        """
        again = derived_from(self.placements, {robot})
        for r in (robot, *again):
            self.placements.pop(r, None)
            self._tracks.pop(r, None)
        self._pose_checks = {k: v for k, v in self._pose_checks.items() if robot not in k}
        if robot in self.reported or robot in self.pinned:
            self.reported.discard(robot)
            self.pinned.discard(robot)
            self.poses.pop(robot, None)
        return again

    def pin(self, robot: str, pose: Pose2D) -> None:
        """Hold ``robot`` at ``pose`` from now on, as a known pose (the fleet frame's own robot left)."""
        self.poses[robot] = pose
        self.pinned.add(robot)

    def update(
        self,
        maps: Mapping[str, OccupancyGrid],
        *,
        estimate: bool = True,
        tried: Callable[[Placement], None] | None = None,
        enough: Callable[[], bool] | None = None,
        stop: Stop | None = None,
    ) -> dict[str, Placement]:
        """Place every map of ``maps`` (robot -> latest map); returns robot -> placement.

        With ``estimate=False`` nothing is estimated: configured poses and the anchor are placed,
        other robots keep their held placements (a cheap update, e.g. for a last flush).
        ``tried`` is told each estimate as it is made (each can take seconds: a progress bar).
        ``enough`` is asked after each estimate (one robot against one placed map): once it says
        so, the robots not yet estimated keep what they held, and go first at the next update,
        which starts with the placed maps they were not yet searched against. A robot that
        places against no map was searched against every placed one at each new version, so one
        merge of a fleet with a few of them took minutes, and the placed robots' maps waited as
        long.
        ``stop`` is asked more often, between the stages of each search as well (see
        :func:`~mapd.fusion.estimate.estimate_transform`): once it says so, the search under way is
        given up, and the update ends as when ``enough`` says so, at once (a daemon that stops does
        not wait seconds for a search). An accepted placement found before stands; the rest keep
        what they held, with the reason :data:`STOPPED` if they held nothing.
        """
        out: dict[str, Placement] = {}
        placed: dict[str, Pose2D] = {}
        if self.anchor is None and not self.poses and maps:
            # No own map (a base station): the first robot by name fixes the fleet frame, for good.
            self.anchor = min(maps)
        for robot in sorted(maps):
            if robot in self.poses:
                placed[robot] = self.poses[robot]
        if not self.poses and self.anchor in maps:
            assert self.anchor is not None
            placed[self.anchor] = IDENTITY
            out[self.anchor] = Placement(
                self.anchor, IDENTITY, "anchor", True, 1.0, None, "its map frame is the fleet frame"
            )
        for robot in sorted(placed):
            if robot not in out:
                out[robot] = self._pose_placement(robot, maps, placed)
        if not placed:
            waiting = ", ".join(sorted(self.poses)) if self.poses else str(self.anchor)
            for robot in sorted(maps):
                out[robot] = Placement(
                    robot, reason=f"waiting for a map from {waiting} to fix the fleet frame"
                )
            self.placements.update(out)
            return out
        # Held robots first, so chains form in a stable order, each after the robot it is held
        # against (so it sees where that one is placed now); then those an earlier update left for
        # later (so none waits for ever behind the others); then the rest by name.
        unplaced = {r for r in maps if r not in placed}
        pending = sorted(
            unplaced,
            key=lambda r: (
                r not in self.placements,
                self._chain_depth(r, unplaced),
                r not in self._deferred,
                r,
            ),
        )
        if not estimate:
            for robot in pending:
                out[robot] = self.placements.get(robot) or Placement(robot, reason="not estimated yet")
            self.placements.update(out)
            return out
        self._deferred = set()
        progress = True
        while pending and progress:
            progress = False
            for robot in list(pending):
                if stop is not None and stop():
                    return self._cut_short(pending, out, STOPPED)
                if enough is not None and enough():
                    return self._cut_short(pending, out, SPENT)
                try:
                    p = self._place(robot, maps, placed, enough, stop)
                except SearchStopped:  # within this robot's search: it holds what it held
                    return self._cut_short(pending, out, STOPPED)
                if p is None:  # the time ran out within this robot's search: it goes first next time
                    return self._cut_short(pending, out, SPENT)
                if tried is not None:
                    tried(p)
                if p.accepted and p.transform is not None:
                    placed[robot] = p.transform
                    pending.remove(robot)
                    progress = True
                out[robot] = p
        self.placements.update(out)
        return out

    def _chain_depth(self, robot: str, among: set[str]) -> int:
        """How many robots of ``among`` lie under ``robot``'s held estimate (it against b, b
        against c, ...)."""
        n, seen = 0, {robot}
        p = self.placements.get(robot)
        while p is not None and p.source == "estimate" and p.against in among and p.against not in seen:
            seen.add(p.against)
            n += 1
            p = self.placements.get(p.against)
        return n

    def _cut_short(self, pending: list[str], out: dict[str, Placement], why: str) -> dict[str, Placement]:
        """End an update before ``pending`` robots were all estimated (see ``enough``, ``stop``)."""
        self._defer([r for r in pending if r not in out], out, why)
        self.placements.update(out)
        return out

    def _defer(self, robots: list[str], out: dict[str, Placement], why: str) -> None:
        """Leave ``robots`` to the next update, holding what they had (``why``: if nothing)."""
        self._deferred = set(robots)
        for robot in robots:
            out[robot] = self.placements.get(robot) or Placement(robot, reason=why)

    # -----------------------------------------------------------------------------------------

    def _pose_placement(
        self, robot: str, maps: Mapping[str, OccupancyGrid], placed: Mapping[str, Pose2D]
    ) -> Placement:
        """A configured pose, with its agreement against the first other placed map it overlaps."""
        t = placed[robot]
        for other in sorted(placed):
            if other == robot:
                continue
            rel = compose(inverse(placed[other]), t)
            # Cached while neither map nor the poses change: every merge checked every pair of
            # robots with known poses again (32 robots: 7.7 s a merge).
            key = (maps[other].digest(), maps[robot].digest(), rel)
            held = self._pose_checks.get((robot, other))
            if held is not None and held[0] == key:
                chk = held[1]
            else:
                chk = check_transform(maps[other], maps[robot], rel, options=self.options)
                self._pose_checks[(robot, other)] = (key, chk)
            if chk.overlap > 0:
                note = ""
                if chk.confidence < self.min_confidence or chk.agreement < self.min_agreement:
                    fit = chk.details.get("fit", 0.0)
                    note = (
                        f"; it does not line up with '{other}' (wall fit {fit:.2f}, agreement "
                        f"{chk.agreement:.2f}): check the pose (x, y in meters and yaw in radians of "
                        "the map frame, not of the map's origin cell)"
                    )
                return Placement(
                    robot, t, "pose", True, 1.0, chk.agreement, self._pose_word(robot) + note, other
                )
        return Placement(robot, t, "pose", True, 1.0, None, self._pose_word(robot))

    def _pose_word(self, robot: str) -> str:
        if robot in self.pinned:
            return "held where it was placed when the fleet frame's robot left"
        return "start pose reported by the robot" if robot in self.reported else "configured pose"
