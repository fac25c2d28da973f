"""A robot's placement in the fleet frame: where its map goes, and why.

:class:`Placement` is the one record every part shares: the placer decides it
(:mod:`mapd.fusion.placer`), the worker merges by it and shows it in ``mapd status``, the state
directory keeps it in ``transforms.json`` (:mod:`mapd.fusion.store`), and the outputs publish it.
Its transform is the robot's *map frame* in the fleet frame (x, y in meters, yaw in radians). Read
back from a file, it is checked strictly (:meth:`Placement.from_dict`): a damaged or hostile file
must not place a map at 1e308 m, or at NaN.

:func:`derived_from` says which placements rest on which maps: one estimated against a robot that
is revoked, or along a chain through it, is estimated afresh (that map may have been forged to
misplace it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from mapd.grid import MAX_ORIGIN_M, Pose2D


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
