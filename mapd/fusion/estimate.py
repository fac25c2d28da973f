"""Where is map b in map a? A rigid transform with a confidence, or a clear "no" with the reason.

:func:`estimate_transform` returns b's map frame expressed in a's map frame: ``p_a = R(yaw) p_b + t``,
``t = (x, y)`` in meters and ``yaw`` in radians. It honours both grids' origins (yaw included) and
resolutions, has no side effects beyond a small cache of prepared maps, and never raises for bad maps.

How (each stage keeps several hypotheses, so one wrong peak cannot decide):

1. Both maps are brought to one working resolution, the coarser of the two (the finer map is pooled
   so that thin walls survive), and coarser still when a map would have more than
   ``max_match_cells`` cells there, so that no map, however large, costs more to match than one of
   that size. Resolutions more than ``max_resolution_ratio`` apart are refused.
   Matching uses *wall faces*: occupied cells that are not lone speckle nor inside a thick wall.
2. **Candidates** (:mod:`mapd.fusion.candidates`): SIFT features with a 2-point rigid RANSAC, plus
   a search that needs no features: a wall-orientation signature proposes headings and FFT
   correlations propose translations, ranked four ways (total wall likelihood, likelihood per
   overlapping wall, wall evidence with misses counted hard, and free space laid on free space) so
   that neither large repetitive overlaps, nor small chance fits, nor placements slid along a
   corridor, nor patches that fit a degraded copy's walls better crowd out the truth, and
   every signature heading keeps its own best few peaks (in a warehouse, patches turned by 90 or
   180 degrees fit better per wall than the true heading, and would fill a global top list). When
   that finds nothing acceptable, every heading is tried in 2 degree steps. A previous answer
   (``prior``) is one more candidate.
3. **Refinement** (:mod:`mapd.fusion.refine`): every candidate is aligned cheaply and ranked (wall
   evidence and fit, times the agreement of a sample of known cells near walls); the best few get
   ICP and a Gauss-Newton polish on the distance field.
4. **Verification** of each refined candidate on the whole overlap: the *agreement* (the acceptance
   index: cells known in both maps whose class agrees, over cells known in both), the *wall fit*
   (walls of each map within 1.5 cells of a wall of the other, where the other map knows the
   place), the wall *evidence* (met walls for, missed walls against), the free-space evidence
   (agreeing known cells for, disagreeing ones strongly against) and the *constraint* (how many
   met walls pin the least constrained direction: a bare corridor pins nothing along it). The key
   of a candidate is fit x support (below ``support_walls`` overlapping walls it is discounted) x
   an agreement factor (agreement 0.8 -> 0, 0.95 -> 1; an overlap that is nearly all wall, thick
   wall on thick wall, counts nothing: :func:`mapd.fusion.judge.agree_factor`).
5. **Judging** (:mod:`mapd.fusion.judge`): confidence = quality (fit 0.65 -> 0, 0.9 -> 1) x support
   (walls plus free-space evidence) x constrained x distinct. Constrained also counts the walls a
   slide of 3 cells along the weakest direction loses. Distinct is judged against every *rival* (a
   candidate more than ``rival_cells`` or ``rival_deg`` away): one that fits worse must fit clearly
   worse or have clearly less evidence, walls and free space (``evidence_margin``); one that fits as
   well vetoes, unless it also agrees worse cell for cell and has far less evidence (twice the
   margin). Each candidate is judged so, and the most trusted one is the answer. An aliased
   corridor or a repetitive warehouse gives two placements that fit alike, and then neither is
   merged.

An estimate is accepted only when confidence >= ``min_confidence`` and agreement >= ``min_agreement``;
otherwise ``reason`` says which test failed and why.

A search takes seconds on a large map (10 s for two 2,500-cell-wide maps that do not match).
``stop``, when given, is asked between its stages (before each candidate source, each heading of
the correlation search, each candidate refined); once it says so, :class:`SearchStopped` is raised
and there is no answer. The module reads no clock: the caller's ``stop`` decides (an event's
``is_set``: the daemon stops).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mapd.fusion import candidates as cand
from mapd.fusion import refine
from mapd.fusion.candidates import Hyp, Stop, check_stop
from mapd.fusion.candidates import SearchStopped as SearchStopped  # raised here, caught by callers
from mapd.fusion.judge import Result, Verdict, agree_factor, confidence_factors, effective_fit, judge, weakest
from mapd.fusion.options import EstimateOptions
from mapd.fusion.transforms import from_matrix, to_matrix
from mapd.fusion.views import MAX_SIDE, view
from mapd.grid import OccupancyGrid, Pose2D


@dataclass(frozen=True)
class Estimate:
    """b's map frame in a's map frame, and how much to trust it.

    ``x``, ``y`` are meters and ``yaw`` radians, such that ``p_a = R(yaw) p_b + (x, y)``.
    ``confidence`` is in [0, 1]; ``agreement`` is the acceptance index over the ``overlap`` cells
    known in both maps; ``inliers`` counts b's wall cells that met a wall of a; ``accepted`` is False
    with a ``reason`` when the estimate must not be merged. ``method`` names the candidate source
    (``features``, ``search``, ``prior``, or ``none``).
    """

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    confidence: float = 0.0
    agreement: float = 0.0
    inliers: int = 0
    accepted: bool = False
    reason: str = ""
    method: str = "none"
    overlap: int = 0
    details: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def transform(self) -> Pose2D:
        return Pose2D(self.x, self.y, self.yaw)

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary (``details`` left out)."""
        return {
            "x": self.x,
            "y": self.y,
            "yaw": self.yaw,
            "confidence": self.confidence,
            "agreement": self.agreement,
            "inliers": self.inliers,
            "accepted": self.accepted,
            "reason": self.reason,
            "method": self.method,
            "overlap": self.overlap,
        }


def _measured(t: Pose2D, conf: float, sc: refine.Score, **kw: Any) -> Estimate:
    """An estimate placing b at ``t``, with ``conf`` and what verifying it measured (``sc``)."""
    return Estimate(
        x=t.x,
        y=t.y,
        yaw=t.yaw,
        confidence=conf,
        agreement=sc.agreement,
        inliers=sc.hits_b,
        overlap=sc.overlap,
        **kw,
    )


def rejected(reason: str, **kw: Any) -> Estimate:
    """A "not accepted" estimate with its reason."""
    return Estimate(accepted=False, reason=reason, **kw)


def _check_input(a: OccupancyGrid, b: OccupancyGrid, opt: EstimateOptions) -> str:
    for name, g in (("a", a), ("b", b)):
        if g.cells == 0:
            return f"map {name} is empty"
        if max(g.height, g.width) > MAX_SIDE:
            return (
                f"map {name} is {g.width} x {g.height} cells, too large to match (at most {MAX_SIDE} a side)"
            )
        if not bool((g.data >= 0).any()):
            return f"map {name} is all unknown"
    ratio = max(a.resolution, b.resolution) / min(a.resolution, b.resolution)
    if ratio > opt.max_resolution_ratio:
        return (
            f"resolutions {a.resolution:g} and {b.resolution:g} m/cell differ {ratio:.1f}x "
            f"(at most {opt.max_resolution_ratio:g}x can be matched)"
        )
    return ""


def working_resolution(a: OccupancyGrid, b: OccupancyGrid, opt: EstimateOptions) -> float:
    """The resolution both maps are matched at: the coarser of the two, coarser still when a map
    would have more than ``opt.max_match_cells`` cells there (a peer's map is untrusted: its size
    must not decide how much memory and time matching takes)."""
    res = max(a.resolution, b.resolution)
    cells = max(g.cells * (g.resolution / res) ** 2 for g in (a, b))
    cap = max(1, opt.max_match_cells)
    if cells > cap:
        # a whole factor: the coarser map is pooled by whole cells, as a map of that resolution
        # would be made (a fractional pooling smears walls, and judging was tuned on whole cells)
        res *= math.ceil(math.sqrt(cells / cap) - 1e-9)
    return res


def estimate_transform(
    a: OccupancyGrid,
    b: OccupancyGrid,
    *,
    min_confidence: float | None = None,
    min_agreement: float | None = None,
    prior: Pose2D | None = None,
    search: bool = True,
    options: EstimateOptions | None = None,
    seed: int = 0,
    stop: Stop | None = None,
) -> Estimate:
    """b's map frame expressed in a's map frame, with confidence and overlap agreement.

    ``prior`` (an earlier answer, b in a) is refined and kept as a candidate; its refined effective
    fit is reported as ``details["prior_fit"]`` next to the best's ``details["best_fit"]``. With
    ``search=False`` only the prior is refined (cheap tracking as maps grow; no rivals are looked
    for, so the confidence is not discounted for them). Empty, all-unknown, structureless,
    non-overlapping or incompatible maps give ``accepted=False`` and a reason. Deterministic for a
    given ``seed``. ``stop`` is asked between stages: :class:`SearchStopped` once it says so.
    """
    opt = options or EstimateOptions()
    min_conf = opt.min_confidence if min_confidence is None else min_confidence
    min_agr = opt.min_agreement if min_agreement is None else min_agreement
    problem = _check_input(a, b, opt)
    if problem:
        return rejected(problem)
    res = working_resolution(a, b, opt)
    va, vb = view(a, res), view(b, res)
    for name, v in (("a", va), ("b", vb)):
        if v.n_walls < opt.min_walls:
            return rejected(
                f"map {name} has {v.n_walls} wall cells, too few to match (needs {opt.min_walls})"
            )
    check_stop(stop)  # (preparing a new map's view, before, takes a tenth of a second at most)
    rng = np.random.default_rng(seed)
    at = vb.centre()
    results: list[Result] = []

    def pinning(r: Result) -> float:
        return refine.slide_pinning(va, vb, r.hyp, r.score)

    def decide() -> Verdict:
        return judge(results, at, opt, pinning if opt.slide_test else None, min_conf)

    def consider(hyps: list[Hyp], gate0: float) -> None:
        # cheap alignment and ranking of all, full refinement and check of the best few
        ranked: list[tuple[float, float, Hyp]] = []
        for h in hyps:
            check_stop(stop)  # a few milliseconds each, but up to hundreds of candidates
            if any(cand.same(h, r.hyp, at, 2.0, 1.0) for r in results):
                continue
            aligned = refine.polish(va, vb, h, rng, iters=20, gate0=gate0, npts=1500)
            ranked.append((*refine.quick(va, vb, aligned, opt.support_walls), aligned))
        # the most evidence, and (so that a true but smaller overlap is not crowded out by large
        # overlaps of a repetitive layout) the best fits
        by_evidence = sorted(ranked, key=lambda q: -q[0])
        by_fit = sorted(ranked, key=lambda q: -q[1])[: max(1, opt.refine_top // 2)]
        done: list[Hyp] = []
        for _e, _f, h in by_fit + by_evidence:
            if any(cand.same(h, d, at, 2.0, 1.0) for d in done):
                continue
            check_stop(stop)
            done.append(h)
            final = refine.polish(va, vb, refine.icp(va, vb, h, 3.0, rng), rng)
            if any(cand.same(final, r.hyp, at, 1.0, 0.5) for r in results):
                continue
            sc = refine.verify(va, vb, final)
            results.append(Result(final, sc, effective_fit(sc, opt)))
            if len(done) >= opt.refine_top + len(by_fit):
                break

    def good_enough() -> bool:
        if not results:
            return False
        v = decide()
        return bool(v.confidence >= min_conf and v.best.score.agreement >= min_agr)

    prior_fit: float | None = None
    f = cand.coarse_factor(va, vb, opt.coarse_cells, opt.max_coarse_m)
    if prior is not None:
        p = from_matrix(np.linalg.inv(va.g) @ to_matrix(prior) @ vb.g)
        consider([Hyp(p.yaw, p.x, p.y, 0.0, "prior")], 4.0)
        prior_fit = results[0].key if results else 0.0
    if search or prior is None:
        if opt.use_features:
            check_stop(stop)
            consider(cand.feature_hyps(va, vb, rng), 4.0)
        check_stop(stop)
        # The signature search always runs: besides finding matches, it finds the rivals that show
        # an aliased feature match for the doubtful thing it is.
        corr = cand.Correlator(va.coarse(f), vb.coarse(f), opt.coarse_floor / f)
        at_coarse = (at - (f - 1) / 2.0) / f
        gate = 1.5 * f + 2.0
        offsets = (-3.0, -1.5, 0.0, 1.5, 3.0)
        headings = [h + math.radians(d) for h in cand.signature_angles(va, vb) for d in offsets]
        peaks = corr.search(
            headings,
            opt.search_peaks[0],
            at_coarse,
            k=6,
            group=len(offsets),
            per_group=opt.heading_peaks,
            stop=stop,
        )
        consider([cand.to_fine(h, f) for h in peaks], gate)
        if opt.exhaustive and not good_enough():
            headings = [math.radians(float(d)) for d in np.arange(-180.0, 180.0, 2.0)]
            consider(
                [
                    cand.to_fine(h, f)
                    for h in corr.search(headings, opt.search_peaks[1], at_coarse, stop=stop)
                ],
                gate,
            )
    if not results:
        return rejected("no candidate placement: the maps share no recognisable structure")
    verdict = decide()
    best, conf, rival = verdict.best, verdict.confidence, verdict.rival
    sc = best.score
    t = from_matrix(va.g @ best.hyp.matrix() @ np.linalg.inv(vb.g))
    details = {
        "fit": sc.fit,
        "walls": sc.walls,
        "best_fit": best.key,
        "prior_fit": prior_fit,
        "rival": rival,
        "candidates": len(results),
        "coarse": f,
        "factors": verdict.factors,
        "slide": best.slide,
    }
    if sc.overlap == 0:
        return rejected(
            "the maps do not overlap under any candidate placement", method=best.hyp.source, details=details
        )
    reason = ""
    if conf < min_conf:
        reason = f"confidence {conf:.2f} below {min_conf:.2f} ({weakest(sc, verdict.factors)})"
    elif sc.agreement < min_agr:
        reason = f"overlap agreement {sc.agreement:.2f} below {min_agr:.2f}"
    return _measured(t, conf, sc, accepted=not reason, reason=reason, method=best.hyp.source, details=details)


def check_transform(
    a: OccupancyGrid, b: OccupancyGrid, t: Pose2D, *, options: EstimateOptions | None = None
) -> Estimate:
    """Score a given placement (b's map frame in a's) without searching or refining it.

    Used for known poses: a configured pose whose agreement is poor points at a wrong pose (meters
    taken for cells, a forgotten map origin). Confidence here has no rival discount.
    """
    opt = options or EstimateOptions()
    problem = _check_input(a, b, opt)
    if not all(math.isfinite(v) for v in t):
        # checked here too, not only where poses come in: a NaN would raise deep in verify()
        problem = f"the placement ({t.x:g}, {t.y:g}, {t.yaw:g}) is not finite"
    if problem:
        return rejected(problem, x=t.x, y=t.y, yaw=t.yaw, method="given")
    res = working_resolution(a, b, opt)
    va, vb = view(a, res), view(b, res)
    h = Hyp.from_matrix(np.linalg.inv(va.g) @ to_matrix(t) @ vb.g, source="given")
    sc = refine.verify(va, vb, h)
    conf = math.prod(confidence_factors(sc, sc.fit * agree_factor(sc), 0.0, opt).values())
    return _measured(t, conf, sc, accepted=True, method="given", details={"fit": sc.fit, "walls": sc.walls})
