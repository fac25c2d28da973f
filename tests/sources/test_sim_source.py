"""The sim source: generated buildings, the simulated lidar, routes, determinism, fleets."""

from __future__ import annotations

import asyncio
import itertools
import math
from pathlib import Path

import numpy as np
import pytest
from pydantic import ValidationError

from mapd import plugins
from mapd.grid import OCCUPIED, OccupancyGrid, Pose2D
from mapd.grid.save import save_map
from mapd.mapping import worldgen
from mapd.mapping.lidar import Lidar
from mapd.mapping.replay import resample
from mapd.mapping.simrobot import Planner
from mapd.sources.base import SourceContext
from mapd.sources.sim import SimOptions, SimSource


def _run(src: SimSource) -> list[OccupancyGrid]:
    async def go() -> list[OccupancyGrid]:
        return [g async for g in src.maps()]

    return asyncio.run(go())


def test_registered_under_mapd_sources() -> None:
    assert plugins.load("source", "sim") is SimSource


def test_world_is_deterministic_for_a_seed_and_varies_between_seeds() -> None:
    a, b, c = worldgen.generate(7), worldgen.generate(7), worldgen.generate(8)
    assert a.grid.same_map(b.grid) and a.goals == b.goals
    assert not a.grid.same_map(c.grid)
    # 30 x 20 m at 0.05 m plus a 1 m margin; mostly free inside, walls around.
    assert (a.grid.width, a.grid.height) == (640, 440)
    counts = a.grid.counts()
    assert counts["free"] > 0.7 * 600 * 400 and counts["occupied"] > 0.03 * 600 * 400
    assert len(a.rooms) >= 8


def test_every_room_can_be_reached_through_its_doors() -> None:
    w = worldgen.generate(3)
    planner = Planner(w, clearance=0.3)
    assert w.corridor is not None
    start = (w.corridor[0] + 1.0, w.corridor[2])
    for room in w.rooms:
        path = planner.path(start, room.center)
        assert path is not None, f"room at {room.center} unreachable"
        # Every leg of the path keeps the clearance (no shortcut through a wall).
        legs = [start, *path]
        assert all(planner.visible(p, q) for p, q in itertools.pairwise(legs))


def test_lidar_ranges_in_a_known_room(box_world: OccupancyGrid) -> None:
    occ = box_world.data == OCCUPIED
    lidar = Lidar(
        occ, 0.05, box_world.origin, beams=4, fov_deg=360.0, max_range=12.0, noise_std=0.0, dropout=0.0
    )
    # Room 8 m wide with 0.15 m walls; from (2, 2) facing +x the beams go +x, +y, -x, -y.
    r = lidar.scan(Pose2D(2.0, 2.0, math.pi / 2 - math.pi / 2))
    assert lidar.angles.tolist() == pytest.approx([-math.pi, -math.pi / 2, 0.0, math.pi / 2])
    # -x: wall inner face at 0.15 m -> 1.85 m; +x: 8 - 0.15 - 2 = 5.85 m (first sample inside the wall).
    assert r[0] == pytest.approx(1.85, abs=0.05) and r[2] == pytest.approx(5.85, abs=0.05)
    short = Lidar(
        occ, 0.05, box_world.origin, beams=1, fov_deg=1.0, max_range=3.0, noise_std=0.0, dropout=0.0
    )
    assert math.isinf(short.scan(Pose2D(2.0, 2.0, 0.0))[0])  # wall beyond max range: no return
    noisy = Lidar(occ, 0.05, box_world.origin, beams=2000, max_range=12.0, noise_std=0.02, dropout=0.1)
    out = noisy.scan(Pose2D(4.0, 3.0, 0.3), np.random.default_rng(1))
    assert 0.07 < np.isinf(out).mean() < 0.13


def test_same_seed_same_maps_and_versions() -> None:
    opts = SimOptions(seed=11, robots=2, index=1, realtime=0, duration=12.0, emit_period=4.0)
    a = _run(SimSource(opts, SourceContext(robot="r1")))
    b = _run(SimSource(opts, SourceContext(robot="r1")))
    assert [g.version for g in a] == [1, 2, 3, 4]
    assert [g.stamp for g in a] == pytest.approx([0.2, 4.2, 8.2, 12.0])
    assert [g.digest() for g in a] == [g.digest() for g in b]
    assert all(g.robot == "r1" for g in a)
    # The map grows as the robot drives.
    known = [g.cells - g.counts()["unknown"] for g in a]
    assert known[-1] > known[0]
    other = _run(SimSource(opts.model_copy(update={"seed": 12}), SourceContext(robot="r1")))
    assert other[-1].digest() != a[-1].digest()


def test_fleet_slots_start_apart_and_cover_more_together() -> None:
    srcs = [
        SimSource(SimOptions(seed=5, robots=2, index=i, realtime=0, duration=60.0, emit_period=60.0),
                  SourceContext(robot=f"r{i}"))
        for i in range(2)
    ]  # fmt: skip
    starts = [s.start_pose() for s in srcs]
    assert math.dist(starts[0][:2], starts[1][:2]) > 5.0
    finals = [_run(s)[-1] for s in srcs]
    world = srcs[0].sim.world.grid
    seen = []
    for g, pose in zip(finals, starts, strict=True):
        # Each map is in its robot's own frame; start_pose puts it back into the world (fleet) frame.
        in_world = resample(g, pose, world)
        seen.append(in_world.data != -1)
        agree = (in_world.data == 100) & (world.data == OCCUPIED)
        assert agree.sum() > 0.5 * (in_world.data == 100).sum()  # its walls are the world's walls
    free = world.data == 0
    alone = max((s & free).sum() for s in seen)
    together = ((seen[0] | seen[1]) & free).sum()
    assert together > 1.2 * alone


def test_explicit_and_random_starts() -> None:
    s = SimSource(SimOptions(start=[3.0, 9.75, 0.5], realtime=0, duration=1.0), SourceContext(robot="r"))
    assert s.start_pose() == Pose2D(3.0, 9.75, 0.5)
    r1 = SimSource(SimOptions(start="random", seed=4, realtime=0), SourceContext(robot="r")).start_pose()
    r2 = SimSource(SimOptions(start="random", seed=4, realtime=0), SourceContext(robot="r")).start_pose()
    assert r1 == r2
    # A random start is a free cell where the robot fits.
    sim = s.sim
    fr, fc = sim.world.grid.world_to_cell(np.array(r1.x), np.array(r1.y))
    assert sim.planner.clear[int(np.floor(fr)), int(np.floor(fc))] >= sim.planner.clearance


def test_loaded_map_as_world(box_world: OccupancyGrid, tmp_path: Path) -> None:
    path = save_map(box_world, tmp_path / "room.yaml")
    src = SimSource(
        SimOptions(world=path, realtime=0, duration=10.0, emit_period=5.0, beams=180),
        SourceContext(robot="r"),
    )
    maps = _run(src)
    assert len(maps) == 3 and src.stats()["goals_reached"] >= 1
    assert maps[-1].counts()["occupied"] > 200


def test_bad_world_and_options() -> None:
    from mapd.errors import SourceError

    src = SimSource(SimOptions(world=Path("/nonexistent/map.yaml"), realtime=0), SourceContext(robot="r"))
    with pytest.raises(SourceError, match="no such map file"):
        src.start_pose()
    with pytest.raises(ValidationError):
        SimOptions(robots=2, index=2)
    with pytest.raises(ValidationError):
        SimOptions(start=[1.0, 2.0])
    big = SimSource(SimOptions(width_m=500, height_m=500, world_resolution=0.01), SourceContext(robot="r"))
    with pytest.raises(SourceError, match="over the limit"):
        big.start_pose()


def test_realtime_factor_paces_sim_time() -> None:
    import time

    src = SimSource(SimOptions(realtime=4.0, duration=2.0, emit_period=1.0), SourceContext(robot="r"))
    src.start_pose()  # build the world first: only the driving is timed
    t0 = time.perf_counter()
    maps = _run(src)
    took = time.perf_counter() - t0
    assert [g.stamp for g in maps] == pytest.approx([0.2, 1.2, 2.0])
    assert 0.45 <= took < 5.0  # 2 sim seconds at 4x real time


def test_driving_and_mapping_run_off_the_event_loop(monkeypatch: pytest.MonkeyPatch) -> None:
    """A scan's ray-casting and mapping, and each snapshot, are CPU work: never on the loop's
    thread, where they would delay every timer and link of the daemon (the demo's source)."""
    import threading

    from mapd.mapping.mapper import Mapper

    seen: dict[str, set[int]] = {"integrate": set(), "snapshot": set()}
    integrate, snapshot = Mapper.integrate, Mapper.snapshot

    def spy(name: str, fn: object) -> object:
        def wrapped(*a: object, **k: object) -> object:
            seen[name].add(threading.get_ident())
            return fn(*a, **k)  # type: ignore[operator]

        return wrapped

    monkeypatch.setattr(Mapper, "integrate", spy("integrate", integrate))
    monkeypatch.setattr(Mapper, "snapshot", spy("snapshot", snapshot))
    src = SimSource(SimOptions(seed=3, duration=4.0, realtime=0, emit_period=2.0), SourceContext(robot="r1"))

    async def go() -> tuple[int, list[OccupancyGrid]]:
        return threading.get_ident(), [g async for g in src.maps()]

    loop_thread, maps = asyncio.run(go())
    assert len(maps) >= 2
    for name, threads in seen.items():
        assert threads and loop_thread not in threads, name


@pytest.mark.parametrize("seed", [-1, 1 << 63])
def test_a_seed_numpy_refuses_is_refused_by_the_config(seed: int) -> None:
    """seed = -1 passed check-config, then the source failed with numpy's ValueError traceback."""
    with pytest.raises(ValueError, match="seed"):
        SimOptions(seed=seed)
