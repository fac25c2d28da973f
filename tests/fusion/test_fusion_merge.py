"""merge(): frames, origins, resolutions, the two modes, a stable origin, limits."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from mapd.errors import FusionError, LimitError
from mapd.fusion.merge import Bounds, extent, merge, merge_with_owner, save_png
from mapd.fusion.transforms import IDENTITY
from mapd.grid import OccupancyGrid, Pose2D


def _cell(grid: OccupancyGrid, x: float, y: float) -> int:
    r, c = grid.world_to_cell(np.array([x]), np.array([y]))
    return int(grid.data[int(np.floor(r[0])), int(np.floor(c[0]))])


def _patch(value: int, shape: tuple[int, int] = (10, 10), **kw: object) -> OccupancyGrid:
    return OccupancyGrid(data=np.full(shape, value, np.int8), resolution=0.1, **kw)  # type: ignore[arg-type]


@pytest.mark.parametrize("mode", ["logodds", "occupied_wins"])
def test_one_map_comes_back_cell_for_cell(building: OccupancyGrid, mode: str) -> None:
    g = building.replace(origin=Pose2D(-3.0, -4.0, 0.0))  # on the 5 cm lattice
    out = merge([g], [IDENTITY], mode)
    c0 = round((g.origin.x - out.origin.x) / g.resolution)
    r0 = round((g.origin.y - out.origin.y) / g.resolution)
    assert np.array_equal(out.data[r0 : r0 + g.height, c0 : c0 + g.width], g.data)
    assert out.origin.yaw == 0.0
    assert (out.data == -1).sum() == (g.data == -1).sum() + out.cells - g.cells


def test_logodds_keeps_graded_values_and_adds_evidence() -> None:
    values = np.arange(2, 99, dtype=np.int8).reshape(1, -1)
    g = OccupancyGrid(data=values, resolution=1.0)
    assert np.array_equal(merge([g], [IDENTITY], chunk=1).data, values)
    free, occ, unk = _patch(0), _patch(100), _patch(-1)
    assert (merge([free, free], [IDENTITY, IDENTITY]).data[:10, :10] == 0).all()
    assert (merge([free, occ], [IDENTITY, IDENTITY]).data[:10, :10] == 50).all()
    assert (merge([occ, occ, free], [IDENTITY] * 3).data[:10, :10] == 100).all()
    assert (merge([unk, occ], [IDENTITY, IDENTITY]).data[:10, :10] == 100).all()
    assert (merge([unk], [IDENTITY]).data == -1).all()


def test_occupied_wins_is_the_m_explore_rule() -> None:
    free, occ, unk = _patch(0), _patch(100), _patch(-1)
    assert (merge([free, occ], [IDENTITY, IDENTITY], "occupied_wins").data[:10, :10] == 100).all()
    assert (merge([unk, free], [IDENTITY, IDENTITY], "occupied_wins").data[:10, :10] == 0).all()


def test_transform_and_origin_yaw_place_cells_where_they_are() -> None:
    # a single wall cell at cell (row 2, col 5) of a grid whose origin is turned 90 degrees
    d = np.zeros((8, 8), np.int8)
    d[2, 5] = 100
    g = OccupancyGrid(data=d, resolution=0.5, origin=Pose2D(1.0, -2.0, math.pi / 2))
    t = Pose2D(10.0, 20.0, -math.pi / 2)
    out = merge([g], [t], chunk=4)
    xs, ys = g.cell_to_world(np.array([2]), np.array([5]))  # in g's map frame
    c, s = math.cos(t.yaw), math.sin(t.yaw)
    fx, fy = t.x + c * xs[0] - s * ys[0], t.y + s * xs[0] + c * ys[0]
    assert _cell(out, fx, fy) == 100
    assert int((out.data == 100).sum()) == 1


def test_different_resolutions_are_resampled() -> None:
    fine = np.zeros((40, 40), np.int8)
    fine[20, :] = 100  # a one-cell wall at 2.5 cm
    g_fine = OccupancyGrid(data=fine, resolution=0.025)
    g_coarse = OccupancyGrid(data=np.zeros((10, 10), np.int8), resolution=0.1)
    up = merge([g_coarse], [IDENTITY], resolution=0.05, chunk=1)
    assert up.data.shape == (20, 20) and (up.data == 0).all()
    down = merge([g_fine, g_coarse], [IDENTITY, IDENTITY], resolution=0.1, chunk=1)
    # the thin wall survives pooling to 10 cm (row 20 of 2.5 cm is row 5 of 10 cm)
    assert (down.data[5, :] >= 50).all()
    assert (down.data[0:4, :] == 0).all()


def test_origin_stays_on_the_lattice_and_only_grows(building: OccupancyGrid) -> None:
    g = building.replace(origin=Pose2D(-3.03, -4.01, 0.0))
    first = merge_with_owner([g], [IDENTITY])
    r = g.resolution
    assert math.isclose(first.grid.origin.x / r, round(first.grid.origin.x / r), abs_tol=1e-9)
    assert first.bounds.width % 64 == 0 and first.bounds.height % 64 == 0
    # the map grows a little: the origin does not move
    grown = g.replace(data=np.pad(g.data, ((0, 0), (0, 5)), constant_values=-1))
    second = merge_with_owner([grown], [IDENTITY], bounds=first.bounds)
    assert second.grid.origin == first.grid.origin
    # a smaller map later does not shrink the global map
    small = g.replace(data=g.data[:50, :50])
    third = merge_with_owner([small], [IDENTITY], bounds=second.bounds)
    assert third.bounds == second.bounds
    assert Bounds.of_grid(third.grid) == third.bounds


def test_owner_and_png(tmp_path: Path, building: OccupancyGrid) -> None:
    other = building.replace(data=np.flipud(building.data).copy(), robot="b")
    res = merge_with_owner([building, other], [IDENTITY, Pose2D(30.0, 0.0, 0.0)])
    owners = set(np.unique(res.owner).tolist())
    assert {0, 1, 255} <= owners
    png = tmp_path / "m.png"
    save_png(res, str(png))
    with Image.open(png) as im:
        assert im.size == (res.grid.width, res.grid.height)
        assert im.mode == "RGB"


def test_bad_inputs_raise_one_clear_error(building: OccupancyGrid) -> None:
    with pytest.raises(FusionError, match="unknown merge mode"):
        merge([building], [IDENTITY], "average")
    with pytest.raises(FusionError, match="transforms"):
        merge([building], [IDENTITY, IDENTITY])
    with pytest.raises(LimitError, match="over the limit"):
        merge([building, building], [IDENTITY, Pose2D(1e4, 0.0, 0.0)])
    with pytest.raises(FusionError, match="absurdly far"):
        merge([building], [Pose2D(1e300, 0.0, 0.0)])
    # nothing placed: an empty (all unknown) block, not an error
    assert (merge([building], [None]).data == -1).all()


@pytest.mark.parametrize("res", [0.05, 0.1, 0.025, 0.03])
def test_a_map_whose_edges_lie_on_block_edges_is_not_padded_by_another_block(res: float) -> None:
    # A map's corners were computed a hair past its edges (320.00000000000006 cells), and rounding
    # out took them to the next block: a map of whole blocks on block edges (the global map merged
    # again, say) came back with a further 64 unknown cells on a side in 194 of 480 such cases.
    for k in range(-20, 20):
        for w in (64, 192):
            m = OccupancyGrid(np.zeros((w, w), np.int8), res, origin=Pose2D(k * 64 * res, -k * 64 * res, 0.0))
            box = extent([m], [IDENTITY], res)
            assert box == Bounds(k * 64, -k * 64, k * 64 + w, -k * 64 + w), (k, w, box)
    # without blocks (chunk=1), a map on its lattice merged with itself comes back as it was
    g = OccupancyGrid(np.zeros((320, 360), np.int8), res, origin=Pose2D(-60 * res, -80 * res, 0.0))
    out = merge_with_owner([g, g], [IDENTITY, IDENTITY], chunk=1)
    assert out.bounds == Bounds(-60, -80, 300, 240) and out.grid.data.shape == g.data.shape
