"""Candidate search: every signature heading keeps its own best peaks; the evidence ranking."""

from __future__ import annotations

import math

import numpy as np

from mapd.fusion import candidates as cand
from mapd.fusion.views import (
    FREE_C,
    MEET_WEIGHT,
    MISS_WEIGHT,
    OCC_C,
    UNK_C,
    MapView,
    evidence_field,
    free_fields,
)
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


def _ranking_finds_the_crop(data: np.ndarray, rows: slice, cols: slice, ranking: int) -> None:
    """One ranking of :meth:`Correlator.peaks` puts its clear best peak where the crop was cut."""
    a = MapView(OccupancyGrid(data=data, resolution=0.05), 0.05)
    b = MapView(OccupancyGrid(data=np.ascontiguousarray(data[rows, cols]), resolution=0.05), 0.05)
    f = 2
    peaks = cand.Correlator(a.coarse(f), b.coarse(f), 40.0).peaks(0.0, 3)[ranking]
    best = cand.to_fine(peaks[0], f)
    assert peaks[0].score > peaks[1].score
    assert abs(best.tx - cols.start) <= f and abs(best.ty - rows.start) <= f


def test_the_evidence_ranking_finds_the_true_shift(building: OccupancyGrid) -> None:
    _ranking_finds_the_crop(building.data, slice(40, 200), slice(60, 260), 2)


def test_free_fields_leave_out_free_cells_beside_walls() -> None:
    cls = np.full((9, 9), UNK_C, dtype=np.uint8)
    cls[:, :7] = FREE_C
    cls[:, 2] = OCC_C
    free, clear = free_fields(cls)
    assert free[4, 3] == 1.0 and clear[4, 3] == 0.0  # beside the wall: a wall seen thicker
    assert free[4, 5] == 1.0 and clear[4, 5] == 1.0
    assert free[4, 2] == free[4, 8] == 0.0  # the wall itself and unknown space


def _open_ground(seed: int) -> np.ndarray:
    """Open ground with a handful of posts: an irregular explored area and almost no walls."""
    rng = np.random.default_rng(seed)
    d = np.full((260, 300), -1, np.int8)
    yy, xx = np.mgrid[0:260, 0:300]
    for _ in range(14):
        cy, cx, r = rng.integers(30, 230), rng.integers(30, 270), rng.integers(12, 40)
        d[(yy - cy) ** 2 + (xx - cx) ** 2 < r * r] = 0
    for _ in range(6):
        y, x = rng.integers(40, 220), rng.integers(40, 260)
        d[y : y + 2, x : x + 2] = 100
    return d


def test_the_free_space_ranking_places_open_ground() -> None:
    _ranking_finds_the_crop(_open_ground(3), slice(30, 230), slice(50, 270), 3)
