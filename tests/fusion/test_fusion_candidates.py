"""Candidate search: every signature heading keeps its own best peaks; the evidence ranking."""

from __future__ import annotations

import math

import numpy as np

from mapd.fusion import candidates as cand
from mapd.fusion.views import FREE_C, MEET_WEIGHT, MISS_WEIGHT, OCC_C, UNK_C, MapView, evidence_field
from mapd.grid import OccupancyGrid


def test_each_heading_group_keeps_its_best_peaks(building: OccupancyGrid) -> None:
    a = MapView(building, building.resolution)
    b = MapView(building.replace(data=np.ascontiguousarray(building.data[40:200, 60:260])), a.res)
    corr = cand.Correlator(a.coarse(2), b.coarse(2), 40.0)
    at = (b.centre() - 0.5) / 2.0
    angles = [math.radians(d) for d in (0.0, 1.0, 90.0, 91.0, 180.0, 181.0)]

    def headings(hyps: list[cand.Hyp]) -> set[int]:
        return {round(math.degrees(h.yaw)) % 360 // 90 for h in hyps}

    # a global top list (one peak per ranking) leaves a group out ...
    assert len(headings(corr.search(angles, 1, at, k=2))) < 3
    # ... and with per-group peaks every group of two headings is represented
    assert headings(corr.search(angles, 1, at, k=2, group=2, per_group=1)) == {0, 1, 2}


def test_evidence_field_counts_meets_for_and_misses_against() -> None:
    cls = np.full((9, 9), UNK_C, dtype=np.uint8)
    cls[:, :6] = FREE_C
    cls[:, 2] = OCC_C
    ev = evidence_field(cls)
    assert ev[4, 2] == ev[4, 3] == np.float32(MEET_WEIGHT)  # on and beside the wall: a meet
    assert ev[4, 5] == np.float32(MISS_WEIGHT)  # known free away from it: a miss
    assert ev[4, 7] == 0.0  # unknown: no evidence either way
    assert MISS_WEIGHT < 0.0 < MEET_WEIGHT


def test_the_evidence_ranking_finds_the_true_shift(building: OccupancyGrid) -> None:
    a = MapView(building, building.resolution)
    b = MapView(building.replace(data=np.ascontiguousarray(building.data[40:200, 60:260])), a.res)
    f = 2
    corr = cand.Correlator(a.coarse(f), b.coarse(f), 40.0)
    evidence = corr.peaks(0.0, 3)[2]
    best = cand.to_fine(evidence[0], f)
    assert evidence[0].score > evidence[1].score
    assert abs(best.tx - 60.0) <= f and abs(best.ty - 40.0) <= f
