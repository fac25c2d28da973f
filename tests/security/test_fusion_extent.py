"""A map with an absurd origin is left out of the global map; the others keep merging.

Before the fix a peer map with origin x = 1e6 m made every merge fail (the global map would have
been 20,000,320 x 320 cells): the receiver's global map froze until that robot sent a sane version.
"""

from __future__ import annotations

import asyncio

import numpy as np
import pytest
from pydantic import ValidationError

from mapd.config import FusionSection
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid, Pose2D
from mapd.mapping.synthetic import building

RES = 0.05


@pytest.fixture(scope="module")
def fleet() -> dict[str, OccupancyGrid]:
    world = building()

    def crop(r0: int, r1: int, c0: int, c1: int, name: str) -> OccupancyGrid:
        return world.replace(data=np.ascontiguousarray(world.data[r0:r1, c0:c1]), origin=Pose2D(), robot=name)

    return {"a": crop(0, 220, 0, 170, "a"), "b": crop(60, 300, 110, 260, "b")}


def _poses(b_x: float = 110 * RES) -> dict[str, list[float] | str]:
    return {"a": [0.0, 0.0, 0.0], "b": [b_x, 60 * RES, 0.0]}


def _changed(g: OccupancyGrid, version: int) -> OccupancyGrid:
    data = g.data.copy()
    data[10:20, 10:20] = 100  # a new box in a's map
    return g.replace(data=data, version=version)


@pytest.mark.parametrize("origin", [Pose2D(1e6, 0.0, 0.0), Pose2D(0.0, -2e4, 0.0)])
def test_far_origin_is_left_out_and_the_global_map_keeps_updating(
    fleet: dict[str, OccupancyGrid], origin: Pose2D
) -> None:
    async def main() -> None:
        w = FusionWorker("a", FusionSection(debounce_s=0.0, poses=_poses()), None)
        w.submit(fleet["a"])
        w.submit(fleet["b"].replace(version=1))
        await w.merge_now()
        before = w.global_map
        assert w.status()["maps"] == 2 and before is not None
        w.submit(fleet["b"].replace(version=2, origin=origin))
        a2 = _changed(fleet["a"], 2)
        w.submit(a2)
        await w.merge_now()
        st = w.status()
        assert st["error"] is None and st["merges"] == 2 and st["maps"] == 1
        b = st["robots"]["b"]
        assert not b["accepted"] and "fusion.max_extent_m = 10000 m" in b["reason"]
        assert st["robots"]["a"]["accepted"]
        g = w.global_map
        assert g is not None and g is not before and g.cells <= before.cells
        # a's new box is in the global map (a's frame is the fleet frame here)
        rows, cols = g.world_to_cell(np.array([15 * RES]), np.array([15 * RES]))
        assert g.data[int(rows[0]), int(cols[0])] == 100
        # b's next sane version goes back in, placed as before
        w.submit(fleet["b"].replace(version=3))
        await w.merge_now()
        st = w.status()
        assert (
            st["maps"] == 2
            and st["robots"]["b"]["accepted"]
            and st["robots"]["b"]["reason"] == "configured pose"
        )

    asyncio.run(main())


def test_a_map_within_the_extent_but_over_the_cell_limit_is_left_out(fleet: dict[str, OccupancyGrid]) -> None:
    # 5 km away is within a 10 km extent, but at 5 cm it would make the global map 100,000 cells wide.
    async def main() -> None:
        cfg = FusionSection(debounce_s=0.0, poses=_poses(b_x=5000.0))
        w = FusionWorker("a", cfg, None)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        st = w.status()
        assert st["error"] is None and st["merges"] == 1 and st["maps"] == 1
        b = st["robots"]["b"]
        assert not b["accepted"] and "over the limit of" in b["reason"]
        assert w.global_map is not None and w.global_map.cells < 1_000_000

    asyncio.run(main())


def test_the_extent_is_configurable(fleet: dict[str, OccupancyGrid]) -> None:
    async def main() -> None:
        w = FusionWorker("a", FusionSection(debounce_s=0.0, poses=_poses(), max_extent_m=16.0), None)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        st = w.status()  # a reaches 13.9 m from the origin, b 19.9 m
        assert st["robots"]["a"]["accepted"] and not st["robots"]["b"]["accepted"]
        assert (
            "it reaches 19.85 m from the fleet frame's origin, beyond fusion.max_extent_m = 16 m"
            in st["robots"]["b"]["reason"]
        )

    asyncio.run(main())
    for bad in (0.0, -1.0, 1e9):
        with pytest.raises(ValidationError):
            FusionSection(max_extent_m=bad)


def test_a_map_left_out_is_said_once_while_it_stays_out(
    fleet: dict[str, OccupancyGrid], caplog: pytest.LogCaptureFixture
) -> None:
    # It was said again at every merge: a warning a merge for as long as the robot sent such maps.
    async def main() -> None:
        w = FusionWorker("a", FusionSection(debounce_s=0.0, poses=_poses()), None)
        w.submit(fleet["b"].replace(version=1, origin=Pose2D(1e6, 0.0, 0.0)))
        for v in range(1, 5):
            w.submit(_changed(fleet["a"], v))
            await w.merge_now()
        w.submit(fleet["b"].replace(version=2))  # back in
        await w.merge_now()
        w.submit(fleet["b"].replace(version=3, origin=Pose2D(1e6, 0.0, 0.0)))  # out again: said again
        await w.merge_now()

    with caplog.at_level("WARNING", logger="mapd.fusion"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records if "left out of the global map" in r.getMessage()]
    assert len(said) == 2 and all(m.startswith("fusion: b: ") for m in said), said
