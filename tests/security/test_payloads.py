"""Hostile payloads: refused at the header when they claim too much, bounded when they decode.

Measured before the fix: a 132-byte ``paper`` payload took 1.7 GB and 9 s (one whose Huffman codes
are all 15 bits long took 6.8 GB before running out of memory); a 3.2 KB ``lossless`` payload
claiming 1 x 67 M cells took 1.8 GB; a header with resolution 1e-9 or origin 1e9 decoded.
"""

from __future__ import annotations

import math
import subprocess
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.codec import decode, encode, read_header
from mapd.codec.api import MAX_SIDE, get_codec, pack_payload
from mapd.codec.ctx_kernels import MODEL_VERSION
from mapd.errors import CodecError
from mapd.grid import DEFAULT_MAX_CELLS, MAX_ORIGIN_M, OccupancyGrid, Pose2D
from mapd.mapping.synthetic import room_grid

CODECS = ["raw", "zstd", "lossless", "pooled", "paper"]
#: Peak memory a decode may add to a warm process, for a map at the default cell limit (MiB).
BOUND_MB = 300
#: The lossless body of a stream of zeros: the arithmetic decoder happily reads it for ever.
LOSSLESS_ZEROS = bytes([MODEL_VERSION << 3 | 0x04]) + bytes(3200)


def _variant(codec: str) -> str:
    return get_codec(codec).variant()


@pytest.mark.parametrize("shape", [(1, 1 << 26), (1 << 26, 1), (2, MAX_SIDE + 1), (MAX_SIDE + 1, 2)])
def test_degenerate_shapes_are_refused_at_the_header(shape: tuple[int, int]) -> None:
    h, w = shape
    payload = pack_payload(
        "lossless", "", height=h, width=w, resolution=0.05, origin=(0, 0, 0), body=LOSSLESS_ZEROS
    )
    t0 = time.perf_counter()
    with pytest.raises(CodecError, match=f"over {MAX_SIDE} cells a side"):
        decode(payload)
    assert time.perf_counter() - t0 < 0.1


@pytest.mark.parametrize("codec", CODECS)
def test_claims_over_the_cell_limit_are_refused_before_allocating(codec: str) -> None:
    def claim(h: int, w: int) -> bytes:
        return pack_payload(
            codec,
            _variant(codec),
            height=h,
            width=w,
            resolution=0.05,
            origin=(0, 0, 0),
            body=bytes(64),
            lossy=not get_codec(codec).lossless,
        )

    big, small = claim(16384, 8192), claim(40, 40)
    t0 = time.perf_counter()
    with pytest.raises(CodecError, match=f"over the limit of {DEFAULT_MAX_CELLS}"):
        decode(big)
    with pytest.raises(CodecError, match=r"over the limit of 1000$"):
        decode(small, max_cells=1000)  # limits.max_cells as configured
    assert time.perf_counter() - t0 < 0.5


def test_lossless_zeros_claiming_many_cells_fail_in_bounded_memory(
    in_child: Callable[..., dict[str, Any]],
) -> None:
    got = in_child(
        f"""
        from mapd.codec import decode, encode
        from mapd.codec.api import pack_payload
        from mapd.errors import CodecError
        from mapd.mapping.synthetic import room_grid
        decode(encode(room_grid(), "lossless"))  # compiled kernels loaded: the baseline
        before = peak_mb()
        out = {{}}
        for h, w in ((1024, 65536), (8192, 8192)):
            p = pack_payload("lossless", "", height=h, width=w, resolution=0.05, origin=(0, 0, 0), body={LOSSLESS_ZEROS!r})
            t0 = time.perf_counter()
            try:
                decode(p)
                out[f"{{h}}x{{w}}"] = "decoded"
            except CodecError as exc:
                out[f"{{h}}x{{w}}"] = str(exc)
            out[f"{{h}}x{{w}} s"] = time.perf_counter() - t0
        report(before=before, after=peak_mb(), **out)
        """
    )
    assert "truncated or corrupt" in got["1024x65536"] and "truncated or corrupt" in got["8192x8192"]
    # The 67 M-cell output and the model's tables; a 1 x 67 M claim took 1.8 GB before the fix.
    assert got["after"] - got["before"] < 2.5 * DEFAULT_MAX_CELLS / 2**20, got
    assert got["8192x8192 s"] < 30


_PAPER_CHILD = """
import numpy as np
from mapd.codec import decode, hexruns, huffman
from mapd.codec.api import get_codec, pack_payload
codec = get_codec("paper")
levels = codec.model().levels
two = np.array([1, 1] + [0] * (levels - 2), np.uint8)
warm = huffman.pack_table(two) + hexruns.pack_runs(np.array([1]), np.array([0], np.uint8))
decode(pack_payload("paper", codec.variant(), height=4, width=2, resolution=0.05, origin=(0, 0, 0),
                    body=bytes([7]) + warm, lossy=True))
before = peak_mb()
h = w = {side}
n = (h // 2) * (w // 2)
if {deep}:
    # every symbol the one with a 15-bit code: 15 one-bits each, one run of n * 15 / 4 hex 'F'
    lengths = np.array(list(range(1, levels)) + [levels - 1], np.uint8)
    body = huffman.pack_table(lengths) + hexruns.pack_runs(np.array([n * 15 // 4]), np.array([15], np.uint8))
else:
    # symbols 0 and 1 alternating (1-bit codes, hex '5'): no tile is constant, the CNN runs everywhere
    body = huffman.pack_table(two) + hexruns.pack_runs(np.array([n // 4]), np.array([5], np.uint8))
payload = pack_payload("paper", codec.variant(), height=h, width=w, resolution=0.05, origin=(0, 0, 0),
                       body=bytes([7]) + body, lossy=True)
t0 = time.perf_counter()
grid = decode(payload)
report(bytes=len(payload), shape=list(grid.data.shape), seconds=time.perf_counter() - t0,
       before=before, after=peak_mb())
"""


def test_paper_payload_of_15_bit_codes_decodes_in_bounded_memory(
    in_child: Callable[..., dict[str, Any]],
) -> None:
    # 135 bytes that expand to 250 M bits: the old decoder built int64 arrays per bit (6.8 GB, then
    # MemoryError); now the runs are decoded as they stand.
    got = in_child(_PAPER_CHILD.format(side=8192, deep=True))
    assert got["bytes"] < 200 and got["shape"] == [8192, 8192]
    assert got["after"] - got["before"] < BOUND_MB, got
    assert got["seconds"] < 60, got


def test_paper_payload_that_runs_the_cnn_everywhere_decodes_in_bounded_memory(
    in_child: Callable[..., dict[str, Any]],
) -> None:
    # 127 bytes, a 16.7 M-cell map, every tile active: the CNN's float32 maps are made band by band.
    got = in_child(_PAPER_CHILD.format(side=4096, deep=False))
    assert got["bytes"] < 200 and got["shape"] == [4096, 4096]
    assert got["after"] - got["before"] < BOUND_MB / 2, got


# --------------------------------------------------------------------------- header fields


@pytest.fixture(scope="module")
def payloads() -> dict[str, bytes]:
    g = room_grid(30, 40, seed=1, origin=Pose2D(-1.5, 2.0, 0.25))
    return {codec: encode(g, codec) for codec in CODECS}


BAD_FIELDS = [
    ("resolution", 0.0),
    ("resolution", -0.05),
    ("resolution", math.nan),
    ("resolution", math.inf),
    ("resolution", 1e-9),
    ("resolution", 1e4),
    ("x", math.nan),
    ("x", 2 * MAX_ORIGIN_M),
    ("y", -1e300),
    ("y", math.inf),
    ("yaw", math.nan),
    ("yaw", 7.0),
    ("yaw", -100.0),
]


@pytest.mark.parametrize("codec", CODECS)
@pytest.mark.parametrize(("field", "value"), BAD_FIELDS)
def test_header_resolution_and_origin_are_checked(
    payloads: dict[str, bytes], codec: str, field: str, value: float
) -> None:
    good = payloads[codec]
    h = read_header(good)
    fields = {"resolution": h.resolution, "x": h.origin.x, "y": h.origin.y, "yaw": h.origin.yaw}
    fields[field] = value
    bad = pack_payload(
        h.codec,
        h.variant,
        height=h.height,
        width=h.width,
        resolution=fields["resolution"],
        origin=(fields["x"], fields["y"], fields["yaw"]),
        body=good[h.body_offset :],
        lossy=h.lossy,
        check=h.check,  # the body's own checksum still matches: only the header is wrong
    )
    with pytest.raises(CodecError, match="payload header"):
        decode(bad)


@pytest.mark.parametrize("origin", [Pose2D(2 * MAX_ORIGIN_M, 0.0, 0.0), Pose2D(0.0, 0.0, 10.0)])
def test_encode_refuses_what_decode_would(origin: Pose2D) -> None:
    g = OccupancyGrid(np.zeros((4, 4), np.int8), 0.05, origin)
    with pytest.raises(CodecError, match="cannot encode this map: origin"):
        encode(g, "raw")
    with pytest.raises(CodecError, match="cannot encode this map: the grid is empty"):
        encode(OccupancyGrid(np.zeros((0, 4), np.int8), 0.05), "raw")


def test_mapd_decode_reads_at_most_one_payload(
    mapd_run: Callable[..., subprocess.CompletedProcess[str]],
    one_error_line: Callable[..., str],
    tmp_path: Path,
) -> None:
    t0 = time.perf_counter()
    line = one_error_line(mapd_run("decode", "/dev/zero", "-o", str(tmp_path / "x.yaml")), code=1)
    assert "larger than any payload mapd decodes" in line
    assert time.perf_counter() - t0 < 30
