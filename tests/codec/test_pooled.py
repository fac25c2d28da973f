"""The ``pooled`` codec: walls never lost, deltas on the base the receiver holds, hostile bodies refused."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from mapd.codec import decode, encode, read_header
from mapd.codec.api import get_codec
from mapd.codec.base import Target
from mapd.codec.pooled import PooledCodec, PooledOptions
from mapd.errors import CodecError
from mapd.grid import OCCUPIED, UNKNOWN, OccupancyGrid, Pose2D
from mapd.mapping.synthetic import room_grid

CELLS = st.sampled_from([UNKNOWN, 0, 30, 70, OCCUPIED])
grids = st.builds(
    lambda d, res, cx, cy, yaw: OccupancyGrid(d, res, Pose2D(cx * res, cy * res, yaw)),
    arrays(np.int8, st.tuples(st.integers(1, 30), st.integers(1, 30)), elements=CELLS),
    st.sampled_from([0.05, 0.1]),
    st.integers(-1000, 1000),
    st.integers(-1000, 1000),
    st.sampled_from([0.0, 0.5, -2.0]),
)


def body(payload: bytes) -> int:
    return read_header(payload).body_len


def codec(factor: int = 2) -> PooledCodec:
    impl = get_codec("pooled", PooledOptions(factor=factor))
    assert isinstance(impl, PooledCodec)
    return impl


@settings(max_examples=80, deadline=None)
@given(grid=grids, factor=st.integers(2, 4))
def test_no_cell_comes_back_below_what_it_was_and_the_decoded_map_is_what_the_sender_holds(
    grid: OccupancyGrid, factor: int
) -> None:
    opts = PooledOptions(factor=factor)
    back = decode(encode(grid, "pooled", options=opts), options=opts)
    assert (
        back.data.shape == grid.data.shape
        and back.origin == grid.origin
        and back.resolution == grid.resolution
    )
    # The block's largest value: an occupied cell is never lost, a known one never becomes unknown.
    assert (back.data >= grid.data).all()
    assert np.array_equal(back.data, codec(factor).held(grid).data)
    assert np.array_equal(codec(factor).held(back).data, back.data)  # pooling again changes nothing


def test_a_wall_comes_back_at_most_a_cell_thicker_and_the_map_in_fewer_bytes() -> None:
    grid = room_grid(300, 400)
    back = decode(encode(grid, "pooled"))
    walls, got = grid.data == OCCUPIED, back.data == OCCUPIED
    assert (got[walls]).all()
    # Every cell that turned occupied touches a wall cell of the original (8-neighbourhood).
    near = np.zeros_like(walls)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            near |= np.roll(np.roll(walls, dr, 0), dc, 1)
    assert not (got & ~near).any()
    assert body(encode(grid, "pooled")) < body(encode(grid, "lossless"))  # the ratio: mapd bench codec
    head = read_header(encode(grid, "pooled"))
    assert head.lossy and head.codec == "pooled"


def test_deltas_go_against_the_base_the_receiver_decoded_also_when_the_map_grows_by_odd_cells() -> None:
    rng = np.random.default_rng(1)
    old = room_grid(300, 400).replace(version=1)
    # The map grows by 3 cells to the left and 1 down (odd: the blocks stay on the map frame's
    # lattice, not on the grid's corner), and a box appears in it.
    data = np.full((old.height + 1, old.width + 3), UNKNOWN, np.int8)
    data[1:, 3:] = old.data
    data[40:44, 50:60] = OCCUPIED
    data[rng.integers(1, data.shape[0], 30), rng.integers(3, data.shape[1], 30)] = 0
    x, y, yaw = old.origin
    new = old.replace(data=data, origin=Pose2D(x - 3 * old.resolution, y - old.resolution, yaw), version=2)

    held_old = decode(encode(old, "pooled"))  # what the receiver holds
    delta = encode(new, "pooled", base=old)  # the sender codes against its own original
    assert read_header(delta).delta and body(delta) * 4 < body(encode(new, "pooled"))
    back = decode(delta, base=held_old.replace(version=1))
    assert np.array_equal(back.data, codec().held(new).data)
    # The sender's original base names the same one (mapd decode --base OLD.yaml); another does not.
    assert np.array_equal(decode(delta, base=old).data, back.data)
    with pytest.raises(CodecError, match="delta against version 1"):
        decode(delta, base=new)


def test_a_base_held_at_another_factor_is_refused() -> None:
    old, new = room_grid().replace(version=1), room_grid().replace(version=2)
    held_at_4 = decode(
        encode(old, "pooled", options=PooledOptions(factor=4)), options=PooledOptions(factor=4)
    )
    delta = encode(new, "pooled", base=old)
    assert read_header(delta).delta
    with pytest.raises(CodecError, match="delta against version 1"):
        decode(delta, base=held_at_4.replace(version=1))


@settings(max_examples=150, deadline=None)
@given(body=st.binary(max_size=60), h=st.integers(1, 50), w=st.integers(1, 50), factor=st.integers(0, 6))
def test_arbitrary_bodies_give_a_grid_of_the_right_shape_or_a_codec_error(
    body: bytes, h: int, w: int, factor: int
) -> None:
    body = bytes([factor]) + body
    try:
        out = codec().decode_cells(body, Target(h, w, 0.05, Pose2D(0.35, -0.1, 0.0), ""), None)
    except CodecError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    assert out.shape == (h, w) and out.dtype == np.int8 and 2 <= factor <= 4


def test_bad_factors_and_origins_are_refused() -> None:
    with pytest.raises(CodecError, match="pooling factor of 9"):
        codec().decode_cells(b"\x09\x00", Target(4, 4, 0.05, Pose2D(), ""), None)
    with pytest.raises(CodecError, match="empty"):
        codec().decode_cells(b"", Target(4, 4, 0.05, Pose2D(), ""), None)
    with pytest.raises(CodecError, match="out of range"):
        codec().decode_cells(b"\x02", Target(4, 4, 1e-4, Pose2D(1e300, 0.0, 0.0), ""), None)
    with pytest.raises(ValueError):
        PooledOptions(factor=5)
