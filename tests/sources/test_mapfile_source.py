"""The mapfile source: rewrites become versions; half-written, broken or vanished files never do."""

from __future__ import annotations

import asyncio
import os
import time
from pathlib import Path

import numpy as np
import pytest

from mapd import plugins
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.save import save_map
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


def _watching(path: Path, k: int, settle_s: float) -> tuple[MapFileSource, dict[str, object]]:
    """A source whose first check emitted ``_grid(k)``, saved at ``path`` long ago; and its state."""
    save_map(_grid(k), path)
    _age(path, 10)
    src = _source(path, settle_s=settle_s)
    state: dict[str, object] = {}
    first = src.check(state, 0.0)
    assert first is not None and first.same_map(_grid(k))
    return src, state


def test_registered_under_mapd_sources() -> None:
    assert plugins.load("source", "mapfile") is MapFileSource


def test_rewrites_emit_new_versions_and_touches_do_not(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    src = _source(path, settle_s=0.5)
    state: dict[str, object] = {}
    assert src.check(state, 0.0) is None  # nothing written yet: a fault once it has lasted settle_s
    assert src.stats()["load_errors"] == 0
    assert src.check(state, 0.6) is None
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
    src, state = _watching(path, 0, settle_s=0.2)
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
    src, state = _watching(path, 1, settle_s=0.0)
    full = path.read_text()
    path.write_text(full[: full.index("resolution") + 5])  # cut in the middle of a key
    assert src.check(state, 1.0) is None
    path.unlink()
    assert src.check(state, 2.0) is None
    assert "vanished" in str(src.stats()["last_error"])
    save_map(_grid(2), path)
    g = src.check(state, 3.0)
    assert g is not None and g.version == 2 and g.same_map(_grid(2))


def test_a_writer_mid_way_through_the_yaml_is_not_a_fault(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # map_saver rewrites the YAML in place: a poll between its truncate and its write reads nothing.
    path = tmp_path / "map.yaml"
    src, state = _watching(path, 1, settle_s=0.3)
    whole = path.read_text()
    with caplog.at_level("WARNING", logger="mapd.sources.mapfile"):
        path.write_text("")
        assert src.check(state, 1.0) is None
        path.write_text(whole[: whole.index("resolution") + 5])
        assert src.check(state, 1.1) is None
        path.write_text(whole)
        assert src.check(state, 1.2) is None
        assert src.check(state, 2.0) is None  # settled, loads, and it is the same map: nothing new
    st = src.stats()
    assert st["load_errors"] == 0 and st["last_error"] == "" and st["versions"] == 1
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    # A YAML that stays broken is still a fault, once it has lasted settle_s.
    path.write_text(whole[: whole.index("resolution") + 5])
    assert src.check(state, 3.0) is None and src.stats()["load_errors"] == 0
    assert src.check(state, 3.4) is None
    assert src.stats()["load_errors"] == 1 and "map.yaml" in str(src.stats()["last_error"])


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


def test_pgm_cut_inside_its_header_is_one_logged_error(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The cut that crashed the daemon (exit 1 and a traceback; systemd restarted it into the same crash).
    path = tmp_path / "map.yaml"
    src, state = _watching(path, 0, settle_s=0.0)
    for cut in (b"P5\n100 ", b"P5\n50 40\n0\n", b"P5\n50 40\n65536\n", b""):
        path.with_suffix(".pgm").write_bytes(cut)
        _age(path, 10 + len(cut))  # a new signature each time
        with caplog.at_level("WARNING", logger="mapd.sources.mapfile"):
            assert src.check(state, 1.0) is None
            assert src.check(state, 2.0) is None  # the same fault is not logged again
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 4 and all("\n" not in r.getMessage() and r.exc_info is None for r in warnings)
    assert "truncated in its PNM header" in warnings[0].getMessage()
    st = src.stats()
    assert st["versions"] == 1 and st["load_errors"] == 4
    save_map(_grid(2), path)
    _age(path, 5)
    g = src.check(state, 3.0)
    assert g is not None and g.version == 2 and g.same_map(_grid(2))


def test_a_bug_while_loading_does_not_end_the_stream(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    import mapd.sources.mapfile as mapfile

    path = tmp_path / "map.yaml"
    save_map(_grid(0), path)
    _age(path, 10)
    src = _source(path, poll_s=0.02, settle_s=0.0)
    calls = {"n": 0}
    real = mapfile.load_map

    def buggy(*a: object, **kw: object) -> OccupancyGrid:
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("a bug, not a bad file")
        return real(*a, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(mapfile, "load_map", buggy)

    async def go() -> OccupancyGrid:
        it = src.maps().__aiter__()
        pending = asyncio.ensure_future(it.__anext__())
        await asyncio.sleep(0.3)  # the first polls hit the bug ...
        assert calls["n"] == 1 and not pending.done()  # ... and the stream neither ended nor raised
        save_map(_grid(3), path)  # the files change: they are tried again
        grid = await asyncio.wait_for(pending, 5)
        await it.aclose()  # type: ignore[attr-defined]
        return grid

    with caplog.at_level("WARNING", logger="mapd.sources.mapfile"):
        grid = asyncio.run(go())
    assert grid.version == 1 and grid.same_map(_grid(3))
    errors = [r for r in caplog.records if "internal error while loading" in r.getMessage()]
    assert len(errors) == 1 and errors[0].exc_info is not None  # logged once, with its traceback
    assert src.stats()["load_errors"] == 1


def test_a_map_no_codec_would_send_is_refused_like_a_bad_file(tmp_path: Path) -> None:
    from mapd.codec.api import encode
    from mapd.errors import CodecError
    from mapd.grid import MAX_GRID_SIDE

    path = tmp_path / "map.yaml"
    strip = OccupancyGrid(np.zeros((1, MAX_GRID_SIDE + 1), np.int8), 0.05)
    with pytest.raises(CodecError, match="a side"):
        encode(strip, "raw")  # so the daemon could not publish it
    save_map(strip, path)
    _age(path, 10)
    src = _source(path, settle_s=0.0)
    assert src.check({}, 0.0) is None
    st = src.stats()
    assert st["versions"] == 0 and f"over {MAX_GRID_SIDE} a side" in str(st["last_error"])
