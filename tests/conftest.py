"""Shared fixtures. Real data is read in place from ../shared/data (override with MAPD_DATA)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from mapd.data import data_dir as _data_dir
from mapd.data import shared_maps as _shared_maps
from mapd.grid import OccupancyGrid, Pose2D

NO_DATA = "shared data folder not found: set MAPD_DATA or place ../shared/data beside the checkout"


@pytest.fixture(scope="session")
def data_dir() -> Path:
    """The shared data folder; tests that use it skip with a clear reason when it is absent."""
    d = _data_dir()
    if d is None:
        pytest.skip(NO_DATA)
    return d


@pytest.fixture(scope="session")
def shared_maps(data_dir: Path) -> list[Path]:
    maps = _shared_maps(data_dir)
    if not maps:
        pytest.skip(f"no map_server YAML under {data_dir}/maps")
    return maps


@pytest.fixture(scope="session")
def intel_log(data_dir: Path) -> Path:
    p = data_dir / "logs" / "intel-corrected.log.gz"
    if not p.exists():
        pytest.skip(f"{p} not found")
    return p


def make_room_grid(
    height: int = 60,
    width: int = 80,
    *,
    seed: int = 0,
    resolution: float = 0.05,
    origin: Pose2D | None = None,
) -> OccupancyGrid:
    """A small synthetic trinary map: unknown outside, a walled room with a box inside, some speckle."""
    rng = np.random.default_rng(seed)
    d = np.full((height, width), -1, dtype=np.int8)
    r0, r1, c0, c1 = height // 6, height - height // 6, width // 8, width - width // 8
    d[r0:r1, c0:c1] = 0
    d[r0, c0:c1] = d[r1 - 1, c0:c1] = 100
    d[r0:r1, c0] = d[r0:r1, c1 - 1] = 100
    br, bc = height // 2, width // 2
    d[br - 3 : br + 3, bc - 4 : bc + 4] = 100
    speck = rng.random((height, width)) < 0.01
    d[speck & (d == 0)] = 100
    return OccupancyGrid(data=d, resolution=resolution, origin=origin or Pose2D(-1.0, -2.0, 0.0))


@pytest.fixture
def room_grid() -> OccupancyGrid:
    return make_room_grid()
