"""Bit flips and truncations of real payloads of every codec: only MapdErrors, never a bad map.

A payload that still decodes must give a grid of the header's size with a finite, positive,
in-bounds resolution and origin; for the exact codecs (raw, zstd, lossless, lossless delta) it must
be the very map that was sent, since their checksum covers the cells, the size and the geometry.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.codec import api, decode, encode, read_header
from mapd.errors import MapdError
from mapd.grid import MAX_ORIGIN_M, MAX_ORIGIN_YAW, MAX_RESOLUTION, MIN_RESOLUTION, OccupancyGrid, Pose2D
from mapd.mapping.synthetic import room_grid

BASE = room_grid(36, 44, seed=5, origin=Pose2D(-0.8, 1.25, 0.1))


def _next_version() -> OccupancyGrid:
    data = BASE.data.copy()
    data[10:14, 8:30] = 100  # a new wall, as the next version of the same map
    data[2:5, 2:6] = 0
    return BASE.replace(data=data, version=2)


NEXT = _next_version()
# name -> (payload, base to decode against, the map that was sent)
SENT: dict[str, tuple[bytes, OccupancyGrid | None, OccupancyGrid]] = {
    "raw": (encode(BASE, "raw"), None, BASE),
    "zstd": (encode(BASE, "zstd"), None, BASE),
    "lossless": (encode(BASE, "lossless"), None, BASE),
    "lossless-delta": (encode(NEXT, "lossless", base=BASE), BASE, NEXT),
}
assert read_header(SENT["lossless-delta"][0]).delta


@st.composite
def damage(draw: st.DrawFn, payload: bytes) -> bytes:
    """The payload with a few bits flipped (header or body), cut short, or both.

    Half the flips land in the header's resolution and origin (32 of a few hundred bytes), which
    uniform flips would seldom hit.
    """
    out = bytearray(payload)
    geometry = read_header(payload).body_offset - api._FIXED.size + 8  # after height and width
    where = st.one_of(st.integers(0, len(out) - 1), st.integers(geometry, geometry + 31))
    flips = draw(st.lists(st.tuples(where, st.integers(0, 7)), max_size=4))
    for i, bit in flips:
        out[i] ^= 1 << bit
    cut = draw(st.one_of(st.none(), st.integers(0, len(out) - 1)))
    if cut is not None:
        del out[cut:]
    if bytes(out) == payload:  # nothing changed: flip one bit at least
        i = draw(st.integers(0, len(out) - 1))
        out[i] ^= 1 << draw(st.integers(0, 7))
    return bytes(out)


def _check_geometry(grid: OccupancyGrid, payload: bytes) -> None:
    head = read_header(payload)
    assert grid.data.shape == (head.height, head.width) and grid.data.dtype == np.int8
    assert grid.resolution == head.resolution and tuple(grid.origin) == tuple(head.origin)
    assert math.isfinite(grid.resolution) and MIN_RESOLUTION <= grid.resolution <= MAX_RESOLUTION
    x, y, yaw = grid.origin
    assert all(math.isfinite(v) for v in (x, y, yaw))
    assert abs(x) <= MAX_ORIGIN_M and abs(y) <= MAX_ORIGIN_M and abs(yaw) <= MAX_ORIGIN_YAW


@pytest.mark.parametrize("name", sorted(SENT))
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_exact_codecs_give_the_sent_map_or_a_mapd_error(name: str, data: st.DataObject) -> None:
    payload, base, sent = SENT[name]
    bad = data.draw(damage(payload))
    try:
        grid = decode(bad, base)
    except MapdError:
        return
    _check_geometry(grid, bad)
    # A flip that leaves the payload meaning the same (a zstd frame flag) is fine; a wrong map is not.
    assert grid.same_map(sent)


_PAPER: dict[str, bytes] = {}


def _paper_payload() -> bytes:
    if "p" not in _PAPER:
        _PAPER["p"] = encode(BASE, "paper")
    return _PAPER["p"]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_paper_gives_a_map_of_the_header_geometry_or_a_mapd_error(data: st.DataObject) -> None:
    bad = data.draw(damage(_paper_payload()))
    try:
        grid = decode(bad)
    except MapdError:
        return
    # Lossy: the checksum covers the body only, so a low mantissa bit of the resolution or origin
    # can still change unnoticed (signed envelopes catch it); anything out of bounds is refused.
    _check_geometry(grid, bad)
    assert set(np.unique(grid.data).tolist()) <= {-1, 0, 100}
