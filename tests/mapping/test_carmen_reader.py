"""The CARMEN log reader: good lines, bad lines skipped and counted, gzip and plain, fuzzed input."""

from __future__ import annotations

import gzip
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.errors import SourceError
from mapd.mapping import carmen


def _flaser(
    n: int = 4, ranges: str | None = None, tail: str = "1.0 2.0 0.5 1.0 2.0 0.5 12.5 host 12.5"
) -> str:
    rs = ranges if ranges is not None else " ".join(["1.5"] * n)
    return f"FLASER {n} {rs} {tail}\n"


def test_flaser_fields_angles_and_pose(tmp_path: Path) -> None:
    p = tmp_path / "a.log"
    p.write_text(_flaser(180) + _flaser(181) + _flaser(361))
    scans = list(carmen.read_scans(p))
    assert [s.ranges.size for s in scans] == [180, 181, 361]
    a180, a181, a361 = (s.angles for s in scans)
    assert a180[0] == pytest.approx(-math.pi / 2) and a180[1] - a180[0] == pytest.approx(math.radians(1))
    assert a181[-1] == pytest.approx(math.pi / 2)
    assert a361[1] - a361[0] == pytest.approx(math.radians(0.5)) and a361[-1] == pytest.approx(math.pi / 2)
    s = scans[0]
    assert tuple(s.pose) == (1.0, 2.0, 0.5) and s.stamp == 12.5 and s.line == 1 and s.index == 0
    assert [x.index for x in scans] == [0, 1, 2]


def test_bad_lines_are_skipped_counted_and_logged_with_file_and_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    p = tmp_path / "bad.log"
    lines = [
        _flaser(),  # line 1: good
        "FLASER 4 1 2 3\n",  # 2: wrong number of fields
        _flaser(ranges="1 nan 2 3"),  # 3: NaN range
        _flaser(ranges="1 -2 2 3"),  # 4: negative range
        "BOGUS 1 2 3\n",  # 5: unknown message type
        "ODOM 0 0 0 0 0 0 1 host 1\n",  # 6: known, ignored
        _flaser(ranges="1 x 2 3"),  # 7: not a number
        "FLASER many 1 2\n",  # 8: bad count
        "# a comment\n",
        "\n",
        _flaser(),  # 11: good
    ]
    p.write_text("".join(lines))
    stats = carmen.LogStats()
    with caplog.at_level(logging.WARNING, logger="mapd.mapping.carmen"):
        scans = list(carmen.read_scans(p, stats=stats))
    assert [s.line for s in scans] == [1, 11]
    assert stats.scans == 2 and stats.skipped == 6 and stats.ignored == 1
    text = caplog.text
    for where, why in [
        (2, "fields"),
        (3, "NaN"),
        (4, "negative"),
        (5, "unknown message type"),
        (7, "number"),
    ]:
        assert f"{p}: line {where}: " in text and why in text
    assert stats.last_error.startswith(f"{p}: line 8:")


def test_gzip_and_plain_read_the_same(tmp_path: Path) -> None:
    text = _flaser() * 3
    plain, gz = tmp_path / "x.log", tmp_path / "x.log.gz"
    plain.write_text(text)
    gz.write_bytes(gzip.compress(text.encode()))
    a, b = list(carmen.read_scans(plain)), list(carmen.read_scans(gz))
    assert len(a) == len(b) == 3
    assert all(np.array_equal(x.ranges, y.ranges) for x, y in zip(a, b, strict=True))
    assert carmen.count_scans(gz) == 3


def test_missing_and_truncated_logs_raise_one_source_error(tmp_path: Path) -> None:
    with pytest.raises(SourceError, match="no such log file"):
        list(carmen.read_scans(tmp_path / "nope.log"))
    data = gzip.compress((_flaser(180) * 200).encode())
    cut = tmp_path / "cut.log.gz"
    # Cut before any scan: nothing usable, one error. (Cut after scans, the log is read up to the
    # cut: tests/mapping/test_cut_logs.py.)
    cut.write_bytes(data[:12])
    with pytest.raises(SourceError, match=r"cut\.log\.gz: line 1: log is corrupt or truncated"):
        list(carmen.read_scans(cut))
    cut.write_bytes(data[: len(data) // 2])
    stats = carmen.LogStats()
    assert 0 < len(list(carmen.read_scans(cut, stats=stats))) < 200 and "log ends early" in stats.cut


def test_overlong_line_is_skipped_without_reading_it_whole(tmp_path: Path) -> None:
    p = tmp_path / "long.log"
    p.write_bytes(b"FLASER 3 " + b"1 " * (carmen.MAX_LINE_BYTES) + b"\n" + _flaser().encode())
    stats = carmen.LogStats()
    scans = list(carmen.read_scans(p, stats=stats))
    assert len(scans) == 1 and stats.skipped == 1 and "longer than" in stats.last_error


def test_robotlaser1(tmp_path: Path) -> None:
    n = 5
    ranges = " ".join(["2.0"] * n)
    line = (
        f"ROBOTLASER1 0 -1.5708 3.1416 0.7854 30.0 0.01 0 {n} {ranges} 0 "
        "1.0 2.0 0.3 1.1 2.1 0.3 0 0 0 0 0 44.0 host 44.0\n"
    )
    p = tmp_path / "rl.log"
    p.write_text(line)
    (s,) = list(carmen.read_scans(p))
    assert s.angles[0] == pytest.approx(-1.5708) and s.angles[-1] == pytest.approx(-1.5708 + 3.1416)
    assert tuple(s.pose) == (1.0, 2.0, 0.3) and s.stamp == 44.0


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    junk=st.lists(
        st.one_of(
            st.binary(max_size=80),
            st.text(alphabet="FLASER0123456789.-naife \t", max_size=80).map(str.encode),
            st.builds(
                lambda n, xs: f"FLASER {n} {' '.join(xs)}".encode(),
                st.integers(-3, 12),
                st.lists(st.sampled_from(["1", "nan", "-1", "inf", "x", "1e400", "0"]), max_size=24),
            ),
        ),
        max_size=12,
    )
)
def test_fuzz_lines_never_escape_as_anything_but_counted_skips(tmp_path: Path, junk: list[bytes]) -> None:
    p = tmp_path / "fuzz.log"
    p.write_bytes(b"\n".join(junk) + b"\n" + _flaser().encode())
    stats = carmen.LogStats()
    if p.read_bytes()[:2] == b"\x1f\x8b":
        # gzip's magic: the reader takes it for a compressed log, which this is not: one clear error
        with pytest.raises(SourceError, match="corrupt or truncated"):
            list(carmen.read_scans(p, stats=stats))
        return
    scans = list(carmen.read_scans(p, stats=stats))
    # The good last line always comes through; every scan read is finite and non-negative.
    assert scans and scans[-1].ranges.size == 4
    for s in scans:
        assert not np.isnan(s.ranges).any() and (s.ranges >= 0).all()
        assert all(math.isfinite(v) for v in s.pose)
    assert stats.scans == len(scans)
