"""A simulated 2D lidar: ranges from a pose on a world occupancy grid, vectorised with numpy.

Every beam is sampled at fixed steps (half a world cell by default) out to the maximum range, all
beams at once as one (beams x samples) array; the first sample that lands on an occupied cell gives
the range. Cells outside the world are open space. Beams that hit nothing within ``max_range``, and
random dropouts, read ``inf`` (no return); returns get Gaussian range noise.

The sampling step trades exactness for speed: a step of half a cell never misses a wall two cells
thick (the generated worlds' walls are three), though a ray may slip between two diagonally touching
cells of a one-cell wall in a loaded map.
"""

from __future__ import annotations

import math

import numpy as np

from mapd.grid import Pose2D


class Lidar:
    """A 2D lidar on a world grid. ``occupied`` is a (H, W) bool array, row 0 at ``origin``."""

    def __init__(
        self,
        occupied: np.ndarray,
        resolution: float,
        origin: Pose2D,
        *,
        beams: int = 360,
        fov_deg: float = 360.0,
        max_range: float = 12.0,
        noise_std: float = 0.01,
        dropout: float = 0.01,
        step: float | None = None,
    ) -> None:
        if beams < 1 or not 0.0 < fov_deg <= 360.0 or max_range <= 0.0:
            raise ValueError("need beams >= 1, 0 < fov_deg <= 360 and max_range > 0")
        if not 0.0 <= dropout < 1.0 or noise_std < 0.0:
            raise ValueError("need 0 <= dropout < 1 and noise_std >= 0")
        occ = np.asarray(occupied, dtype=np.bool_)
        # A border of open cells lets out-of-world samples be clipped onto it instead of masked.
        self._occ = np.pad(occ, 1, constant_values=False)
        self._h, self._w = occ.shape
        self.resolution = float(resolution)
        self.origin = origin
        self.max_range = float(max_range)
        self.noise_std = float(noise_std)
        self.dropout = float(dropout)
        fov = math.radians(fov_deg)
        if beams == 1:
            self.angles = np.zeros(1)
        elif fov_deg >= 360.0:
            # A full circle: from -pi in steps of 2 pi / beams, never the same direction twice.
            self.angles = -math.pi + (2 * math.pi / beams) * np.arange(beams, dtype=np.float64)
        else:
            self.angles = -fov / 2 + (fov / (beams - 1)) * np.arange(beams, dtype=np.float64)
        st = step if step is not None else 0.5 * self.resolution
        self._t = np.arange(st, self.max_range + 1e-9, st, dtype=np.float32)

    def scan(self, pose: Pose2D, rng: np.random.Generator | None = None) -> np.ndarray:
        """Ranges (m) of one scan from the sensor at ``pose`` in the world frame; ``inf`` = no return."""
        res = self.resolution
        c0, s0 = math.cos(self.origin.yaw), math.sin(self.origin.yaw)
        dx, dy = pose.x - self.origin.x, pose.y - self.origin.y
        # Sensor position and beam directions in grid (col, row) units.
        pc, pr = (c0 * dx + s0 * dy) / res, (-s0 * dx + c0 * dy) / res
        th = pose.yaw - self.origin.yaw + self.angles
        ux = (np.cos(th) / res).astype(np.float32)[:, None]
        uy = (np.sin(th) / res).astype(np.float32)[:, None]
        t = self._t[None, :]
        cols = np.floor(pc + ux * t).astype(np.int32)
        rows = np.floor(pr + uy * t).astype(np.int32)
        np.clip(cols + 1, 0, self._w + 1, out=cols)
        np.clip(rows + 1, 0, self._h + 1, out=rows)
        hit = self._occ[rows, cols]
        first = np.argmax(hit, axis=1)
        found = hit[np.arange(hit.shape[0]), first]
        ranges = np.where(found, self._t[first].astype(np.float64), np.inf)
        if rng is not None:
            if self.noise_std > 0:
                ranges = ranges + rng.normal(0.0, self.noise_std, size=ranges.shape)
            if self.dropout > 0:
                ranges[rng.random(ranges.shape) < self.dropout] = np.inf
            ranges = np.where(np.isfinite(ranges), np.maximum(ranges, 0.01), ranges)
        return ranges
