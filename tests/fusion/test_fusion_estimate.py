"""estimate_transform(): accuracy, frames and resolutions, and a clear "no" for bad pairs."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.fusion import synth
from mapd.fusion.estimate import Estimate, check_transform, estimate_transform
from mapd.fusion.transforms import apply, compose, inverse, pose_distance
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map


def _errors(est: Estimate, truth: Pose2D, b: OccupancyGrid) -> tuple[float, float]:
    x, y = b.cell_to_world(np.array([b.height / 2]), np.array([b.width / 2]))
    d, yaw = pose_distance(est.transform, truth, (float(x[0]), float(y[0])))
    return d / b.resolution, math.degrees(yaw)


def _pair(building: OccupancyGrid, seed: int, overlap: float) -> synth.Pair:
    pair = synth.make_pair(building, overlap, np.random.default_rng(seed), size=(170, 210))
    assert pair is not None
    return pair


@pytest.mark.parametrize(("seed", "overlap"), [(1, 0.6), (2, 0.35)])
def test_turned_shifted_degraded_crop_is_found(building: OccupancyGrid, seed: int, overlap: float) -> None:
    pair = _pair(building, seed, overlap)
    est = estimate_transform(pair.a, pair.b)
    cells, deg = _errors(est, pair.truth, pair.b)
    assert est.accepted, est.reason
    assert cells <= 2.0 and deg <= 1.0
    assert 0.8 <= est.agreement <= 1.0 and est.confidence >= 0.5 and est.inliers > 0


def test_map_origins_with_yaw_are_honoured(building: OccupancyGrid) -> None:
    pair = _pair(building, 1, 0.6)
    moved = Pose2D(5.0, -7.0, 0.9)
    b2 = pair.b.replace(origin=moved)
    # same cells, other origin: b2's map frame differs from b's by origin_b * inverse(origin_b2)
    truth2 = compose(pair.truth, compose(pair.b.origin, inverse(moved)))
    est = estimate_transform(pair.a, b2)
    cells, deg = _errors(est, truth2, b2)
    assert est.accepted and cells <= 2.0 and deg <= 1.0


def test_different_resolutions_are_matched(building: OccupancyGrid) -> None:
    pair = _pair(building, 1, 0.6)
    # b seen at 10 cm: pool 2 x 2 blocks, walls winning
    d = pair.b.data[: pair.b.height // 2 * 2, : pair.b.width // 2 * 2].astype(np.int16)
    blocks = d.reshape(d.shape[0] // 2, 2, d.shape[1] // 2, 2)
    coarse = np.where(
        (blocks == 100).any(axis=(1, 3)), 100, np.where((blocks >= 0).sum(axis=(1, 3)) >= 2, 0, -1)
    )
    b10 = pair.b.replace(data=coarse.astype(np.int8), resolution=0.1)
    est = estimate_transform(pair.a, b10)
    cells, deg = _errors(est, pair.truth, b10)
    assert est.accepted, est.reason
    assert cells <= 2.0 and deg <= 1.0


def test_prior_tracking_without_search(building: OccupancyGrid) -> None:
    pair = _pair(building, 1, 0.6)
    # 2-3 cells and 1.5 degrees off, turned about b's middle (as a slightly stale answer would be)
    b = pair.b
    x, y = b.cell_to_world(np.array([b.height / 2]), np.array([b.width / 2]))
    cx, cy = apply(pair.truth, float(x[0]), float(y[0]))
    about = Pose2D(float(cx), float(cy), 0.0)
    nudge = compose(compose(about, Pose2D(0.12, -0.1, math.radians(1.5))), inverse(about))
    nudged = compose(nudge, pair.truth)
    est = estimate_transform(pair.a, pair.b, prior=nudged, search=False)
    cells, deg = _errors(est, pair.truth, pair.b)
    assert est.accepted and est.method == "prior"
    assert cells <= 2.0 and deg <= 1.0
    assert est.details["prior_fit"] == pytest.approx(est.details["best_fit"])


def test_check_transform_tells_a_good_pose_from_a_wrong_one(building: OccupancyGrid) -> None:
    pair = _pair(building, 1, 0.6)
    good = check_transform(pair.a, pair.b, pair.truth)
    bad = check_transform(pair.a, pair.b, compose(pair.truth, Pose2D(1.0, 0.6, 0.0)))
    assert good.agreement > 0.95 and good.confidence > 0.8
    assert bad.confidence < 0.2 and bad.agreement < good.agreement


def test_bad_pairs_are_refused_with_a_reason(
    building: OccupancyGrid, make_building_map: Callable[..., OccupancyGrid]
) -> None:
    empty = OccupancyGrid(data=np.zeros((0, 0), np.int8), resolution=0.05)
    unknown = building.replace(data=np.full((50, 50), -1, np.int8))
    free = building.replace(data=np.zeros((80, 80), np.int8))
    coarse = building.replace(resolution=1.0)
    other = make_building_map(seed=7)
    cases = {
        "empty": (building, empty),
        "all unknown": (unknown, building),
        "wall cells": (building, free),
        "differ": (building, coarse),
    }
    for words, (a, b) in cases.items():
        est = estimate_transform(a, b)
        assert not est.accepted and words in est.reason, (words, est.reason)
    # two different buildings, and two parts of one building that do not overlap (similar rooms!)
    est = estimate_transform(building, other.replace(data=np.ascontiguousarray(other.data[:150, :170])))
    assert not est.accepted and est.reason
    top = building.replace(data=np.ascontiguousarray(building.data[:150]))
    bottom = building.replace(data=np.ascontiguousarray(building.data[175:]))
    est = estimate_transform(top, bottom)
    assert not est.accepted and est.reason


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.integers(0, 2**31 - 1),
    st.tuples(st.integers(1, 90), st.integers(1, 90)),
    st.floats(0.0, 0.5),
    st.sampled_from([0.02, 0.05, 0.1, 0.5]),
)
def test_random_grids_never_raise_and_never_match(
    seed: int, shape: tuple[int, int], occ: float, res: float
) -> None:
    rng = np.random.default_rng(seed)
    vals = rng.choice(
        np.array([-1, 0, 100, 50, -7], np.int8), size=shape, p=[0.3, 0.7 - occ, occ * 0.9, occ * 0.1, 0.0]
    )
    a = OccupancyGrid(data=vals, resolution=res)
    b = OccupancyGrid(data=rng.permutation(vals.ravel()).reshape(shape), resolution=0.05)
    est = estimate_transform(a, b)
    assert isinstance(est, Estimate)
    assert not est.accepted and est.reason
    assert all(math.isfinite(v) for v in (est.x, est.y, est.yaw, est.confidence, est.agreement))


def test_real_part_maps_are_placed(data_dir: Path) -> None:
    base = data_dir / "maps" / "radish_derived"
    p1, p2 = base / "intel_part1" / "intel_part1.yaml", base / "intel_part2" / "intel_part2.yaml"
    if not (p1.exists() and p2.exists()):
        pytest.skip("intel part maps not in the shared data")
    pair = synth.hide_pose(load_map(p1), load_map(p2), np.random.default_rng(5))
    est = estimate_transform(pair.a, pair.b)
    cells, deg = _errors(est, pair.truth, pair.b)
    assert est.accepted and cells <= 2.0 and deg <= 1.0
