"""The laserlog source on a gzip log that ends early: it replays up to the cut, says so once, ends."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from pathlib import Path

import pytest

from mapd.errors import SourceError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.mapping import carmen
from mapd.mapping.replay import first_pose, replay_log, split_range
from mapd.sources.base import SourceContext
from mapd.sources.laserlog import LaserLogOptions, LaserLogSource
from tests.mapping.cutlog import blocked_gzip, scan_lines, whole_lines, write_prefix

BoxLog = Callable[..., tuple[Path, list[Pose2D]]]
ENDS_EARLY = "log ends early"


def _collect(src: LaserLogSource) -> list[OccupancyGrid]:
    async def go() -> list[OccupancyGrid]:
        return [g async for g in src.maps()]

    return asyncio.run(go())


def _cut_box_log(box_log: BoxLog, tmp_path: Path, block: int) -> tuple[Path, Path]:
    """A 30-scan box log cut in the middle of its ``block``-th deflate block, and the lines it keeps."""
    whole, _poses = box_log(name="whole.log", scans=30)
    gz, marks = blocked_gzip(whole.read_bytes(), lines_per_block=5)
    end = (marks[block] + marks[block + 1]) // 2
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[:end])
    return cut, write_prefix(tmp_path / "prefix.log", gz, end)


@pytest.mark.parametrize(("robots", "index"), [(1, 0), (2, 0), (2, 1)])
def test_a_cut_log_is_replayed_up_to_the_cut_said_once_and_the_source_ends(
    box_log: BoxLog, tmp_path: Path, caplog: pytest.LogCaptureFixture, robots: int, index: int
) -> None:
    cut, prefix = _cut_box_log(box_log, tmp_path, block=7)
    k = scan_lines(prefix.read_bytes())
    src = LaserLogSource(
        LaserLogOptions(log=cut, every=4, realtime=0, robots=robots, index=index), SourceContext(robot="r")
    )
    with caplog.at_level(logging.WARNING, logger="mapd"):
        assert src.start_pose() == first_pose(prefix, robots=robots, index=index)
        maps = _collect(src)  # ends as at the log's end: no SourceError
    part = split_range(k, robots, index)
    st = src.stats()
    assert st["scans"] == len(part) and st["skipped_lines"] == 0
    *_, (_t, final) = replay_log(prefix, every=4, robots=robots, index=index)
    assert maps and maps[-1].same_map(final)
    said = [r.getMessage() for r in caplog.records if ENDS_EARLY in r.getMessage()]
    # Said once by the pass that reaches the cut; robot 0 of 2 stops before it and says nothing.
    reaches = part.stop == k
    assert len(said) == int(reaches), said
    if reaches:
        assert said[0].startswith(f"{cut}: line ") and st["last_error"] == said[0]


def test_a_log_damaged_before_any_scan_is_one_source_error(box_log: BoxLog, tmp_path: Path) -> None:
    whole, _poses = box_log(name="whole.log", scans=10)
    gz, marks = blocked_gzip(whole.read_bytes(), lines_per_block=2)  # block 1: the comment and PARAM
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[: marks[0] + 3])
    src = LaserLogSource(LaserLogOptions(log=cut, realtime=0), SourceContext(robot="r"))
    with pytest.raises(SourceError, match=r"cut\.log\.gz: line 3: log is corrupt or truncated"):
        _collect(src)


def test_the_intel_log_cut_in_half_maps_its_first_half(
    intel_log: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    gz = intel_log.read_bytes()
    end = len(gz) // 2
    cut = tmp_path / "intel-cut.log.gz"
    cut.write_bytes(gz[:end])
    k = scan_lines(whole_lines(gz, end))
    assert 300 < k < 910
    src = LaserLogSource(LaserLogOptions(log=cut, every=300, realtime=0), SourceContext(robot="intel"))
    with caplog.at_level(logging.WARNING, logger="mapd"):
        maps = _collect(src)
    assert src.stats()["scans"] == k and src.stats()["skipped_lines"] == 0
    whole = carmen.read_scans(intel_log)
    assert maps[-1].stamp == next(s for i, s in enumerate(whole) if i == k - 1).stamp
    said = [r.getMessage() for r in caplog.records if ENDS_EARLY in r.getMessage()]
    assert len(said) == 1 and f"{cut}: line " in said[0] and f"of {end} bytes" in said[0]
