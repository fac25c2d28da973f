"""Nothing lost on a crash: kill -9 mid-write, a full disk, a torn append, a clock that steps back.

A full disk is a file-size limit (``RLIMIT_FSIZE``) in a child process: writes past it fail with
EFBIG exactly where a full disk fails with ENOSPC (Python ignores SIGXFSZ), without filling a real
disk. A kill -9 mid-write is the child killing itself between a temp file's fsync and its rename.
"""

from __future__ import annotations

import asyncio
import csv
import json
import logging
import os
import struct
import subprocess
import sys
import textwrap
import zlib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.daemon.coding import Coder, CsvLog
from mapd.daemon.state import StateStore
from mapd.daemon.versions import split
from mapd.errors import MapFileError
from mapd.files import atomic_write_bytes
from mapd.fusion.store import GLOBAL_YAML
from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map
from mapd.imaging import read_pixels

ROOT = Path(__file__).resolve().parents[2]


def _child(script: str, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``script`` in a fresh interpreter (its own rlimits, its own death)."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script), *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _temps(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob(".*") if ".tmp" in p.name)


# ---------------------------------------------------------------------- atomic writes


def test_atomic_write_fsyncs_the_file_before_the_rename_and_the_directory_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    events: list[tuple[str, str]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        events.append(("replace", str(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    target = tmp_path / "state.json"
    atomic_write_bytes(target, b"{}\n")
    kinds = [k for k, _ in events]
    assert kinds == ["fsync", "replace", "fsync"]
    assert ".state.json.tmp" in events[0][1]  # the temp file's data is on disk before it is renamed
    assert events[1][1] == str(target)
    assert events[2][1] == str(tmp_path)  # and the rename itself, by the directory's fsync
    assert target.read_bytes() == b"{}\n" and _temps(tmp_path) == []


KILLED_MID_WRITE = """
    import os, signal, sys
    from pathlib import Path
    import numpy as np
    from mapd.daemon.state import StateStore
    from mapd.grid import OccupancyGrid

    root, what = Path(sys.argv[1]), sys.argv[2]
    store = StateStore(root)
    store.open()
    grid = OccupancyGrid(np.zeros((40, 60), np.int8), 0.05, robot="alpha", version=1)
    if what == "first":
        store.save_own(grid)
        store.save_peer(grid.replace(robot="beta", version=7))
    # kill -9 after the temp file is written and fsynced, before it is renamed over the map
    os.replace = lambda src, dst: os.kill(os.getpid(), signal.SIGKILL)
    if what == "peer":
        store.save_peer(grid.replace(robot="beta", version=8, data=np.full((40, 60), 100, np.int8)))
    else:
        store.save_own(grid.replace(version=2, data=np.full((40, 60), 100, np.int8)))
"""


def test_temp_files_left_by_kill_9_are_removed_at_start_and_the_state_is_intact(tmp_path: Path) -> None:
    root = tmp_path / "state"
    left: set[Path] = set()
    for what in ("first", "own", "peer"):
        done = _child(KILLED_MID_WRITE, str(root), what)
        assert done.returncode == -9, done.stderr
        # Each killed writer leaves temp files named by its pid, which no later write reuses: the
        # new image and YAML, written before either is renamed (the image has a name of its own,
        # so no old image is kept aside to go back to).
        assert _temps(root), "the writer was not killed mid-write"
        left |= set(_temps(root))
    assert len(left) == 6 and len({p.name.split(".tmp")[1].split(".")[0] for p in left}) == 3
    # A temp named with this process's pid, which no write of this process is using: what a
    # daemon that got its predecessor's pid again after a power cut finds. Removed too.
    same_pid = root / "global" / f".global.pgm.tmp{os.getpid()}.1"
    same_pid.write_bytes(b"P5")
    other = root / "notes.tmp"  # not a name mapd gives its temps: kept
    other.write_bytes(b"x")

    store = StateStore(root)
    data = store.open()
    assert _temps(root) == []  # without the sweep, every crash's temp stayed for ever
    assert other.exists()
    own, peer = store.own_map(), store.peer_map("beta")
    assert own is not None and own.version == 1 and int(own.data.max()) == 0
    assert peer is not None and peer.version == 7 and int(peer.data.max()) == 0
    assert split(data.own_version)[1] == 1


KILLED_AT = """
    import os, signal, sys
    from pathlib import Path
    import numpy as np
    from mapd.daemon.state import StateStore
    from mapd.grid import OccupancyGrid

    root, what, at = Path(sys.argv[1]), sys.argv[2], sys.argv[3]
    store = StateStore(root)
    store.open()
    grid = OccupancyGrid(np.zeros((40, 60), np.int8), 0.05, robot="alpha", version=1)
    store.save_own(grid)
    store.save_base(grid)
    store.save_peer(grid.replace(robot="beta", version=7))
    real = os.replace

    def replace(src, dst):  # kill -9 just before the rename of the file named by ``at``
        if str(dst).endswith(at):
            os.kill(os.getpid(), signal.SIGKILL)
        real(src, dst)

    os.replace = replace
    full = np.full((40, 60), 100, np.int8)
    if what == "peer":
        store.save_peer(grid.replace(robot="beta", version=8, data=full))
    elif what == "base":
        store.save_base(grid.replace(version=2, data=full))
    else:
        store.save_own(grid.replace(version=2, data=full))
"""


def _restored(root: Path, what: str) -> tuple[StateStore, OccupancyGrid | None]:
    store = StateStore(root)
    store.open()
    load = {"own": store.own_map, "base": store.base_map, "peer": lambda: store.peer_map("beta")}
    return store, load[what]()


def _record(root: Path, what: str) -> int:
    doc = json.loads((root / "state.json").read_text())
    return int((doc["peers"]["beta"] if what == "peer" else doc[what])["version"])


@pytest.mark.parametrize("what", ["own", "base", "peer"])
def test_a_map_saved_just_before_a_kill_9_is_restored_with_its_version(tmp_path: Path, what: str) -> None:
    # Killed after the map was written whole, before state.json recorded it: state.json names the
    # old version, the files hold the new one. Its version is in its YAML, so it is not lost.
    root = tmp_path / "state"
    done = _child(KILLED_AT, str(root), what, "state.json")
    assert done.returncode == -9, done.stderr
    new = 8 if what == "peer" else 2
    assert _record(root, what) == new - 1  # the kill came before state.json named the new map
    store, grid = _restored(root, what)
    assert grid is not None and int(grid.data.min()) == 100 and grid.version == new
    if what == "own":
        assert store.next_own_version(0.0) == 3  # the restored version is never given out again
    store.flush()
    assert _record(root, what) == new  # and state.json names it from now on


@pytest.mark.parametrize("what", ["own", "base", "peer"])
def test_a_kill_9_between_the_image_and_its_yaml_keeps_the_old_map_whole(tmp_path: Path, what: str) -> None:
    # The new image is in place under a name of its own; the YAML naming the old image was not
    # replaced, and the old image is still there: the old version loads, the stray image goes.
    root = tmp_path / "state"
    done = _child(KILLED_AT, str(root), what, ".yaml")
    assert done.returncode == -9, done.stderr
    store, grid = _restored(root, what)
    assert grid is not None and int(grid.data.max()) == 0 and grid.version == (7 if what == "peer" else 1)
    folder = root / "peers" / "beta" if what == "peer" else root / "own"
    stem = "base" if what == "base" else "map"
    assert len(list(folder.glob(f"{stem}-*.pgm"))) == 2  # the new image, which no YAML names
    if what == "peer":
        store.save_peer(grid.replace(version=9))
    else:
        (store.save_base if what == "base" else store.save_own)(grid.replace(version=9))
    assert [p.name for p in folder.glob(f"{stem}-*.pgm")] == [f"{stem}-9.pgm"]  # one image a map


def test_an_image_not_matching_its_yaml_is_ignored(tmp_path: Path) -> None:
    store = StateStore(tmp_path)
    store.open()
    grid = OccupancyGrid(np.zeros((40, 60), np.int8), 0.05, robot="beta", version=5)
    store.save_peer(grid)
    image = tmp_path / "peers" / "beta" / "map-5.pgm"
    raw = bytearray(image.read_bytes())
    raw[-1] = 0  # one cell flipped from free to occupied (a disk that lies)
    image.write_bytes(bytes(raw))
    again = StateStore(tmp_path)
    again.open()
    assert again.peer_map("beta") is None


# ---------------------------------------------------------------------- a full disk

FULL_DISK_STATE = """
    import resource, sys
    from pathlib import Path
    import numpy as np
    from mapd.daemon.state import StateStore
    from mapd.errors import StateError
    from mapd.grid import OccupancyGrid

    root = Path(sys.argv[1])
    store = StateStore(root)
    store.open()
    small = OccupancyGrid(np.zeros((20, 20), np.int8), 0.05, robot="alpha", version=1)
    store.save_own(small)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (2000, hard))
    try:
        store.save_own(small.replace(version=2, data=np.zeros((100, 100), np.int8)))
    except StateError as exc:
        print("ERROR", exc)
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    store.save_own(small.replace(version=3))  # the disk has room again: the store goes on
    print("SAVED")
"""


def test_a_full_disk_while_saving_state_is_one_error_and_the_old_state_is_kept(tmp_path: Path) -> None:
    root = tmp_path / "state"
    done = _child(FULL_DISK_STATE.replace("store.save_own(small.replace(version=3))", "pass"), str(root))
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("ERROR ") and "own/map.yaml: cannot write map: File too large" in lines[0]
    assert len(lines) == 2 and lines[1] == "SAVED"
    assert _temps(root) == []  # the failed write's temp file is gone at once
    again = StateStore(root)
    again.open()
    own = again.own_map()
    assert own is not None and own.version == 1 and own.width == 20  # the old map, whole

    done = _child(FULL_DISK_STATE, str(tmp_path / "state2"))
    assert done.returncode == 0 and done.stdout.splitlines()[-1] == "SAVED", done.stderr
    later = StateStore(tmp_path / "state2")
    later.open()
    assert later.own_map() is not None and later.own_map().version == 3  # type: ignore[union-attr]


FULL_DISK_SECRET = """
    import resource, sys
    from pathlib import Path
    from mapd.files import write_new_secret

    path = Path(sys.argv[1])
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (16, hard))
    try:
        write_new_secret(path, b"-----BEGIN PRIVATE KEY-----\\n" + b"A" * 64 + b"\\n")
    except OSError as exc:
        print("ERROR", exc.strerror)
    resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    write_new_secret(path, b"key\\n")  # once there is room, the same command works
    print("WRITTEN")
"""


def test_a_key_that_cannot_be_written_whole_leaves_no_half_key_behind(tmp_path: Path) -> None:
    key = tmp_path / "robot.key"
    done = _child(FULL_DISK_SECRET, str(key))
    # A half key left in place would be refused as "exists" by every later keygen.
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["ERROR File too large", "WRITTEN"]
    assert key.read_bytes() == b"key\n"
    assert oct(key.stat().st_mode & 0o777) == "0o600"


FULL_DISK_PNG = """
    import resource, sys
    import numpy as np
    from mapd.errors import FusionError
    from mapd.fusion.merge import MergeResult, NO_OWNER, Bounds, save_png
    from mapd.grid import OccupancyGrid

    path = sys.argv[1]
    rng = np.random.default_rng(1)
    data = rng.choice(np.array([-1, 0, 100], np.int8), size=(128, 128))
    grid = OccupancyGrid(data, 0.05)
    owner = np.full(data.shape, NO_OWNER, np.uint8)
    result = MergeResult(grid=grid, bounds=Bounds.of_grid(grid), owner=owner)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (1000, hard))
    try:
        save_png(result, path)
    except FusionError as exc:
        print("ERROR", exc)
"""


def test_the_png_preview_is_written_atomically(tmp_path: Path) -> None:
    png = tmp_path / "fused.png"
    png.write_bytes(b"the previous preview")
    done = _child(FULL_DISK_PNG, str(png))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == f"ERROR {png}: cannot write preview: File too large"
    # Written in place, the preview was cut to the first 1000 bytes of a new PNG: a broken image.
    assert png.read_bytes() == b"the previous preview"
    assert _temps(tmp_path) == []


FULL_DISK_FUSION = """
    import asyncio, resource, sys
    from pathlib import Path
    import numpy as np
    from mapd.config import FusionSection
    from mapd.fusion.worker import FusionWorker
    from mapd.grid import OccupancyGrid

    state = Path(sys.argv[1])
    got = []
    rng = np.random.default_rng(2)
    room = OccupancyGrid(rng.choice(np.array([-1, 0, 100], np.int8), size=(120, 120)), 0.05, robot="a")

    async def main():
        worker = FusionWorker("a", FusionSection(), state, [got.append])
        worker.submit(room)
        await worker.merge_now()
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        resource.setrlimit(resource.RLIMIT_FSIZE, (2000, hard))  # the disk fills up
        worker.submit(room.replace(version=2, data=np.zeros((120, 120), np.int8)))
        await worker.merge_now()
        print("GLOBALS", len(got), int(got[-1].data.max()), worker.status()["error"])

    asyncio.run(main())
"""


def test_a_peer_folder_that_cannot_be_made_is_said_once_and_the_map_still_used(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    # A regular file where robot1 makes robot0's folder (as a full disk fails the mkdir): the
    # OSError it raised ended robot1's daemon, and systemd restarted it into the same, for ever.
    caplog.set_level(logging.INFO, logger="mapd.daemon")
    channel = dk.channel()
    d0, s0 = dk.virtual_daemon(tmp_path, "robot0", channel)
    d1, _ = dk.virtual_daemon(tmp_path, "robot1", channel)
    blocker = d1.cfg.state.dir / "peers" / "robot0"
    blocker.parent.mkdir(parents=True)
    blocker.write_bytes(b"")

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d in (d0, d1)]
        try:
            await dk.wait_for(
                lambda: bool(d0.transports) and d0.transports[0].peers() == ["robot1"], what="up"
            )
            for v in (1, 2):
                await s0.queue.put(dk.growing_map(v))
                await dk.wait_for(
                    lambda v=v: split(getattr(d1.receiver.maps.get("robot0"), "version", 0))[1] == v,
                    20,
                    what=f"v{v} held",
                )
            await dk.wait_for(lambda: "robot0" in d1.fusion.status()["robots"], 20, what="fused")
            assert not any(t.done() for t in tasks)  # robot1 runs on
            blocker.unlink()  # room again: the next map is saved
            await s0.queue.put(dk.growing_map(3))
            # The line comes once the save's worker returned; the record is set inside it, before.
            await dk.wait_for(
                lambda: any(r.getMessage() == "state saved again" for r in caplog.records),
                20,
                what="v3 saved",
            )
        finally:
            for d in (d0, d1):
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())
    said = [r.getMessage() for r in caplog.records if "cannot create the folder" in r.getMessage()]
    assert len(said) == 1 and str(blocker) in said[0] and "\n" not in said[0]
    assert any(r.getMessage() == "state saved again" for r in caplog.records)
    assert "Traceback" not in caplog.text


KILLED_AT_GLOBAL = """
    import asyncio, os, signal, sys
    from pathlib import Path
    import numpy as np
    from mapd.config import FusionSection
    from mapd.fusion.worker import FusionWorker
    from mapd.grid import OccupancyGrid, Pose2D

    state = Path(sys.argv[1])
    worker = FusionWorker("robot0", FusionSection(debounce_s=0), state)
    room = np.zeros((100, 100), np.int8)
    room[50, :] = 100  # a wall 2.525 m up the fleet frame
    worker.submit(OccupancyGrid(room, 0.05, robot="robot0", version=1))
    asyncio.run(worker.merge_now())
    # v2: the robot explored 10 m further to -x and -y: the global map grows, its origin moves
    grown = np.full((300, 300), -1, np.int8)
    grown[200:, 200:] = room
    real = os.replace

    def replace(src, dst):  # kill -9 between the new image's rename and the YAML's
        if str(dst).endswith("global.yaml"):
            os.kill(os.getpid(), signal.SIGKILL)
        real(src, dst)

    os.replace = replace
    worker.submit(OccupancyGrid(grown, 0.05, origin=Pose2D(-10.0, -10.0, 0.0), robot="robot0", version=2))
    asyncio.run(worker.merge_now())
"""


def test_a_kill_9_between_the_global_image_and_its_yaml_restores_the_old_map_in_place(
    tmp_path: Path,
) -> None:
    # A fixed global.pgm was renamed first: the old YAML's origin over the new, larger image put
    # the restored wall 12.8 m off, served and filling every merge until all robots sent again.
    from mapd.config import FusionSection
    from mapd.fusion.worker import FusionWorker

    state = tmp_path / "global"
    done = _child(KILLED_AT_GLOBAL, str(state))
    assert done.returncode == -9, done.stderr
    worker = FusionWorker("robot0", FusionSection(debounce_s=0), state)
    worker._load_state()
    g = worker.global_map
    assert g is not None and tuple(g.origin) == (0.0, 0.0, 0.0)
    rows = np.unique(np.nonzero(g.data == 100)[0])
    assert [round(g.origin.y + (r + 0.5) * g.resolution, 3) for r in rows] == [2.525]
    assert len(list(state.glob("global*.pgm"))) == 2  # the new image, which no YAML names yet


def test_a_full_disk_does_not_freeze_the_global_map(tmp_path: Path) -> None:
    # A base station sends no map of its own: with a full disk, fusion was all that stopped, the
    # fleet's global map frozen at the last one that could be written.
    state = tmp_path / "global"
    done = _child(FULL_DISK_FUSION, str(state))
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == ["GLOBALS 2 0 None"]  # the new map (all free) went out
    assert done.stderr.count("global map not saved") == 1  # one clear line
    assert _temps(state) == []
    saved = load_map(state / GLOBAL_YAML)
    assert int(saved.data.max()) == 100  # the last map written is kept whole on disk


# ---------------------------------------------------------------------- CSV logs


def test_a_torn_last_csv_row_is_cut_before_the_next_append(tmp_path: Path) -> None:
    path = tmp_path / "updates.csv"
    CsvLog(path).write([{"time": 1.5, "version": 1, "kind": "keyframe"}])
    with open(path, "ab") as fh:  # power lost in the middle of the second row
        fh.write(b"2.5,2,del")
    CsvLog(path).write([{"time": 3.5, "version": 3, "kind": "delta"}])
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert rows == [
        {"time": "1.5", "version": "1", "kind": "keyframe"},
        {"time": "3.5", "version": "3", "kind": "delta"},
    ]


def test_a_csv_torn_inside_its_header_starts_again(tmp_path: Path) -> None:
    path = tmp_path / "fused.csv"
    path.write_bytes(b"time,rob")
    CsvLog(path).write([{"time": 1.0, "robot": "beta", "version": 4}])
    assert path.read_text() == "time,robot,version\n1.0,beta,4\n"


def test_a_csv_log_rotates_so_it_never_fills_the_disk(tmp_path: Path) -> None:
    path = tmp_path / "fused.csv"
    log = CsvLog(path, max_bytes=200)
    for t in range(100):  # ~20 bytes a row: 2000 bytes in all
        log.write([{"time": float(t), "robot": "beta", "version": t}])
    old = tmp_path / "fused.1.csv"
    assert path.stat().st_size < 200 + 40 and old.stat().st_size < 200 + 40  # two files at most
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fused.1.csv", "fused.csv"]
    rows = []
    for p in (old, path):  # each starts with its header, and together they hold the newest rows
        with open(p, newline="") as fh:
            rows += list(csv.DictReader(fh))
    versions = [int(r["version"]) for r in rows]
    assert versions == list(range(versions[0], 100)) and versions[0] > 0


def test_a_csv_log_that_cannot_be_written_never_stops_coding_a_map(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "file").write_bytes(b"")
    bad = CsvLog(tmp_path / "file" / "updates.csv")  # as a full disk: every append fails
    store = StateStore(tmp_path / "state")
    store.open()
    coder = Coder(
        robot="alpha",
        fleet="lab",
        codec="raw",
        options=None,
        lossless=True,
        measure_quality=False,
        identity=None,
        max_cells=1_000_000,
        store=store,
        log=bad,
    )
    grid = OccupancyGrid(np.zeros((30, 30), np.int8), 0.05, robot="alpha", version=5)
    with caplog.at_level(logging.INFO, logger="mapd.daemon.coding"):
        # The publisher catches MapdError only: an OSError here stopped the daemon.
        assert coder.envelope(grid, None).version == 5
        assert coder.envelope(grid.replace(version=6), None).version == 6
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(errors) == 1 and "cannot write" in errors[0].getMessage()  # one line, not one per row


# ---------------------------------------------------------------------- versions and the clock


def test_own_versions_keep_increasing_across_a_restart_with_the_clock_set_back(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    store = StateStore(tmp_path)
    store.open()
    now = 1_800_000_000.0
    first = store.next_own_version(now)
    store.save_own(room_grid.replace(robot="alpha", version=first))
    again = StateStore(tmp_path)
    again.open()
    # NTP stepped the clock back a year (or a robot without an RTC booted at 1970)
    later = [again.next_own_version(t) for t in (now - 365 * 86400, 0.0, now + 86400)]
    assert first < later[0] < later[1] < later[2]
    assert {split(v)[0] for v in (first, *later)} == {split(first)[0]}


# ---------------------------------------------------------------------- palette PNGs


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _palette_png(
    rows: list[list[int]], chunks: list[tuple[bytes, bytes]], *, plte_after: bool = False
) -> bytes:
    raw = b"".join(b"\x00" + bytes(r) for r in rows)
    ihdr = struct.pack(">IIBBBBB", len(rows[0]), len(rows), 8, 3, 0, 0, 0)
    idat = _chunk(b"IDAT", zlib.compress(raw))
    extra = b"".join(_chunk(k, d) for k, d in chunks)
    body = idat + extra if plte_after else extra + idat
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + body + _chunk(b"IEND", b"")


GREYS = bytes([0, 0, 0, 128, 128, 128, 254, 254, 254])  # three colours: wall, grey, free


@pytest.mark.parametrize(
    ("case", "chunks", "plte_after", "match"),
    [
        ("no PLTE", [], False, "without a PLTE chunk"),
        ("PLTE after IDAT", [(b"PLTE", GREYS)], True, "without a PLTE chunk"),
        ("two PLTE", [(b"PLTE", GREYS), (b"PLTE", GREYS)], False, "a second PLTE"),
        ("ragged PLTE", [(b"PLTE", GREYS[:-1])], False, "a PLTE chunk of 8 bytes"),
        ("empty PLTE", [(b"PLTE", b"")], False, "a PLTE chunk of 0 bytes"),
        ("index past it", [(b"PLTE", GREYS[:6])], False, "pixel index 2 lies beyond its palette of 2"),
    ],
)
def test_palette_pngs_libpng_refuses_are_refused(
    tmp_path: Path, case: str, chunks: list[tuple[bytes, bytes]], plte_after: bool, match: str
) -> None:
    # Pillow decodes each of these, every pixel it has no colour for as black: a wall on the map.
    path = tmp_path / "map.png"
    path.write_bytes(_palette_png([[0, 1, 2], [2, 1, 0]], chunks, plte_after=plte_after))
    with pytest.raises(MapFileError, match=match):
        read_pixels(path, "map.yaml", 1000)


def test_a_well_formed_palette_png_still_reads(tmp_path: Path) -> None:
    path = tmp_path / "map.png"
    path.write_bytes(_palette_png([[0, 1, 2], [2, 1, 0]], [(b"PLTE", GREYS)]))
    pixels = read_pixels(path, "map.yaml", 1000)
    assert pixels.arr[..., 0].tolist() == [[0, 128, 254], [254, 128, 0]]


def test_a_failing_recording_is_said_once_and_its_recovery_too(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A full recording disk logged one error a message (99 in 12 s) and nothing when space returned."""
    import logging

    from mapd.daemon.coding import CsvLog
    from mapd.daemon.sinks import Sinks

    sinks = Sinks([], None, CsvLog(tmp_path / "fused.csv"))
    full = [True]

    def write(i: int) -> None:
        if full[0]:
            raise OSError(28, "No space left on device")

    with caplog.at_level(logging.INFO, logger="mapd"):
        for i in range(5):
            sinks._record(write, i)
        sinks._files.submit(lambda: full.__setitem__(0, False))
        sinks._record(write, 5)
        sinks.close()
    said = [r.getMessage() for r in caplog.records if "record" in r.getMessage()]
    assert sinks.record_failures == 5
    assert len(said) == 2 and "No space left" in said[0] and said[1] == "recording again", said


def test_a_slow_recording_disk_holds_a_bounded_backlog_and_says_so_once(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A disk that is slow rather than full (an SD card stalling): the file thread's queue held
    every map the fleet made meanwhile, without bound."""
    import logging
    import threading

    from mapd.commands.status_text import render_status
    from mapd.daemon import sinks as sinksmod
    from mapd.daemon.coding import CsvLog

    monkeypatch.setattr(sinksmod, "MAX_QUEUED_BYTES", 10_000)
    sinks = sinksmod.Sinks([], None, CsvLog(tmp_path / "fused.csv"))
    # (only for recording(): nothing is written through it here)
    sinks.recorder = SimpleNamespace(removed=0)  # type: ignore[assignment]
    stalled, written = threading.Event(), []
    high = [0]

    def write(grid: OccupancyGrid) -> None:
        stalled.wait(30)
        written.append(grid.version)

    big = OccupancyGrid(np.zeros((200, 200), np.int8), 0.05, version=0)  # over the budget on its own
    with caplog.at_level(logging.INFO, logger="mapd"):
        sinks._record(write, big)  # taken: the queue was empty
        for v in range(1, 41):
            sinks._record(write, OccupancyGrid(np.zeros((50, 80), np.int8), 0.05, version=v))
            high[0] = max(high[0], sinks._queued)
        assert sinks.record_dropped == 40 and high[0] == 40_000  # the big map alone, nothing more
        stalled.set()
        sinks._files.submit(lambda: None).result(10)
        for v in range(41, 44):  # the disk keeps up again
            sinks._record(write, OccupancyGrid(np.zeros((50, 80), np.int8), 0.05, version=v))
            sinks._files.submit(lambda: None).result(10)
        rec = sinks.recording()
        assert rec is not None and rec["dropped"] == 40
        assert "40 left out behind a slow disk" in render_status({"recording": rec})
        sinks.recorder = None
        sinks.close()
    assert written == [0, 41, 42, 43]
    said = [r.getMessage() for r in caplog.records if "recording" in r.getMessage()]
    assert len(said) == 2 and "behind the disk" in said[0] and said[1].startswith("recording caught up"), said


def test_a_report_written_again_is_whole_or_as_it_was(tmp_path: Path) -> None:
    """Reports (the paper bench's results.json and figures, the demo's) were written in place: a run
    stopped mid-write left the last run's results cut short."""
    from mapd.files import atomic_write_via

    path = tmp_path / "results.json"
    atomic_write_via(path, lambda fh: fh.write(b'{"run": 1}'))

    def fails_half_way(fh: Any) -> None:
        fh.write(b'{"run": 2, "rows": [')
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        atomic_write_via(path, fails_half_way)
    assert path.read_bytes() == b'{"run": 1}' and _temps(tmp_path) == []


def test_the_sweep_keeps_a_temp_file_that_a_write_is_filling_now(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The sweep runs while other threads write (the files output starts beside the state): a
    temp file in use is kept, whatever its name, and the write completes."""
    import threading

    from mapd import files

    entered, release = threading.Event(), threading.Event()
    real_fsync = os.fsync

    def slow_fsync(fd: int) -> None:
        entered.set()
        release.wait(30)
        real_fsync(fd)

    monkeypatch.setattr(files.os, "fsync", slow_fsync)
    target = tmp_path / "map.pgm"
    writer = threading.Thread(target=files.atomic_write_bytes, args=(target, b"P5 new"))
    writer.start()
    try:
        assert entered.wait(30)
        (in_flight,) = _temps(tmp_path)
        stale = tmp_path / ".map.yaml.tmp999999.1"
        stale.write_bytes(b"left by a crash")
        assert files.remove_stale_temps(tmp_path) == [stale]
        assert in_flight.exists()
    finally:
        release.set()
        writer.join(30)
    assert target.read_bytes() == b"P5 new"
    assert _temps(tmp_path) == []


def test_a_replaced_file_keeps_the_mode_an_operator_gave_it(tmp_path: Path) -> None:
    """``chmod o+r map.pgm`` for a map_server of another user must survive the next write."""
    from mapd.files import atomic_write_bytes, atomic_write_files

    one, two = tmp_path / "map.pgm", tmp_path / "map.yaml"
    atomic_write_files([(one, b"a"), (two, b"b")])
    one.chmod(0o644)
    two.chmod(0o604)
    atomic_write_files([(one, b"c"), (two, b"d")])
    assert (one.stat().st_mode & 0o777, two.stat().st_mode & 0o777) == (0o644, 0o604)
    assert one.read_bytes() == b"c"
    fresh = tmp_path / "new.json"
    atomic_write_bytes(fresh, b"{}")  # a new file: the umask decides, as for any file
    assert fresh.stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_the_record_settings_reach_the_daemons_recorder(tmp_path: Path, dk: SimpleNamespace) -> None:
    """``[record] max_total_bytes`` and ``min_free_bytes`` are what the running recorder keeps to
    (the daemon once built it with max_bytes alone: the defaults, whatever the config said)."""
    from mapd import config as configmod
    from mapd.daemon.server import Daemon

    rec = tmp_path / "rec" / "fleet.mcap"
    path = dk.write_config(
        tmp_path, "robot0",
        record=f'path = "{rec}"\nmax_bytes = 2097152\nmax_total_bytes = 6291456\nmin_free_bytes = 1048576',
    )  # fmt: skip
    d = Daemon(configmod.load(path), source=dk.QueueSource("robot0"))
    recorder = d.sinks.recorder
    assert recorder is not None
    disk = recorder.disk
    assert (disk.max_bytes, disk.max_total_bytes, disk.min_free_bytes) == (
        2 << 20,
        6 << 20,
        1 << 20,
    )
