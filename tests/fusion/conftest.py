"""Fixtures for the fusion tests: a procedural building that needs no shared data."""

from __future__ import annotations

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D


def make_building(
    height: int = 320,
    width: int = 360,
    *,
    seed: int = 0,
    resolution: float = 0.05,
    origin: Pose2D | None = None,
) -> OccupancyGrid:
    """A random floor plan: rooms by recursive splits, doors, furniture, 1-cell walls, unknown outside."""
    rng = np.random.default_rng(seed)
    d = np.full((height, width), -1, dtype=np.int8)
    r0, c0, r1, c1 = 10, 10, height - 10, width - 10
    d[r0:r1, c0:c1] = 0
    d[r0, c0:c1] = d[r1 - 1, c0:c1] = 100
    d[r0:r1, c0] = d[r0:r1, c1 - 1] = 100

    def split(a0: int, b0: int, a1: int, b1: int, depth: int) -> None:
        h, w = a1 - a0, b1 - b0
        if depth > 5 or (h < 60 and w < 60):
            # furniture: a couple of boxes per room
            for _ in range(int(rng.integers(0, 3))):
                bh, bw = int(rng.integers(3, 9)), int(rng.integers(3, 12))
                if h > bh + 8 and w > bw + 8:
                    y = int(rng.integers(a0 + 4, a1 - bh - 4))
                    x = int(rng.integers(b0 + 4, b1 - bw - 4))
                    d[y : y + bh, x : x + bw] = 100
            return
        if h >= w:
            cut = int(rng.integers(a0 + h // 3, a1 - h // 3))
            d[cut, b0:b1] = 100
            door = int(rng.integers(b0 + 3, b1 - 12))
            d[cut, door : door + 9] = 0
            split(a0, b0, cut, b1, depth + 1)
            split(cut + 1, b0, a1, b1, depth + 1)
        else:
            cut = int(rng.integers(b0 + w // 3, b1 - w // 3))
            d[a0:a1, cut] = 100
            door = int(rng.integers(a0 + 3, a1 - 12))
            d[door : door + 9, cut] = 0
            split(a0, b0, a1, cut, depth + 1)
            split(a0, cut + 1, a1, b1, depth + 1)

    split(r0 + 1, c0 + 1, r1 - 1, c1 - 1, 0)
    return OccupancyGrid(data=d, resolution=resolution, origin=origin or Pose2D(-3.0, -4.0, 0.0), robot="a")


@pytest.fixture(scope="session")
def building() -> OccupancyGrid:
    return make_building()


@pytest.fixture(scope="session")
def make_building_map() -> object:
    """The generator itself, for tests that need other seeds or sizes."""
    return make_building
