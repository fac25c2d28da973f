"""Hostile and damaged map files: every one is one MapFileError (or LimitError) line, never a crash.

Attacks measured before the fix: a PGM cut after ``P5\\n100 `` crashed the mapfile source; 38 of the
first 200 prefixes of a real PGM gave tracebacks in ``mapd info``; so did maxval 0 and 65536; a PNG
whose zlib stream holds too few rows loaded as 90 % walls; an 80 KB 8192 x 8192 PNG took 2.35 GB in
``mapd info``; a 400-digit origin, a date where a number belongs, nested YAML and ``/dev/zero`` as a
map or an image gave tracebacks or hung.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import time
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from mapd.errors import LimitError, MapdError, MapFileError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import MAX_YAML_BYTES, load_map, read_map_yaml
from mapd.grid.save import save_map
from mapd.imaging import PLAIN_PNM_MAX_CELLS
from mapd.mapping.synthetic import room_grid

YAML = "image: {image}\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"


def _yaml_for(tmp: Path, image: str, name: str = "m.yaml") -> Path:
    y = tmp / name
    y.write_text(YAML.format(image=image))
    return y


@pytest.fixture(scope="module")
def grid() -> OccupancyGrid:
    # A real-looking map: walls, a box, speckle, unknown around; graded values take raw mode.
    return room_grid(48, 64, seed=3, origin=Pose2D(-1.0, 2.0, 0.0))


@pytest.fixture(scope="module")
def pgm_bytes(grid: OccupancyGrid, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    d = tmp_path_factory.mktemp("pgm")
    save_map(grid, d / "full.yaml")
    return (d / "full.pgm").read_bytes()


@pytest.fixture(scope="module")
def png_bytes(grid: OccupancyGrid, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    d = tmp_path_factory.mktemp("png")
    Image.fromarray(grid.to_image()).save(d / "full.png")
    return (d / "full.png").read_bytes()


def _refuses_every_prefix(tmp: Path, whole: bytes, ext: str, cuts: list[int] | range) -> None:
    image = tmp / f"cut.{ext}"
    y = _yaml_for(tmp, image.name)
    for cut in cuts:
        image.write_bytes(whole[:cut])
        with pytest.raises(MapFileError) as info:
            load_map(y)
        msg = str(info.value)
        assert "\n" not in msg and str(y) in msg, (cut, msg)


def test_every_prefix_of_a_pgm_is_refused(tmp_path: Path, pgm_bytes: bytes, grid: OccupancyGrid) -> None:
    _refuses_every_prefix(tmp_path, pgm_bytes, "pgm", range(len(pgm_bytes)))
    (tmp_path / "cut.pgm").write_bytes(pgm_bytes)  # and the whole file loads, exactly
    assert load_map(tmp_path / "m.yaml").data.tolist() == grid.data.tolist()


def test_every_prefix_of_a_png_is_refused(tmp_path: Path, png_bytes: bytes, grid: OccupancyGrid) -> None:
    _refuses_every_prefix(tmp_path, png_bytes, "png", range(len(png_bytes)))
    (tmp_path / "cut.png").write_bytes(png_bytes)
    assert load_map(tmp_path / "m.yaml").data.tolist() == grid.data.tolist()


def _shared_image(shared_maps: list[Path], suffix: str) -> Path:
    images = [read_map_yaml(y)["image"] for y in shared_maps]
    picked = sorted((p for p in images if p.suffix == suffix), key=lambda p: p.stat().st_size)
    if not picked:
        pytest.skip(f"no shared {suffix} map")
    return picked[0]


@pytest.mark.parametrize("suffix", [".pgm", ".png"])
def test_prefixes_of_a_real_shared_map_are_refused(
    tmp_path: Path, shared_maps: list[Path], suffix: str
) -> None:
    whole = _shared_image(shared_maps, suffix).read_bytes()
    n = len(whole)
    # Every cut in the header and the first pixel rows, then spread over the file, then the tail.
    cuts = sorted({*range(min(n, 400)), *range(0, n, max(1, n // 150)), *range(max(0, n - 40), n)})
    _refuses_every_prefix(tmp_path, whole, suffix[1:], cuts)


# In a child process, through the CLI's own error handling: a crash (even a segfault) would show.
_CLI_PREFIXES = """
import contextlib, io, json, sys
from pathlib import Path
from mapd.cli import main
whole = Path(sys.argv[1]).read_bytes()
image, yaml = Path(sys.argv[2]), sys.argv[3]
for cut in range(int(sys.argv[4])):
    image.write_bytes(whole[:cut])
    err, out = io.StringIO(), io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            rc = main(["info", yaml])
        except BaseException as exc:  # what would reach the console as a traceback
            rc = f"{type(exc).__name__}: {exc}"
    print(json.dumps([cut, rc, err.getvalue()]))
"""


@pytest.mark.parametrize("ext", ["pgm", "png"])
def test_mapd_info_gives_one_error_line_for_every_prefix(
    tmp_path: Path, pgm_bytes: bytes, png_bytes: bytes, ext: str
) -> None:
    whole = pgm_bytes if ext == "pgm" else png_bytes
    (tmp_path / "whole").write_bytes(whole)
    y = _yaml_for(tmp_path, f"cut.{ext}")
    count = min(len(whole), 400)
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            _CLI_PREFIXES,
            str(tmp_path / "whole"),
            str(tmp_path / f"cut.{ext}"),
            str(y),
            str(count),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    rows = [json.loads(line) for line in out.stdout.splitlines()]
    assert len(rows) == count
    for cut, rc, err in rows:
        assert rc == 1, (cut, rc, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mapd: error: "), (cut, err)


@pytest.mark.parametrize(
    ("image", "match"),
    [
        (b"P5\n100 ", "truncated in its PNM header"),  # the cut that crashed the mapfile source
        (b"P5\n4 4\n0\n" + bytes(16), "maxval 0"),
        (b"P5\n4 4\n65536\n" + bytes(32), "maxval 65536"),
        (b"P5\n4 4\n255\n" + bytes(15), "ends early: 15 of 16"),
        (b"P5\n-4 4\n255\n" + bytes(16), "malformed PNM header"),
        (b"P5\n9999999999 4\n255\n", "malformed PNM header"),
        (b"P6\n2 2\n255\n" + bytes(11), "ends early"),
        (b"P5 4 4 255x" + bytes(16), "no white space"),  # no separator before the pixels
        (b"P4\n9 2\n" + bytes(3), "ends early"),
        (b"P2\n2 2\n255\n1 2 3", "ends early"),
        (b"Pf\n2 2\n-1\n" + bytes(16), "not an image mapd reads"),
        (b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 1 1\n", "not an image mapd reads"),
    ],
)
def test_malformed_pnm_through_the_cli(
    tmp_path: Path,
    image: bytes,
    match: str,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    (tmp_path / "m.pgm").write_bytes(image)
    line = one_error_line(mapd_run("info", str(_yaml_for(tmp_path, "m.pgm"))), code=1)
    assert match in line


def _png(width: int, height: int, raw_rows: bytes, *, crc_ok: bool = True, iend: bool = True) -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        crc = zlib.crc32(kind + data) ^ (0 if crc_ok or kind != b"IDAT" else 1)
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    out = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw_rows))
    return out + (chunk(b"IEND", b"") if iend else b"")


def test_png_whose_data_stops_early_is_refused_not_padded(tmp_path: Path) -> None:
    # A complete, valid zlib stream holding 10 of 100 rows: Pillow pads the rest black (= walls).
    rows = b"".join(b"\x00" + bytes([254]) * 100 for _ in range(10))
    (tmp_path / "m.png").write_bytes(_png(100, 100, rows))
    y = _yaml_for(tmp_path, "m.png")
    with pytest.raises(MapFileError, match=r"ends early: its pixel data holds 1010 of 10100 bytes"):
        load_map(y)
    full = rows * 10
    (tmp_path / "m.png").write_bytes(_png(100, 100, full))
    assert load_map(y).counts() == {"free": 10_000, "occupied": 0, "unknown": 0}
    (tmp_path / "m.png").write_bytes(_png(100, 100, full, crc_ok=False))
    with pytest.raises(MapFileError, match="CRC mismatch in its IDAT chunk"):
        load_map(y)
    (tmp_path / "m.png").write_bytes(_png(100, 100, full, iend=False))
    with pytest.raises(MapFileError, match="before its IEND"):
        load_map(y)


def test_image_size_is_checked_from_the_header_before_decoding(tmp_path: Path) -> None:
    # 80 KB of PNG that decodes to 67 M pixels, and a PGM header with nothing behind it.
    rows = zlib.compress(b"".join(b"\x00" + bytes(8192) for _ in range(8192)), 9)
    (tmp_path / "big.png").write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + struct.pack(">I", 13)
        + b"IHDR"
        + (ihdr := struct.pack(">IIBBBBB", 8192, 8192, 8, 0, 0, 0, 0))
        + struct.pack(">I", zlib.crc32(b"IHDR" + ihdr))
        + struct.pack(">I", len(rows))
        + b"IDAT"
        + rows
        + struct.pack(">I", zlib.crc32(b"IDAT" + rows))
    )
    t0 = time.perf_counter()
    with pytest.raises(LimitError, match="8192x8192 = 67108864 cells, over the limit of 1000000"):
        load_map(_yaml_for(tmp_path, "big.png"), max_cells=1_000_000)
    assert time.perf_counter() - t0 < 0.5  # refused from IHDR: nothing was inflated
    (tmp_path / "big.pgm").write_bytes(b"P5\n8192 8192\n255\n")
    with pytest.raises(LimitError, match="over the limit of 1000000"):
        load_map(_yaml_for(tmp_path, "big.pgm"), max_cells=1_000_000)


def test_plain_pnm_has_its_own_smaller_limit(tmp_path: Path) -> None:
    side = int(PLAIN_PNM_MAX_CELLS**0.5) + 1
    (tmp_path / "m.pgm").write_bytes(b"P2\n%d %d\n255\n" % (side, side) + b"0 " * (side * side))
    with pytest.raises(LimitError, match=r"plain \(ASCII\) PNM"):
        load_map(_yaml_for(tmp_path, "m.pgm"))
    (tmp_path / "s.pgm").write_bytes(b"P2\n# a comment\n3 1\n255\n254 0\n205\n")
    assert load_map(_yaml_for(tmp_path, "s.pgm")).data.tolist() == [[0, 100, -1]]


def test_mapd_info_of_an_8192_square_png_stays_small(
    tmp_path: Path, in_child: Callable[..., dict[str, Any]]
) -> None:
    # At the default cell limit exactly (8192 x 8192): it loads, in a few bytes a cell.
    Image.new("L", (8192, 8192), 254).save(tmp_path / "big.png")
    _yaml_for(tmp_path, "big.png", "big.yaml")
    save_map(room_grid(), tmp_path / "small.yaml")
    code = """
    import contextlib, io
    from mapd.cli import main
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["info", {small!r}]) == 0
        before = peak_mb()
        t0 = time.perf_counter()
        rc = main(["info", {big!r}])
    report(rc=rc, before=before, after=peak_mb(), seconds=time.perf_counter() - t0)
    """
    got = in_child(code.format(small=str(tmp_path / "small.yaml"), big=str(tmp_path / "big.yaml")))
    assert got["rc"] == 0
    # Before the fix: 2.35 GB. Now the pixels, the cells and bands of temporaries: about 3 B a cell.
    cells_mb = 8192 * 8192 / 2**20
    assert got["after"] - got["before"] < 6 * cells_mb, got


# --------------------------------------------------------------------------- YAML


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "image: m.pgm\nresolution: 0.05\norigin: [1" + "0" * 400 + ", 0, 0]\n",
            "origin must hold three numbers",
        ),
        (
            "image: m.pgm\nresolution: 1" + "0" * 400 + "\norigin: [0, 0, 0]\n",
            "key 'resolution' must be a float",
        ),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: 2001-13-45\n", "malformed YAML"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 0]\nnegate: !!float x\n", "malformed YAML"),
        ("image: m.pgm\nresolution: 0.05\norigin: &o [*o, *o, *o]\n", "origin must hold three numbers"),
        ("image: m.pgm\nresolution: 0.05\norigin: [1.0e+9, 0, 0]\n", "origin x 1000000000.0 is not within"),
        ("image: m.pgm\nresolution: 1.0e-9\norigin: [0, 0, 0]\n", "resolution 1e-09 m/cell is not within"),
        ("image: m.pgm\nresolution: 0.05\norigin: [0, 0, 100.0]\n", "origin yaw 100.0 is not within"),
        ("image: m.pgm\nresolution: 0.05\norigin: [true, 0, 0]\n", "origin must hold three numbers"),
        ("image: m.pgm\nresolution: 0.05\norigin: " + "[" * 5000 + "]" * 5000 + "\n", "nested too deeply"),
        ("a: " + "{b: " * 3000 + "1" + "}" * 3000 + "\n", "nested too deeply"),
        # a newline in the image's name went into the error as it was: a second, forged error line
        (
            'image: "nofile\\nmapd: error: forged line"\nresolution: 0.05\norigin: [0, 0, 0]\n',
            "key 'image' must name an image file, got 'nofile\\nmapd: error: forged line'",
        ),
    ],
)
def test_hostile_yaml_through_the_cli(
    tmp_path: Path,
    text: str,
    match: str,
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
) -> None:
    (tmp_path / "m.pgm").write_bytes(b"P5\n1 1\n255\n\xfe")
    (tmp_path / "m.yaml").write_text(text)
    line = one_error_line(mapd_run("info", str(tmp_path / "m.yaml")), code=1)
    assert match in line


def test_yaml_over_the_size_limit_is_refused_unread(tmp_path: Path) -> None:
    y = tmp_path / "m.yaml"
    y.write_text(YAML.format(image="m.pgm") + "#" * MAX_YAML_BYTES)
    with pytest.raises(MapFileError, match=f"over {MAX_YAML_BYTES} bytes"):
        load_map(y)


def test_devices_and_fifos_are_refused_at_once(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "fifo.pgm")  # opening a FIFO for reading would wait for a writer
    cases = [
        (Path("/dev/zero"), "not a regular file"),  # a map yaml read forever
        (_yaml_for(tmp_path, "/dev/zero", "zero.yaml"), "image '/dev/zero' is not a regular file"),
        (_yaml_for(tmp_path, "fifo.pgm", "fifo.yaml"), "fifo.pgm' is not a regular file"),
        (_yaml_for(tmp_path, str(tmp_path), "dir.yaml"), "is not a regular file"),
        (tmp_path, "not a regular file"),
    ]
    for path, match in cases:
        t0 = time.perf_counter()
        with pytest.raises(MapFileError, match=match):
            load_map(path)
        assert time.perf_counter() - t0 < 1.0


def test_bytes_fuzz_of_pgm_and_png_gives_only_mapd_errors(
    pgm_bytes: bytes, png_bytes: bytes, tmp_path: Path
) -> None:
    # Flipped bytes anywhere (header, chunk lengths, pixels): a map or a MapdError, nothing else.
    rng = np.random.default_rng(7)
    for whole, ext in ((pgm_bytes, "pgm"), (png_bytes, "png")):
        y = _yaml_for(tmp_path, f"f.{ext}", f"f{ext}.yaml")
        for _ in range(300):
            bad = bytearray(whole)
            for i in rng.integers(
                0, min(len(bad), 120 if rng.random() < 0.7 else len(bad)), size=rng.integers(1, 4)
            ):
                bad[int(i)] ^= int(rng.integers(1, 256))
            (tmp_path / f"f.{ext}").write_bytes(bytes(bad))
            try:
                g = load_map(y, max_cells=1 << 20)
            except MapdError as exc:
                assert "\n" not in str(exc)
                continue
            assert g.data.dtype == np.int8 and g.cells <= 1 << 20


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_a_float_image_of_nan_or_inf_is_refused_not_loaded_as_free(tmp_path: Path, value: float) -> None:
    """A 32-bit float TIFF (Pillow's mode F) of NaN loaded as 100 % free in raw mode."""
    from PIL import Image

    pixels = np.full((10, 10), 200.0, np.float32)
    pixels[3, 4] = value
    Image.fromarray(pixels, mode="F").save(tmp_path / "f.tif")
    y = tmp_path / "f.yaml"
    y.write_text(YAML.format(image="f.tif") + "mode: raw\n")
    with pytest.raises(MapFileError, match="not numbers"):
        load_map(y)
