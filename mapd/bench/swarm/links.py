"""Who hears whom: range by line-of-sight distance, and the walls a straight line between two robots crosses.

Two robots hear each other when their straight-line distance is at most ``range_m`` (walls do not
shorten the range; each wall crossed adds a per-frame loss in :class:`~mapd.bench.swarm.radio.Radio`).
A wall is a run of occupied cells of the building's grid along the segment: the segment is sampled
every half cell, and each step from a non-occupied sample to an occupied one counts one crossing, so
a thick wall counts once and a door does not count. Furniture in the simulator's building and
clutter in a logged map count as walls too. Links are symmetric.
"""

from __future__ import annotations

import math

import numpy as np

from mapd.bench.swarm.streams import Building


def link_matrices(
    positions: np.ndarray, range_m: float, building: Building | None
) -> tuple[np.ndarray, np.ndarray]:
    """``(hears, walls)`` for robots at ``positions`` ((N, 2) metres in the building's frame)."""
    n = len(positions)
    diff = positions[:, None, :] - positions[None, :, :]
    dist = np.hypot(diff[..., 0], diff[..., 1])
    hears = dist <= range_m
    np.fill_diagonal(hears, False)
    walls = np.zeros((n, n), dtype=np.int32)
    if building is None:
        return hears, walls
    iu, ju = np.nonzero(np.triu(hears, 1))
    if len(iu) == 0:
        return hears, walls
    counts = count_walls(building, positions[iu], positions[ju])
    walls[iu, ju] = counts
    walls[ju, iu] = counts
    return hears, walls


def hop_counts(hears: np.ndarray) -> np.ndarray:
    """(N, N) radio hops between robots over ``hears`` (0 to itself, -1 where no path joins them)."""
    from scipy.sparse.csgraph import shortest_path

    d = shortest_path(hears.astype(np.float64), method="D", unweighted=True)
    return np.where(np.isfinite(d), d, -1).astype(np.int16)


def count_walls(building: Building, a: np.ndarray, b: np.ndarray, batch: int = 256) -> np.ndarray:
    """Walls crossed by each segment ``a[k]`` -> ``b[k]`` ((K, 2) arrays, metres)."""
    if len(a) > batch:
        parts = [
            count_walls(building, a[k : k + batch], b[k : k + batch], batch) for k in range(0, len(a), batch)
        ]
        return np.concatenate(parts)
    g = building.grid
    occ = building.occupied
    step = 0.5 * g.resolution
    length = np.hypot(b[:, 0] - a[:, 0], b[:, 1] - a[:, 1])
    m = max(2, math.ceil(float(length.max(initial=0.0)) / step) + 1)
    t = np.linspace(0.0, 1.0, m)[None, :]
    xs = a[:, :1] + t * (b[:, :1] - a[:, :1])
    ys = a[:, 1:] + t * (b[:, 1:] - a[:, 1:])
    fr, fc = g.world_to_cell(xs, ys)
    r = np.floor(fr).astype(np.int64)
    c = np.floor(fc).astype(np.int64)
    inside = (r >= 0) & (r < g.height) & (c >= 0) & (c < g.width)
    hit = np.zeros(r.shape, dtype=bool)
    hit[inside] = occ[r[inside], c[inside]]
    # Samples beyond each segment's own length repeat nothing: the grid is uniform in t, so short
    # segments are sampled more finely, which only makes their count more exact.
    rising = hit[:, 1:] & ~hit[:, :-1]
    return (rising.sum(axis=1) + hit[:, 0]).astype(np.int32)
