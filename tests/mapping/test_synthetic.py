"""The seeded test and bench maps of :mod:`mapd.mapping.synthetic` stay the same, cell for cell.

The lossless corpus, the golden digests and many tests are built from these exact cells; a digest
that changes here means a generator changed (add a new one instead).
"""

from __future__ import annotations

import hashlib

import numpy as np

from mapd.grid import Pose2D
from mapd.mapping import synthetic


def digest(*arrays: np.ndarray) -> str:
    return hashlib.sha256(b"".join(a.tobytes() for a in arrays)).hexdigest()[:16]


def test_room_grid_is_pinned() -> None:
    g = synthetic.room_grid()
    assert g.data.shape == (60, 80) and g.resolution == 0.05 and g.origin == Pose2D(-1.0, -2.0, 0.0)
    assert digest(g.data) == "3ee2c9487e83d34e"


def test_building_is_pinned() -> None:
    g = synthetic.building()
    assert g.data.shape == (320, 360) and g.origin == Pose2D(-3.0, -4.0, 0.0) and g.robot == "a"
    assert digest(g.data) == "7a4e8cf3ec8a4adb"


def test_indoor_maps_are_pinned() -> None:
    maps = synthetic.indoor_maps()
    assert [label for label, _ in maps] == [f"synthetic/{i}" for i in range(6)]
    assert digest(*(g.data for _, g in maps)) == "a18bb489c5f55fb4"
    # Fewer maps are the first ones: ``mapd bench codec --limit N`` takes a prefix.
    assert all(
        np.array_equal(a.data, b.data)
        for (_, a), (_, b) in zip(synthetic.indoor_maps(2), maps[:2], strict=True)
    )


def test_generators_follow_their_arguments() -> None:
    g = synthetic.room_grid(30, 40, seed=3, resolution=0.1, origin=Pose2D(1.0, 2.0, 0.5))
    assert g.data.shape == (30, 40) and g.resolution == 0.1 and g.origin == Pose2D(1.0, 2.0, 0.5)
    assert set(np.unique(g.data)) <= {-1, 0, 100}
    assert not np.array_equal(synthetic.building(seed=1).data, synthetic.building(seed=2).data)
