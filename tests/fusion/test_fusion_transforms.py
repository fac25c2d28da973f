"""SE(2) helpers and grid cell geometry."""

from __future__ import annotations

import math

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.fusion.transforms import (
    IDENTITY,
    apply,
    compose,
    from_matrix,
    index_to_map,
    inverse,
    pose_distance,
    to_matrix,
    transformed_corners,
    warp_matrix,
    wrap_angle,
)
from mapd.grid import OccupancyGrid, Pose2D

poses = st.builds(
    Pose2D,
    st.floats(-1e3, 1e3),
    st.floats(-1e3, 1e3),
    st.floats(-10.0, 10.0),
)


@settings(max_examples=40, deadline=None)
@given(poses, poses)
def test_compose_matches_matrices_and_inverse_undoes(a: Pose2D, b: Pose2D) -> None:
    ab = compose(a, b)
    m = to_matrix(a) @ to_matrix(b)
    assert np.allclose(to_matrix(ab), m, atol=1e-6)
    back = compose(inverse(a), a)
    assert abs(back.x) < 1e-6 and abs(back.y) < 1e-6 and abs(back.yaw) < 1e-9
    assert -math.pi < ab.yaw <= math.pi


def test_apply_is_p_a_equals_r_p_b_plus_t() -> None:
    t = Pose2D(1.0, 2.0, math.pi / 2)
    x, y = apply(t, 1.0, 0.0)
    assert np.allclose([x, y], [1.0, 3.0])
    assert from_matrix(to_matrix(t)) == Pose2D(1.0, 2.0, wrap_angle(math.pi / 2))


def test_index_to_map_honours_origin_yaw_and_resolution() -> None:
    g = OccupancyGrid(data=np.zeros((4, 6), np.int8), resolution=0.5, origin=Pose2D(10.0, 20.0, math.pi / 2))
    m = index_to_map(g)
    # centre of cell (row 0, col 0) is 0.25 m along both grid axes; the grid x axis points along +y
    p = m @ np.array([0.0, 0.0, 1.0])
    assert np.allclose(p[:2], [10.0 - 0.25, 20.0 + 0.25])
    xs, ys = g.cell_to_world(np.array([3]), np.array([5]))
    q = m @ np.array([5.0, 3.0, 1.0])
    assert np.allclose(q[:2], [xs[0], ys[0]])


def test_warp_identity_and_whole_cell_shift_are_exact() -> None:
    rng = np.random.default_rng(0)
    data = rng.choice(np.array([-1, 0, 100], np.int8), size=(30, 40))
    src = OccupancyGrid(data=data, resolution=0.1, origin=Pose2D(-1.0, 2.0, 0.3))
    dst = src.replace(data=np.zeros_like(data))
    m = warp_matrix(src, IDENTITY, dst)
    out = cv2.warpAffine(data.view(np.uint8), m, (40, 30), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP)
    assert np.array_equal(out.view(np.int8), data)
    # moving src's frame by 3 cells along its own x axis shifts the content by 3 columns
    shift = Pose2D(0.3 * math.cos(0.3), 0.3 * math.sin(0.3), 0.0)
    m = warp_matrix(src, shift, dst)
    out = cv2.warpAffine(
        data.view(np.uint8), m, (40, 30), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP, borderValue=255
    ).view(np.int8)
    assert np.array_equal(out[:, 3:], data[:, :-3])
    assert (out[:, :3] == -1).all()


def test_corners_and_pose_distance() -> None:
    g = OccupancyGrid(data=np.zeros((2, 4), np.int8), resolution=1.0)
    c = transformed_corners(g, Pose2D(0.0, 0.0, math.pi))
    assert np.allclose(sorted(c[:, 0]), [-4, -4, 0, 0], atol=1e-9)
    d, yaw = pose_distance(Pose2D(0, 0, 0), Pose2D(0, 0, math.radians(1)), at=(100.0, 0.0))
    assert math.isclose(d, 2 * 100 * math.sin(math.radians(0.5)), rel_tol=1e-9)
    assert math.isclose(yaw, math.radians(1))
