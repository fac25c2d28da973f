"""Localize a 2D scan in an occupancy grid: a correlative scan matcher on a likelihood field.

Used by the paper evaluation (Figure 9): the same scan is localized in the original map and in
each recovered map, from the same perturbed start, and the poses are compared.

Method (Olson's correlative matching, coarse to fine): occupied cells become a likelihood field
``exp(-d^2 / 2 sigma^2)`` of the distance ``d`` to the surface of occupied areas (from free space
or from inside a thick wall), on a grid ``UPSAMPLE`` times finer than the map. Scoring against
cell centres instead biases poses by up to half a cell, since a beam ends where it enters a cell.
Candidate poses on a grid over (x, y, yaw) are scored by the mean field value under the scan's end points, looked up
with bilinear interpolation. The best few candidates of each level seed a finer grid around them,
ending at about 2 mm and 0.05 degrees. Everything is vectorised over candidates and beams.
Poses are in the grid's map frame: meters and radians, counter-clockwise (REP-103).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage

from mapd.grid import OCCUPIED_AT, OccupancyGrid, Pose2D

UPSAMPLE = 4
#: (half window in xy as a multiple of the step, xy step m, half window yaw steps, yaw step rad)
_LEVELS_FROM_RES = ((1.0, 1.0), (0.25, 0.25), (0.05, 0.05))


@dataclass(frozen=True)
class Match:
    """The localized pose, its score (mean likelihood of the end points, 0..1) and the beams used."""

    pose: Pose2D
    score: float
    beams: int


class ScanMatcher:
    """Scores and searches scan poses against one occupancy grid."""

    def __init__(self, grid: OccupancyGrid, sigma: float | None = None) -> None:
        self.grid = grid
        self.sigma = sigma if sigma is not None else 1.5 * grid.resolution
        occ = (grid.data >= OCCUPIED_AT).astype(np.uint8)
        if occ.any():
            fine = np.kron(occ, np.ones((UPSAMPLE, UPSAMPLE), np.uint8))
            # Distance to the surface of occupied areas, from outside and from inside: a return lies on
            # the first occupied cell a beam meets, not deep inside a thick wall.
            outside = cv2.distanceTransform(1 - fine, cv2.DIST_L2, 5)
            inside = cv2.distanceTransform(fine, cv2.DIST_L2, 5)
            dist = np.where(fine > 0, inside - 0.5, outside - 0.5).clip(0).astype(np.float64)
            dist *= grid.resolution / UPSAMPLE
            self.field = np.exp(-0.5 * (dist / self.sigma) ** 2).astype(np.float32)
        else:
            self.field = np.zeros((grid.height * UPSAMPLE, grid.width * UPSAMPLE), np.float32)

    def endpoints(self, ranges: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """Sensor-frame (x, y) of valid returns, shape (N, 2)."""
        r = np.asarray(ranges, np.float64)
        a = np.asarray(angles, np.float64)
        ok = np.isfinite(r) & (r > 0.0) & (r < max_range)
        return np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1)

    def score(self, points: np.ndarray, poses: np.ndarray) -> np.ndarray:
        """Mean likelihood of ``points`` (N, 2) under each pose of ``poses`` (K, 3)."""
        if len(points) == 0:
            return np.zeros(len(poses))
        x, y, yaw = poses[:, 0:1], poses[:, 1:2], poses[:, 2:3]
        c, s = np.cos(yaw), np.sin(yaw)
        px = x + c * points[:, 0] - s * points[:, 1]
        py = y + s * points[:, 0] + c * points[:, 1]
        rows, cols = self.grid.world_to_cell(px, py)
        # map_coordinates samples at sub-cell centres: sub-cell i spans [i, i+1), its centre is i + 0.5.
        vals = ndimage.map_coordinates(
            self.field, [rows.ravel() * UPSAMPLE - 0.5, cols.ravel() * UPSAMPLE - 0.5], order=1, cval=0.0
        )
        return vals.reshape(px.shape).mean(axis=1)

    def match(
        self,
        ranges: np.ndarray,
        angles: np.ndarray,
        guess: Pose2D,
        *,
        max_range: float = 80.0,
        search_xy: float = 0.4,
        search_yaw: float = math.radians(12.0),
        keep: int = 6,
    ) -> Match:
        """Find the pose near ``guess`` that best explains the scan."""
        pts = self.endpoints(ranges, angles, max_range)
        if len(pts) > 360:  # every beam is not needed to find the peak; keep the work bounded
            pts = pts[np.linspace(0, len(pts) - 1, 360).astype(int)]
        res = self.grid.resolution
        seeds = np.array([[guess.x, guess.y, guess.yaw]])
        half_xy, half_yaw = search_xy, search_yaw
        best = seeds[0]
        best_score = 0.0
        for xy_mult, yaw_deg in _LEVELS_FROM_RES:
            step_xy = xy_mult * res
            step_yaw = math.radians(yaw_deg)
            nxy = max(1, math.ceil(half_xy / step_xy))
            nyaw = max(1, math.ceil(half_yaw / step_yaw))
            dxy = np.arange(-nxy, nxy + 1) * step_xy
            dyaw = np.arange(-nyaw, nyaw + 1) * step_yaw
            gx, gy, gt = np.meshgrid(dxy, dxy, dyaw, indexing="ij")
            offsets = np.stack([gx.ravel(), gy.ravel(), gt.ravel()], axis=1)
            cands = (seeds[:, None, :] + offsets[None, :, :]).reshape(-1, 3)
            scores = np.concatenate(
                [self.score(pts, chunk) for chunk in np.array_split(cands, max(1, len(cands) // 2048))]
            )
            order = np.argsort(scores)[::-1][:keep]
            seeds = cands[order]
            best, best_score = cands[order[0]], float(scores[order[0]])
            # The next level searches one step of this level around each seed.
            half_xy, half_yaw = step_xy, step_yaw
        yaw = math.atan2(math.sin(best[2]), math.cos(best[2]))
        return Match(Pose2D(float(best[0]), float(best[1]), yaw), best_score, len(pts))


def raycast(grid: OccupancyGrid, pose: Pose2D, angles: np.ndarray, max_range: float) -> np.ndarray:
    """Ranges from ``pose`` to the first occupied cell along each beam (inf when none within range).

    Samples every quarter cell along each ray, vectorised over beams: a simple reference sensor for
    tests and for simulating scans in a known map.
    """
    step = grid.resolution / 4.0
    dists = np.arange(step, max_range, step)
    a = pose.yaw + np.asarray(angles, np.float64)
    px = pose.x + np.cos(a)[:, None] * dists
    py = pose.y + np.sin(a)[:, None] * dists
    rows, cols = grid.world_to_cell(px, py)
    r = np.floor(rows).astype(np.int64)
    c = np.floor(cols).astype(np.int64)
    inside = (r >= 0) & (r < grid.height) & (c >= 0) & (c < grid.width)
    hit = np.zeros(r.shape, bool)
    hit[inside] = grid.data[r[inside], c[inside]] >= OCCUPIED_AT
    first = np.where(hit.any(axis=1), hit.argmax(axis=1), -1)
    out = np.full(len(a), np.inf)
    out[first >= 0] = dists[first[first >= 0]]
    return out
