"""A gzip CARMEN log that ends early (cut short, or damaged part-way) is read up to there, said once.

A robot that loses power while logging, or a copy that is interrupted, leaves a gzip log without its
end; the scans before the cut are good data. The reader, ``mapd replay`` and the mapper use them and
say in one warning line that the log ends early; a log with no scan before the damage is one error.
"""

from __future__ import annotations

import gzip
import logging
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.errors import SourceError
from mapd.grid import Pose2D
from mapd.grid.load import load_map
from mapd.mapping import carmen
from mapd.mapping.replay import first_pose, replay_log
from tests.mapping.cutlog import blocked_gzip, scan_lines, whole_lines, write_prefix

BoxLog = Callable[..., tuple[Path, list[Pose2D]]]
ENDS_EARLY = "log ends early"


def _text(box_log: BoxLog, scans: int) -> bytes:
    log, _poses = box_log(name="whole.log", scans=scans)
    return log.read_bytes()


def _same_scans(a: list[carmen.LaserScan], b: list[carmen.LaserScan]) -> bool:
    return len(a) == len(b) and all(
        np.array_equal(x.ranges, y.ranges) and x.pose == y.pose and (x.line, x.index) == (y.line, y.index)
        for x, y in zip(a, b, strict=True)
    )


def _cut_warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if ENDS_EARLY in r.getMessage()]


@pytest.mark.parametrize("where", ["between two blocks", "mid-block", "mid-line", "in the trailer"])
def test_a_cut_log_is_read_up_to_the_cut_with_one_warning(
    box_log: BoxLog, tmp_path: Path, caplog: pytest.LogCaptureFixture, where: str
) -> None:
    gz, marks = blocked_gzip(_text(box_log, 30), lines_per_block=7)
    end = {
        "between two blocks": marks[3],
        "mid-block": (marks[3] + marks[4]) // 2,
        "mid-line": marks[3] + 5,
        "in the trailer": len(gz) - 3,
    }[where]
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[:end])
    kept = whole_lines(gz, end)
    expected = list(carmen.read_scans(write_prefix(tmp_path / "prefix.log", gz, end)))
    assert expected and len(expected) == scan_lines(kept)
    stats = carmen.LogStats()
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        got = list(carmen.read_scans(cut, stats=stats))
        assert carmen.count_scans(cut) == len(expected)  # the first pass is quiet: the reading says it
    assert _same_scans(got, expected)
    assert stats.scans == len(expected) and stats.skipped == 0  # no half line parsed as a bad one
    (said,) = _cut_warnings(caplog)
    assert len(caplog.records) == 1
    line = kept.count(b"\n") + 1
    assert said.startswith(f"{cut}: line {line}: {ENDS_EARLY}")
    assert f"after {end} of {end} bytes" in said and f"{len(expected)} scans" in said
    assert "\n" not in said and stats.cut == said and stats.last_error == said


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.0, 1.0))
def test_a_log_cut_anywhere_gives_the_scans_before_the_cut_or_one_error(
    box_log: BoxLog, tmp_path: Path, caplog: pytest.LogCaptureFixture, frac: float
) -> None:
    gz, _marks = blocked_gzip(_text(box_log, 12), lines_per_block=3)
    end = 2 + round(frac * (len(gz) - 3))  # from just past gzip's magic to one byte short
    cut = tmp_path / "any.log.gz"
    cut.write_bytes(gz[:end])
    whole = list(carmen.read_scans(write_prefix(tmp_path / "whole.log", gz, len(gz))))
    k = scan_lines(whole_lines(gz, end))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        if k == 0:
            with pytest.raises(SourceError, match=r"any\.log\.gz: line \d+: log is corrupt or truncated"):
                list(carmen.read_scans(cut))
            assert not _cut_warnings(caplog)
            return
        got = list(carmen.read_scans(cut))
    assert _same_scans(got, whole[:k])
    assert len(_cut_warnings(caplog)) == 1


def test_a_damaged_byte_mid_stream_keeps_the_scans_before_it(
    box_log: BoxLog, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    text = _text(box_log, 40)
    gz = gzip.compress(text, mtime=0)
    pos = len(gz) // 2
    damaged = bytearray(gz)
    damaged[pos] ^= 0xFF
    log = tmp_path / "damaged.log.gz"
    log.write_bytes(bytes(damaged))
    whole = list(carmen.read_scans(write_prefix(tmp_path / "whole.log", gz, len(gz))))
    k = scan_lines(whole_lines(gz, pos))  # the scans wholly before the damaged byte
    assert 0 < k < len(whole)
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        got = list(carmen.read_scans(log))
        carmen.count_scans(log)
    assert _same_scans(got[:k], whole[:k])
    (said,) = _cut_warnings(caplog)
    assert said.startswith(f"{log}: line ") and f"of {len(gz)} bytes" in said


@pytest.mark.parametrize("damage", ["cut in the header", "cut before the first scan", "damaged at once"])
def test_a_log_damaged_before_any_scan_is_one_source_error(
    box_log: BoxLog, tmp_path: Path, caplog: pytest.LogCaptureFixture, damage: str
) -> None:
    text = _text(box_log, 10)
    gz, marks = blocked_gzip(text, lines_per_block=2)  # block 1: the comment and PARAM
    if damage == "damaged at once":
        # In the code lengths of the first (dynamic Huffman) block: inflating fails at once. (A flip
        # in a literal would pass unseen until the CRC check at the end, after every scan.)
        data = bytearray(gzip.compress(text, mtime=0))
        data[12] ^= 0xFF
        blob = bytes(data)
    else:
        blob = gz[: 8 if damage == "cut in the header" else marks[0]]
    log = tmp_path / "bad.log.gz"
    log.write_bytes(blob)
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        for read in (lambda: list(carmen.read_scans(log)), lambda: carmen.count_scans(log)):
            with pytest.raises(SourceError) as err:
                read()
            msg = str(err.value)
            assert (
                msg.startswith(f"{log}: line ") and "log is corrupt or truncated" in msg and "\n" not in msg
            )
    assert not _cut_warnings(caplog)


def test_replay_log_of_a_cut_log_is_the_replay_of_its_first_lines(box_log: BoxLog, tmp_path: Path) -> None:
    gz, marks = blocked_gzip(_text(box_log, 30), lines_per_block=5)
    end = (marks[6] + marks[7]) // 2
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[:end])
    prefix = write_prefix(tmp_path / "prefix.log", gz, end)
    for index in (0, 1):
        a = list(replay_log(cut, every=4, resolution=0.1, robots=2, index=index))
        b = list(replay_log(prefix, every=4, resolution=0.1, robots=2, index=index))
        assert [t for t, _ in a] == [t for t, _ in b]
        assert all(x.same_map(y) for (_, x), (_, y) in zip(a, b, strict=True))
        assert first_pose(cut, robots=2, index=index) == first_pose(prefix, robots=2, index=index)


def _mapd(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], capture_output=True, text=True, timeout=120, check=False
    )


def test_mapd_replay_of_a_cut_log_writes_its_scans_says_so_once_and_exits_0(
    box_log: BoxLog, tmp_path: Path
) -> None:
    gz, marks = blocked_gzip(_text(box_log, 40), lines_per_block=5)
    end = (marks[9] + marks[10]) // 2
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[:end])
    prefix = write_prefix(tmp_path / "prefix.log", gz, end)
    out, ref = tmp_path / "out", tmp_path / "ref"
    args = ("-o", "--every", "6", "--robots", "2", "--resolution", "0.1")
    r = _mapd("replay", str(cut), args[0], str(out), *args[1:])
    assert r.returncode == 0, r.stderr
    assert "Traceback" not in r.stderr
    said = [ln for ln in r.stderr.splitlines() if ENDS_EARLY in ln]
    assert len(said) == 1 and f"{cut}: line " in said[0], r.stderr
    assert _mapd("replay", str(prefix), args[0], str(ref), *args[1:]).returncode == 0
    for robot in ("robot0", "robot1"):
        mine = sorted(p.name for p in (out / robot).glob("map_*.yaml"))
        assert mine and mine == sorted(p.name for p in (ref / robot).glob("map_*.yaml"))
        assert load_map(out / robot / mine[-1]).same_map(load_map(ref / robot / mine[-1]))
    assert yaml.safe_load((out / "poses.yaml").read_text()) == yaml.safe_load(
        (ref / "poses.yaml").read_text()
    )


def test_mapd_replay_of_a_log_damaged_before_any_scan_is_one_error_line(
    box_log: BoxLog, tmp_path: Path
) -> None:
    gz, marks = blocked_gzip(_text(box_log, 10), lines_per_block=2)
    cut = tmp_path / "cut.log.gz"
    cut.write_bytes(gz[: marks[0] + 3])
    r = _mapd("replay", str(cut), "-o", str(tmp_path / "out"))
    assert r.returncode == 1
    assert r.stderr.strip().splitlines() == [
        f"mapd: error: {cut}: line 3: log is corrupt or truncated after {marks[0] + 3} of {marks[0] + 3} bytes "
        "(Compressed file ended before the end-of-stream marker was reached)"
    ]
    assert not (tmp_path / "out").exists()
