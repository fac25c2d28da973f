"""The ``lossless`` codec gives back every cell exactly: whole maps, deltas, growing and shrinking grids."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mapd.codec import decode, encode, read_header
from mapd.codec.base import CodecOptions
from mapd.codec.lossless import LosslessCodec, LosslessOptions, alignment
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map

RES = 0.05
TRINARY = np.array([-1, 0, 100], dtype=np.int8)


def _opts(delta: str) -> CodecOptions:
    return LosslessOptions(delta=delta)  # type: ignore[arg-type]


def blocky(draw: st.DrawFn, h: int, w: int, values: np.ndarray) -> np.ndarray:
    """A grid of a few rectangles plus speckle: the structure the context model is made for."""
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    d = np.full((h, w), values[0], dtype=np.int8)
    for _ in range(int(rng.integers(0, 6))):
        r0, c0 = int(rng.integers(0, h)), int(rng.integers(0, w))
        d[r0 : r0 + int(rng.integers(1, h + 1)), c0 : c0 + int(rng.integers(1, w + 1))] = rng.choice(values)
    speck = rng.random((h, w)) < draw(st.sampled_from([0.0, 0.01, 0.2]))
    d[speck] = rng.choice(values, size=int(speck.sum()))
    return d


@st.composite
def trinary_grids(draw: st.DrawFn) -> np.ndarray:
    h, w = draw(st.integers(1, 48)), draw(st.integers(1, 48))
    if draw(st.booleans()):
        return blocky(draw, h, w, TRINARY)
    return draw(arrays(np.int8, (h, w), elements=st.sampled_from([-1, 0, 100])))


@st.composite
def any_grids(draw: st.DrawFn) -> np.ndarray:
    h, w = draw(st.integers(1, 40)), draw(st.integers(1, 40))
    kind = draw(st.sampled_from(["int8", "0..100", "mostly-trinary"]))
    if kind == "int8":
        return draw(arrays(np.int8, (h, w)))
    if kind == "0..100":
        return blocky(draw, h, w, np.array([-1, *range(0, 101, 7), 100], dtype=np.int8))
    d = blocky(draw, h, w, TRINARY)
    d.flat[draw(st.integers(0, h * w - 1))] = draw(st.integers(-128, 127))
    return d


def roundtrip(grid: OccupancyGrid, base: OccupancyGrid | None = None, delta: str = "auto") -> bytes:
    payload = encode(grid, "lossless", base=base, options=_opts(delta))
    back = decode(payload, base=base if read_header(payload).delta else None, options=_opts(delta))
    assert back.same_map(grid)
    return payload


@settings(max_examples=80, deadline=None)
@given(data=trinary_grids())
def test_trinary_grids_round_trip(data: np.ndarray) -> None:
    roundtrip(OccupancyGrid(data, RES, Pose2D(-1.0, 2.5, 0.0)))


@settings(max_examples=80, deadline=None)
@given(data=any_grids())
def test_any_int8_grid_round_trips_through_the_escape_path(data: np.ndarray) -> None:
    roundtrip(OccupancyGrid(data, RES))


@pytest.mark.parametrize("shape", [(1, 1), (1, 257), (257, 1), (2, 3), (3, 2), (17, 1000)])
@pytest.mark.parametrize("value", [-1, 0, 100, 42, -128, 127])
def test_odd_shapes_and_constant_grids(shape: tuple[int, int], value: int) -> None:
    payload = roundtrip(OccupancyGrid(np.full(shape, value, dtype=np.int8), RES))
    if value in (-1, 0, 100) and shape[0] * shape[1] >= 1000:
        assert read_header(payload).body_len < 40  # a uniform map costs next to nothing


@st.composite
def versions(draw: st.DrawFn) -> tuple[OccupancyGrid, OccupancyGrid]:
    """A base and a later version that grew or shrank on the same lattice, with some cells changed."""
    base = draw(trinary_grids() if draw(st.booleans()) else any_grids())
    hb, wb = base.shape
    top, left = draw(st.integers(-6, 6)), draw(st.integers(-6, 6))
    h = max(1, hb + top + draw(st.integers(-6, 6)))
    w = max(1, wb + left + draw(st.integers(-6, 6)))
    new = np.full((h, w), -1, dtype=np.int8)
    # Base cell (i, j) lands on new cell (i + top, j + left).
    r0, c0 = max(0, top), max(0, left)
    r1, c1 = min(h, hb + top), min(w, wb + left)
    if r1 > r0 and c1 > c0:
        new[r0:r1, c0:c1] = base[r0 - top : r1 - top, c0 - left : c1 - left]
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    changed = rng.random((h, w)) < draw(st.sampled_from([0.0, 0.02, 0.3]))
    pool = TRINARY if draw(st.booleans()) else np.array([-1, 0, 100, 55, -7], dtype=np.int8)
    new[changed] = rng.choice(pool, size=int(changed.sum()))
    yaw = draw(st.sampled_from([0.0, 0.7]))
    bo = Pose2D(3.0, -2.0, yaw)
    # The new origin is the base origin moved by (-left, -top) cells along the rotated axes.
    dx, dy = -left * RES, -top * RES
    no = Pose2D(
        bo.x + math.cos(yaw) * dx - math.sin(yaw) * dy, bo.y + math.sin(yaw) * dx + math.cos(yaw) * dy, yaw
    )
    return OccupancyGrid(base, RES, bo, version=4), OccupancyGrid(new, RES, no, version=5)


@settings(max_examples=80, deadline=None)
@given(pair=versions(), mode=st.sampled_from(["auto", "always", "never"]))
def test_versions_that_grow_and_shrink_round_trip_as_deltas(
    pair: tuple[OccupancyGrid, OccupancyGrid], mode: str
) -> None:
    base, new = pair
    payload = roundtrip(new, base, mode)
    head = read_header(payload)
    if mode != "auto":
        assert head.delta == (mode == "always")  # these grids always align
    if head.delta:
        assert head.base_version == base.version and head.base_digest == base.digest()


@settings(max_examples=40, deadline=None)
@given(pair=versions())
def test_auto_sends_the_smaller_of_delta_and_whole(pair: tuple[OccupancyGrid, OccupancyGrid]) -> None:
    base, new = pair
    auto = encode(new, "lossless", base=base, options=_opts("auto"))
    always = encode(new, "lossless", base=base, options=_opts("always"))
    never = encode(new, "lossless", base=base, options=_opts("never"))
    assert len(auto) == min(len(always), len(never))
    assert read_header(always).delta and not read_header(never).delta


def test_alignment_by_origin() -> None:
    base = OccupancyGrid(np.zeros((4, 4), np.int8), RES, Pose2D(1.0, 1.0, 0.0))
    assert alignment(RES, Pose2D(1.0 - 3 * RES, 1.0 + 2 * RES, 0.0), base) == (2, -3)
    assert alignment(RES, Pose2D(1.0 + 0.5 * RES, 1.0, 0.0), base) is None  # half a cell
    assert alignment(0.1, Pose2D(1.0, 1.0, 0.0), base) is None  # resolution
    assert alignment(RES, Pose2D(1.0, 1.0, 0.1), base) is None  # yaw


@pytest.mark.parametrize(
    "origin, resolution",
    [(Pose2D(0.025, 0.0, 0.0), RES), (Pose2D(0.0, 0.0, 0.3), RES), (Pose2D(0.0, 0.0, 0.0), 0.1)],
)
def test_unalignable_base_falls_back_to_a_whole_map(origin: Pose2D, resolution: float) -> None:
    rng = np.random.default_rng(3)
    base = OccupancyGrid(rng.choice(TRINARY, size=(30, 30)), RES, Pose2D(0.0, 0.0, 0.0), version=1)
    new = OccupancyGrid(base.data.copy(), resolution, origin, version=2)
    payload = encode(new, "lossless", base=base, options=_opts("always"))
    assert not read_header(payload).delta
    assert decode(payload).same_map(new)  # a whole map needs no base


def test_small_change_costs_a_small_fraction_of_the_whole(room_grid: OccupancyGrid) -> None:
    grown = np.full((room_grid.height + 4, room_grid.width + 6), -1, np.int8)
    grown[4:, 6:] = room_grid.data
    grown[10:12, 10:30] = 0  # a corridor seen for the first time
    new = OccupancyGrid(grown, RES, Pose2D(room_grid.origin.x - 6 * RES, room_grid.origin.y - 4 * RES, 0.0))
    base = room_grid.replace(version=1)
    delta = roundtrip(new, base)
    assert read_header(delta).delta
    whole = encode(new, "lossless")
    assert read_header(delta).body_len < 0.5 * read_header(whole).body_len


def test_delta_of_an_identical_map_is_tiny(room_grid: OccupancyGrid) -> None:
    payload = roundtrip(room_grid.replace(version=2), room_grid.replace(version=1))
    assert read_header(payload).delta and read_header(payload).body_len <= 8


def test_shared_maps_round_trip_and_beat_zstd(shared_maps: list[Path]) -> None:
    import zstandard

    small = [p for p in shared_maps if p.stat().st_size < 400_000][:6]
    assert small
    for path in small:
        grid = load_map(path)
        payload = roundtrip(grid)
        zs = len(zstandard.ZstdCompressor(level=19).compress(grid.data.tobytes()))
        assert len(payload) < zs, path


def test_replayed_log_snapshots_round_trip_as_deltas(intel_log: Path) -> None:
    from mapd.mapping.replay import replay_log

    prev = None
    deltas = 0
    for n, (_, grid) in enumerate(replay_log(intel_log, every=10)):
        if n >= 6:
            break
        payload = roundtrip(grid, prev)
        deltas += read_header(payload).delta
        assert len(payload) <= len(encode(grid, "lossless"))
        prev = grid
    # Early on the map doubles between snapshots and a whole map can win; later deltas must.
    assert deltas >= 3


def test_codec_is_registered_and_shaped_as_the_api_expects() -> None:
    from mapd import plugins

    assert plugins.load("codec", "lossless") is LosslessCodec
    assert LosslessCodec.lossless and LosslessCodec.uses_base
