"""The mapfile source: rewrites become versions; half-written, broken or vanished files never do."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import numpy as np
import pytest

from mapd import plugins
from mapd.grid import OccupancyGrid, Pose2D, save_map
from mapd.sources.base import SourceContext
from mapd.sources.mapfile import MapFileOptions, MapFileSource


def _grid(k: int) -> OccupancyGrid:
    d = np.full((40, 50), -1, dtype=np.int8)
    d[5 : 10 + k, 5:30] = 0
    d[10 + k, 5:30] = 100
    return OccupancyGrid(d, 0.05, Pose2D(-1.0, -1.0, 0.0))


def _age(path: Path, seconds: float) -> None:
    """Pretend the map files were written ``seconds`` ago (so they count as settled)."""
    for p in (path, path.with_suffix(".pgm")):
        t = time.time() - seconds
        os.utime(p, (t, t))


def _source(path: Path, **kw: float) -> MapFileSource:
    return MapFileSource(MapFileOptions(path=path, **kw), SourceContext(robot="r3"))


def test_registered_under_mapd_sources() -> None:
    assert plugins.load("source", "mapfile") is MapFileSource


def test_rewrites_emit_new_versions_and_touches_do_not(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    src = _source(path, settle_s=0.5)
    state: dict[str, object] = {}
    assert src.check(state, 0.0) is None  # nothing written yet
    assert "vanished or not written yet" in str(src.stats()["last_error"])

    save_map(_grid(0), path)
    _age(path, 10)
    g1 = src.check(state, 1.0)
    assert g1 is not None and g1.version == 1 and g1.robot == "r3" and g1.same_map(_grid(0))
    assert src.check(state, 2.0) is None  # unchanged files: nothing new

    save_map(_grid(3), path)  # a fresh rewrite: waits until it has settled
    assert src.check(state, 3.0) is None
    g2 = src.check(state, 3.6)
    assert g2 is not None and g2.version == 2 and g2.same_map(_grid(3))

    save_map(_grid(3), path)  # same map written again: new mtime, same cells
    _age(path, 5)
    assert src.check(state, 10.0) is None
    assert src.stats()["versions"] == 2


def test_half_written_image_is_retried_never_emitted(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    save_map(_grid(0), path)
    _age(path, 10)
    src = _source(path, settle_s=0.2)
    state: dict[str, object] = {}
    assert src.check(state, 0.0) is not None
    # A writer died half-way through the image: the files settle, but the map must not be emitted.
    pgm = path.with_suffix(".pgm")
    save_map(_grid(5), tmp_path / "full.yaml")
    whole = (tmp_path / "full.pgm").read_bytes()
    pgm.write_bytes(whole[: len(whole) // 2])
    _age(path, 10)
    assert src.check(state, 1.0) is None
    assert src.check(state, 2.0) is None
    st = src.stats()
    assert st["load_errors"] == 1 and "map.yaml" in str(st["last_error"]) and st["versions"] == 1
    # The writer finishes: the next check emits the complete map.
    pgm.write_bytes(whole)
    _age(path, 10)
    g = src.check(state, 3.0)
    assert g is not None and g.version == 2 and g.same_map(_grid(5))


def test_half_written_yaml_and_vanished_files(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    save_map(_grid(1), path)
    _age(path, 10)
    src = _source(path, settle_s=0.0)
    state: dict[str, object] = {}
    assert src.check(state, 0.0) is not None
    full = path.read_text()
    path.write_text(full[: full.index("resolution") + 5])  # cut in the middle of a key
    assert src.check(state, 1.0) is None
    path.unlink()
    assert src.check(state, 2.0) is None
    assert "vanished" in str(src.stats()["last_error"])
    save_map(_grid(2), path)
    g = src.check(state, 3.0)
    assert g is not None and g.version == 2 and g.same_map(_grid(2))


def test_stream_picks_up_rewrites(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    save_map(_grid(0), path)
    _age(path, 10)
    src = _source(path, poll_s=0.05, settle_s=0.1)

    async def go() -> list[OccupancyGrid]:
        out: list[OccupancyGrid] = []
        it = src.maps().__aiter__()
        out.append(await asyncio.wait_for(it.__anext__(), 5))
        await asyncio.to_thread(save_map, _grid(4), path)
        out.append(await asyncio.wait_for(it.__anext__(), 5))
        await it.aclose()  # type: ignore[attr-defined]
        return out

    maps = asyncio.run(go())
    assert [g.version for g in maps] == [1, 2]
    assert maps[1].same_map(_grid(4))


def test_start_pose_option() -> None:
    src = MapFileSource(
        MapFileOptions(path=Path("x.yaml"), start_pose=[1.0, 2.0, 0.5]), SourceContext(robot="r")
    )
    assert src.start_pose() == Pose2D(1.0, 2.0, 0.5)
    with pytest.raises(ValueError):
        MapFileOptions(path=Path("x.yaml"), start_pose=[1.0])
