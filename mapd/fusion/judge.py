"""Judging refined candidate placements: which one is best, and how far to trust it.

Every candidate is judged as if it were the answer, against all the others as its rivals, and the
one with the highest confidence wins (near-ties go to the better ranked). Judging only the top-ranked
one lost true placements to candidates that fit slightly better but slide (a sliver of corridor
under a wide, well pinned true overlap), and judging each against all keeps every rival's veto.

Confidence = quality x support x constrained x distinct (see :func:`confidence_factors`), where

* **constrained** is the larger of the normal-based estimate (``Score.constraint``) and the walls
  actually lost when the placement is slid 3 cells along its weakest direction
  (:func:`mapd.fusion.refine.slide_pinning`): warehouse shelf ends and door frames pin a match that
  the smoothed normals call a corridor;
* **distinct** is judged rival by rival, the worst one counting. The evidence of a placement
  (:func:`total_evidence`) is its walls' (:attr:`mapd.fusion.refine.Score.evidence`: met walls
  for, missed walls against) plus its free space's (:attr:`mapd.fusion.refine.Score.free_evidence`:
  cells known in both maps that agree for, those that disagree strongly against). A rival that fits
  worse (fit x agreement, discounted as in :func:`rival_strength`) is beaten either by fitting
  clearly worse or by clearly less evidence: a large true overlap whose walls meet a little less
  often than a small aliased patch's leaves hundreds more walls and thousands more cells explained.
  A rival that fits at least as well vetoes, whatever the sizes (a small patch that fits as well as
  the best is an alternative: symmetric buildings, repeated rooms), unless its overlap also agrees
  worse, cell for cell, and its evidence is short by twice the margin: a few dozen walls that meet
  on a patch that lays its free space on walls, against a large overlap that agrees nearly
  everywhere (open ground with few walls, where the truth's walls fit only 0.8).
* **support** is the overlapping walls (``support_walls`` for full marks) plus the free-space
  evidence (``support_free`` for full marks): on open ground a true overlap can hold under a
  hundred walls but tens of thousands of agreeing cells, and an overlap whose free space disagrees
  more than it agrees loses support (a corner of one building on a corner of another).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from mapd.fusion.candidates import Hyp
from mapd.fusion.options import EstimateOptions
from mapd.fusion.refine import Score, agreement_ramp


@dataclass
class Result:
    """A refined, verified candidate; ``key`` is its :func:`effective_fit`."""

    hyp: Hyp
    score: Score
    key: float
    #: walls lost when slid along the weakest direction; measured on demand (None: not yet)
    slide: float | None = field(default=None, compare=False)


@dataclass(frozen=True)
class Verdict:
    """The chosen candidate, its confidence and factors, and the rival that limited it."""

    best: Result
    confidence: float
    factors: dict[str, float]
    #: strength (fit x agreement factor, discounted) of the rival that set ``distinct``; 0 if none
    rival: float


def agree_factor(sc: Score) -> float:
    """Agreement factor: 0.8 -> 0, 0.95 -> 1, times an open-overlap factor: the cells known in
    both maps over the overlapping walls of both, 0.75 -> 0, 1.5 -> 1.

    Two robots that mapped the same place both saw the free space in front of its walls, so a true
    overlap holds several known cells per wall (at least 1.75 over the 472 true placements of
    ``mapd bench merge`` seeds 1-3, mostly over 4). A patch of thick wall laid on thick wall is all
    wall: every wall meets one, and nothing else overlaps to contradict it.
    """
    walls = sc.walls_a + sc.walls_b
    open_ = (sc.overlap / walls - 0.75) / 0.75 if walls else 1.0
    return agreement_ramp(sc.agreement) * float(np.clip(open_, 0.0, 1.0))


def effective_fit(sc: Score, opt: EstimateOptions) -> float:
    """Key of a candidate: the wall fit x a small-overlap discount (below ``support_walls`` walls)
    x an agreement factor (0.8 -> 0, 0.95 -> 1): a placement that puts free space on the other
    map's walls is no placement, however good its wall fit."""
    return sc.fit * min(1.0, sc.walls / opt.support_walls) * agree_factor(sc)


def rank(r: Result, opt: EstimateOptions) -> float:
    """Order of candidates: effective fit, near-ties broken towards the larger overlap (log)."""
    return r.key * (1.0 + 0.02 * math.log(max(r.score.walls, opt.support_walls) / opt.support_walls))


def confidence_factors(sc: Score, key: float, rival: float, opt: EstimateOptions) -> dict[str, float]:
    """quality: the wall fit (0.65 -> 0, 0.9 -> 1); support: enough overlapping walls plus free-space
    evidence;
    constrained: enough walls pin the least constrained direction (a bare corridor lets a match
    slide along it); distinct: the best fits clearly better than a rival of strength ``rival``."""
    return {
        "quality": float(np.clip((sc.fit - 0.65) / 0.25, 0.0, 1.0)),
        "support": float(
            np.clip(sc.walls / opt.support_walls + sc.free_evidence / opt.support_free, 0.0, 1.0)
        ),
        "constrained": float(np.clip(sc.constraint / opt.constraint_walls, 0.0, 1.0)),
        # the rival must leave clearly more walls unexplained than the best does
        "distinct": distinct_by_fit(key, rival),
    }


def distinct_by_fit(key: float, rival: float) -> float:
    """1 when the rival leaves clearly more walls unexplained (as a share) than the best."""
    return float(np.clip((key - rival) / (0.05 + max(0.0, 1.0 - key)), 0.0, 1.0))


def total_evidence(sc: Score) -> float:
    """Wall evidence plus free-space evidence (:attr:`Score.free_evidence`), before the agreement
    factor."""
    return sc.evidence + sc.free_evidence


def distinct_by_evidence(best: float, rival: float, opt: EstimateOptions, times: float = 1.0) -> float:
    """1 when the rival's evidence is short of the best's by twice the margin, 0 within it.

    The margin is ``times`` the larger of ``evidence_margin[0]`` and ``evidence_margin[1]`` x the
    best's evidence: neighbouring cells' errors are correlated (a wall seen thicker is thicker over
    a stretch), so the evidence, summed as if cells were independent, is trusted only in bulk.
    """
    if best <= 0.0:
        return 0.0
    margin = times * max(opt.evidence_margin[0], opt.evidence_margin[1] * best)
    return float(np.clip((best - rival) / margin - 1.0, 0.0, 1.0))


def _positions(results: list[Result], at: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pts = np.array([(r.hyp.matrix() @ np.array([at[0], at[1], 1.0]))[:2] for r in results])
    return pts, np.array([r.hyp.yaw for r in results])


def judge(
    results: list[Result],
    at: np.ndarray,
    opt: EstimateOptions,
    pinning: Callable[[Result], float] | None = None,
    min_confidence: float | None = None,
) -> Verdict:
    """The most trusted candidate of ``results`` (not empty), judged against all the others.

    ``at`` is where placements are compared (b's centre, working pixels): candidates within
    ``rival_cells`` there and ``rival_deg`` in heading are the same placement, not rivals.
    ``pinning(result)`` measures the slide test; it is only called for candidates that it could
    lift to ``min_confidence`` (default ``opt.min_confidence``), as it costs two more checks.
    """
    floor = opt.min_confidence if min_confidence is None else min_confidence
    ranked = sorted(results, key=lambda r: -rank(r, opt))
    pts, yaws = _positions(ranked, at)
    best: Verdict | None = None
    for i, r in enumerate(ranked):
        near = np.hypot(*(pts - pts[i]).T) < opt.rival_cells
        turn = np.abs(np.remainder(yaws - yaws[i] + math.pi, 2.0 * math.pi) - math.pi) < math.radians(
            opt.rival_deg
        )
        rivals = [ranked[j] for j in np.nonzero(~(near & turn))[0]]
        v = _judge_one(r, rivals, opt, pinning, floor)
        if best is None or v.confidence > best.confidence + 1e-9:
            best = v
    assert best is not None
    return best


def rival_strength(best: Score, rival: Score, opt: EstimateOptions) -> float:
    """A rival's fit x agreement factor, discounted when it explains under a quarter of the walls
    the best explains (a patch that happens to fit, against a large true overlap) or when it could
    slide while the best is well pinned down and has more wall evidence (a sliver of corridor fits
    anywhere along it; a wide corridor match with more evidence than the best is no sliver). It is
    not discounted for its size otherwise."""
    few = min(1.0, rival.matched / (0.25 * best.matched)) if best.matched else 1.0
    sliver = best.constraint >= 3.0 * opt.constraint_walls and rival.evidence < best.evidence
    pinned = float(np.clip(rival.constraint / opt.constraint_walls, 0.0, 1.0)) if sliver else 1.0
    return rival.fit * agree_factor(rival) * few * pinned


def _judge_one(
    r: Result,
    rivals: list[Result],
    opt: EstimateOptions,
    pinning: Callable[[Result], float] | None,
    floor: float,
) -> Verdict:
    sc = r.score
    key = sc.fit * agree_factor(sc)
    ev = total_evidence(sc) * agree_factor(sc)
    well_pinned = sc.constraint >= 3.0 * opt.constraint_walls
    distinct, limiting = 1.0, 0.0
    for o in rivals:
        s = rival_strength(sc, o.score, opt)
        d = distinct_by_fit(key, s)
        pinned = float(np.clip(o.score.constraint / opt.constraint_walls, 0.0, 1.0)) if well_pinned else 1.0
        oev = total_evidence(o.score) * agree_factor(o.score) * pinned
        if s < key:
            d = max(d, distinct_by_evidence(ev, oev, opt))
        elif sc.agreement >= o.score.agreement:
            # a rival that fits the walls better but on an overlap that agrees worse, cell for cell:
            # beaten only by twice the margin of evidence (a far larger overlap that agrees better)
            d = max(d, distinct_by_evidence(ev, oev, opt, 2.0))
        if d < distinct:
            distinct, limiting = d, s
    factors = confidence_factors(sc, key, 0.0, opt)
    factors["distinct"] = distinct
    if pinning is not None and factors["constrained"] < 1.0:
        rest = math.prod(v for k, v in factors.items() if k != "constrained")
        if rest >= floor and sc.agreement >= opt.min_agreement:
            if r.slide is None:
                r.slide = pinning(r)
            factors["constrained"] = max(
                factors["constrained"], float(np.clip(r.slide / opt.constraint_walls, 0.0, 1.0))
            )
    return Verdict(r, math.prod(factors.values()), factors, limiting)


def weakest(sc: Score, factors: dict[str, float]) -> str:
    """Why a confidence is low, in words: its weakest factor."""
    if sc.agreement < 0.85:
        return f"overlap agreement {sc.agreement:.2f}: free space of one map lies on walls of the other"
    worst = min(factors, key=lambda k: factors[k])
    return {
        "quality": f"only {sc.fit:.0%} of overlapping walls meet",
        "support": f"only {sc.walls} wall cells overlap"
        + (
            ""
            if sc.free_evidence >= 0.0
            else f", and {1.0 - sc.agreement:.0%} of the cells known in both disagree"
        ),
        "constrained": "the overlap does not pin the match down: it could slide, as along a bare corridor",
        "distinct": "another placement fits almost as well",
    }[worst]
