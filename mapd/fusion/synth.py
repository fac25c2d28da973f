"""Overlapping map pairs with a known answer, made from one real map (for the bench and the tests).

:func:`make_pair` cuts two overlapping crops out of one real map, turns the second by a random angle
(nearest-neighbour resampling, as a robot that started at another heading would see the place) and
then degrades it the way another robot's map of the same place differs: patches it never explored,
walls seen thicker or thinner in places, and speckle. :func:`hide_pose` does the turning and the
re-origining for real pairs already in one world frame. Each returns the true transform: the second
map's frame expressed in the first map's frame (``p_a = R(yaw) p_b + t``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from mapd.fusion.transforms import compose, index_to_map, inverse, warp_matrix
from mapd.grid import OCCUPIED_AT, UNKNOWN, OccupancyGrid, Pose2D


@dataclass(frozen=True)
class Pair:
    """Two maps of one place and the truth: b's map frame in a's map frame."""

    a: OccupancyGrid
    b: OccupancyGrid
    truth: Pose2D
    overlap: float
    label: str


def crop(
    grid: OccupancyGrid, r0: int, c0: int, h: int, w: int, origin: Pose2D
) -> tuple[OccupancyGrid, Pose2D]:
    """Cells ``[r0:r0+h, c0:c0+w]`` as a grid with a new ``origin``; returns it and its frame in grid's."""
    data = np.ascontiguousarray(grid.data[r0 : r0 + h, c0 : c0 + w])
    out = grid.replace(data=data, origin=origin)
    r = grid.resolution
    # p_grid = O_grid (r (u + c0), r (v + r0)) and p_crop = O_crop (r u, r v)
    t = compose(compose(grid.origin, Pose2D(r * c0, r * r0, 0.0)), inverse(origin))
    return out, t


def rotate(grid: OccupancyGrid, theta: float, origin: Pose2D) -> tuple[OccupancyGrid, Pose2D]:
    """The grid turned by ``theta`` about its centre (nearest neighbour, canvas grown to fit).

    The result gets ``origin``; returns it and its map frame expressed in ``grid``'s map frame.
    """
    h, w = grid.height, grid.width
    c, s = abs(math.cos(theta)), abs(math.sin(theta))
    w2 = math.ceil(w * c + h * s) + 2
    h2 = math.ceil(w * s + h * c) + 2
    # In pixel-index coordinates: q_new = R(theta) (q_old - ctr_old) + ctr_new.
    ctr_old = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    ctr_new = np.array([(w2 - 1) / 2.0, (h2 - 1) / 2.0])
    rot = np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])
    fwd = np.eye(3)
    fwd[:2, :2] = rot
    fwd[:2, 2] = ctr_new - rot @ ctr_old
    inv = np.linalg.inv(fwd)
    src = grid.data.view(np.uint8)
    data = cv2.warpAffine(
        src,
        inv[:2],
        (w2, h2),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=255,
    ).view(np.int8)
    out = grid.replace(data=np.ascontiguousarray(data), origin=origin)
    # p_old = G_old q_old = G_old inv q_new = G_old inv G_new^-1 p_new
    m = index_to_map(grid) @ inv @ np.linalg.inv(index_to_map(out))
    t = Pose2D(float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))
    return out, t


def degrade(grid: OccupancyGrid, rng: np.random.Generator, strength: float = 1.0) -> OccupancyGrid:
    """Another robot's view of the same place: unexplored patches, thicker/thinner walls, speckle."""
    d = grid.data.copy()
    h, w = d.shape
    known = d >= 0
    occ = d >= OCCUPIED_AT
    # Walls seen thicker in some places and thinner (broken up) in others.
    for _ in range(int(rng.integers(2, 5))):
        region = _blob(rng, h, w, 0.15, 0.35)
        if rng.random() < 0.5:
            thick = ndimage.binary_dilation(occ, iterations=1) & region & known
            d[thick] = 100
        else:
            thin = occ & region & (rng.random((h, w)) < 0.45 * strength)
            # only cells beside free space, so a wall thins or frays rather than vanishes
            near_free = ndimage.binary_dilation(known & ~occ, iterations=1)
            d[thin & near_free] = 0
    # Patches never explored.
    for _ in range(int(rng.integers(1, 4))):
        d[_blob(rng, h, w, 0.08, 0.2 * strength)] = UNKNOWN
    # Speckle: spurious hits in free space, missed cells, a few stray unknowns.
    known = d >= 0
    u = rng.random((h, w))
    free = known & (d < OCCUPIED_AT)
    d[free & (u < 0.004 * strength)] = 100
    d[known & (u > 1.0 - 0.003 * strength)] = UNKNOWN
    return grid.replace(data=d)


def _blob(rng: np.random.Generator, h: int, w: int, lo: float, hi: float) -> np.ndarray:
    """A random ellipse covering about ``lo``..``hi`` of the grid's area."""
    area = rng.uniform(lo, hi) * h * w
    aspect = rng.uniform(0.5, 2.0)
    a = math.sqrt(area * aspect / math.pi)
    b = area / (math.pi * a)
    cy, cx = rng.uniform(0, h), rng.uniform(0, w)
    ang = rng.uniform(0, math.pi)
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = xx - cx, yy - cy
    ca, sa = math.cos(ang), math.sin(ang)
    return ((ca * dx + sa * dy) / a) ** 2 + ((-sa * dx + ca * dy) / b) ** 2 <= 1.0


def _random_origin(rng: np.random.Generator) -> Pose2D:
    return Pose2D(float(rng.uniform(-30, 30)), float(rng.uniform(-30, 30)), 0.0)


def make_pair(
    grid: OccupancyGrid,
    overlap: float,
    rng: np.random.Generator,
    *,
    size: tuple[int, int] = (360, 480),
    min_occupied: int = 50,
    tolerance: float | None = None,
    tries: int = 60,
    label: str = "",
) -> Pair | None:
    """Two crops of ``grid`` that share ``overlap`` of the smaller one's known cells, b turned.

    The crop rectangles are laid to overlap by ``overlap`` of the smaller one; a draw is kept when
    the shared rectangle holds at least ``min_occupied`` occupied cells and the measured overlap
    (:func:`known_overlap`, after b is degraded) is within ``tolerance`` of the target (default
    0.05 + 0.1 x target). None when ``tries`` draws all fail (a small or mostly unexplored map).
    """
    tol = 0.05 + 0.1 * overlap if tolerance is None else tolerance
    occ = grid.data >= OCCUPIED_AT
    occ_sum = occ.astype(np.int32).cumsum(0).cumsum(1)
    gh, gw = grid.height, grid.width
    for _ in range(tries):
        # crops of a robot-sized area, but at most 55% of the map each way, so that two fit side by side
        cap_h, cap_w = max(8, int(0.55 * gh)), max(8, int(0.55 * gw))
        sides = [int(rng.integers(size[0], size[1] + 1)) for _ in range(4)]
        ha, wa, hb, wb = (
            min(sides[0], cap_h),
            min(sides[1], cap_w),
            min(sides[2], cap_h),
            min(sides[3], cap_w),
        )
        small = min(ha * wa, hb * wb)
        # Shape of the shared rectangle: area overlap * small, random aspect, fitting both crops.
        target = overlap * small
        ow_lo = max(1.0, target / min(ha, hb))
        ow_hi = float(min(wa, wb))
        if ow_lo > ow_hi:
            continue
        ow = round(float(rng.uniform(ow_lo, ow_hi)))
        oh = round(target / max(ow, 1))
        if not (1 <= oh <= min(ha, hb)):
            continue
        # b sits to the left/right and above/below a so that exactly ow x oh are shared.
        dx = (wa - ow) if rng.random() < 0.5 else -(wb - ow)
        dy = (ha - oh) if rng.random() < 0.5 else -(hb - oh)
        x_lo = max(0, -dx)
        x_hi = min(gw - wa, gw - wb - dx)
        y_lo = max(0, -dy)
        y_hi = min(gh - ha, gh - hb - dy)
        if x_lo > x_hi or y_lo > y_hi:
            continue
        ca = int(rng.integers(x_lo, x_hi + 1))
        ra = int(rng.integers(y_lo, y_hi + 1))
        cb, rb = ca + dx, ra + dy
        r0, r1 = max(ra, rb), min(ra + ha, rb + hb)
        c0, c1 = max(ca, cb), min(ca + wa, cb + wb)
        if _box_sum(occ_sum, r0, c0, r1, c1) < min_occupied:
            continue
        a, t_src_a = crop(grid, ra, ca, ha, wa, _random_origin(rng))
        b0, t_src_b0 = crop(grid, rb, cb, hb, wb, Pose2D(0.0, 0.0, 0.0))
        b0 = degrade(b0, rng)
        b, t_b0_b = rotate(b0, float(rng.uniform(-math.pi, math.pi)), _random_origin(rng))
        truth = compose(compose(inverse(t_src_a), t_src_b0), t_b0_b)
        # The overlap that matters is shared *content*: crops of a half-explored map, or with the
        # shared part left unexplored by b, would overlap on paper only. Keep draws whose measured
        # overlap is near the target.
        real = known_overlap(a, b, truth)
        if abs(real - overlap) > tol:
            continue
        return Pair(a=a, b=b.replace(robot="b"), truth=truth, overlap=real, label=label)
    return None


def _box_sum(s: np.ndarray, r0: int, c0: int, r1: int, c1: int) -> int:
    if r1 <= r0 or c1 <= c0:
        return 0
    total = int(s[r1 - 1, c1 - 1])
    if r0 > 0:
        total -= int(s[r0 - 1, c1 - 1])
    if c0 > 0:
        total -= int(s[r1 - 1, c0 - 1])
    if r0 > 0 and c0 > 0:
        total += int(s[r0 - 1, c0 - 1])
    return total


def hide_pose(a: OccupancyGrid, b: OccupancyGrid, rng: np.random.Generator, label: str = "") -> Pair:
    """Two maps already in one world frame, with b turned and both re-origined to hide the answer."""
    a2 = a.replace(origin=_random_origin(rng))
    t_world_a2 = compose(a.origin, inverse(a2.origin))  # a's map frame is the world frame
    b_turned, t_b_b2 = rotate(b, float(rng.uniform(-math.pi, math.pi)), _random_origin(rng))
    # a's and b's map frames are both the world frame.
    truth = compose(inverse(t_world_a2), t_b_b2)
    return Pair(
        a=a2,
        b=b_turned.replace(robot="b"),
        truth=truth,
        overlap=known_overlap(a2, b_turned, truth),
        label=label,
    )


def known_overlap(a: OccupancyGrid, b: OccupancyGrid, truth: Pose2D) -> float:
    """Cells known in both under ``truth``, over the known cells of the map with fewer of them."""
    m = warp_matrix(b, truth, a)
    bw = cv2.warpAffine(
        b.data.view(np.uint8),
        m,
        (a.width, a.height),
        flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=255,
    ).view(np.int8)
    both = int(((a.data >= 0) & (bw >= 0)).sum())
    small = min(int((a.data >= 0).sum()), int((b.data >= 0).sum()))
    return both / small if small else 0.0


__all__ = ["Pair", "crop", "degrade", "hide_pose", "known_overlap", "make_pair", "rotate"]
