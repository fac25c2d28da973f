"""The payload header around every codec: round trips, and clear errors for hostile payloads."""

from __future__ import annotations

import contextlib
import struct

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mapd.codec import decode, encode, read_header
from mapd.codec.api import FORMAT_VERSION, MAGIC
from mapd.errors import CodecError
from mapd.grid import OccupancyGrid, Pose2D

grids = st.builds(
    lambda d, res, ox, yaw: OccupancyGrid(d, res, Pose2D(ox, -ox, yaw)),
    arrays(np.int8, st.tuples(st.integers(1, 40), st.integers(1, 40))),
    st.sampled_from([0.01, 0.05, 0.1, 0.25]),
    st.floats(-1e4, 1e4),
    st.floats(-3.2, 3.2),
)


@settings(max_examples=60, deadline=None)
@given(grid=grids, codec=st.sampled_from(["raw", "zstd"]))
def test_round_trip_any_int8_grid(grid: OccupancyGrid, codec: str) -> None:
    back = decode(encode(grid, codec))
    assert back.same_map(grid)


def test_header_is_self_describing(room_grid: OccupancyGrid) -> None:
    payload = encode(room_grid, "zstd")
    h = read_header(payload)
    assert payload[:4] == MAGIC
    assert (h.codec, h.height, h.width, h.resolution) == ("zstd", room_grid.height, room_grid.width, 0.05)
    assert h.origin == room_grid.origin and not h.delta and not h.lossy
    assert h.check == room_grid.digest()


@pytest.mark.parametrize("codec", ["raw", "zstd"])
def test_every_truncation_is_a_codec_error(room_grid: OccupancyGrid, codec: str) -> None:
    payload = encode(room_grid, codec)
    for cut in range(len(payload)):
        with pytest.raises(CodecError):
            decode(payload[:cut])


@pytest.mark.parametrize("codec", ["raw", "zstd"])
def test_bit_flips_never_give_a_wrong_map(room_grid: OccupancyGrid, codec: str) -> None:
    payload = encode(room_grid, codec)
    body_at = read_header(payload).body_offset
    for i in range(len(payload)):
        for bit in range(8):
            bad = bytearray(payload)
            bad[i] ^= 1 << bit
            if i < body_at:  # every header bit is protected
                with pytest.raises(CodecError):
                    decode(bytes(bad))
                continue
            try:
                out = decode(bytes(bad))
            except CodecError:
                continue
            # zstd has a few bits (frame flags) that do not change the output: same map, not a wrong one.
            assert codec == "zstd" and out.same_map(room_grid)


def _forge(codec: str, h: int, w: int, body: bytes) -> bytes:
    name = codec.encode()
    fixed = struct.pack("<IId3dQ16s16sI", h, w, 0.05, 0, 0, 0, 0, bytes(16), bytes(16), len(body))
    return MAGIC + bytes([FORMAT_VERSION, 0, len(name)]) + name + b"\x00" + fixed + body


def test_header_claiming_a_billion_cells_is_refused() -> None:
    with pytest.raises(CodecError, match="over the limit"):
        decode(_forge("raw", 40_000, 25_000, b""))


def test_zstd_bomb_is_bounded_by_the_declared_size() -> None:
    bomb = zstandard.ZstdCompressor(level=1).compress(bytes(50_000_000))
    with pytest.raises(CodecError, match="expected 100"):
        decode(_forge("zstd", 10, 10, bomb))


def test_unknown_codec_and_version() -> None:
    with pytest.raises(CodecError, match="no codec plugin named 'nosuch'"):
        decode(_forge("nosuch", 2, 2, bytes(4)))
    good = bytearray(encode(OccupancyGrid(np.zeros((2, 2), np.int8), 0.05), "raw"))
    good[4] = 99
    with pytest.raises(CodecError, match="format version 99"):
        decode(bytes(good))


def test_empty_and_garbage() -> None:
    for blob in (b"", b"MAPD", b"\x00" * 100, b"hello world"):
        with pytest.raises(CodecError):
            decode(blob)


@settings(max_examples=200, deadline=None)
@given(blob=st.binary(max_size=200))
def test_fuzz_decode_only_raises_codec_errors(blob: bytes) -> None:
    for data in (blob, MAGIC + bytes([FORMAT_VERSION]) + blob):
        with contextlib.suppress(CodecError):
            decode(data)


def test_delta_flag_without_base_is_refused(room_grid: OccupancyGrid) -> None:
    payload = bytearray(encode(room_grid, "raw"))
    payload[5] |= 0x01  # claim it's a delta
    with pytest.raises(CodecError, match="no base was given"):
        decode(bytes(payload))
    with pytest.raises(CodecError, match="base given is version"):
        decode(bytes(payload), base=room_grid)
