"""The scan matcher recovers a known offset in a synthetic room."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D
from mapd.mapping.localize import ScanMatcher, raycast


def room(seed: int = 0) -> OccupancyGrid:
    """A 12 x 8 m room at 5 cm with inner walls and boxes, so no pose is ambiguous."""
    rng = np.random.default_rng(seed)
    h, w = 160, 240
    d = np.zeros((h, w), np.int8)
    d[:2, :] = d[-2:, :] = d[:, :2] = d[:, -2:] = 100
    d[60:62, 40:120] = 100
    d[90:150, 170:172] = 100
    for _ in range(8):
        r, c = int(rng.integers(10, h - 20)), int(rng.integers(10, w - 20))
        d[r : r + int(rng.integers(3, 9)), c : c + int(rng.integers(3, 9))] = 100
    return OccupancyGrid(d, 0.05, Pose2D(-2.0, -1.0, 0.0))


@pytest.mark.parametrize("seed", range(6))
def test_recovers_seeded_offsets(seed: int) -> None:
    grid = room()
    rng = np.random.default_rng(seed)
    truth = Pose2D(
        float(rng.uniform(1.0, 8.0)), float(rng.uniform(1.5, 5.5)), float(rng.uniform(-math.pi, math.pi))
    )
    angles = np.linspace(-math.pi / 2, math.pi / 2, 181)
    ranges = raycast(grid, truth, angles, 20.0) + rng.normal(0, 0.01, 181)
    # Start up to 0.3 m and 10 degrees away, as the paper evaluation does.
    off = rng.uniform(-1, 1, 3) * np.array([0.3 / math.sqrt(2), 0.3 / math.sqrt(2), math.radians(10)])
    guess = Pose2D(truth.x + off[0], truth.y + off[1], truth.yaw + off[2])
    m = ScanMatcher(grid).match(ranges, angles, guess, max_range=20.0)
    assert math.hypot(m.pose.x - truth.x, m.pose.y - truth.y) < 0.03
    dyaw = math.atan2(math.sin(m.pose.yaw - truth.yaw), math.cos(m.pose.yaw - truth.yaw))
    assert abs(math.degrees(dyaw)) < 0.5
    assert m.score > 0.5


def test_wrong_map_scores_low() -> None:
    grid = room()
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    truth = Pose2D(5.0, 3.0, 0.3)
    ranges = raycast(grid, truth, angles, 20.0)
    good = ScanMatcher(grid).match(ranges, angles, truth, max_range=20.0)
    empty = OccupancyGrid(np.zeros_like(grid.data), 0.05, grid.origin)
    bad = ScanMatcher(empty).match(ranges, angles, truth, max_range=20.0)
    assert good.score > 0.8 and bad.score == 0.0


def test_raycast_hits_known_wall() -> None:
    d = np.zeros((100, 100), np.int8)
    d[80, :] = 100  # a wall whose near edge is at y = -1 + 80 * 0.05 = 3.0
    grid = OccupancyGrid(d, 0.05, Pose2D(-2.0, -1.0, 0.0))
    r = raycast(grid, Pose2D(0.0, 1.0, math.pi / 2), np.array([0.0, math.pi / 6, math.pi]), 20.0)
    assert r[0] == pytest.approx(2.0, abs=0.015)
    assert r[1] == pytest.approx(2.0 / math.cos(math.pi / 6), abs=0.02)
    assert math.isinf(r[2])
