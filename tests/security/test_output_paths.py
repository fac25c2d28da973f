"""Output paths the commands are given: what they name must be written, or refused in one line.

Each of these failed before its fix:

* ``mapd encode MAP -o /dev/null`` as root replaced the null device with a regular file (the atomic
  write renamed its temp file over whatever the name held: a device, a FIFO, a symlink);
* ``mapd decode P -o out.pgm`` wrote the YAML over the image it names (exit 0, the map lost), and
  ``merge --png`` the preview over the merged map;
* ``-o .`` (or ``''``, ``/``) ended in a ValueError traceback, and a legal 245-character name was
  refused (its temp file's name was too long);
* ``merge`` said "at most 254 maps" only after placing every map against the others, and
  ``--pose '²=0,0,0'`` ended in a traceback;
* the merge preview took 80 bytes a cell in float temporaries (5.6 GB at the cell limit).
"""

from __future__ import annotations

import os
import stat
import subprocess
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from mapd.errors import MapFileError
from mapd.files import atomic_write_bytes
from mapd.files.reading import NotRegularFileError
from mapd.fusion.merge import NO_OWNER, MergeResult, colour_image
from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map
from mapd.grid.save import save_map

Run = Callable[..., subprocess.CompletedProcess[str]]
OneLine = Callable[..., str]


def _map(tmp_path: Path, name: str = "m.yaml") -> Path:
    data = np.full((40, 60), -1, np.int8)
    data[5:35, 5:55] = 0
    data[5, 5:55] = 100
    return save_map(OccupancyGrid(data, 0.05, (-1.0, -1.0, 0.0)), tmp_path / name)


def _null_device(tmp_path: Path) -> Path | None:
    """A null device of our own (never the system's: a broken fix would replace it), where allowed."""
    try:
        os.mknod(tmp_path / "null", 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:
        return None
    return tmp_path / "null"


def test_atomic_write_refuses_what_is_not_a_regular_file(tmp_path: Path) -> None:
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    (tmp_path / "dir").mkdir()
    null = _null_device(tmp_path)  # (root only, as the user it hit)
    for target in (fifo, tmp_path / "dir", *([null] if null else [])):
        with pytest.raises(NotRegularFileError):
            atomic_write_bytes(target, b"x")
    assert fifo.is_fifo() and (null is None or null.is_char_device())
    for target in (Path("."), Path("/"), tmp_path / ".."):
        with pytest.raises(IsADirectoryError):
            atomic_write_bytes(target, b"x")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["dir", "fifo", *(["null"] if null else [])])


def test_atomic_write_goes_through_a_symlink_and_takes_a_long_name(tmp_path: Path) -> None:
    real = tmp_path / "real.bin"
    real.write_bytes(b"old")
    link = tmp_path / "link.bin"
    link.symlink_to(real)
    atomic_write_bytes(link, b"new")
    assert link.is_symlink() and real.read_bytes() == b"new"
    long = tmp_path / ("n" * 250)  # a legal name; its temp file once was not
    atomic_write_bytes(long, b"x")
    assert long.read_bytes() == b"x"
    utf8 = tmp_path / ("é" * 120)  # 240 bytes: the temp name is cut in bytes, not characters
    atomic_write_bytes(utf8, b"y")
    assert utf8.read_bytes() == b"y"


def test_encode_to_a_device_or_fifo_is_refused(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    src = _map(tmp_path)
    fifo = tmp_path / "out.fifo"
    os.mkfifo(fifo)
    null = _null_device(tmp_path)
    for out in (fifo, *([null] if null else [])):
        line = one_error_line(mapd_run("encode", str(src), "-o", str(out), "--codec", "raw"))
        assert "not a regular file" in line, line
    assert fifo.is_fifo() and (null is None or null.is_char_device())


def test_a_map_named_pgm_is_refused_not_written_over_its_image(tmp_path: Path) -> None:
    grid = load_map(_map(tmp_path, "src.yaml"))
    with pytest.raises(MapFileError, match=r"name the YAML NAME\.yaml"):
        save_map(grid, tmp_path / "out.pgm")
    assert not (tmp_path / "out.pgm").exists()


def test_decode_to_a_directory_or_pgm_name_is_one_line(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    payload = tmp_path / "m.mapd"
    assert mapd_run("encode", str(_map(tmp_path)), "-o", str(payload), "--codec", "raw").returncode == 0
    for out, says in ((".", "is a directory"), ("", "is a directory"), ("out.pgm", "NAME.yaml")):
        line = one_error_line(mapd_run("decode", str(payload), "-o", out, cwd=tmp_path))
        assert says in line, line
    assert not (tmp_path / "out.pgm").exists()


def test_merge_refuses_a_preview_over_its_output_and_too_many_maps_at_once(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    a, b = _map(tmp_path, "a.yaml"), _map(tmp_path, "b.yaml")
    for png in ("out.yaml", "out.pgm"):
        line = one_error_line(mapd_run("merge", str(a), str(b), "-o", "out.yaml", "--png", png, cwd=tmp_path))
        assert "the merged map's own file" in line, line
    assert not (tmp_path / "out.yaml").exists()
    many = [str(tmp_path / f"m{i}.yaml") for i in range(NO_OWNER)]  # refused before any is read
    line = one_error_line(mapd_run("merge", *many, "-o", "out.yaml", cwd=tmp_path, timeout=30))
    assert f"at most {NO_OWNER - 1} maps" in line, line
    line = one_error_line(
        mapd_run("merge", str(a), str(b), "-o", "out.yaml", "--pose", "²=0,0,0", cwd=tmp_path)
    )
    assert "no input named" in line, line


def test_the_merge_preview_takes_a_few_bytes_a_cell() -> None:
    h, w = 2000, 2000
    rng = np.random.default_rng(1)
    data = rng.integers(-1, 101, (h, w)).astype(np.int8)
    owner = rng.integers(0, 4, (h, w)).astype(np.uint8)
    result = MergeResult(OccupancyGrid(data, 0.05), None, owner)  # type: ignore[arg-type]  # (bounds: unused)
    tracemalloc.start()
    try:
        rgb = colour_image(result)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert rgb.shape == (h, w, 3) and rgb[0, 0].tolist() != [0, 0, 0]
    assert peak < rgb.nbytes + (40 << 20), peak  # before: 80 bytes a cell, 320 MB here


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file in ``folder`` (symlinks by target name), to show a refused command changed none."""
    return {
        p.name: (os.readlink(p).encode() if p.is_symlink() else p.read_bytes() if p.is_file() else b"dir")
        for p in sorted(folder.iterdir())
    }


def test_encode_decode_and_merge_refuse_to_write_over_their_own_inputs(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    """``encode in.yaml -o in.yaml`` replaced the map by a payload (exit 0); decode and merge alike."""
    a = _map(tmp_path, "a.yaml")
    _map(tmp_path, "b.yaml")
    payload = tmp_path / "a.mapd"
    assert mapd_run("encode", str(a), "-o", str(payload), "--codec", "raw").returncode == 0
    (tmp_path / "via_link.yaml").symlink_to("a.yaml")  # the output reached through a symlink
    (tmp_path / "sub").mkdir()
    before = _tree(tmp_path)
    cases = [
        (["encode", "a.yaml", "-o", "a.yaml"], "input map a.yaml"),
        (["encode", "a.yaml", "-o", "a.pgm"], "the image"),  # the image the YAML names
        (["encode", "a.yaml", "-o", "via_link.yaml"], "input map a.yaml"),
        (["encode", "a.yaml", "-o", "sub/../b.pgm", "--base", "b.yaml"], "--base b.yaml"),
        (["decode", "a.mapd", "-o", "a.mapd"], "the payload a.mapd"),
        (["decode", "a.mapd", "-o", "b.yaml", "--base", "b.yaml"], "--base b.yaml"),
        (["merge", "a.yaml", "b.yaml", "-o", "a.yaml", "--pose", "1=0,0,0"], "input map a.yaml"),
        (["merge", "a.yaml", "b.yaml", "-o", "out.yaml", "--png", "b.pgm"], "input map b.yaml"),
        (["merge", "a.yaml", "b.yaml", "-o", "via_link.yaml"], "input map a.yaml"),
    ]
    for args, says in cases:
        out = mapd_run(*args, cwd=tmp_path)
        line = one_error_line(out, code=2)
        assert "refusing to write over an input" in line and says in line, (args, line)
        assert _tree(tmp_path) == before, args
    # a payload decoded beside (not over) its source is fine: the check is no blanket refusal
    assert mapd_run("decode", "a.mapd", "-o", "copy.yaml", cwd=tmp_path).returncode == 0


def test_merge_checks_its_preview_path_before_writing_anything(
    tmp_path: Path, mapd_run: Run, one_error_line: OneLine
) -> None:
    """A --png in a missing folder was found only after the merged map had been written."""
    a, b = _map(tmp_path, "a.yaml"), _map(tmp_path, "b.yaml")
    (tmp_path / "adir").mkdir()
    for png, says in (("nodir/x.png", "no such directory"), ("adir", "is a directory")):
        args = ("merge", str(a), str(b), "-o", "out.yaml", "--pose", "0=0,0,0", "--png", png)
        line = one_error_line(mapd_run(*args, cwd=tmp_path), code=2)
        assert f"--png {png}" in line and says in line, line
        assert not (tmp_path / "out.yaml").exists() and not (tmp_path / "out.pgm").exists()
