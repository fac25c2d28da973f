"""Small hand-made fleets for the swarm bench's tests (``swarm`` fixture)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from mapd.bench.swarm.streams import Building, Fleet, RobotStream
from mapd.codec import encode
from mapd.grid import OccupancyGrid


def stream(i: int, xy: tuple[float, float], versions: int = 3, period: float = 30.0) -> RobotStream:
    """A robot standing at ``xy`` whose map grows by a row of cells every ``period`` seconds."""
    data = np.full((8, 16), -1, dtype=np.int8)
    kfs = []
    for v in range(versions):
        data[v % 8, :] = 0
        data[v % 8, (i + v) % 16] = 100
        kfs.append(encode(OccupancyGrid(data.copy(), 0.05), "lossless"))
    poses = np.tile(np.asarray(xy, dtype=np.float64), (10, 1))
    return RobotStream(f"r{i}", f"test-{i}", [v * period for v in range(versions)], kfs, poses)


def fleet(positions: list[tuple[float, float]], building: Building | None = None) -> Fleet:
    """Robots standing at ``positions`` (metres), each with a :func:`stream`."""
    return Fleet([stream(i, xy) for i, xy in enumerate(positions)], building, "test")


@pytest.fixture
def swarm() -> SimpleNamespace:
    """The helpers above, for test modules (importlib mode keeps conftest out of reach of imports)."""
    return SimpleNamespace(stream=stream, fleet=fleet)
