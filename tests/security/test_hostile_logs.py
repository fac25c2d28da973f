"""Hostile gzip CARMEN logs: a decompression bomb is one LimitError line, found while it inflates.

Measured before the fix: a 204 KB gzip log holding 200 MiB of newlines kept ``mapd replay`` busy for
minutes, inflating all of it on every pass (a count, then one per robot). Real logs inflate about
4-5x (intel 3.9x, freiburg-079 4.6x) and are read as before, as is a far more compressible one of a
robot standing still with a noiseless laser.
"""

from __future__ import annotations

import asyncio
import gzip
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.config import MapdConfig
from mapd.errors import LimitError
from mapd.grid import OccupancyGrid
from mapd.mapping import carmen
from mapd.mapping.replay import first_pose, replay_log, replay_scans
from mapd.sources.base import SourceContext
from mapd.sources.laserlog import LaserLogOptions, LaserLogSource

Run = Callable[..., subprocess.CompletedProcess[str]]
OneLine = Callable[..., str]

#: One good scan line (3 beams), so that a bomb after it is refused even once scans were read.
SCAN = b"FLASER 3 1.0 2.0 3.0 0.5 0.5 0.1 0.5 0.5 0.1 100.0 host 100.0\n"


def _gzip_log(path: Path, piece: bytes, copies: int, *, head: bytes = b"", tail: bytes = SCAN) -> Path:
    """A gzip log of ``head``, ``piece`` ``copies`` times, then ``tail``, compressed as it is written.

    The scan after the bomb makes every reader go through it, even one that wants the first scan.
    """
    with gzip.open(path, "wb") as g:
        g.write(head)
        for _ in range(copies):
            g.write(piece)
        g.write(tail)
    return path


def _newlines(tmp: Path) -> Path:
    # 4 Mi empty lines in 4 KB: far past MIN_GZIP_LIMIT_LINES, and 1000 lines per byte.
    return _gzip_log(tmp / "newlines.log.gz", b"\n" * (1 << 20), 4)


def _long_lines(tmp: Path) -> Path:
    # 16 MiB of 1 KiB comment lines (16 Ki lines, under the line limit) in some 16 KB.
    return _gzip_log(tmp / "long.log.gz", b"#" + b"x" * 1022 + b"\n", 16384)


def _one_line(tmp: Path) -> Path:
    # 16 MiB without a newline: an overlong line, drained piece by piece, never kept.
    return _gzip_log(tmp / "oneline.log.gz", b"x" * (1 << 20), 16, tail=b"\n" + SCAN)


BOMBS: dict[str, tuple[Callable[[Path], Path], str]] = {
    "newlines": (_newlines, f"lines, over {carmen.MAX_GZIP_LINES_PER_BYTE} per byte of its size on disk"),
    "long lines": (_long_lines, f"bytes, over {carmen.MAX_GZIP_RATIO} times its size on disk"),
    "one overlong line": (_one_line, f"bytes, over {carmen.MAX_GZIP_RATIO} times its size on disk"),
}


def _collect(src: LaserLogSource) -> list[OccupancyGrid]:
    async def go() -> list[OccupancyGrid]:
        return [g async for g in src.maps()]

    return asyncio.run(go())


def _check_config(p: Path) -> Any:
    """check-config's hook: its ValueError becomes the config's one line, naming the option
    (``source.laserlog.log: ...``); given back here as the LimitError it wraps."""
    try:
        LaserLogOptions(log=p, realtime=0).check_with_config(
            MapdConfig.model_validate({"robot": {"name": "r"}})
        )
    except ValueError as exc:
        assert str(exc).startswith("log: "), exc
        raise LimitError(str(exc).removeprefix("log: ")) from None


#: Every way mapd reads a log: the commands (replay, bench, demo) and the laserlog source.
READERS: dict[str, Callable[[Path], Any]] = {
    "count_scans": carmen.count_scans,
    "read_scans": lambda p: list(carmen.read_scans(p, stats=carmen.LogStats(quiet=True))),
    "replay_scans of 2 robots": lambda p: list(replay_scans(p, robots=2, index=1)),
    "first_pose": first_pose,
    "replay_log": lambda p: list(replay_log(p, every=5)),
    "laserlog check_with_config": _check_config,
    "laserlog start_pose": lambda p: LaserLogSource(
        LaserLogOptions(log=p, realtime=0), SourceContext(robot="r")
    ).start_pose(),
    "laserlog maps": lambda p: _collect(
        LaserLogSource(LaserLogOptions(log=p, realtime=0, robots=2), SourceContext(robot="r"))
    ),
}


@pytest.mark.parametrize("bomb", list(BOMBS))
@pytest.mark.parametrize("reader", list(READERS))
def test_a_gzip_bomb_is_one_limit_error_from_every_reader(tmp_path: Path, bomb: str, reader: str) -> None:
    make, says = BOMBS[bomb]
    p = make(tmp_path)
    with pytest.raises(LimitError) as info:
        READERS[reader](p)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"{p}: gzip log ") and says in msg
    assert msg.endswith("refused as a decompression bomb")


def test_a_gzip_bomb_is_one_line_from_mapd_replay(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    p = _newlines(tmp_path)
    out = tmp_path / "out"
    line = one_error_line(mapd_run("replay", str(p), "-o", str(out), "--robots", "2", timeout=60))
    assert line.startswith(f"mapd: error: {p}: gzip log holds more than ") and "decompression bomb" in line
    assert not (out / "poses.yaml").exists()


def test_scans_read_before_a_bomb_do_not_make_it_a_cut_log(tmp_path: Path) -> None:
    # A log cut short is read up to the cut; a bomb after good scans is refused all the same.
    p = _gzip_log(tmp_path / "after.log.gz", b"\n" * (1 << 20), 4, head=SCAN * 3, tail=b"")
    stats = carmen.LogStats(quiet=True)
    read = []
    with pytest.raises(LimitError, match="decompression bomb"):
        read.extend(carmen.read_scans(p, stats=stats))
    assert len(read) == 3 and not stats.cut


def test_the_same_bytes_uncompressed_are_read(tmp_path: Path) -> None:
    # The limits are on inflating, not on the text: a plain log costs its own size to read.
    plain = tmp_path / "newlines.log"
    plain.write_bytes(gzip.decompress(_newlines(tmp_path).read_bytes()))
    assert carmen.count_scans(plain) == 1


def test_a_small_log_of_identical_lines_is_read_whatever_its_ratio(tmp_path: Path) -> None:
    # 5000 identical scans compress past the ratio, but stay under the floor: a test log is no bomb.
    p = _gzip_log(tmp_path / "same.log.gz", SCAN, 5000)
    assert p.stat().st_size * carmen.MAX_GZIP_RATIO < 5001 * len(SCAN) < carmen.MIN_GZIP_LIMIT_BYTES
    assert len(list(carmen.read_scans(p))) == 5001


def test_a_robot_standing_still_with_a_noiseless_laser_is_read(tmp_path: Path) -> None:
    # The most compressible log a real run could write (a simulation without noise): the same 361
    # ranges and pose on every line, only the times moving, with odometry between. Over 100x, and
    # past the floor of 4 MiB.
    rng = np.random.default_rng(3)
    ranges = " ".join(f"{v:.3f}" for v in np.abs(4.0 + np.cumsum(rng.normal(0.0, 0.05, 361))))
    lines = []
    for i in range(4000):
        t = 1000.0 + 0.1 * i
        lines.append(f"FLASER 361 {ranges} 1.5 2.5 0.3 1.5 2.5 0.3 {t:.6f} robot {t + 0.001:.6f}\n")
        lines.append(f"ODOM 1.5 2.5 0.3 0.0 0.0 0.0 {t:.6f} robot {t + 0.001:.6f}\n")
    text = "".join(lines).encode()
    p = tmp_path / "still.log.gz"
    p.write_bytes(gzip.compress(text))
    ratio = len(text) / p.stat().st_size
    assert len(text) > carmen.MIN_GZIP_LIMIT_BYTES and 100 < ratio < carmen.MAX_GZIP_RATIO, ratio
    assert carmen.count_scans(p) == len(list(carmen.read_scans(p))) == 4000


@pytest.mark.parametrize("name", ["intel-corrected.log.gz", "freiburg-079-corrected.log.gz"])
def test_real_logs_inflate_far_below_the_limits(data_dir: Path, name: str) -> None:
    p = data_dir / "logs" / name
    if not p.exists():
        pytest.skip(f"{p} not found")
    text = gzip.decompress(p.read_bytes())
    size = p.stat().st_size
    # A tenth of each limit: the margin the constants' comments promise.
    assert len(text) / size * 10 < carmen.MAX_GZIP_RATIO
    assert text.count(b"\n") / size * 10 < carmen.MAX_GZIP_LINES_PER_BYTE
    assert carmen.count_scans(p) == len(list(carmen.read_scans(p))) == text.count(b"\nFLASER ")
