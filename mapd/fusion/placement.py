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
* **never flip**: once accepted, a robot's placement is *held*. Each update refines it from the held
  value (cheap, no search); a full search runs again every ``research_every`` updates, and at once
  when the held placement fails its check against the map it was placed against, or while a
  different placement is being watched. A different placement replaces the held one only when it
  is accepted, beats the held one's current fit by ``switch_margin``, and does so on
  ``switch_after`` searched updates in a row. A held placement whose confidence drops stays merged
  (dropping it would flip the map too) and says so in its reason;
* a placement estimated against another robot's map is held *relative to that map*: when that
  robot is placed anew (its pose corrected, or it switched), the placement moves with it, unless
  only the old fleet-frame placement still fits that robot's map (its map frame itself moved).
  Where that robot was placed then is part of the placement (``against_at``), saved with it, so a
  restored placement follows too;
* an estimate below threshold is never merged; its ``reason`` says why;
* a search can be given up (``stop``: the daemon stops): the robots not placed yet keep what they
  held, as when the time budget is spent, and are searched again at the next update.

Pure logic over :func:`~mapd.fusion.estimate.estimate_transform`: no asyncio, no clock, no files.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from mapd.fusion.estimate import Estimate, SearchStopped, Stop, check_transform, estimate_transform
from mapd.fusion.options import EstimateOptions
from mapd.fusion.transforms import IDENTITY, compose, inverse, pose_distance
from mapd.grid import MAX_ORIGIN_M, OccupancyGrid, Pose2D

#: The reason of a robot left unestimated because the update's time budget (``enough``) was spent.
SPENT = "not estimated yet (this merge's search time was spent)"
#: ... because the update was stopped (``stop``: the daemon stops); its map is searched next time.
STOPPED = "not estimated yet (the search was stopped; it is searched again at the next merge)"


@dataclass(frozen=True)
class Placement:
    """Where one robot's map goes: its map frame in the fleet frame, and why.

    ``source`` is ``anchor`` (its frame is the fleet frame), ``pose`` (configured), ``estimate``,
    or ``none`` (not merged). ``accepted`` says whether it is merged. An accepted estimate's
    ``against_at`` is where the robot it was estimated ``against`` was placed then: the placement
    is held relative to that map, and follows it when it is placed anew (None: not known, as in a
    ``transforms.json`` of an earlier release).
    """

    robot: str
    transform: Pose2D | None = None
    source: str = "none"
    accepted: bool = False
    confidence: float = 0.0
    agreement: float | None = None
    reason: str = ""
    against: str | None = None
    watching: dict[str, float] | None = None
    against_at: Pose2D | None = None

    def as_dict(self) -> dict[str, Any]:
        """JSON-able form (used by ``status()`` and ``transforms.json``)."""
        t = self.transform
        return {
            "robot": self.robot,
            "x": None if t is None else t.x,
            "y": None if t is None else t.y,
            "yaw": None if t is None else t.yaw,
            "source": self.source,
            "accepted": self.accepted,
            "confidence": round(self.confidence, 4),
            "agreement": None if self.agreement is None else round(self.agreement, 4),
            "reason": self.reason,
            "against": self.against,
            "watching": self.watching,
            "against_at": _pose_dict(self.against_at),
        }

    @staticmethod
    def from_dict(d: object) -> Placement:
        """Inverse of :meth:`as_dict`: KeyError, TypeError or ValueError on malformed input (a file
        read back may be damaged: not a mapping, numbers too large for a float, a text for one)."""
        if not isinstance(d, Mapping):
            raise TypeError(f"a placement is a mapping, not {type(d).__name__}")
        t = _pose(d) if all(d.get(k) is not None for k in ("x", "y", "yaw")) else None
        at = d.get("against_at")
        agr = d.get("agreement")
        return Placement(
            robot=str(d["robot"]),
            transform=t,
            source=str(d.get("source", "estimate")),
            accepted=bool(d.get("accepted", False)) and t is not None,
            confidence=_number(d.get("confidence", 0.0)),
            agreement=None if agr is None else _number(agr),
            reason=str(d.get("reason", "")),
            against=None if d.get("against") is None else str(d["against"]),
            against_at=None if at is None else _against_at(at),
        )


def _pose_dict(t: Pose2D | None) -> dict[str, float] | None:
    return None if t is None else {"x": t.x, "y": t.y, "yaw": t.yaw}


def _pose(d: Mapping[Any, Any]) -> Pose2D:
    """``d``'s x, y and yaw as a pose; KeyError, TypeError or ValueError when they are not finite
    numbers, or x or y lies beyond :data:`~mapd.grid.MAX_ORIGIN_M` (no global map holds a map placed
    there, and one at 1e308 m overflowed every merge's arithmetic to NaN: the global map froze)."""
    vals = tuple(_number(d[k]) for k in ("x", "y", "yaw"))
    if not all(math.isfinite(v) for v in vals):
        raise ValueError("transform is not finite")
    for name, v in (("x", vals[0]), ("y", vals[1])):
        if abs(v) > MAX_ORIGIN_M:
            raise ValueError(f"{name} {v:g} is not within +-{MAX_ORIGIN_M:g} m")
    return Pose2D(*vals)


def _against_at(v: object) -> Pose2D:
    """A saved ``against_at``, as :func:`_pose` reads a transform."""
    if not isinstance(v, Mapping):
        raise TypeError(f"against_at is a mapping, not {type(v).__name__}")
    try:
        return _pose(v)
    except KeyError as exc:
        raise ValueError(f"against_at has no {exc}") from None
    except (TypeError, ValueError) as exc:
        raise ValueError(f"against_at: {exc}") from None


def _number(v: object) -> float:
    """``v`` as a float; TypeError for what is no number (a text, a list), ValueError for an int too
    large for a float (JSON allows any)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise TypeError(f"{v!r:.40} is not a number")
    try:
        return float(v)
    except OverflowError:
        raise ValueError("a number too large for a float") from None


def derived_from(placements: Mapping[str, Placement], gone: set[str]) -> set[str]:
    """Robots whose estimated placement rests on a map of ``gone``: estimated against one of them,
    or against a robot so placed (chains), not counting ``gone`` itself."""
    out: set[str] = set()
    base = set(gone)
    grew = True
    while grew:
        grew = False
        for robot, p in placements.items():
            if robot not in base and p.source == "estimate" and p.against in base:
                base.add(robot)
                out.add(robot)
                grew = True
    return out


@dataclass
class _Track:
    """Per-robot memory between updates."""

    updates_since_search: int = 0
    challenger: Pose2D | None = None
    #: searched updates in a row that saw ``challenger`` clearly better
    streak: int = 0
    #: other robot -> ((digest of its map, digest of this map, other's placement, held transform),
    #: answer)
    last: dict[str, tuple[tuple[bytes, bytes, Pose2D, Pose2D | None], Placement]] = field(
        default_factory=dict
    )
    #: Placed robots this robot was searched against since its round began (a new round once it
    #: holds them all): an update starts with the others, so a robot the time budget cuts short
    #: whose map changes every update is not searched against the first placed map only, for ever
    tried: set[str] = field(default_factory=set)


class Placer:
    """Placements of a fleet's maps in the fleet frame, kept stable across updates.

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
        self._tracks: dict[str, _Track] = {}
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

    def _place(
        self,
        robot: str,
        maps: Mapping[str, OccupancyGrid],
        placed: Mapping[str, Pose2D],
        enough: Callable[[], bool] | None = None,
        stop: Stop | None = None,
    ) -> Placement | None:
        """The best placement of ``robot`` against the placed maps; None when ``enough`` said so
        before one was found (one pair at least is tried first, so every update gets on).
        :class:`SearchStopped` when ``stop`` said so before an accepted one was found."""
        track = self._tracks.setdefault(robot, _Track())
        held = self.placements.get(robot)
        if held is not None and not (
            held.accepted and held.transform is not None and held.source == "estimate"
        ):
            held = None
        if set(placed) <= track.tried:
            track.tried.clear()  # each tried once since the round began: a new round
        others = sorted(placed, key=lambda r: (held is None or r != held.against, r in track.tried, r))
        best: Placement | None = None
        for other in others:
            if best is not None and enough is not None and enough():
                if not best.accepted:
                    return None
                break  # (on to what follows: an accepted one says where its map lies now)
            try:
                p = self._place_against(robot, other, maps, placed, held, track, stop)
            except SearchStopped:
                if best is None or not best.accepted:
                    raise
                break  # an accepted placement was found already: it stands
            track.tried.add(other)
            if best is None or (p.accepted and (not best.accepted or p.confidence > best.confidence)):
                best = p
            if best.accepted and held is not None:
                break  # a held robot is tracked against one map, not re-shopped every update
        assert best is not None
        if best.accepted and best.source == "estimate" and best.against in placed:
            assert best.against is not None
            # where the map it is held against lies now: it follows that map from here
            best = replace(best, against_at=placed[best.against])
        return best

    def _place_against(
        self,
        robot: str,
        other: str,
        maps: Mapping[str, OccupancyGrid],
        placed: Mapping[str, Pose2D],
        held: Placement | None,
        track: _Track,
        stop: Stop | None = None,
    ) -> Placement:
        # A SearchStopped from an estimate leaves the track as it was but for a watched challenger
        # dropped (it is dropped again next time: the map it follows has not moved back).
        a, b = maps[other], maps[robot]
        t_other = placed[other]
        key = (a.digest(), b.digest(), t_other, None if held is None else held.transform)
        cached = track.last.get(other)
        if cached is not None and cached[0] == key:
            return cached[1]  # neither map nor a placement changed: same answer
        own = held is not None and other == held.against
        prior = None if held is None else compose(inverse(t_other), held.transform or IDENTITY)
        est: Estimate | None = None
        if held is not None and own and held.against_at is not None and held.against_at != t_other:
            # The map it was found against was placed anew (a corrected pose, a switch): the held
            # placement is relative to that map, and moves with it. Unless that map's frame moved
            # itself (SLAM re-anchored, and that robot switched to follow): then the old
            # fleet-frame placement is the one that still fits, and stays.
            track.challenger, track.streak = None, 0  # seen against the old placement
            rel = compose(inverse(held.against_at), held.transform or IDENTITY)
            follow = self._estimate(a, b, rel, search=False, stop=stop)
            if self._holds(follow, rel, b):
                held = replace(held, transform=compose(t_other, rel))
                prior, est = rel, follow
        # Search on schedule, and while a different placement is watched: only a search sees it
        # again, and a switch needs it seen on searched updates in a row.
        search = (
            prior is None
            or track.challenger is not None
            or track.updates_since_search + 1 >= self.research_every
        )
        if est is None or search:
            est = self._estimate(a, b, prior, search=search, stop=stop)
        if not search and own and not self._holds(est, prior, b):
            # The held placement fails its check against the map it was placed against: look for
            # a better one now, not at the next scheduled search (between those, a robot whose
            # SLAM restarted elsewhere was held wrong for good). It costs no more than a robot
            # that is not placed yet, which is searched at every new map.
            search = True
            est = self._estimate(a, b, prior, search=True, stop=stop)
        track.updates_since_search = 0 if search else track.updates_since_search + 1
        result = self._judge(robot, other, b, t_other, est, held, prior, track, search)
        track.last[other] = (key, result)
        return result

    def _estimate(
        self, a: OccupancyGrid, b: OccupancyGrid, prior: Pose2D | None, search: bool, stop: Stop | None
    ) -> Estimate:
        return estimate_transform(
            a,
            b,
            min_confidence=self.min_confidence,
            min_agreement=self.min_agreement,
            prior=prior,
            search=search,
            options=self.options,
            stop=stop,
        )

    def _holds(self, est: Estimate, prior: Pose2D | None, b: OccupancyGrid) -> bool:
        """Whether ``est`` accepts the placement ``prior`` (refined no farther than a rival lies)."""
        return prior is not None and est.accepted and _close(est.transform, prior, b, self.options)

    def _judge(
        self,
        robot: str,
        other: str,
        b: OccupancyGrid,
        t_other: Pose2D,
        est: Estimate,
        held: Placement | None,
        prior: Pose2D | None,
        track: _Track,
        searched: bool,
    ) -> Placement:
        """``est`` (b in ``other``'s map) as ``robot``'s placement: held, tracked, or switched.
        Only a ``searched`` estimate counts towards a switch, or breaks a run of sightings."""
        new_t = compose(t_other, est.transform)
        if held is None or prior is None:
            if est.accepted:
                return Placement(
                    robot, new_t, "estimate", True, est.confidence, est.agreement, "estimated", other
                )
            return Placement(robot, None, "none", False, est.confidence, est.agreement, est.reason, other)
        assert held.transform is not None
        if _close(est.transform, prior, b, self.options):
            if searched:
                track.challenger, track.streak = None, 0
            if est.accepted:
                return Placement(
                    robot, new_t, "estimate", True, est.confidence, est.agreement, "tracking", other
                )
            return replace(
                held,
                confidence=est.confidence,
                agreement=est.agreement,
                reason=f"held (current check: {est.reason})",
                watching=None,
            )
        # A different placement: switch only to a clearly better one, seen more than once.
        prior_fit = est.details.get("prior_fit") or 0.0
        best_fit = est.details.get("best_fit") or 0.0
        clearly = est.accepted and best_fit >= prior_fit + self.switch_margin
        if not searched:
            pass  # a refine of the held placement alone says nothing of another one
        elif clearly:
            same = track.challenger is not None and _close(track.challenger, new_t, b, self.options)
            track.streak = track.streak + 1 if same else 1
            track.challenger = new_t
            if track.streak >= self.switch_after:
                track.challenger, track.streak = None, 0
                return Placement(
                    robot,
                    new_t,
                    "estimate",
                    True,
                    est.confidence,
                    est.agreement,
                    f"switched to a clearly better placement (fit {best_fit:.2f} vs {prior_fit:.2f})",
                    other,
                )
        else:
            track.challenger, track.streak = None, 0
        watching = {
            "x": new_t.x,
            "y": new_t.y,
            "yaw": new_t.yaw,
            "confidence": est.confidence,
            "fit": float(best_fit),
            "held_fit": float(prior_fit),
        }
        why = "a different placement is being watched" if clearly else "a different placement fits no better"
        return replace(held, reason=f"held; {why}", watching=watching)


def _centre(g: OccupancyGrid) -> tuple[float, float]:
    x, y = g.cell_to_world(np.array([g.height / 2.0]), np.array([g.width / 2.0]))
    return float(x[0]), float(y[0])


def _close(t1: Pose2D, t2: Pose2D, b: OccupancyGrid, opt: EstimateOptions) -> bool:
    d, dyaw = pose_distance(t1, t2, _centre(b))
    return d <= opt.rival_cells * b.resolution and dyaw <= math.radians(opt.rival_deg)
