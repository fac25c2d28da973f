"""Refining and scoring one placement of b on a (pixel indices of the working resolution).

* :func:`icp`: trimmed point-to-point ICP of b's wall cells onto a's (KD-tree), with a gate that
  shrinks from the coarse search's cell size to 2 cells: a wide capture range.
* :func:`polish`: robust Gauss-Newton on the bilinear distance from b's walls to a's nearest wall:
  sub-cell, sub-tenth-of-a-degree settling (ICP stops on cell-quantised correspondences). With a
  wide first gate it is also the cheap aligner used to rank many candidates.
* :func:`quick`: a cheap wall fit to rank aligned candidates before the full check.
* :func:`verify`: the full check on the overlap: the acceptance index and the two-way wall fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from mapd.fusion.candidates import Hyp
from mapd.fusion.transforms import to_matrix
from mapd.fusion.views import (
    AGREE_WEIGHT,
    DISAGREE_WEIGHT,
    FREE_CELLS,
    MEET_WEIGHT,
    MISS_WEIGHT,
    UNK_C,
    MapView,
    wall_distance,
)
from mapd.grid import Pose2D

#: a wall of one map "fits" when a wall of the other lies within this many cells
FIT_CELLS = 1.5


def evidence(hits: float, walls: float) -> float:
    """Log-likelihood-ratio style evidence of ``hits`` met walls out of ``walls`` (may be < 0)."""
    return MEET_WEIGHT * hits + MISS_WEIGHT * (walls - hits)


def _sample(pts: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return pts if len(pts) <= n else pts[rng.choice(len(pts), n, replace=False)]


def icp(a: MapView, b: MapView, h: Hyp, gate0: float, rng: np.random.Generator, iters: int = 30) -> Hyp:
    """Trimmed point-to-point ICP of b's walls onto a's, starting at ``h``."""
    if a.n_walls < 3 or b.n_walls < 3:
        return h
    pts = _sample(b.pts, 6000, rng)
    m = h.matrix()
    gate = max(gate0, 2.0)
    ha, wa = a.shape
    for it in range(iters):
        q = pts @ m[:2, :2].T + m[:2, 2]
        xi = np.clip(np.rint(q[:, 0]).astype(np.int64), 0, wa - 1)
        yi = np.clip(np.rint(q[:, 1]).astype(np.int64), 0, ha - 1)
        inside = (q[:, 0] >= -0.5) & (q[:, 0] < wa - 0.5) & (q[:, 1] >= -0.5) & (q[:, 1] < ha - 0.5)
        near = inside & (a.dist[yi, xi] <= gate)
        if int(near.sum()) < 6:
            break
        dist, idx = a.tree.query(q[near], distance_upper_bound=gate + 1.0)
        ok = np.isfinite(dist)
        if int(ok.sum()) < 6:
            break
        src, dst, dd = pts[near][ok], a.pts[idx[ok]], dist[ok]
        # trim the worst fifth: clutter and walls only one robot saw
        if len(dd) > 20:
            keep = dd <= np.quantile(dd, 0.8) + 1e-9
            src, dst = src[keep], dst[keep]
        new = kabsch(src, dst)
        step = float(np.abs(new - m).max())
        m = new
        if it >= 3:
            gate = max(2.0, gate * 0.7)
        if step < 1e-3 and gate <= 2.0:
            break
    return Hyp.from_matrix(m, h.score, h.source)


def kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (3x3) taking ``src`` points onto ``dst`` points."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((src - ms).T @ (dst - md))
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[1] *= -1
        r = vt.T @ u.T
    out = np.eye(3)
    out[:2, :2] = r
    out[:2, 2] = md - r @ ms
    return out


def polish(
    a: MapView,
    b: MapView,
    h: Hyp,
    rng: np.random.Generator,
    *,
    iters: int = 15,
    gate0: float = 2.0,
    npts: int = 4000,
) -> Hyp:
    """Robust Gauss-Newton on the distance from b's walls to a's nearest wall, from ``h``.

    Only walls within ``gate`` cells of a wall of a count (the gate shrinks from ``gate0`` to 2);
    residuals beyond 0.7 cells are down-weighted (Huber). Steps are clamped so that a bad start
    cannot fling the estimate far away.
    """
    pts = _sample(b.pts, npts, rng)
    if len(pts) < 6 or a.n_walls < 6:
        return h
    dist, gx, gy = a.field()
    m = h.matrix()
    gate = gate0
    for _ in range(iters):
        q = pts @ m[:2, :2].T + m[:2, 2]
        mx = q[:, 0].astype(np.float32).reshape(-1, 1)
        my = q[:, 1].astype(np.float32).reshape(-1, 1)
        d = cv2.remap(
            dist, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=99.0
        ).ravel()
        sel = d <= gate
        gate = max(2.0, 0.75 * gate)
        if int(sel.sum()) < 6:
            break
        qs, ds = q[sel], d[sel]
        gxs = cv2.remap(gx, mx, my, cv2.INTER_LINEAR).ravel()[sel]
        gys = cv2.remap(gy, mx, my, cv2.INTER_LINEAR).ravel()[sel]
        c = qs.mean(axis=0)
        # parameters: shift (cells) and a turn about the centroid of the walls in use
        jac = np.column_stack([gxs, gys, -gxs * (qs[:, 1] - c[1]) + gys * (qs[:, 0] - c[0])])
        w = np.where(ds <= 0.7, 1.0, 0.7 / np.maximum(ds, 1e-6))
        hess = jac.T @ (jac * w[:, None]) + np.diag([1e-3, 1e-3, 1e-3 * len(qs)])
        try:
            step = -np.linalg.solve(hess, jac.T @ (w * ds))
        except np.linalg.LinAlgError:
            break
        step[:2] = np.clip(step[:2], -1.0, 1.0)
        step[2] = float(np.clip(step[2], -0.01, 0.01))
        dm = to_matrix(Pose2D(0.0, 0.0, float(step[2])))
        dm[:2, 2] = c - dm[:2, :2] @ c + step[:2]
        m = dm @ m
        if abs(step[0]) < 0.01 and abs(step[1]) < 0.01 and abs(step[2]) < 1e-4 and gate <= 2.0:
            break
    return Hyp.from_matrix(m, h.score, h.source)


def _landing(a: MapView, pts: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The cells of a where b's points ``pts`` land under ``m`` (nearest), and which lie inside a."""
    q = pts @ m[:2, :2].T + m[:2, 2]
    ha, wa = a.shape
    xi = np.rint(q[:, 0]).astype(np.int64)
    yi = np.rint(q[:, 1]).astype(np.int64)
    return xi, yi, (xi >= 0) & (xi < wa) & (yi >= 0) & (yi < ha)


def quick(a: MapView, b: MapView, h: Hyp, support_walls: int) -> tuple[float, float]:
    """Cheap ranks of an aligned candidate from b's walls where a knows the place: their
    :func:`evidence`, and the share of them within 1.5 cells of a wall of a (discounted below
    ``support_walls`` walls), both times the agreement factor of a sample of b's known cells
    (agreement 0.8 -> 0, 0.95 -> 1, as in the full check's key). Without the agreement, bands of
    thick wall laid across thick wall (every face meets one, but free space lies on walls) outrank
    the truth and take the few places in the full check."""
    step = max(1, len(b.pts) // 3000)
    pts = b.pts[::step]
    m = h.matrix()
    xi, yi, inside = _landing(a, pts, m)
    xi, yi = xi[inside], yi[inside]
    known = a.known[yi, xi]
    n = int(known.sum())
    if n == 0:
        return 0.0, 0.0
    hits = int((a.dist[yi[known], xi[known]] <= FIT_CELLS).sum())
    agree = sample_agreement(a, b, m)
    return agree * evidence(hits * step, n * step), agree * hits / n * min(1.0, n * step / support_walls)


def agreement_ramp(agreement: float) -> float:
    """The agreement factor of candidates: agreement 0.8 (or less) -> 0, 0.95 (or more) -> 1.

    Even degraded copies of one place agree on about 0.93 or more of their common known cells
    (the 1 % quantile of the true placements of ``mapd bench merge`` seeds 1-3); a placement that
    lays a fifth of one map's known cells on the other's opposite class is no placement.
    """
    return float(np.clip((agreement - 0.8) / 0.15, 0.0, 1.0))


def sample_agreement(a: MapView, b: MapView, m: np.ndarray) -> float:
    """:func:`agreement_ramp` of b's sampled known cells near its walls that land on known cells
    of a; 1 when too few land there to tell."""
    pts, cls = b.known_sample()
    xi, yi, inside = _landing(a, pts, m)
    ac = a.cls[yi[inside], xi[inside]]
    both = ac != UNK_C
    if int(both.sum()) < 30:
        return 1.0
    return agreement_ramp(float((ac[both] == cls[inside][both]).mean()))


@dataclass(frozen=True)
class Score:
    """How well b placed by a candidate agrees with a.

    ``agreement``: cells known in both whose class (free/occupied) agrees, over cells known in
    both (the acceptance index); ``overlap``: cells known in both; ``walls_a``/``walls_b``: wall
    cells of each map where the other map knows the place; ``hits_a``/``hits_b``: those of them
    within 1.5 cells of a wall of the other map.
    """

    agreement: float = 0.0
    overlap: int = 0
    walls_a: int = 0
    walls_b: int = 0
    hits_a: int = 0
    hits_b: int = 0
    #: walls' worth of constraint in the least constrained direction (0 for a bare corridor)
    constraint: float = 0.0
    #: direction (radians, in a's pixel index) along which the met walls pin the least
    weak_dir: float = 0.0

    @property
    def fit(self) -> float:
        """Share of overlapping walls that meet a wall of the other map, pooled both ways."""
        n = self.walls_a + self.walls_b
        return (self.hits_a + self.hits_b) / n if self.walls_a and self.walls_b else 0.0

    @property
    def walls(self) -> int:
        return min(self.walls_a, self.walls_b)

    @property
    def evidence(self) -> float:
        """:func:`evidence` of the overlapping walls of both maps."""
        return evidence(self.hits_a + self.hits_b, self.walls_a + self.walls_b)

    @property
    def free_evidence(self) -> float:
        """Evidence of the cells known in both maps: agreeing ones for, disagreeing ones (strongly)
        against, counted in blocks of ``FREE_CELLS`` (neighbours are not independent)."""
        agree = self.agreement * self.overlap
        return (AGREE_WEIGHT * agree + DISAGREE_WEIGHT * (self.overlap - agree)) / FREE_CELLS

    @property
    def matched(self) -> int:
        return min(self.hits_a, self.hits_b)


def verify(a: MapView, b: MapView, h: Hyp) -> Score:
    """Score b placed on a by ``h`` over their whole overlap."""
    ha, wa = a.shape
    m = h.matrix()
    # only the part of a that b can cover
    hb, wb = b.shape
    corners = np.array([[-1, -1, 1], [wb, -1, 1], [wb, hb, 1], [-1, hb, 1]], dtype=np.float64) @ m.T
    x0 = max(0, int(np.floor(corners[:, 0].min())))
    x1 = min(wa, int(np.ceil(corners[:, 0].max())) + 1)
    y0 = max(0, int(np.floor(corners[:, 1].min())))
    y1 = min(ha, int(np.ceil(corners[:, 1].max())) + 1)
    if x1 <= x0 or y1 <= y0:
        return Score()
    roi = np.array([[1.0, 0.0, x0], [0.0, 1.0, y0], [0.0, 0.0, 1.0]])
    inv = (np.linalg.inv(m) @ roi)[:2]
    size = (x1 - x0, y1 - y0)
    flags = cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
    bw = cv2.warpAffine(b.cls, inv, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=UNK_C)
    bwall = cv2.warpAffine(
        b.walls.view(np.uint8), inv, size, flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=0
    ).astype(bool)
    acls = a.cls[y0:y1, x0:x1]
    aknown = a.known[y0:y1, x0:x1]
    awalls = a.walls[y0:y1, x0:x1]
    bknown = bw != UNK_C
    both = aknown & bknown
    n_both = int(both.sum())
    if n_both == 0:
        return Score()
    agree = int((acls[both] == bw[both]).sum())
    b_on_a = bwall & aknown
    a_on_b = awalls & bknown
    hits_b = int((a.dist[y0:y1, x0:x1][b_on_a] <= FIT_CELLS).sum())
    if not a_on_b.any():
        return Score(agree / n_both, n_both, 0, int(b_on_a.sum()), 0, hits_b)
    met = a_on_b & (wall_distance(bwall) <= FIT_CELLS)
    c2, s2 = a.normals()
    sc, ss = float(c2[y0:y1, x0:x1][met].sum()), float(s2[y0:y1, x0:x1][met].sum())
    hits_a = int(met.sum())
    # smallest eigenvalue of sum(n n^T) over the met walls: how many walls pin the weakest direction
    constraint = 0.5 * (hits_a - math.hypot(sc, ss))
    # the dominant normal is at half the angle of (sc, ss); the weak direction is across it
    weak = 0.5 * math.atan2(ss, sc) + 0.5 * math.pi
    return Score(
        agree / n_both, n_both, int(a_on_b.sum()), int(b_on_a.sum()), hits_a, hits_b, constraint, weak
    )


def slide_pinning(a: MapView, b: MapView, h: Hyp, sc: Score, step: float = 3.0) -> float:
    """Walls' worth that pin ``h`` along its weakest direction, measured rather than inferred.

    b is slid ``step`` cells both ways along ``sc.weak_dir``; the met walls lost (the drop in wall
    fit times the overlapping walls, averaged over both maps) is the smaller of the two. The normal
    based ``constraint`` undercounts short wall ends (warehouse shelving: thousands of long faces
    and a few dozen end cells, whose smoothed normals read as the long side's); sliding loses them
    all the same. A bare corridor loses nothing. Using the fit, not the hit count, keeps walls that
    merely leave the overlap at its edge from counting as pinning.
    """
    if sc.walls_a == 0 or sc.walls_b == 0:
        return 0.0
    lost = math.inf
    n = 0.5 * (sc.walls_a + sc.walls_b)
    for sign in (1.0, -1.0):
        d = np.eye(3)
        d[0, 2] = sign * step * math.cos(sc.weak_dir)
        d[1, 2] = sign * step * math.sin(sc.weak_dir)
        moved = verify(a, b, Hyp.from_matrix(d @ h.matrix(), h.score, h.source))
        lost = min(lost, (sc.fit - moved.fit) * n)
    return max(0.0, float(lost))
