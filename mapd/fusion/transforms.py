"""SE(2) helpers: rigid transforms between map frames, and the cell geometry of grids.

Every transform here is a :class:`~mapd.grid.Pose2D` ``(x, y, yaw)`` read as "frame B expressed in
frame A": a point maps as ``p_a = R(yaw) @ p_b + (x, y)``, meters and radians. ``compose(t_ab, t_bc)``
is ``t_ac``. A grid's own geometry is the affine map from *pixel index* coordinates (column, row, with
the centre of cell ``(row, col)`` at ``(col, row)``, the OpenCV convention) to its map frame, which
honours the grid's resolution and its origin, yaw included.
"""

from __future__ import annotations

import math

import numpy as np

from mapd.grid import OccupancyGrid, Pose2D

# The SE(2) basics live in mapd.grid (mapping uses them too); fusion's modules reach them here.
from mapd.grid import compose as compose
from mapd.grid import inverse as inverse
from mapd.grid import wrap_angle as wrap_angle

IDENTITY = Pose2D(0.0, 0.0, 0.0)


def to_matrix(t: Pose2D) -> np.ndarray:
    """3x3 homogeneous matrix of ``t``."""
    c, s = math.cos(t.yaw), math.sin(t.yaw)
    return np.array([[c, -s, t.x], [s, c, t.y], [0.0, 0.0, 1.0]])


def from_matrix(m: np.ndarray) -> Pose2D:
    """The rigid transform of a 3x3 (or 2x3) matrix; the rotation part is read with atan2."""
    return Pose2D(float(m[0, 2]), float(m[1, 2]), wrap_angle(math.atan2(m[1, 0], m[0, 0])))


def apply(t: Pose2D, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
    """Map points given in B's frame into A's frame."""
    c, s = math.cos(t.yaw), math.sin(t.yaw)
    xa = np.asarray(x, dtype=np.float64)
    ya = np.asarray(y, dtype=np.float64)
    return t.x + c * xa - s * ya, t.y + s * xa + c * ya


def index_to_map(grid: OccupancyGrid) -> np.ndarray:
    """3x3 affine from pixel index (col, row; cell centres at integers) to the grid's map frame."""
    r = grid.resolution
    o = to_matrix(grid.origin)
    return o @ np.array([[r, 0.0, 0.5 * r], [0.0, r, 0.5 * r], [0.0, 0.0, 1.0]])


def warp_matrix(src: OccupancyGrid, t_dst_src: Pose2D, dst: OccupancyGrid | np.ndarray) -> np.ndarray:
    """2x3 matrix for ``cv2.warpAffine(..., WARP_INVERSE_MAP)`` that resamples ``src`` into ``dst``.

    ``t_dst_src`` is src's map frame in dst's map frame. ``dst`` may be a grid, or directly its 3x3
    index-to-map affine (for a target that is not a grid yet).
    """
    g_dst = dst if isinstance(dst, np.ndarray) else index_to_map(dst)
    m = np.linalg.inv(index_to_map(src)) @ to_matrix(inverse(t_dst_src)) @ g_dst
    return m[:2].astype(np.float64)


def transformed_corners(grid: OccupancyGrid, t: Pose2D) -> np.ndarray:
    """(4, 2) corners of ``grid``'s cell area, in the frame that ``t`` maps its map frame into."""
    g = to_matrix(t) @ index_to_map(grid)
    w, h = grid.width, grid.height
    pts = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
    return (pts @ g.T)[:, :2]


def pose_distance(a: Pose2D, b: Pose2D, at: tuple[float, float] = (0.0, 0.0)) -> tuple[float, float]:
    """(meters, radians) between two transforms of the same frame, measured at point ``at`` of it.

    The translation part is how far the point ``at`` (in the moved frame) lands apart, which is what
    a user sees on the merged map; the angle is the absolute yaw difference.
    """
    ax, ay = apply(a, at[0], at[1])
    bx, by = apply(b, at[0], at[1])
    return float(math.hypot(float(ax - bx), float(ay - by))), abs(wrap_angle(a.yaw - b.yaw))
