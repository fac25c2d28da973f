"""Candidate search: every signature heading keeps its own best peaks."""

from __future__ import annotations

import math

import numpy as np

from mapd.fusion import candidates as cand
from mapd.fusion.views import MapView
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
