"""A stop during a placement search: the search gives up at its next stage, the merge goes on
with what is placed and is saved, and the map it did not place is searched again after a restart.

A search of a large map takes seconds (10 s for two 2,500-cell-wide maps of the shared data), and
a daemon's stop used to wait for it to end.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.config import FusionSection
from mapd.fusion import candidates
from mapd.fusion.estimate import SearchStopped, estimate_transform
from mapd.fusion.placer import STOPPED, Placer
from mapd.fusion.store import GLOBAL_YAML, TRANSFORMS_JSON
from mapd.fusion.worker import FusionWorker
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map

ZERO = Pose2D(0.0, 0.0, 0.0)


@pytest.fixture(scope="module")
def fleet(building: OccupancyGrid) -> dict[str, OccupancyGrid]:
    """a: this robot's map; b and c overlap a (b a lot, c less), neither with a known pose."""

    def crop(r0: int, r1: int, c0: int, c1: int, name: str) -> OccupancyGrid:
        return building.replace(
            data=np.ascontiguousarray(building.data[r0:r1, c0:c1]), origin=ZERO, robot=name
        )

    return {
        "a": crop(0, 220, 0, 170, "a"),
        "b": crop(60, 300, 110, 260, "b"),
        "c": crop(120, 320, 0, 150, "c"),
    }


def _grown(grid: OccupancyGrid) -> OccupancyGrid:
    """``grid``'s next version, with a 6 x 6 block of unknown cells (its corner) now known free."""
    data = grid.data.copy()
    assert (data[:6, :6] < 0).all()  # (the building's outside: unknown)
    data[:6, :6] = 0
    return grid.replace(data=data, version=grid.version + 1)


class _Headings:
    """Counts the headings the correlation search computed (each costs tens of ms on a large map)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.n = 0
        peaks = candidates.Correlator.peaks

        def counted(corr: candidates.Correlator, yaw: float, k: int = 3) -> tuple[list[Any], ...]:
            self.n += 1
            return peaks(corr, yaw, k)

        monkeypatch.setattr(candidates.Correlator, "peaks", counted)


def test_a_search_gives_up_at_the_next_heading_once_stop_says_so(
    fleet: dict[str, OccupancyGrid], monkeypatch: pytest.MonkeyPatch
) -> None:
    headings = _Headings(monkeypatch)
    full = estimate_transform(fleet["a"], fleet["c"])
    assert full.accepted  # (what the stopped search would have found)
    whole = headings.n
    assert whole > 10

    headings.n = 0
    with pytest.raises(SearchStopped):
        estimate_transform(fleet["a"], fleet["c"], stop=lambda: headings.n >= 3)
    assert headings.n == 3  # not one heading more once stop said so

    asked: list[int] = []

    def never() -> bool:
        asked.append(headings.n)
        return False

    headings.n = 0
    again = estimate_transform(fleet["a"], fleet["c"], stop=never)
    assert again == full  # a stop that never says so changes nothing
    assert len(asked) > whole  # asked before every heading at least


def test_a_stopped_update_keeps_what_is_placed_and_searches_the_rest_next_time(
    fleet: dict[str, OccupancyGrid], monkeypatch: pytest.MonkeyPatch
) -> None:
    placer = Placer({}, anchor="a")
    first = placer.update({"a": fleet["a"], "b": fleet["b"]})
    assert first["b"].accepted
    headings = _Headings(monkeypatch)
    maps = {"a": _grown(fleet["a"]), "b": fleet["b"], "c": fleet["c"]}
    got = placer.update(maps, stop=lambda: headings.n >= 1)  # stopped in c's search
    assert headings.n == 1
    assert got["a"].source == "anchor"
    assert got["b"].accepted and got["b"].source == "estimate"  # held (tracked before c's search)
    assert not got["c"].accepted and got["c"].reason == STOPPED
    assert placer.placements["c"].reason == STOPPED
    again = placer.update(maps)
    assert again["c"].accepted and again["c"].source == "estimate"


def _known(grid: OccupancyGrid) -> int:
    return int((grid.data >= 0).sum())


def test_a_stop_during_a_search_returns_without_it_and_the_restart_places_its_map(
    tmp_path: Path, fleet: dict[str, OccupancyGrid], monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = FusionSection(debounce_s=0.0)
    a2 = _grown(fleet["a"])
    searching = threading.Event()
    seen: dict[str, object] = {}
    search = candidates.Correlator.search

    def held_search(corr: candidates.Correlator, *args: Any, **kw: Any) -> list[candidates.Hyp]:
        """c's correlation search: it waits until the stop reaches it (as a long search would still
        run then), and goes on as the search does."""
        stop: Callable[[], bool] = kw["stop"]
        searching.set()
        end = time.monotonic() + 30.0
        while not stop() and time.monotonic() < end:  # polled: the stop comes from the loop's thread
            time.sleep(0.005)
        seen["stop"] = stop()
        try:
            return search(corr, *args, **kw)
        except BaseException as exc:
            seen["raised"] = type(exc)
            raise

    async def first() -> FusionWorker:
        w = FusionWorker("a", cfg, tmp_path)
        w.submit(fleet["a"])
        w.submit(fleet["b"])
        await w.merge_now()
        assert w.placements["b"].accepted  # placed before the stop
        fuse, returned = w._fuse, threading.Event()

        def watched(maps: dict[str, OccupancyGrid], search: bool) -> Any:
            try:
                return fuse(maps, search)
            finally:
                returned.set()

        w._fuse = watched  # type: ignore[method-assign]
        monkeypatch.setattr(candidates.Correlator, "search", held_search)
        headings = _Headings(monkeypatch)
        task = asyncio.create_task(w.run())
        w.submit(a2)  # a new version of this robot's map, and a robot of unknown pose
        w.submit(fleet["c"])
        await asyncio.to_thread(searching.wait, 30.0)
        assert searching.is_set()
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
        # The search saw the stop and gave up before its first heading; the merge's thread was
        # done before the stop returned.
        assert seen == {"stop": True, "raised": SearchStopped} and headings.n == 0
        assert returned.is_set()
        return w

    w = asyncio.run(first())
    monkeypatch.undo()

    # Saved at the stop: a's new version and b where it was placed; c, not placed, left out.
    on_disk = load_map(tmp_path / GLOBAL_YAML)
    assert w.global_map is not None and on_disk.same_map(w.global_map)
    b_at = w.placements["b"].transform
    assert b_at is not None
    expected = FusionWorker(
        "a", FusionSection(debounce_s=0.0, poses={"a": [0.0, 0.0, 0.0], "b": list(b_at)}), None
    )
    expected.submit(a2)
    expected.submit(fleet["b"])
    asyncio.run(expected.merge_now())
    assert expected.global_map is not None and on_disk.same_map(expected.global_map)
    doc = json.loads((tmp_path / TRANSFORMS_JSON).read_text())
    assert doc["robots"]["b"]["accepted"] and not doc["robots"]["c"]["accepted"]
    assert doc["robots"]["c"]["reason"] == STOPPED

    async def restart() -> FusionWorker:
        # As the daemon does at start: its own map and the peers' saved maps are submitted again.
        w = FusionWorker("a", cfg, tmp_path)
        for grid in (a2, fleet["b"], fleet["c"]):
            w.submit(grid)
        await w.merge_now()
        return w

    w2 = asyncio.run(restart())
    st = w2.status()["robots"]
    assert st["c"]["accepted"] and st["c"]["source"] == "estimate" and st["b"]["accepted"]
    assert w2.global_map is not None and _known(w2.global_map) > _known(on_disk)
