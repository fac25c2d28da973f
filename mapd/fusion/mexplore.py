"""The m-explore ``multirobot_map_merge`` estimator, re-done for comparison in ``mapd bench merge``.

What its ``MergingPipeline::estimateTransforms`` does for a pair: the occupancy data taken as an 8-bit
image as it lies in memory (unknown -1 reads as 255, free 0, occupied 100), features on both images,
OpenCV stitching's ``AffineBestOf2NearestMatcher`` (nearest/second-nearest ratio 1 - match_conf =
0.7, both directions, at least 6 matches), ``estimateAffinePartial2D`` with RANSAC (rotation,
translation *and scale*; reprojection threshold 3 px), confidence = inliers / (8 + 0.3 * matches)
(0 when above 3, as OpenCV does for near-identical images), and the pair kept when confidence >= 1.0.

Features are AKAZE with OpenCV's defaults, m-explore's default ``estimation_feature_type`` (OpenCV 5
moved AKAZE out of the main modules, hence mapd's ``opencv-python-headless<5``). Unlike m-explore,
the result is expressed with both maps' origins and resolutions honoured, so the comparison
measures its matching, not its frame bugs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from mapd.fusion.transforms import index_to_map
from mapd.grid import OccupancyGrid, Pose2D

CONFIDENCE_THRESHOLD = 1.0
MATCH_CONF = 0.3
MIN_MATCHES = 6


@dataclass(frozen=True)
class BaselineEstimate:
    """b's map frame in a's map frame as a 3x3 similarity (meters), its confidence and verdict."""

    matrix: np.ndarray
    confidence: float
    accepted: bool
    matches: int
    inliers: int

    @property
    def transform(self) -> Pose2D:
        m = self.matrix
        return Pose2D(float(m[0, 2]), float(m[1, 2]), math.atan2(m[1, 0], m[0, 0]))


def _features(grid: OccupancyGrid) -> tuple[list[cv2.KeyPoint], np.ndarray | None]:
    img = np.ascontiguousarray(grid.data.view(np.uint8))
    kps, desc = cv2.AKAZE.create().detectAndCompute(img, None)
    return list(kps), desc


def _ratio_matches(d1: np.ndarray, d2: np.ndarray) -> set[tuple[int, int]]:
    """OpenCV stitching's CpuMatcher: ratio test both ways, union of the pairs."""
    bf = cv2.BFMatcher(cv2.NORM_HAMMING)
    out: set[tuple[int, int]] = set()
    for m in bf.knnMatch(d1, d2, k=2):
        if len(m) == 2 and m[0].distance < (1.0 - MATCH_CONF) * m[1].distance:
            out.add((m[0].queryIdx, m[0].trainIdx))
    for m in bf.knnMatch(d2, d1, k=2):
        if len(m) == 2 and m[0].distance < (1.0 - MATCH_CONF) * m[1].distance:
            out.add((m[0].trainIdx, m[0].queryIdx))
    return out


def estimate(a: OccupancyGrid, b: OccupancyGrid) -> BaselineEstimate:
    """The m-explore-style estimate of b's map frame in a's map frame."""
    none = BaselineEstimate(np.eye(3), 0.0, False, 0, 0)
    ka, da = _features(a)
    kb, db = _features(b)
    if da is None or db is None or len(ka) < 2 or len(kb) < 2:
        return none
    pairs = sorted(_ratio_matches(db, da))
    if len(pairs) < MIN_MATCHES:
        return BaselineEstimate(np.eye(3), 0.0, False, len(pairs), 0)
    src = np.array([kb[i].pt for i, _ in pairs], dtype=np.float32)
    dst = np.array([ka[j].pt for _, j in pairs], dtype=np.float32)
    m, mask = cv2.estimateAffinePartial2D(src, dst, method=cv2.RANSAC, ransacReprojThreshold=3.0)
    if m is None or mask is None:
        return BaselineEstimate(np.eye(3), 0.0, False, len(pairs), 0)
    inliers = int(mask.sum())
    conf = inliers / (8.0 + 0.3 * len(pairs))
    if conf > 3.0:
        conf = 0.0
    # pixel (col, row of the data array) of b -> of a, to map frames: G_a M G_b^-1
    pix = np.vstack([m, [0.0, 0.0, 1.0]])
    full = index_to_map(a) @ pix @ np.linalg.inv(index_to_map(b))
    return BaselineEstimate(full, conf, conf >= CONFIDENCE_THRESHOLD, len(pairs), inliers)
