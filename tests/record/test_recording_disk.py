"""A recording and its disk: old files removed within ``max_total_bytes``, nothing written while
free space is under ``min_free_bytes``, a full disk mid-chunk leaving every file readable, and
``mapd record info`` reading maps over the default cell limit.

A full disk is a fake (``os.write`` in the writer given a byte budget, as the kernel gives one: a
partial write, then ENOSPC) or a file size limit (RLIMIT_FSIZE) in a subprocess.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import struct
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.stream_reader import StreamReader

from mapd.daemon.coding import CsvLog
from mapd.daemon.sinks import Sinks
from mapd.errors import MapFileError, StateError
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D
from mapd.record import files as files_mod
from mapd.record.info import summarize
from mapd.record.writer import Recorder

REPO = Path(__file__).resolve().parents[2]


def grid(seed: int, w: int = 400, h: int = 400) -> OccupancyGrid:
    """Random cells: about 35 kB a 400 x 400 map, zstd or not."""
    rng = np.random.default_rng(seed)
    data = rng.choice(np.array([-1, 0, 100], np.int8), size=(h, w))
    return OccupancyGrid(data, 0.05, version=seed, robot="robot0")


def recording_files(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("fleet") and p.suffix == ".mcap")


def read_stream(path: Path) -> list[tuple[str, int]]:
    """(topic, log time in s) of every message, read in order as a streaming reader does: a file
    without its footer ends with EndOfFile, anything else (a damaged chunk) raises."""
    out: list[tuple[str, int]] = []
    channels: dict[int, str] = {}
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                name = type(record).__name__
                if name == "Channel":
                    channels[record.id] = record.topic
                elif name == "Message":
                    out.append((channels[record.channel_id], round(record.log_time / 1e9)))
        except EndOfFile:
            pass
    return out


def ends_at_a_record(path: Path) -> bool:
    """Whether the file's top-level records (after the magic) end exactly where the file does."""
    data = path.read_bytes()
    pos = 8
    while pos < len(data):
        if data[pos:] == b"\x89MCAP0\r\n":  # the closing magic of a whole file
            return True
        if pos + 9 > len(data):
            return False
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        pos += 9 + length
    return pos == len(data)


# ------------------------------------------------------------------ max_total_bytes


def test_the_oldest_files_are_removed_to_stay_within_max_total_bytes(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Rotation opened fleet.1.mcap, fleet.2.mcap, ... and removed none: the disk filled up."""
    max_bytes, max_total = 256 << 10, 1 << 20
    rec = Recorder(
        tmp_path / "fleet.mcap", max_bytes=max_bytes, chunk_bytes=64 << 10, max_total_bytes=max_total,
        min_free_bytes=0,
    )  # fmt: skip
    rec.transforms("/tf_static", "map", {"robot0/map": Pose2D(0, 0, 0)}, 1.0)
    highest = 0.0
    with caplog.at_level(logging.INFO, logger="mapd"):
        for i in range(48):  # ~1.7 MB: seven files of 256 KiB
            rec.grid("/map", grid(i), "map", 2.0 + i)
            total = sum((tmp_path / n).stat().st_size for n in recording_files(tmp_path))
            highest = max(highest, total)
        rec.close()
    names = recording_files(tmp_path)
    # the newest, in order; the one written last is whole
    assert names == ["fleet.4.mcap", "fleet.5.mcap", "fleet.6.mcap"], names
    assert rec.removed == 4 and rec.files == [tmp_path / n for n in names]
    assert summarize(tmp_path / "fleet.6.mcap").complete
    # within the cap, but for the one message that ends a file, and its summary
    assert highest <= max_total + (64 << 10), highest
    said = [r.getMessage() for r in caplog.records if "removed" in r.getMessage()]
    assert [s.split()[2].rsplit("/", 1)[1] for s in said] == [
        "fleet.mcap", "fleet.1.mcap", "fleet.2.mcap", "fleet.3.mcap",
    ], said  # fmt: skip
    for name in names:  # each file starts with the transforms, as before
        assert read_stream(tmp_path / name)[0][0] == "/tf_static"


def test_the_file_just_finished_stays_with_the_tightest_cap(tmp_path: Path) -> None:
    """A file ends a chunk and a summary past max_bytes, so with max_total_bytes at twice max_bytes
    the file just finished never fit beside a new one and went at every rotation: right after it
    the recording held almost nothing."""
    max_bytes = 256 << 10
    rec = Recorder(
        tmp_path / "fleet.mcap", max_bytes=max_bytes, chunk_bytes=64 << 10, max_total_bytes=2 * max_bytes,
        min_free_bytes=0,
    )  # fmt: skip
    seen = []
    for i in range(40):
        rec.grid("/map", grid(i), "map", 2.0 + i)
        seen.append(recording_files(tmp_path))
    rec.close()
    assert rec.removed > 0  # the cap is kept to
    rotated = [names for names in seen if names != ["fleet.mcap"]]
    assert rotated  # (it did rotate)
    # from the first rotation on, the file just finished is there beside the one being written
    assert all(len(names) == 2 for names in rotated), seen


def test_a_restart_goes_on_after_the_highest_number_and_keeps_to_the_cap(tmp_path: Path) -> None:
    """After the oldest files were removed, a restart took the first free number: fleet.mcap, the
    newest file, sorted as the oldest and was the next removed."""
    kib = 1 << 10
    for name, size in [("fleet.3.mcap", 600), ("fleet.4.mcap", 600)]:
        (tmp_path / name).write_bytes(bytes(size * kib))
    # named like the recording's, but not as the recorder names its files: never counted or removed
    others = ["fleet.01.mcap", "fleet.x.mcap", "fleet.mcap.bak", "other.mcap", "fleet.2.mcap.tmp"]
    for name in others:
        (tmp_path / name).write_bytes(bytes(900 * kib))
    os.symlink(tmp_path / "other.mcap", tmp_path / "fleet.2.mcap")  # not a regular file: kept
    rec = Recorder(tmp_path / "fleet.mcap", max_bytes=256 * kib, max_total_bytes=1024 * kib, min_free_bytes=0)
    rec.grid("/map", grid(0, 40, 30), "map", 10.0)
    rec.close()
    # 600 + 600 + 256 KiB is over the cap: fleet.3 went; 600 + 256 fit
    assert rec.files == [tmp_path / "fleet.5.mcap"] and rec.removed == 1
    assert not (tmp_path / "fleet.3.mcap").exists() and (tmp_path / "fleet.4.mcap").exists()
    assert all((tmp_path / n).exists() for n in others) and (tmp_path / "fleet.2.mcap").is_symlink()
    # a gap where the first files were is never filled
    (tmp_path / "fleet.4.mcap").unlink()
    again = Recorder(tmp_path / "fleet.mcap", max_bytes=256 * kib, min_free_bytes=0)
    again.grid("/map", grid(1, 40, 30), "map", 11.0)
    again.close()
    assert again.files == [tmp_path / "fleet.6.mcap"]


def test_max_total_bytes_under_twice_max_bytes_is_refused() -> None:
    from pydantic import ValidationError

    from mapd.config import RecordSection
    from mapd.errors import ConfigError

    for total in (4 << 20, 12 << 20):
        with pytest.raises(ValidationError, match=r"max_total_bytes .* must be at least twice max_bytes"):
            RecordSection(max_bytes=8 << 20, max_total_bytes=total)
        with pytest.raises(ConfigError, match="max_total_bytes"):
            Recorder(Path("fleet.mcap"), max_bytes=8 << 20, max_total_bytes=total)
    RecordSection(max_bytes=8 << 20, max_total_bytes=16 << 20)
    with pytest.raises(ValidationError):
        RecordSection(max_total_bytes=0)  # no "0 means no cap": a recording always has one
    # the recorder's defaults are the config's (the daemon passes the config's values)
    d = RecordSection()
    rec = Recorder(Path("fleet.mcap"))
    assert (rec.disk.max_bytes, rec.disk.max_total_bytes, rec.disk.min_free_bytes) == (
        d.max_bytes, d.max_total_bytes, d.min_free_bytes,
    )  # fmt: skip


# ------------------------------------------------------------------ min_free_bytes


@pytest.fixture
def free_space(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The free bytes ``os.statvfs`` reports (set ``[0]``), for every filesystem."""
    free = [1 << 40]
    real = os.statvfs

    def statvfs(path: Any) -> Any:
        st = real(path)
        return SimpleNamespace(f_bavail=free[0] // st.f_frsize, f_frsize=st.f_frsize)

    monkeypatch.setattr(files_mod.os, "statvfs", statvfs)
    return free


def test_low_free_space_refuses_messages_said_once_until_there_is_room(
    tmp_path: Path, free_space: list[int], caplog: pytest.LogCaptureFixture
) -> None:
    """A recording filled the state directory's disk: the robot could not save its own map."""
    rec = Recorder(tmp_path / "fleet.mcap", min_free_bytes=100 << 20)
    sinks = Sinks([], rec, CsvLog(tmp_path / "fused.csv"))

    def set_free(n: int) -> None:  # in the file thread's order
        sinks._files.submit(lambda: free_space.__setitem__(0, n))

    with caplog.at_level(logging.INFO, logger="mapd"):
        sinks.robot_map(grid(0, 40, 30))
        set_free(99 << 20)
        for i in range(1, 4):
            sinks.robot_map(grid(i, 40, 30))
        set_free(101 << 20)
        sinks.robot_map(grid(4, 40, 30))
        sinks._files.submit(lambda: None).result(30)
        status = sinks.recording()
        sinks.close()
    assert status is not None and status["failures"] == 3 and status["removed_files"] == 0
    said = [r.getMessage() for r in caplog.records if "record" in r.getMessage()]
    assert len(said) == 2 and said[1] == "recording again", said
    assert "StateError" in said[0] and "99 MiB free" in said[0] and "min_free_bytes (100 MiB)" in said[0]
    assert [t for t, _ in read_stream(tmp_path / "fleet.mcap")] == ["/robot0/map", "/robot0/map"]
    assert rec.messages == 2


def test_a_first_file_is_not_opened_without_room_and_refused_transforms_come_first_later(
    tmp_path: Path, free_space: list[int]
) -> None:
    rec = Recorder(tmp_path / "fleet.mcap", min_free_bytes=100 << 20)
    free_space[0] = 10 << 20
    with pytest.raises(StateError, match="min_free_bytes"):
        rec.grid("/map", grid(0, 40, 30), "map", 1.0)
    assert recording_files(tmp_path) == []  # not even a header
    free_space[0] = 1 << 30
    rec.grid("/map", grid(1, 40, 30), "map", 2.0)
    free_space[0] = 10 << 20
    with pytest.raises(StateError):  # a placement changed while the disk was full ...
        rec.transforms("/tf_static", "map", {"robot1/map": Pose2D(1, 2, 0)}, 3.0)
    free_space[0] = 1 << 30
    rec.grid("/map", grid(2, 40, 30), "map", 4.0)  # ... so the file gets it before the next map
    rec.close()
    assert read_stream(tmp_path / "fleet.mcap") == [("/map", 2), ("/tf_static", 3), ("/map", 4)]


# ------------------------------------------------------------------ a full disk mid-chunk


@pytest.fixture
def disk(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> list[int | None]:
    """Bytes the disk under ``tmp_path`` still takes (``[0]``; None: no limit). A write past them
    is written in part, and the next raises ENOSPC, as the kernel does."""
    budget: list[int | None] = [None]
    real = os.write

    def write(fd: int, data: Any) -> int:
        if budget[0] is None or not os.readlink(f"/proc/self/fd/{fd}").startswith(str(tmp_path)):
            return real(fd, data)
        if budget[0] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = real(fd, bytes(memoryview(data)[: budget[0]]))
        budget[0] -= n
        return n

    monkeypatch.setattr(files_mod.os, "write", write)
    return budget


def test_a_full_disk_mid_chunk_leaves_the_file_at_its_last_chunk_and_goes_on_in_a_new_one(
    tmp_path: Path, disk: list[int | None]
) -> None:
    """The writer went on after a partial chunk: nothing after the outage could be read in order."""
    rec = Recorder(tmp_path / "fleet.mcap", chunk_bytes=64 << 10, min_free_bytes=0)
    rec.transforms("/tf_static", "map", {"robot0/map": Pose2D(0, 0, 0)}, 1.0)
    for i in range(5):
        rec.grid("/map", grid(i), "map", 10.0 + i)
    disk[0] = 20_000  # full in the middle of the next chunk
    failed = []
    for i in range(5, 12):
        try:
            rec.grid("/map", grid(i), "map", 10.0 + i)
        except StateError as exc:
            failed.append(i)
            assert "cannot write" in str(exc) and "No space left" in str(exc)
    disk[0] = None  # space again
    for i in range(12, 16):
        rec.grid("/map", grid(i), "map", 10.0 + i)
    rec.close()
    assert failed and failed[-1] == 11  # every try while the disk was full failed
    # the full disk took one new file (no header-only files, one a try), cut back when it failed
    assert recording_files(tmp_path) == ["fleet.1.mcap", "fleet.mcap"], recording_files(tmp_path)
    first, second = (read_stream(tmp_path / n) for n in ("fleet.mcap", "fleet.1.mcap"))
    assert ends_at_a_record(tmp_path / "fleet.mcap")
    assert first[0] == ("/tf_static", 1) and first[1:] == [("/map", 10 + i) for i in range(len(first) - 1)]
    assert second == [("/tf_static", 1)] + [("/map", 10 + i) for i in range(12, 16)]
    assert summarize(tmp_path / "fleet.1.mcap").complete
    s = summarize(tmp_path / "fleet.mcap")
    assert not s.complete and s.messages == len(first) and "EndOfFile" in str(s.error)


def test_a_full_disk_at_stop_ends_the_file_at_its_last_chunk(tmp_path: Path, disk: list[int | None]) -> None:
    rec = Recorder(tmp_path / "fleet.mcap", chunk_bytes=64 << 10, min_free_bytes=0)
    for i in range(10):  # 10 kB each: the last ones wait in the writer's chunk
        rec.grid("/map", grid(i, 100, 100), "map", 10.0 + i)
    disk[0] = 0  # neither that chunk nor the summary fits
    with pytest.raises(StateError, match="cannot write"):
        rec.close()
    disk[0] = None
    assert ends_at_a_record(tmp_path / "fleet.mcap")
    got = read_stream(tmp_path / "fleet.mcap")
    assert 0 < len(got) < 10 and got == [("/map", 10 + i) for i in range(len(got))]


_CHILD = r"""
import json, resource, signal, sys
from pathlib import Path
import numpy as np
from mapd.errors import StateError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.record.writer import Recorder

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG, not a killed process
folder = Path(sys.argv[1])
rng = np.random.default_rng(0)
def g(i):
    return OccupancyGrid(rng.choice(np.array([-1, 0, 100], np.int8), size=(300, 300)), 0.05, version=i)
rec = Recorder(folder / "fleet.mcap", max_bytes=64 << 20, chunk_bytes=64 << 10, min_free_bytes=0)
rec.transforms("/tf_static", "map", {"r1/map": Pose2D(1, 2, 0.3)}, 999.0)
_, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, hard))  # "disk full" at 200 kB a file
failed = []
for i in range(10):
    try:
        rec.grid("/map", g(i), "map", 1000.0 + i)
    except StateError:
        failed.append(i)
resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))  # space again
for i in range(10, 20):
    rec.grid("/map", g(i), "map", 1000.0 + i)
rec.close()
print(json.dumps({"failed": failed, "files": [p.name for p in rec.files]}))
"""


def test_a_file_size_limit_mid_chunk_leaves_every_file_readable_in_order(tmp_path: Path) -> None:
    """The audit's case (EFBIG from RLIMIT_FSIZE): ZstdError at the partial chunk; 10 maps recorded
    after the outage could not be read by mapd record info or mcap's NonSeekingReader."""
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(tmp_path)], capture_output=True, text=True, timeout=120, cwd=REPO
    )
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["failed"] and res["files"][0] == "fleet.mcap"
    maps: list[int] = []
    for name in res["files"]:
        assert ends_at_a_record(tmp_path / name), name
        got = read_stream(tmp_path / name)
        assert got[0] == ("/tf_static", 999), name
        maps += [t - 1000 for topic, t in got if topic == "/map"]
        s = summarize(tmp_path / name)
        assert s.error is None or "EndOfFile" in s.error, (name, s.error)
    assert maps == sorted(maps) and set(range(10, 20)) <= set(maps), maps
    assert not set(res["failed"]) & set(maps)


# ------------------------------------------------------------------ mapd record info


def test_record_info_reads_a_recording_of_maps_over_the_default_cell_limit(tmp_path: Path) -> None:
    """A daemon with [limits] max_cells above the default recorded maps its own tool refused."""
    path = tmp_path / "big.mcap"
    cells = DEFAULT_MAX_CELLS + (2 << 20)
    side = int(cells**0.5) + 1
    rec = Recorder(path, min_free_bytes=0)
    rec.grid("/map", OccupancyGrid(np.full((side, side), -1, np.int8), 0.05), "map", 1000.0)
    rec.close()

    def info(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "mapd", "record", "info", *args, str(path)],
                              capture_output=True, text=True, timeout=120, cwd=REPO)  # fmt: skip

    refused = info()
    assert refused.returncode == 1 and "--max-cells" in refused.stderr, refused.stderr
    ok = info("--max-cells", str(side * side), "--json")
    assert ok.returncode == 0, ok.stderr
    doc = json.loads(ok.stdout)
    assert doc["complete"] and doc["topics"]["/map"]["messages"] == 1
    # the bound still holds below the map's size
    with pytest.raises(MapFileError, match=r"over the .* --max-cells"):
        summarize(path, max_cells=side * side - (2 << 20))
