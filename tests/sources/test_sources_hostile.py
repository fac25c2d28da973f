"""Hostile CARMEN logs against the laserlog source, ``replay_log`` and the mapper: one clear line
(or a counted skip), bounded log output, and no stall, never a traceback."""

from __future__ import annotations

import asyncio
import logging
import os
import time
from pathlib import Path

import numpy as np
import pytest

from mapd.errors import LimitError, SourceError
from mapd.grid import MIN_RESOLUTION, OccupancyGrid, Pose2D
from mapd.mapping import carmen
from mapd.mapping.mapper import Mapper, MapperOptions
from mapd.mapping.replay import replay_log
from mapd.sources import laserlog
from mapd.sources.base import SourceContext
from mapd.sources.laserlog import LaserLogOptions, LaserLogSource


def _flaser(x: float, stamp: float, n: int = 180) -> str:
    ranges = " ".join(["2.0"] * n)
    return f"FLASER {n} {ranges} {x!r} 0.0 0.0 0.0 0.0 0.0 {stamp!r} host {stamp!r}\n"


def _collect(src: LaserLogSource, timeout: float) -> list[OccupancyGrid]:
    async def go() -> list[OccupancyGrid]:
        return [g async for g in src.maps()]

    async def bounded() -> list[OccupancyGrid]:
        return await asyncio.wait_for(go(), timeout)

    return asyncio.run(bounded())


def test_a_timestamp_years_ahead_pauses_the_replay_briefly_not_for_ever(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(laserlog, "MAX_GAP_S", 0.3)
    p = tmp_path / "jump.log"
    p.write_text(_flaser(0.0, 1.0) + _flaser(0.1, 1e15) + _flaser(0.2, 1.2) + _flaser(0.3, 1.3))
    src = LaserLogSource(LaserLogOptions(log=p, every=1, realtime=1.0), SourceContext(robot="r"))
    t0 = time.monotonic()
    maps = _collect(src, timeout=10.0)  # before the fix: asleep for 1e15 s
    assert [g.version for g in maps] == [1, 2, 3, 4]
    assert time.monotonic() - t0 < 5.0


def test_timestamps_whose_difference_overflows_are_skipped_not_a_hang(tmp_path: Path) -> None:
    # 1e308 after -1e308 is inf seconds later: the pacing went to NaN and slept for ever
    p = tmp_path / "stamps.log"
    p.write_text(_flaser(0.0, -1e308) + _flaser(0.1, 1e308) + _flaser(0.2, 1.0) + _flaser(0.3, 1.1))
    src = LaserLogSource(LaserLogOptions(log=p, every=1, realtime=1.0), SourceContext(robot="r"))
    maps = _collect(src, timeout=10.0)
    st = src.stats()
    assert len(maps) == 2 and st["skipped_lines"] == 2 and "timestamp" in str(st["last_error"])


@pytest.mark.parametrize("kind", ["fifo", "device"])
def test_a_log_that_is_no_regular_file_is_one_source_error_at_once(tmp_path: Path, kind: str) -> None:
    # A FIFO without a writer blocked the open for ever; /dev/zero was read for ever, line by line.
    path = Path("/dev/zero")
    if kind == "fifo":
        path = tmp_path / "log.fifo"
        os.mkfifo(path)
    t0 = time.monotonic()
    with pytest.raises(SourceError, match="not a regular file"):
        list(carmen.read_scans(path))
    assert time.monotonic() - t0 < 5.0


def test_poses_so_far_apart_they_overflow_are_skipped_not_a_crash(tmp_path: Path) -> None:
    p = tmp_path / "far.log"
    p.write_text(_flaser(0.0, 1.0) + _flaser(1.7e308, 2.0) + _flaser(-1.7e308, 3.0) + _flaser(0.5, 4.0))
    src = LaserLogSource(LaserLogOptions(log=p, every=1, realtime=0), SourceContext(robot="r"))
    maps = _collect(src, timeout=10.0)
    st = src.stats()
    assert st["scans"] == 2 and st["skipped_lines"] == 2 and len(maps) == 2
    assert "from the origin" in str(st["last_error"]) and "line 3" in str(st["last_error"])
    # The offline replay (``mapd replay``) reads the same log without a traceback.
    assert [g.version for _, g in replay_log(p, every=1)] == [1, 2]


def test_a_finite_range_that_overflows_in_cells_is_a_limit_error() -> None:
    mapper = Mapper(MapperOptions(no_return=None))
    with pytest.raises(LimitError, match="past any grid"):
        mapper.integrate(np.array([1e308]), np.array([0.3]), Pose2D(0.0, 0.0, 0.0))
    with pytest.raises(LimitError, match="past any grid"):
        # (the finest resolution the options take; 1e-300 is refused by them since)
        Mapper(MapperOptions(resolution=MIN_RESOLUTION)).integrate(
            np.array([1.0]), np.array([0.0]), Pose2D(1e305, 0, 0)
        )
    assert mapper.bounds is None  # nothing changed


def test_a_log_of_garbage_logs_a_few_lines_not_one_per_distinct_word(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    p = tmp_path / "garbage.log"
    rng = np.random.default_rng(3)
    lines = [f"WORD{i} {i}\n" for i in range(500)]
    lines += [f"FLASER {int(k)} 1 2 3\n" for k in rng.integers(1, 8000, 300)]
    lines += [f"FLASER {int(k)} x\n" for k in rng.integers(9000, 10**9, 300)]
    lines += [f"FLASER c{i} 1\n" for i in range(300)]
    p.write_text("".join(lines))
    stats = carmen.LogStats()
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        assert list(carmen.read_scans(p, stats=stats)) == []
    assert stats.skipped == len(lines)
    assert len(caplog.records) <= 4  # one per kind of fault, not 1400
