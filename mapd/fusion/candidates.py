"""Candidate placements of map b on map a, in working-resolution pixel indices.

Two sources, so that one failing does not leave the estimator blind:

* **features**: SIFT keypoints of both map images, ratio-test matches, and a 2-point rigid RANSAC
  (rotation + translation, no scale: both resolutions are known) that keeps the best few distinct
  models, not just the single best;
* **search**, which needs no features: a rotation *signature* (histograms of wall orientation,
  circularly correlated) proposes headings, and for each heading FFT correlations propose
  translations (b's walls against a's wall likelihood and wall evidence, and the two maps' free
  space against each other: :class:`Correlator`). Without a usable signature, every heading is
  tried.

A search is long (seconds on a large map): it can be stopped between stages, by a ``stop`` callable
asked before each heading (:meth:`Correlator.search`), which raises :class:`SearchStopped`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft

from mapd.fusion.transforms import to_matrix, wrap_angle
from mapd.fusion.views import (
    AGREE_WEIGHT,
    DISAGREE_WEIGHT,
    OCC_C,
    UNK_C,
    Coarse,
    MapView,
    evidence_field,
    free_fields,
    score_fields,
    wall_distance,
)
from mapd.grid import Pose2D

#: Asked between the stages of a search: True once the search is to be given up (the daemon stops).
Stop = Callable[[], bool]


class SearchStopped(Exception):
    """A search was given up because its ``stop`` callable said so; it has no answer."""


def check_stop(stop: Stop | None) -> None:
    """Raise :class:`SearchStopped` if ``stop`` says so (a cheap call: an event's ``is_set``)."""
    if stop is not None and stop():
        raise SearchStopped


@dataclass(frozen=True)
class Hyp:
    """A placement ``q_a = R(yaw) q_b + (tx, ty)`` in pixel indices, with the score that proposed it."""

    yaw: float
    tx: float
    ty: float
    score: float = 0.0
    source: str = "search"

    def matrix(self) -> np.ndarray:
        return to_matrix(Pose2D(self.tx, self.ty, self.yaw))

    @staticmethod
    def from_matrix(m: np.ndarray, score: float = 0.0, source: str = "search") -> Hyp:
        return Hyp(wrap_angle(math.atan2(m[1, 0], m[0, 0])), float(m[0, 2]), float(m[1, 2]), score, source)


def same(h1: Hyp, h2: Hyp, at: np.ndarray, cells: float, deg: float) -> bool:
    """True when two placements put point ``at`` of b within ``cells`` and turn within ``deg``."""
    # plain floats, not 3x3 matrices: the search compares candidates pairwise, ~10^4 times a pair
    if abs(wrap_angle(h1.yaw - h2.yaw)) >= math.radians(deg):
        return False
    x, y = float(at[0]), float(at[1])
    c1, s1, c2, s2 = math.cos(h1.yaw), math.sin(h1.yaw), math.cos(h2.yaw), math.sin(h2.yaw)
    dx = (c1 - c2) * x - (s1 - s2) * y + h1.tx - h2.tx
    dy = (s1 - s2) * x + (c1 - c2) * y + h1.ty - h2.ty
    return math.hypot(dx, dy) < cells


def distinct(hyps: list[Hyp], n: int, at: np.ndarray, cells: float = 3.0, deg: float = 3.0) -> list[Hyp]:
    """The first ``n`` hypotheses that are pairwise distinct (input order kept)."""
    out: list[Hyp] = []
    for h in hyps:
        if all(not same(h, o, at, cells, deg) for o in out):
            out.append(h)
            if len(out) >= n:
                break
    return out


# ---------------------------------------------------------------------------------------------
# Features
# ---------------------------------------------------------------------------------------------


def feature_hyps(
    a: MapView, b: MapView, rng: np.random.Generator, keep: int = 6, iters: int = 600
) -> list[Hyp]:
    """Rigid models from SIFT matches by 2-point RANSAC; the best ``keep`` distinct ones."""
    pa, da = a.features()
    pb, db = b.features()
    if len(pa) < 3 or len(pb) < 3:
        return []
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(db, da, k=2)
    pairs = [
        (m[0].queryIdx, m[0].trainIdx) for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance
    ]
    if len(pairs) < 3:
        return []
    idx = np.array(pairs)
    s, d = pb[idx[:, 0]], pa[idx[:, 1]]
    n = len(s)
    i = rng.integers(0, n, iters)
    j = rng.integers(0, n, iters)
    vb, va = s[j] - s[i], d[j] - d[i]
    lb, la = np.hypot(vb[:, 0], vb[:, 1]), np.hypot(va[:, 0], va[:, 1])
    # a rigid motion keeps distances: most random pairs fail this before any model is scored
    ok = (i != j) & (lb > 8) & (np.abs(la - lb) < 2.0)
    if not ok.any():
        return []
    i, vb, va = i[ok], vb[ok], va[ok]
    yaw = np.arctan2(va[:, 1], va[:, 0]) - np.arctan2(vb[:, 1], vb[:, 0])
    c, sn = np.cos(yaw), np.sin(yaw)
    tx = d[i, 0] - (c * s[i, 0] - sn * s[i, 1])
    ty = d[i, 1] - (sn * s[i, 0] + c * s[i, 1])
    px = c[:, None] * s[None, :, 0] - sn[:, None] * s[None, :, 1] + tx[:, None]
    py = sn[:, None] * s[None, :, 0] + c[:, None] * s[None, :, 1] + ty[:, None]
    inliers = (np.hypot(px - d[None, :, 0], py - d[None, :, 1]) < 3.0).sum(axis=1)
    out: list[Hyp] = []
    at = b.centre()
    for k in np.argsort(-inliers):
        if inliers[k] < 3:
            break
        h = Hyp(float(yaw[k]), float(tx[k]), float(ty[k]), float(inliers[k]), "features")
        if all(not same(h, o, at, 4.0, 3.0) for o in out):
            out.append(h)
            if len(out) >= keep:
                break
    return out


# ---------------------------------------------------------------------------------------------
# Search
# ---------------------------------------------------------------------------------------------


def signature_angles(a: MapView, b: MapView, n: int = 4) -> list[float]:
    """Headings (radians, b in a) from the circular correlation of wall-orientation histograms.

    Orientations repeat every 180 degrees, so each peak gives two headings.
    """
    ha, hb = a.orientation_hist(), b.orientation_hist()
    if ha.sum() <= 0 or hb.sum() <= 0:
        return []
    bins = len(ha)
    # c[k] = sum_n ha[n] hb[n + k]: b's walls are a's turned by k bins
    c = np.real(np.fft.ifft(np.conj(np.fft.fft(ha)) * np.fft.fft(hb)))
    out: list[float] = []
    for _ in range(n):
        k = int(np.argmax(c))
        if not math.isfinite(c[k]) or c[k] <= 0:
            break
        lo, mid, hi = c[(k - 1) % bins], c[k], c[(k + 1) % bins]
        den = lo - 2 * mid + hi
        off = 0.5 * (lo - hi) / den if den < 0 and math.isfinite(den) else 0.0
        theta = (k + off) * math.pi / bins
        # b = R(theta) a for orientations, so b's frame sits in a's frame turned by -theta
        out += [wrap_angle(-theta), wrap_angle(-theta + math.pi)]
        for j in range(-6, 7):
            c[(k + j) % bins] = -np.inf
    return out


#: rankings of the correlation search (raw, per wall, evidence, free space)
RANKINGS = 4


class Correlator:
    """FFT correlation of b's coarse walls, turned by a heading, against a's coarse fields.

    Four rankings of the shifts, and peaks of each are proposed:

    * **raw**: a wall likelihood summed over the overlap, which favours large overlaps;
    * **per wall**: the same per overlapping wall (with at least ``floor`` walls), which does not
      let a large overlap of a repetitive layout outrank the true, smaller one but favours small
      chance fits;
    * **evidence**: met walls for, walls landing on known space away from any wall strongly
      against (:func:`mapd.fusion.views.evidence_field`), the tally the full check makes. The
      smooth likelihood forgives a wall that lands a cell beside another, so along a corridor
      with doors, sliding by a door's pitch scores as well as the truth; the evidence does not;
    * **free space**: free cells on free cells for, clear free space under a wall of the other map
      strongly against (the weights of :attr:`mapd.fusion.refine.Score.free_evidence`). It finds
      the placement that lays the most of one map's explored space on the other's: on open
      ground with few walls, and where the truth's walls fit a degraded copy worse than a small
      aliased patch's do, the wall rankings put the truth twenty places down or more.
    """

    def __init__(self, a: Coarse, b: Coarse, floor: float) -> None:
        self.a, self.b = a, b
        self.floor = max(floor, 1.0)
        hb, wb = b.cls.shape
        self.diag = math.ceil(math.hypot(hb, wb)) + 2
        ha, wa = a.cls.shape
        self.shape = (sfft.next_fast_len(ha + self.diag), sfft.next_fast_len(wa + self.diag, real=True))
        self.fa_target = sfft.rfft2(a.target, s=self.shape)
        self.fa_walls = sfft.rfft2(a.walls, s=self.shape)
        self.fa_known = sfft.rfft2((a.cls != UNK_C).astype(np.float32), s=self.shape)
        self.fa_evidence = sfft.rfft2(a.evidence, s=self.shape)
        self.fa_free = sfft.rfft2(a.free, s=self.shape)
        self.fa_clear = sfft.rfft2(a.clear, s=self.shape)

    def peaks(self, yaw: float, k: int = 3) -> tuple[list[Hyp], ...]:
        """The ``k`` best shifts for b turned by ``yaw`` by each ranking (raw, per wall, evidence,
        free space)."""
        b, d = self.b, self.diag
        hb, wb = b.cls.shape
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s], [s, c]])
        shift = np.array([(d - 1) / 2.0, (d - 1) / 2.0]) - rot @ np.array([(wb - 1) / 2.0, (hb - 1) / 2.0])
        fwd = np.hstack([rot, shift[:, None]])
        cls_r = cv2.warpAffine(
            b.cls, fwd, (d, d), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=UNK_C
        )
        # one distance transform of b's turned walls serves all four rankings' fields
        dist = wall_distance(cls_r == OCC_C)
        walls_r, target_r = score_fields(cls_r, dist=dist)
        fb_walls = np.conj(sfft.rfft2(walls_r, s=self.shape))
        # E(t) = sum_q walls_b(q) evidence_a(q + t) + evidence_b(q) walls_a(q + t)
        spec = fb_walls * self.fa_evidence
        spec += np.conj(sfft.rfft2(evidence_field(cls_r, dist=dist), s=self.shape)) * self.fa_walls
        ev = self._best(sfft.irfft2(spec, s=self.shape), yaw, shift, k)
        # S(t) = sum_q walls_b(q) target_a(q + t) + target_b(q) walls_a(q + t)
        spec = fb_walls * self.fa_target
        spec += np.conj(sfft.rfft2(target_r, s=self.shape)) * self.fa_walls
        raw = sfft.irfft2(spec, s=self.shape)
        # A(t): walls of either map landing where the other knows the place
        area = fb_walls * self.fa_known
        area += np.conj(sfft.rfft2((cls_r != UNK_C).astype(np.float32), s=self.shape)) * self.fa_walls
        per_wall = raw / np.maximum(sfft.irfft2(area, s=self.shape), self.floor)
        # F(t): free on free for, a clear free cell under a wall of the other map strongly against
        free_r, clear_r = free_fields(cls_r, dist=dist)
        spec = AGREE_WEIGHT * np.conj(sfft.rfft2(free_r, s=self.shape)) * self.fa_free
        spec += DISAGREE_WEIGHT * fb_walls * self.fa_clear
        spec += DISAGREE_WEIGHT * np.conj(sfft.rfft2(clear_r, s=self.shape)) * self.fa_walls
        free = self._best(sfft.irfft2(spec, s=self.shape), yaw, shift, k)
        return self._best(raw, yaw, shift, k), self._best(per_wall, yaw, shift, k), ev, free

    def _best(self, corr: np.ndarray, yaw: float, shift: np.ndarray, k: int) -> list[Hyp]:
        rows, cols = self.shape
        d = self.diag
        out: list[Hyp] = []
        for _ in range(k):
            idx = int(np.argmax(corr))
            ky, kx = divmod(idx, cols)
            val = float(corr[ky, kx])
            if not math.isfinite(val) or val <= 0:
                break
            ty = ky if ky < rows - d else ky - rows
            tx = kx if kx < cols - d else kx - cols
            out.append(Hyp(yaw, float(tx + shift[0]), float(ty + shift[1]), val, "search"))
            corr[max(0, ky - 3) : ky + 4, max(0, kx - 3) : kx + 4] = -np.inf
        return out

    def search(
        self,
        angles: list[float],
        n: int,
        at: np.ndarray,
        k: int = 3,
        *,
        group: int = 1,
        per_group: int = 0,
        stop: Stop | None = None,
    ) -> list[Hyp]:
        """The ``n`` best distinct peaks by each ranking over all ``angles`` (up to ``RANKINGS`` n),
        plus the ``per_group`` best of each ranking within each run of ``group`` consecutive angles.

        The per-group share matters in repetitive layouts: a warehouse turned by 90 or 180 degrees
        fits small patches of itself better, per wall, than the true heading fits its large overlap,
        so a global top ``n`` can hold no peak of the true heading at all.

        ``stop`` is asked before each heading, and :class:`SearchStopped` raised once it says so:
        the every-heading search of a large map runs 180 headings, seconds in all, a few tens of
        milliseconds each.
        """
        rankings: list[list[Hyp]] = [[] for _ in range(RANKINGS)]
        groups: list[list[list[Hyp]]] = []
        for j, ang in enumerate(angles):
            check_stop(stop)
            if j % max(group, 1) == 0:
                groups.append([[] for _ in range(RANKINGS)])
            for r, found in enumerate(self.peaks(ang, k)):
                rankings[r] += found
                groups[-1][r] += found
        out: list[Hyp] = []
        extra: list[Hyp] = []
        for r, ranked in enumerate(rankings):
            best = distinct(sorted(ranked, key=lambda h: -h.score), n, at)
            (out if r == 0 else extra).extend(best)
        if per_group > 0:
            for g in groups:
                for ranked in g:
                    extra += distinct(sorted(ranked, key=lambda h: -h.score), per_group, at)
        for h in extra:
            if all(not same(h, o, at, 3.0, 3.0) for o in out):
                out.append(h)
        return out


def coarse_factor(a: MapView, b: MapView, cells: int, max_m: float) -> int:
    """Pooling factor for the search: about ``cells`` a side, coarse cells at most ``max_m`` wide,
    but never more than ``2 cells`` a side (coarse maps would make the search slow)."""
    side = max(*a.shape, *b.shape)
    f = max(1, min(math.ceil(side / cells), int(max_m / a.res)))
    return max(f, math.ceil(side / (2 * cells)))


def to_fine(h: Hyp, f: int) -> Hyp:
    """Coarse-pixel hypothesis to working-resolution pixels (coarse centre j is fine j f + (f-1)/2)."""
    c0 = (f - 1) / 2.0
    c, s = math.cos(h.yaw), math.sin(h.yaw)
    return Hyp(h.yaw, f * h.tx + c0 - (c - s) * c0, f * h.ty + c0 - (s + c) * c0, h.score, h.source)
