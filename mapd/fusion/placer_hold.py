"""How one estimated robot's placement is found, then held: never flip.

Once accepted, a robot's placement is *held*. Each update refines it from the held value (cheap, no
search); a full search runs again every ``research_every`` updates, and at once when the held
placement fails its check against the map it was placed against, or while a different placement is
being watched. A different placement replaces the held one only when it is accepted, beats the held
one's current fit by ``switch_margin``, and does so on ``switch_after`` searched updates in a row. A
held placement whose confidence drops stays merged (dropping it would flip the map too) and says so
in its reason.

A placement estimated against another robot's map is held *relative to that map*: when that robot
is placed anew (its pose corrected, or it switched), the placement moves with it, unless only the
old fleet-frame placement still fits that robot's map (its map frame itself moved). Where that
robot was placed then is part of the placement (``against_at``), saved with it, so a restored
placement follows too.

:class:`HoldSide` is a mixin: :class:`~mapd.fusion.placer.Placer` owns the state declared here and
decides which robots are placed, in which order, within which time.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from mapd.fusion.estimate import Estimate, SearchStopped, Stop, estimate_transform
from mapd.fusion.options import EstimateOptions
from mapd.fusion.placement import Placement
from mapd.fusion.transforms import IDENTITY, compose, inverse, pose_distance
from mapd.grid import OccupancyGrid, Pose2D


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


class HoldSide:
    """Placing one robot against the placed maps, and holding it there (a mixin:
    :class:`~mapd.fusion.placer.Placer` owns the state declared here)."""

    #: Robot -> its placement as the last update left it (what is held).
    placements: dict[str, Placement]
    #: Robot -> what this side remembers of it between updates.
    _tracks: dict[str, _Track]
    # What an estimate must reach to be accepted, and how it is searched.
    min_confidence: float
    min_agreement: float
    options: EstimateOptions
    # When a held placement is searched again, and what it takes to switch.
    switch_margin: float
    switch_after: int
    research_every: int

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
