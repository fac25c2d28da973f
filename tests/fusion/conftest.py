"""Fixtures for the fusion tests: a procedural building that needs no shared data."""

from __future__ import annotations

import pytest

from mapd.grid import OccupancyGrid
from mapd.mapping.synthetic import building as make_building


@pytest.fixture(scope="session")
def building() -> OccupancyGrid:
    return make_building()


@pytest.fixture(scope="session")
def make_building_map() -> object:
    """The generator itself, for tests that need other seeds or sizes."""
    return make_building
