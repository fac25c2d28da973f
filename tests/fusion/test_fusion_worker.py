"""FusionWorker: debounced merges in a thread, atomic state files, restart, callbacks, status."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest

from mapd.config import FusionSection
from mapd.errors import FusionError
from mapd.fusion.placement import Placement
from mapd.fusion.store import GLOBAL_YAML, TRANSFORMS_JSON
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map

ZERO = Pose2D(0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def fleet(building: OccupancyGrid) -> dict[str, OccupancyGrid]:
    def crop(r0: int, r1: int, c0: int, c1: int, name: str) -> OccupancyGrid:
        return building.replace(
            data=np.ascontiguousarray(building.data[r0:r1, c0:c1]), origin=ZERO, robot=name
        )

    return {"a": crop(0, 220, 0, 170, "a"), "b": crop(60, 300, 110, 260, "b")}


async def _until(cond: object, timeout: float = 20.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while not cond():  # type: ignore[operator]
        if loop.time() > end:
            raise AssertionError("condition not reached in time")
        await asyncio.sleep(0.02)


def test_merges_writes_state_publishes_and_reports(tmp_path: Path, fleet: dict[str, OccupancyGrid]) -> None:
    got: list[OccupancyGrid] = []

    def broken(_grid: OccupancyGrid) -> None:
        raise RuntimeError("sink down")

    async def main() -> dict[str, object]:
        w = FusionWorker("a", FusionSection(debounce_s=0.05), tmp_path, [broken, got.append])
        task = asyncio.create_task(w.run())
        w.submit(fleet["a"])
        w.submit(fleet["b"].replace(version=7))
        await _until(lambda: w.status()["maps"] == 2)
        st = w.status()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        assert w.global_map is not None and got and got[-1] is w.global_map
        return st

    st = asyncio.run(main())
    json.dumps(st)  # JSON-able
    b = st["robots"]["b"]  # type: ignore[index]
    assert b["accepted"] and b["source"] == "estimate" and b["version"] == 7
    assert math.isclose(b["x"], 110 * 0.05, abs_tol=0.1) and math.isclose(b["y"], 60 * 0.05, abs_tol=0.1)
    assert st["fleet_frame"] == "map frame of robot 'a'" and st["last_merge_s"] is not None
    doc = json.loads((tmp_path / TRANSFORMS_JSON).read_text())
    assert doc["robots"]["b"]["accepted"] and "meters" in doc["units"]
    glob = load_map(tmp_path / GLOBAL_YAML)
    assert glob.origin.yaw == 0.0 and glob.cells >= fleet["a"].cells
    assert not list(tmp_path.glob(".*tmp*"))  # no temp files left behind


def test_restart_keeps_map_and_placements(tmp_path: Path, fleet: dict[str, OccupancyGrid]) -> None:
    async def first() -> None:
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()

    async def second() -> tuple[OccupancyGrid | None, dict[str, object], OccupancyGrid | None]:
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path)
        task = asyncio.create_task(w.run())
        await _until(lambda: w.global_map is not None)
        before = w.global_map
        w.submit(fleet["a"])  # b has not come back yet
        await _until(lambda: w.status()["merges"] >= 2)
        after = w.global_map
        st = w.status()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        return before, st, after

    asyncio.run(first())
    saved = load_map(tmp_path / GLOBAL_YAML)
    before, st, after = asyncio.run(second())
    assert before is not None and before.same_map(saved)
    assert st["restored_until"] == ["b"]
    assert st["robots"]["b"]["accepted"]  # type: ignore[index]
    # b's cells are still in the map although only a was merged since the restart
    assert after is not None and after.origin == saved.origin
    assert int((after.data >= 0).sum()) == int((saved.data >= 0).sum())


def test_known_poses_and_cancel_flush(tmp_path: Path, fleet: dict[str, OccupancyGrid]) -> None:
    pb = [5.0, 2.0, 0.3]
    cfg = FusionSection(debounce_s=30.0, poses={"a": [1.0, 1.0, 0.0], "b": pb})

    async def main() -> None:
        w = FusionWorker("a", cfg, tmp_path)
        task = asyncio.create_task(w.run())
        await asyncio.sleep(0.05)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await asyncio.sleep(0.05)
        task.cancel()  # long debounce: the pending update is flushed on the way out
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(main())
    doc = json.loads((tmp_path / TRANSFORMS_JSON).read_text())
    b = doc["robots"]["b"]
    assert b["source"] == "pose" and [b["x"], b["y"], b["yaw"]] == pb
    assert (tmp_path / GLOBAL_YAML).exists()


def test_submit_needs_a_robot_and_caps_robots(fleet: dict[str, OccupancyGrid]) -> None:
    async def main() -> None:
        w = FusionWorker("a", FusionSection(), None, max_robots=1)
        with pytest.raises(FusionError):
            w.submit(fleet["a"].replace(robot=""))
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        assert w.status()["dropped"] == 1 and list(w.status()["robots"]) == ["a"]

    asyncio.run(main())


def _known(grid: OccupancyGrid | None) -> int:
    assert grid is not None
    return int((grid.data >= 0).sum())


def test_a_revoked_robots_map_leaves_the_global_map(tmp_path: Path, fleet: dict[str, OccupancyGrid]) -> None:
    # b sits 30 m east of a: the global map's east part is b's alone.
    cfg = FusionSection(debounce_s=0.0, poses={"a": [0.0, 0.0, 0.0], "b": [30.0, 0.0, 0.0]})

    async def main() -> None:
        w = FusionWorker("a", cfg, tmp_path)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        both = w.global_map
        assert both is not None and both.width > fleet["a"].width + fleet["b"].width
        assert w.forget("b") and not w.forget("b")  # the second time there is nothing left of it
        await w.merge_now()
        alone = w.global_map
        # As if b had never been merged: its cells are gone, and so is the room the map grew to.
        fresh = FusionWorker("a", cfg, None)
        fresh.submit(fleet["a"])
        await fresh.merge_now()
        assert fresh.global_map is not None and alone is not None
        assert alone.same_map(fresh.global_map) and alone.width < both.width
        assert _known(alone) == _known(fleet["a"])
        st = w.status()
        assert set(st["robots"]) == {"a"} and st["maps"] == 1 and st["revoked"] == 1
        doc = json.loads((tmp_path / TRANSFORMS_JSON).read_text())
        assert set(doc["robots"]) == {"a"}
        with pytest.raises(FusionError):
            w.forget("a")  # its own map is not the roster's to take

    asyncio.run(main())


def test_a_robot_revoked_while_a_merge_runs_is_in_no_global_map_after(
    tmp_path: Path, fleet: dict[str, OccupancyGrid]
) -> None:
    """A merge runs on a worker thread with the maps it began with. Revoking a robot meanwhile
    used to let that merge's result, with the revoked map in it, go out and show in the status
    until the next merge (a SIGHUP test caught it)."""
    import threading

    cfg = FusionSection(debounce_s=0.0, poses={"a": [0.0, 0.0, 0.0], "b": [30.0, 0.0, 0.0]})
    published: list[OccupancyGrid] = []

    async def main() -> None:
        w = FusionWorker("a", cfg, tmp_path, [published.append])
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()  # both merged once: b has a placement
        assert set(w.status()["robots"]) == {"a", "b"}
        published.clear()
        w.submit(fleet["b"].replace(version=2))
        started, release = threading.Event(), threading.Event()
        fuse = w._fuse

        def slow_fuse(maps: dict[str, OccupancyGrid], search: bool):  # type: ignore[no-untyped-def]
            started.set()
            release.wait(10)
            return fuse(maps, search)

        w._fuse = slow_fuse  # type: ignore[method-assign]
        merging = asyncio.create_task(w.merge_now())
        await asyncio.to_thread(started.wait, 10)
        assert w.forget("b")  # revoked while the merge with b's map runs
        assert "b" not in w.status()["robots"]  # gone for whoever asks, though the merge still runs
        release.set()
        await merging
        assert published == [] and "b" not in w.status()["robots"]
        w._fuse = fuse  # type: ignore[method-assign]
        await w.merge_now()
        assert len(published) == 1 and set(w.status()["robots"]) == {"a"}
        assert _known(published[0]) == _known(fleet["a"])

    asyncio.run(main())


def test_a_stop_during_a_merge_waits_for_it_before_the_last_merge(
    tmp_path: Path, fleet: dict[str, OccupancyGrid]
) -> None:
    """A stop cancels the worker while a merge runs on its thread; the stop then merges what is
    pending. That last merge used to start at once, beside the thread it could not stop: two merges
    shared the placer, and the older one saved its global map (here with a revoked robot) after
    the newer one, so the state directory held the revoked map after the stop."""
    import threading

    cfg = FusionSection(debounce_s=0.0, poses={"a": [0.0, 0.0, 0.0], "b": [30.0, 0.0, 0.0]})
    guard = threading.Lock()
    active = [0, 0]  # merges on threads now, most at once

    async def main() -> FusionWorker:
        w = FusionWorker("a", cfg, tmp_path)
        started, release = threading.Event(), threading.Event()
        fuse = w._fuse

        def slow_fuse(maps: dict[str, OccupancyGrid], search: bool):  # type: ignore[no-untyped-def]
            with guard:
                active[0] += 1
                active[1] = max(active)
            try:
                started.set()
                release.wait(10)
                return fuse(maps, search)
            finally:
                with guard:
                    active[0] -= 1

        w._fuse = slow_fuse  # type: ignore[method-assign]
        task = asyncio.create_task(w.run())
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await asyncio.to_thread(started.wait, 10)
        assert w.forget("b")  # revoked while the merge with b's map runs; the stop comes next
        task.cancel()
        threading.Timer(0.5, release.set).start()
        with pytest.raises(asyncio.CancelledError):
            await task
        return w

    w = asyncio.run(main())
    assert active[1] == 1  # never two merges at once
    assert w.global_map is not None and _known(w.global_map) == _known(fleet["a"])
    on_disk = load_map(tmp_path / GLOBAL_YAML)
    assert _known(on_disk) == _known(fleet["a"])  # the last map saved is the one without b


def test_a_robot_revoked_across_a_restart_leaves_no_cells_behind(
    tmp_path: Path, fleet: dict[str, OccupancyGrid]
) -> None:
    async def first() -> int:
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        return _known(w.global_map)

    async def restart(admits: object, forget: bool) -> tuple[dict[str, object], int]:
        w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path, admits=admits)  # type: ignore[arg-type]
        await asyncio.to_thread(w._load_state)
        w._loaded = True
        if forget:  # revoked by a reload after the restart, before b was heard again
            assert w.forget("b")
        w.submit(fleet["a"])
        await w.merge_now()
        return w.status(), _known(w.global_map)

    both = asyncio.run(first())
    assert both > _known(fleet["a"])
    for admits, forget in ((lambda r: r != "b", False), (lambda r: True, True)):
        st, known = asyncio.run(restart(admits, forget))
        # Not restored: the cells of a alone, where a plain restart keeps b's until it is back.
        assert known == _known(fleet["a"]) and st["restored_until"] == [] and set(st["robots"]) == {"a"}
        assert st["revoked"] == 1
        asyncio.run(first())  # b back in the state directory for the next variant


def test_a_base_station_keeps_its_fleet_frame_when_the_robot_that_fixed_it_is_revoked(
    fleet: dict[str, OccupancyGrid],
) -> None:
    # No map of its own: the first robot by name (a) fixed the fleet frame, b was placed in it.
    async def main() -> None:
        w = FusionWorker("base", FusionSection(debounce_s=0.0), None, anchor=None)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        placed = w.placements["b"]
        assert placed.accepted and placed.source == "estimate" and placed.transform is not None
        assert w.forget("a")
        w.submit(fleet["b"].replace(version=2))
        await w.merge_now()
        # b stays where it was, and so does its map in the global map: nothing waits for a.
        now = w.placements["b"]
        assert now.accepted and now.transform == placed.transform and "held where it was" in now.reason
        g = w.global_map
        assert g is not None and _known(g) == _known(fleet["b"]) and set(w.status()["robots"]) == {"b"}

    asyncio.run(main())


def test_placements_that_rest_on_a_revoked_robots_map_are_not_restored(tmp_path: Path) -> None:
    # Saved by a run that trusted b: c was placed against b's map, d against a's own.
    t = Pose2D(3.0, -1.0, 0.2)
    saved = {
        "a": Placement("a", ZERO, "anchor", True, 1.0, None, "its map frame is the fleet frame"),
        "b": Placement("b", t, "estimate", True, 0.9, 0.95, "", against="a"),
        "c": Placement("c", t, "estimate", True, 0.9, 0.95, "", against="b"),
        "d": Placement("d", t, "estimate", True, 0.9, 0.95, "", against="a"),
    }
    doc = {"version": 4, "robots": {r: p.as_dict() for r, p in saved.items()}}
    (tmp_path / TRANSFORMS_JSON).write_text(json.dumps(doc))
    w = FusionWorker("a", FusionSection(debounce_s=0.0), tmp_path, admits=lambda r: r != "b")
    w._load_state()
    assert set(w.placements) == {"a", "d"} and set(w.placer.placements) == {"d"}
    assert w.placer.placements["d"].transform == t and w.forgotten == 1


def test_a_placement_found_against_another_robots_map_follows_it_across_a_restart(
    tmp_path: Path, building: OccupancyGrid
) -> None:
    # c overlaps b only, and is found against b's map; b's configured pose was 3 m off, and the
    # daemon is restarted with it put right. c follows b at once (transforms.json says where b
    # was when c was found against it), as it does when the pose is put right without a restart.
    def crop(r0: int, r1: int, c0: int, c1: int, name: str) -> OccupancyGrid:
        data = np.ascontiguousarray(building.data[r0:r1, c0:c1])
        return building.replace(data=data, origin=ZERO, robot=name)

    maps = [crop(0, 220, 0, 170, "a"), crop(60, 300, 110, 260, "b"), crop(80, 320, 210, 360, "c")]
    truth_b, truth_c = Pose2D(110 * 0.05, 60 * 0.05, 0.0), Pose2D(210 * 0.05, 80 * 0.05, 0.0)

    async def run(pose_b: Pose2D) -> dict[str, Placement]:
        poses = {"a": [0.0, 0.0, 0.0], "b": list(pose_b), "c": "estimate"}
        w = FusionWorker("a", FusionSection(debounce_s=0.0, poses=poses), tmp_path)
        for g in maps:
            w.submit(g)
        await w.merge_now()
        return w.placements

    first = asyncio.run(run(Pose2D(truth_b.x + 3.0, truth_b.y, 0.0)))["c"]
    assert first.accepted and first.against == "b" and first.transform is not None
    assert math.isclose(first.transform.x, truth_c.x + 3.0, abs_tol=0.1)
    doc = json.loads((tmp_path / TRANSFORMS_JSON).read_text())
    assert doc["robots"]["c"]["against_at"] == {"x": truth_b.x + 3.0, "y": truth_b.y, "yaw": 0.0}
    c = asyncio.run(run(truth_b))["c"]
    assert c.accepted and c.against == "b" and c.transform is not None, c
    assert math.isclose(c.transform.x, truth_c.x, abs_tol=0.1), c
    assert math.isclose(c.transform.y, truth_c.y, abs_tol=0.1), c
