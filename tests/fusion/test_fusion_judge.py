"""Judging candidates: rivals that fit better veto, wide evidence beats a sliver, slides are measured."""

from __future__ import annotations

import math

import numpy as np

from mapd.fusion import refine
from mapd.fusion.candidates import Hyp
from mapd.fusion.estimate import EstimateOptions
from mapd.fusion.judge import (
    Result,
    agree_factor,
    confidence_factors,
    distinct_by_evidence,
    effective_fit,
    judge,
)
from mapd.fusion.refine import Score
from mapd.fusion.views import MapView
from mapd.grid import OccupancyGrid

OPT = EstimateOptions()
AT = np.array([100.0, 100.0])


def _result(tx: float, *, walls: int, fit: float, constraint: float, agreement: float = 0.99) -> Result:
    hits = round(walls * fit)
    sc = Score(agreement, 40 * walls, walls, walls, hits, hits, constraint)
    return Result(Hyp(0.0, tx, 0.0), sc, effective_fit(sc, OPT))


def test_a_wide_pinned_overlap_beats_a_sliver_that_fits_a_little_better_but_slides() -> None:
    wide = _result(0.0, walls=800, fit=0.93, constraint=150.0)
    sliver = _result(300.0, walls=170, fit=0.985, constraint=0.4)
    # ranked by fit alone the sliver is first; judged against each other the wide overlap wins
    assert sliver.key > wide.key
    v = judge([sliver, wide], AT, OPT)
    assert v.best is wide and v.confidence >= OPT.min_confidence
    assert v.factors["distinct"] == 1.0


def test_a_rival_that_fits_better_vetoes_however_much_less_evidence_it_has() -> None:
    # a symmetric building: a wide placement and a smaller one that fits better. Evidence alone
    # would pick the wide one; the smaller one is as good an explanation, so neither is trusted.
    wide = _result(0.0, walls=200, fit=0.98, constraint=50.0, agreement=0.955)
    small = _result(60.0, walls=90, fit=0.995, constraint=16.0, agreement=0.967)
    v = judge([wide, small], AT, OPT)
    assert v.confidence < OPT.min_confidence


def test_a_rival_with_clearly_less_evidence_is_beaten_even_when_it_fits_nearly_as_well() -> None:
    best = _result(0.0, walls=420, fit=0.91, constraint=60.0, agreement=0.97)
    rival = _result(200.0, walls=265, fit=0.875, constraint=30.0, agreement=0.97)
    v = judge([best, rival], AT, OPT)
    assert v.best is best and v.confidence >= OPT.min_confidence
    # without the evidence test, fitting 3.5 points worse is not distinct enough
    assert v.factors["distinct"] > (best.key - rival.key) / (0.05 + 1.0 - best.key)


def test_evidence_margin_scales_with_the_evidence() -> None:
    assert distinct_by_evidence(1000.0, 920.0, OPT) == 0.0  # 8% short: within the margin
    assert 0.0 < distinct_by_evidence(1000.0, 850.0, OPT) < 1.0
    assert distinct_by_evidence(1000.0, 700.0, OPT) == 1.0
    assert distinct_by_evidence(50.0, 0.0, OPT) < 1.0  # small evidence: the absolute floor rules
    assert distinct_by_evidence(-5.0, -50.0, OPT) == 0.0


def _view(data: np.ndarray) -> MapView:
    return MapView(OccupancyGrid(data=data, resolution=0.05), 0.05)


def _corridor(closed: bool) -> np.ndarray:
    d = np.full((60, 200), -1, np.int8)
    d[20:40, 10:190] = 0
    d[20, 10:190] = d[39, 10:190] = 100
    if closed:
        d[20:40, 10] = d[20:40, 189] = 100
    return d


def test_slide_test_tells_a_bare_corridor_from_one_with_ends() -> None:
    for closed, pinned in ((False, False), (True, True)):
        v = _view(_corridor(closed))
        h = Hyp(0.0, 0.0, 0.0)
        sc = refine.verify(v, v, h)
        # the weak direction of a corridor along x is x (up to sign)
        assert abs(math.cos(sc.weak_dir)) > 0.99
        walls = refine.slide_pinning(v, v, h, sc)
        assert (walls >= OPT.constraint_walls) == pinned, (closed, walls)


def test_the_slide_test_is_only_run_when_it_could_decide() -> None:
    calls: list[Result] = []

    def pinning(r: Result) -> float:
        calls.append(r)
        return 100.0

    slides = _result(0.0, walls=400, fit=0.96, constraint=1.0)
    poor = _result(300.0, walls=400, fit=0.7, constraint=1.0)
    v = judge([slides, poor], AT, OPT, pinning)
    assert calls == [slides]  # the poor fit could not reach the threshold however well pinned
    assert v.best is slides and v.factors["constrained"] == 1.0 and slides.slide == 100.0


def test_an_overlap_that_is_all_wall_is_no_placement() -> None:
    # thick wall laid on thick wall: every wall meets one, and nothing else overlaps
    band = Score(0.94, 102, 99, 99, 99, 99, 13.0)
    true = Score(0.993, 7782, 121, 129, 117, 125, 32.8)
    assert agree_factor(band) == 0.0 and agree_factor(true) == 1.0
    results = [Result(Hyp(0.0, 200.0, 0.0), band, effective_fit(band, OPT))]
    results.append(Result(Hyp(0.0, 0.0, 0.0), true, effective_fit(true, OPT)))
    v = judge(results, AT, OPT)
    assert v.best.score is true and v.factors["distinct"] == 1.0


def test_the_cheap_rank_sees_free_space_landing_on_walls(building: OccupancyGrid) -> None:
    a = MapView(building, building.resolution)
    b = MapView(building.replace(data=np.ascontiguousarray(building.data[40:200, 60:260])), a.res)
    truth = Hyp(0.0, 60.0, 40.0)
    off = Hyp(0.0, 65.0, 45.0)  # every wall moved 5 cells: b's walls on free space, its free on walls
    assert refine.sample_agreement(a, b, truth.matrix()) == 1.0
    assert refine.sample_agreement(a, b, off.matrix()) < 0.5
    assert refine.quick(a, b, truth, OPT.support_walls)[0] > refine.quick(a, b, off, OPT.support_walls)[0]


def test_a_wide_agreeing_overlap_with_few_walls_beats_a_patch_that_fits_its_walls_better() -> None:
    # open ground (cob_environments/izs-campus_2024): the true overlap holds 177 overlapping walls,
    # 80 % of which meet, on 25,000 cells that agree 99.5 %; a patch elsewhere fits 93 % of its
    # 101 walls on 913 cells of which 5 % lay free space on walls
    true = Score(0.995, 25458, 76, 101, 61, 80, 17.6)
    patch = Score(0.947, 913, 43, 58, 40, 54, 0.1)
    assert patch.fit > true.fit and true.walls < OPT.support_walls
    assert true.free_evidence > OPT.support_free > patch.free_evidence
    results = [Result(Hyp(0.0, 300.0, 0.0), patch, effective_fit(patch, OPT))]
    results.append(Result(Hyp(0.0, 0.0, 0.0), true, effective_fit(true, OPT)))
    v = judge(results, AT, OPT)
    assert v.best.score is true and v.confidence >= OPT.min_confidence
    assert v.factors["support"] == 1.0 and v.factors["distinct"] == 1.0
    # a patch that fits better and agrees better, cell for cell, still vetoes however large the
    # overlap it competes with: it is an alternative, not a chance fit
    clean = Score(0.996, 3000, 43, 58, 40, 54, 0.1)
    results[0] = Result(Hyp(0.0, 300.0, 0.0), clean, effective_fit(clean, OPT))
    v = judge(results, AT, OPT)
    assert v.confidence < OPT.min_confidence


def test_free_evidence_counts_agreeing_cells_for_and_disagreeing_ones_strongly_against() -> None:
    assert Score(0.99, 10000).free_evidence > Score(0.99, 1000).free_evidence > 0.0
    assert Score(0.9, 10000).free_evidence < 0.0
    # one disagreeing cell outweighs many agreeing ones
    assert Score(0.999, 10000).free_evidence > Score(0.98, 12000).free_evidence


def test_support_adds_walls_and_free_space_and_disagreeing_free_space_takes_it_away() -> None:
    def support(sc: Score) -> float:
        return confidence_factors(sc, sc.fit, 0.0, OPT)["support"]

    few_walls = Score(0.995, 25000, 80, 80, 70, 70, 20.0)  # open ground: few walls, much agreeing space
    walls_only = Score(0.97, 2000, 160, 160, 150, 150, 20.0)  # about neutral free space: walls alone
    # a corner of one building on a corner of another: enough walls, but 6 % of the cells disagree
    corner = Score(0.938, 4266, 226, 167, 190, 142, 80.0)
    assert few_walls.walls < OPT.support_walls and support(few_walls) == 1.0
    assert support(walls_only) == 1.0
    assert corner.walls > OPT.support_walls and support(corner) < 0.6
