"""Hostile JPEG map images: a scan bomb is one LimitError line before libjpeg decodes it.

Measured before the fix: a 560 KB progressive 8192 x 8192 JPEG whose last refinement scan is
repeated 3000 times kept ``mapd info`` busy for over a minute (libjpeg decodes every scan over the
whole image, and has no scan limit). Real JPEGs (baseline, progressive, grey, colour, CMYK, restart
markers, large APP segments) still load exactly as Pillow decodes them.
"""

from __future__ import annotations

import io
import re
import subprocess
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from mapd.errors import LimitError, MapFileError
from mapd.grid.load import load_map
from mapd.imaging.jpeg import MAX_JPEG_SCANS, check_jpeg
from mapd.mapping.synthetic import room_grid

YAML = "image: {image}\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n"
Run = Callable[..., subprocess.CompletedProcess[str]]
OneLine = Callable[..., str]


def _write_map(tmp: Path, data: bytes, name: str = "m") -> Path:
    """A map YAML beside ``name``.jpg holding ``data``; returns the YAML's path."""
    (tmp / f"{name}.jpg").write_bytes(data)
    y = tmp / f"{name}.yaml"
    y.write_text(YAML.format(image=f"{name}.jpg"))
    return y


def _jpeg(img: Image.Image, **kw: Any) -> bytes:
    b = io.BytesIO()
    img.save(b, "JPEG", **kw)
    return b.getvalue()


def _map_image(h: int = 96, w: int = 128) -> Image.Image:
    """A real-looking map (walls, free space, unknown) as a grey image."""
    return Image.fromarray(room_grid(h, w, seed=5).to_image())


def _scans(data: bytes) -> list[tuple[int, int]]:
    """(start, end) of each scan (SOS segment and its entropy-coded data) of a JPEG Pillow wrote.

    Written for Pillow's well-formed output only (no fill bytes), independently of the checker.
    """
    out = []
    i = 2
    while True:
        assert data[i] == 0xFF, i
        code = data[i + 1]
        if code == 0xD9:
            return out
        length = int.from_bytes(data[i + 2 : i + 4], "big")
        if code != 0xDA:
            i += 2 + length
            continue
        j = i + 2 + length
        while not (data[j] == 0xFF and data[j + 1] != 0 and not 0xD0 <= data[j + 1] <= 0xD7):
            j += 1
        out.append((i, j))
        i = j


def _repeat_last_scan(data: bytes, total: int, sep: bytes = b"") -> bytes:
    """``data`` (progressive) with its last scan (an AC refinement) repeated up to ``total`` scans.

    libjpeg decodes every copy over the whole image, warning at most. ``sep`` goes before each
    copy (fill bytes, which libjpeg skips).
    """
    scans = _scans(data)
    a, e = scans[-1]
    extra = total - len(scans)
    assert extra >= 0
    return data[:e] + (sep + data[a:e]) * extra + data[e:]


@pytest.fixture(scope="module")
def progressive() -> bytes:
    return _jpeg(_map_image(), progressive=True, quality=90)


def test_a_scan_bomb_is_one_limit_error_line(tmp_path: Path, progressive: bytes) -> None:
    y = _write_map(tmp_path, _repeat_last_scan(progressive, MAX_JPEG_SCANS + 300))
    with pytest.raises(LimitError) as info:
        load_map(y)
    msg = str(info.value)
    assert (
        "\n" not in msg
        and msg.startswith(f"{y}: image '{tmp_path / 'm.jpg'}' ")
        and f"{MAX_JPEG_SCANS} scans" in msg
    )


def test_a_scan_bomb_is_one_line_from_mapd_info(
    tmp_path: Path, progressive: bytes, mapd_run: Run, one_error_line: OneLine
) -> None:
    y = _write_map(tmp_path, _repeat_last_scan(progressive, MAX_JPEG_SCANS + 300))
    line = one_error_line(mapd_run("info", str(y), timeout=60))
    assert f"m.jpg' has more than {MAX_JPEG_SCANS} scans" in line


def test_the_cap_is_the_last_scan_count_that_loads(tmp_path: Path, progressive: bytes) -> None:
    at_cap = _repeat_last_scan(progressive, MAX_JPEG_SCANS)
    assert check_jpeg(io.BytesIO(at_cap), "m.yaml", Path("m.jpg")) == MAX_JPEG_SCANS
    assert load_map(_write_map(tmp_path, at_cap, "at")).data.shape == (96, 128)
    with pytest.raises(LimitError):
        load_map(_write_map(tmp_path, _repeat_last_scan(progressive, MAX_JPEG_SCANS + 1), "over"))


def test_scans_behind_fill_bytes_are_counted(tmp_path: Path, progressive: bytes) -> None:
    # libjpeg skips any run of 0xFF before a marker: the repeated scans still decode, so they count.
    y = _write_map(tmp_path, _repeat_last_scan(progressive, MAX_JPEG_SCANS + 50, sep=b"\xff" * 7))
    with pytest.raises(LimitError, match="scans"):
        load_map(y)


def _sos(entropy: bytes) -> bytes:
    """A one-component SOS segment and its entropy-coded bytes (only its structure matters)."""
    return b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + entropy


def test_the_walk_finds_markers_as_libjpeg_does() -> None:
    com = b"\xff\xfe\x00\x06\xff\xda\xff\xd9"  # a COM segment whose text looks like SOS and EOI
    entropy = b"\x12\xff\x00\x34\xff\xd3\x56\xff\x01\x78\xff\xff\x00"  # stuffing, RST3, TEM, fill
    one = b"\xff\xd8" + com + _sos(entropy) + b"\xff\xd9" + _sos(b"") * 5  # scans after EOI: ignored
    assert check_jpeg(io.BytesIO(one), "m.yaml", Path("m.jpg")) == 1
    fill = b"\xff\xd8" + _sos(b"\x01") + b"\xff\xff\xff" + _sos(b"") + b"\x9a\xff\xff\xd9"
    assert check_jpeg(io.BytesIO(fill), "m.yaml", Path("m.jpg")) == 2
    many = b"\xff\xd8" + _sos(b"\x00") * (MAX_JPEG_SCANS + 1) + b"\xff\xd9"
    with pytest.raises(LimitError):
        check_jpeg(io.BytesIO(many), "m.yaml", Path("m.jpg"))


@pytest.mark.parametrize(
    ("data", "says"),
    [
        (b"\xff\xd8" + _sos(b"\x12\x34"), "truncated (ends before its EOI marker)"),
        (b"\xff\xd8\xff\xe0\x10\x00JFIF\xff\xd9", "truncated"),  # a segment running past the end
        (b"\xff\xd8\xff", "truncated"),
        (b"\xff\xd8\xff\xfe\x00\x01\xff\xd9", "a marker segment of length 1"),
        (b"\xff\xd8" + _sos(b"") + b"\xff\xd8\xff\xd9", "a second SOI marker"),
    ],
)
def test_the_walk_refuses_damaged_marker_structure(data: bytes, says: str) -> None:
    with pytest.raises(MapFileError, match=re.escape(says)):
        check_jpeg(io.BytesIO(data), "m.yaml", Path("m.jpg"))


def _after_first_scan(data: bytes, insert: bytes) -> bytes:
    """``data`` with ``insert`` after its first scan, past the header Pillow reads on opening."""
    end = _scans(data)[0][1]
    return data[:end] + insert + data[end:]


@pytest.mark.parametrize(
    ("insert", "says"),
    [
        # No encoder writes a segment length under 2 (it counts its own two bytes); libjpeg skips
        # such a COM or APPn segment without a word, and the image loaded.
        (b"\xff\xfe\x00\x00", "is corrupt (a marker segment of length 0)"),
        (b"\xff\xe5\x00\x01", "is corrupt (a marker segment of length 1)"),
        (b"\xff\xd8", "is corrupt (a second SOI marker)"),
    ],
)
def test_damaged_marker_structure_is_one_map_file_error(
    tmp_path: Path, progressive: bytes, insert: bytes, says: str
) -> None:
    y = _write_map(tmp_path, _after_first_scan(progressive, insert))
    with pytest.raises(MapFileError) as info:
        load_map(y)
    assert str(info.value) == f"{y}: image '{tmp_path / 'm.jpg'}' {says}"


def test_junk_between_segments_loads_as_libjpeg_skips_it(tmp_path: Path, progressive: bytes) -> None:
    # libjpeg passes over bytes that are no marker with a warning: not refused, the same pixels.
    whole = load_map(_write_map(tmp_path, progressive, "whole"))
    junk = load_map(_write_map(tmp_path, _after_first_scan(progressive, b"\x12\x34\xff\x00\x56"), "junk"))
    assert np.array_equal(junk.data, whole.data)


def test_every_prefix_of_a_jpeg_is_refused(tmp_path: Path, progressive: bytes) -> None:
    y = _write_map(tmp_path, b"")
    for cut in range(1, len(progressive), 37):
        (tmp_path / "m.jpg").write_bytes(progressive[:cut])
        with pytest.raises(MapFileError) as info:
            load_map(y)
        assert "\n" not in str(info.value) and str(y) in str(info.value), cut


def _real_jpegs() -> dict[str, tuple[bytes, int]]:
    """Real JPEGs as encoders write them, with the scans each holds."""
    grey = _map_image()
    rng = np.random.default_rng(7)
    noise = rng.integers(0, 40, (96, 128, 3), dtype=np.uint8)
    colour = Image.fromarray(
        (np.asarray(grey.convert("RGB")) - noise.astype(np.int16)).clip(0, 255).astype(np.uint8)
    )
    return {
        "baseline grey": (_jpeg(grey), 1),
        "progressive grey": (_jpeg(grey, progressive=True), 6),
        "baseline colour": (_jpeg(colour, quality=95), 1),
        "progressive colour, optimized, 4:4:4": (
            _jpeg(colour, progressive=True, optimize=True, subsampling=0),
            10,
        ),
        "progressive CMYK": (_jpeg(colour.convert("CMYK"), progressive=True), 18),
        # Restart markers in the entropy-coded data, a comment holding marker-like bytes, and an
        # ICC profile of 200 KB split over APP2 segments that cross the walk's 64 KiB pieces.
        "baseline with restarts, comment and ICC": (
            _jpeg(
                colour,
                restart_marker_blocks=2,
                comment=b"\xff\xda\xff\xd9",
                icc_profile=b"\xff\xd9" * 100_000,
            ),
            1,
        ),
        "progressive with restarts": (_jpeg(grey, progressive=True, restart_marker_rows=1), 6),
    }


@pytest.mark.parametrize("kind", list(_real_jpegs()))
def test_real_jpegs_load_exactly_as_pillow_decodes_them(tmp_path: Path, kind: str) -> None:
    data, scans = _real_jpegs()[kind]
    assert check_jpeg(io.BytesIO(data), "m.yaml", Path("m.jpg")) == scans
    got = load_map(_write_map(tmp_path, data))
    # The same pixels, decoded by Pillow alone and handed over as a PNG (CMYK as mapd converts it).
    with Image.open(io.BytesIO(data)) as im:
        plain = im.convert("RGB") if im.mode == "CMYK" else im.copy()
    plain.save(tmp_path / "p.png")
    (tmp_path / "p.yaml").write_text(YAML.format(image="p.png"))
    want = load_map(tmp_path / "p.yaml")
    assert got.data.shape == (96, 128)
    assert np.array_equal(got.data, want.data)


def test_the_walk_holds_one_piece_of_a_large_file(tmp_path: Path) -> None:
    # 8 MiB of entropy-coded data: walked in pieces, never read whole.
    body = bytes(range(0x40)) * (1 << 17)
    path = tmp_path / "big.jpg"
    path.write_bytes(b"\xff\xd8" + _sos(body) + b"\xff\xd9")
    with path.open("rb") as f:
        tracemalloc.start()
        try:
            assert check_jpeg(f, "m.yaml", path) == 1
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peak < 1 << 20, peak
