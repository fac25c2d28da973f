"""Where is map b in map a? A rigid transform with a confidence, or a clear "no" with the reason.

:func:`estimate_transform` returns b's map frame expressed in a's map frame (``p_a = R(yaw) p_b + t``,
meters and radians), honouring both grids' origins (yaw included) and resolutions. It is a pure
function: no asyncio, no clock, no shared state beyond a small cache of prepared maps.

How (each step keeps several hypotheses, so one wrong peak cannot decide):

1. Both maps are brought to one working resolution (the coarser of the two; a finer map is pooled so
   that thin walls survive). Resolutions more than ``max_resolution_ratio`` apart are refused.
2. **Candidates.** Features (SIFT keypoints on the map image, ratio-test matching, a 2-point rigid
   RANSAC that keeps the best few distinct models) and, because features fail on sparse or repetitive
   maps, a search that needs none: a rotation signature (the histograms of wall orientation of both
   maps, circularly correlated) proposes headings, and for each heading an FFT correlation of one
   map's walls against the other's wall likelihood, minus walls seen where the other map is plainly
   free, gives the translation. When neither proposes an acceptable match, every heading is tried
   in 2 degree steps. A previous answer (``prior``) is one more candidate.
3. **Refinement** at the working resolution: a trimmed point-to-point ICP of b's wall cells onto
   a's (cKDTree), which turns a coarse answer into one within a cell and a fraction of a degree.
4. **Verification** of every refined candidate on the full overlap: the *overlap agreement* (the
   acceptance index: known cells whose class agrees, over cells known in both maps) and the *wall
   fit* (walls of each map that lie within 1.5 cells of a wall of the other, where the other map
   knows the place). The *confidence* is the wall fit, scaled down when the overlap holds few walls
   and when a clearly different candidate fits almost as well (an aliased corridor). An estimate is
   accepted only when confidence >= ``min_confidence`` and agreement >= ``min_agreement``;
   otherwise ``reason`` says which test failed.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import scipy.fft as sfft
from scipy.spatial import cKDTree

from mapd.fusion.transforms import compose, from_matrix, inverse, to_matrix, wrap_angle
from mapd.grid import OCCUPIED_AT, OccupancyGrid, Pose2D

FREE_C, OCC_C, UNK_C = 0, 1, 2


@dataclass(frozen=True)
class EstimateOptions:
    """Knobs of :func:`estimate_transform`; the defaults are what the bench measures."""

    min_confidence: float = 0.5
    min_agreement: float = 0.8
    #: refuse pairs whose resolutions differ by more than this factor
    max_resolution_ratio: float = 4.0
    #: the coarse search works on images of about this many cells on the longer side
    coarse_cells: int = 192
    #: ... but with coarse cells no larger than this (meters)
    max_coarse_m: float = 0.4
    #: fewest wall cells a map needs before it is worth matching
    min_walls: int = 30
    #: wall cells in the overlap at which the confidence stops being discounted for a small overlap
    support_walls: int = 120
    #: a candidate this far from the best (cells at b's centre, or degrees) counts as a rival
    rival_cells: float = 6.0
    rival_deg: float = 4.0
    use_features: bool = True
    #: sweep every heading when signature and features propose nothing acceptable
    exhaustive: bool = True


@dataclass(frozen=True)
class Estimate:
    """b's map frame in a's map frame, and how much to trust it.

    ``x``, ``y`` are meters and ``yaw`` radians, such that ``p_a = R(yaw) p_b + (x, y)``.
    ``agreement`` is the acceptance index over cells known in both maps; ``inliers`` the number of
    wall cells of b that landed on a wall of a; ``accepted`` is False with a ``reason`` when the
    estimate must not be merged.
    """

    x: float = 0.0
    y: float = 0.0
    yaw: float = 0.0
    confidence: float = 0.0
    agreement: float = 0.0
    inliers: int = 0
    accepted: bool = False
    reason: str = ""
    method: str = "none"
    overlap: int = 0
    details: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def transform(self) -> Pose2D:
        return Pose2D(self.x, self.y, self.yaw)

    def as_dict(self) -> dict[str, Any]:
        """JSON-able summary (no details)."""
        return {
            "x": self.x,
            "y": self.y,
            "yaw": self.yaw,
            "confidence": self.confidence,
            "agreement": self.agreement,
            "inliers": self.inliers,
            "accepted": self.accepted,
            "reason": self.reason,
            "method": self.method,
            "overlap": self.overlap,
        }


def rejected(reason: str, **kw: Any) -> Estimate:
    """A "not accepted" estimate with its reason."""
    return Estimate(accepted=False, reason=reason, **kw)


# ---------------------------------------------------------------------------------------------
# Prepared maps
# ---------------------------------------------------------------------------------------------


class _View:
    """One map at the working resolution, with what matching needs (built once, cached)."""

    def __init__(self, grid: OccupancyGrid, res: float) -> None:
        self.res = res
        self.cls = _resample_classes(grid, res)
        self.occ = self.cls == OCC_C
        self.known = self.cls != UNK_C
        self.n_occ = int(self.occ.sum())
        self.n_known = int(self.known.sum())
        r = res
        self.g = to_matrix(grid.origin) @ np.array([[r, 0.0, 0.5 * r], [0.0, r, 0.5 * r], [0.0, 0.0, 1.0]])
        # distance (cells) to the nearest wall; huge where there is none
        self.dist = _wall_distance(self.occ)
        ys, xs = np.nonzero(self.occ)
        self.pts = np.column_stack([xs, ys]).astype(np.float64)
        self._tree: cKDTree | None = None
        self._coarse: dict[int, _Coarse] = {}
        self._features: tuple[np.ndarray, np.ndarray] | None = None
        self._hist: np.ndarray | None = None

    @property
    def tree(self) -> cKDTree:
        if self._tree is None:
            self._tree = cKDTree(self.pts)
        return self._tree

    def coarse(self, f: int) -> _Coarse:
        if f not in self._coarse:
            self._coarse[f] = _Coarse(self.cls, f)
        return self._coarse[f]

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.cls.shape[0]), int(self.cls.shape[1]))

    def centre(self) -> np.ndarray:
        """Centroid of the known cells (pixel index)."""
        ys, xs = np.nonzero(self.known[::4, ::4])
        if len(xs) == 0:
            return np.array([self.cls.shape[1] / 2.0, self.cls.shape[0] / 2.0])
        return np.array([xs.mean() * 4.0, ys.mean() * 4.0])

    def orientation_hist(self) -> np.ndarray:
        if self._hist is None:
            self._hist = _orientation_hist(self.occ)
        return self._hist

    def features(self) -> tuple[np.ndarray, np.ndarray]:
        if self._features is None:
            self._features = _features(self.cls)
        return self._features


class _Coarse:
    """A map pooled by an integer factor for the correlation search."""

    def __init__(self, cls: np.ndarray, f: int) -> None:
        self.f = f
        if f == 1:
            occ = cls == OCC_C
            known = cls != UNK_C
        else:
            occ_f = cv2.resize((cls == OCC_C).astype(np.float32), None, fx=1.0 / f, fy=1.0 / f, interpolation=cv2.INTER_AREA)
            known_f = cv2.resize((cls != UNK_C).astype(np.float32), None, fx=1.0 / f, fy=1.0 / f, interpolation=cv2.INTER_AREA)
            occ = occ_f > 0.0
            known = (known_f >= 0.3) | occ
        self.cls = np.full(occ.shape, UNK_C, dtype=np.uint8)
        self.cls[known] = FREE_C
        self.cls[occ] = OCC_C
        self.target = _fields(self.cls)[1]  # wall likelihood minus plain free space
        self.occ = (self.cls == OCC_C).astype(np.float32)


def _resample_classes(grid: OccupancyGrid, res: float) -> np.ndarray:
    """Cell classes of ``grid`` at resolution ``res`` >= its own (pooled: walls win, half-known is known)."""
    d = grid.data
    cls = np.full(d.shape, UNK_C, dtype=np.uint8)
    cls[d >= 0] = FREE_C
    cls[d >= OCCUPIED_AT] = OCC_C
    k = res / grid.resolution
    if abs(k - 1.0) < 1e-9:
        return cls
    occ_f = cv2.resize((cls == OCC_C).astype(np.float32), None, fx=1.0 / k, fy=1.0 / k, interpolation=cv2.INTER_AREA)
    known_f = cv2.resize((cls != UNK_C).astype(np.float32), None, fx=1.0 / k, fy=1.0 / k, interpolation=cv2.INTER_AREA)
    out = np.full(occ_f.shape, UNK_C, dtype=np.uint8)
    out[known_f >= 0.5] = FREE_C
    out[occ_f >= 0.5 / (k * k)] = OCC_C
    return out


def _wall_distance(occ: np.ndarray) -> np.ndarray:
    if not occ.any():
        return np.full(occ.shape, 1e6, dtype=np.float32)
    return cv2.distanceTransform((~occ).astype(np.uint8), cv2.DIST_L2, 5)


_LAMBDA_FREE = 0.5
_SIGMA = 1.0


def _fields(cls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(walls as float, wall likelihood minus plain free space) for the correlation score."""
    occ = cls == OCC_C
    dist = _wall_distance(occ)
    like = np.exp(-(dist.astype(np.float32) ** 2) / (2.0 * _SIGMA**2))
    free_far = (cls == FREE_C) & (dist > 2.5)
    return occ.astype(np.float32), (like - _LAMBDA_FREE * free_far).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Candidates
# ---------------------------------------------------------------------------------------------


@dataclass
class _Hyp:
    """q_a = R(yaw) q_b + t in working-resolution pixel indices."""

    yaw: float
    tx: float
    ty: float
    score: float
    source: str

    def matrix(self) -> np.ndarray:
        return to_matrix(Pose2D(self.tx, self.ty, self.yaw))


def _orientation_hist(occ: np.ndarray, bins: int = 180) -> np.ndarray:
    """Histogram of wall orientations (mod 180 degrees, 1 degree bins), weighted by gradient."""
    img = cv2.GaussianBlur(occ.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    sel = mag > 1e-3
    ang = np.mod(np.arctan2(gy[sel], gx[sel]), math.pi)
    hist, _ = np.histogram(ang, bins=bins, range=(0.0, math.pi), weights=mag[sel])
    # light circular smoothing so a 1 degree shift does not split a peak
    k = np.array([0.25, 0.5, 1.0, 0.5, 0.25])
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, k, mode="valid")


def _signature_angles(a: _View, b: _View, n: int = 4) -> list[float]:
    """Headings (radians) proposed by the circular correlation of wall-orientation histograms."""
    ha, hb = a.orientation_hist(), b.orientation_hist()
    if ha.sum() <= 0 or hb.sum() <= 0:
        return []
    bins = len(ha)
    # c[k] = sum_phi hb[phi] ha[phi - k]: b's walls are a's turned by k bins
    c = np.real(np.fft.ifft(np.fft.fft(hb) * np.conj(np.fft.fft(ha))))
    out: list[float] = []
    c = c.copy()
    for _ in range(n):
        k = int(np.argmax(c))
        if c[k] <= 0:
            break
        # sub-bin peak by a parabola through the neighbours
        l, m, r = c[(k - 1) % bins], c[k], c[(k + 1) % bins]
        den = l - 2 * m + r
        off = 0.5 * (l - r) / den if den < 0 else 0.0
        theta = (k + off) * math.pi / bins
        # b = R(theta) a on orientations, so b's frame in a's frame turns by -theta; mod 180 both ways
        out += [wrap_angle(-theta), wrap_angle(-theta + math.pi)]
        for j in range(-6, 7):
            c[(k + j) % bins] = -np.inf
    return out


def _features(cls: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints (N, 2) in pixel index and descriptors of the map image."""
    img = np.full(cls.shape, 128, dtype=np.uint8)
    img[cls == FREE_C] = 255
    img[cls == OCC_C] = 0
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    sift = cv2.SIFT_create(nfeatures=1500)
    kps, desc = sift.detectAndCompute(img, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    pts = np.array([kp.pt for kp in kps], dtype=np.float64)
    return pts, desc


def _feature_hyps(a: _View, b: _View, rng: np.random.Generator, keep: int = 4) -> list[_Hyp]:
    """Rigid models from SIFT matches by 2-point RANSAC; the best few distinct ones."""
    pa, da = a.features()
    pb, db = b.features()
    if len(pa) < 3 or len(pb) < 3:
        return []
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    knn = matcher.knnMatch(db, da, k=2)
    src, dst = [], []
    for m in knn:
        if len(m) == 2 and m[0].distance < 0.8 * m[1].distance:
            src.append(pb[m[0].queryIdx])
            dst.append(pa[m[0].trainIdx])
    if len(src) < 3:
        return []
    s = np.array(src)
    d = np.array(dst)
    n = len(s)
    iters = 600
    i = rng.integers(0, n, iters)
    j = rng.integers(0, n, iters)
    vb = s[j] - s[i]
    va = d[j] - d[i]
    lb = np.hypot(vb[:, 0], vb[:, 1])
    la = np.hypot(va[:, 0], va[:, 1])
    ok = (i != j) & (lb > 8) & (np.abs(la - lb) < 2.0)
    if not ok.any():
        return []
    i, j, vb, va = i[ok], j[ok], vb[ok], va[ok]
    yaw = np.arctan2(va[:, 1], va[:, 0]) - np.arctan2(vb[:, 1], vb[:, 0])
    c, sn = np.cos(yaw), np.sin(yaw)
    tx = d[i, 0] - (c * s[i, 0] - sn * s[i, 1])
    ty = d[i, 1] - (sn * s[i, 0] + c * s[i, 1])
    # inliers of every model at once: (models, matches)
    px = c[:, None] * s[None, :, 0] - sn[:, None] * s[None, :, 1] + tx[:, None]
    py = sn[:, None] * s[None, :, 0] + c[:, None] * s[None, :, 1] + ty[:, None]
    err = np.hypot(px - d[None, :, 0], py - d[None, :, 1])
    inl = (err < 3.0).sum(axis=1)
    order = np.argsort(-inl)
    out: list[_Hyp] = []
    for k in order:
        if inl[k] < 3:
            break
        h = _Hyp(float(yaw[k]), float(tx[k]), float(ty[k]), float(inl[k]), "features")
        if all(not _same(h, o, b.centre()) for o in out):
            out.append(h)
        if len(out) >= keep:
            break
    return out


def _same(h1: _Hyp, h2: _Hyp, at: np.ndarray, cells: float = 4.0, deg: float = 3.0) -> bool:
    p1 = h1.matrix() @ np.array([at[0], at[1], 1.0])
    p2 = h2.matrix() @ np.array([at[0], at[1], 1.0])
    return bool(
        math.hypot(p1[0] - p2[0], p1[1] - p2[1]) < cells
        and abs(wrap_angle(h1.yaw - h2.yaw)) < math.radians(deg)
    )


class _Correlator:
    """FFT correlation of b's coarse walls, turned by a heading, against a's coarse fields."""

    def __init__(self, a: _Coarse, b: _Coarse) -> None:
        self.a, self.b = a, b
        hb, wb = b.cls.shape
        diag = int(math.ceil(math.hypot(hb, wb))) + 2
        self.diag = diag
        ha, wa = a.cls.shape
        self.shape = (sfft.next_fast_len(ha + diag), sfft.next_fast_len(wa + diag, real=True))
        self.fa_target = sfft.rfft2(a.target, s=self.shape)
        self.fa_occ = sfft.rfft2(a.occ, s=self.shape)

    def peaks(self, yaw: float, k: int = 3) -> list[_Hyp]:
        """Best shifts for b turned by ``yaw``, as coarse-pixel hypotheses (q_a = R q_b + t)."""
        b = self.b
        hb, wb = b.cls.shape
        d = self.diag
        c, s = math.cos(yaw), math.sin(yaw)
        ctr_b = np.array([(wb - 1) / 2.0, (hb - 1) / 2.0])
        ctr_d = np.array([(d - 1) / 2.0, (d - 1) / 2.0])
        rot = np.array([[c, -s], [s, c]])
        shift = ctr_d - rot @ ctr_b  # q_rot = R q_b + shift
        fwd = np.array([[c, -s, shift[0]], [s, c, shift[1]]])
        cls_r = cv2.warpAffine(
            b.cls, fwd, (d, d), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=UNK_C
        )
        occ_r, target_r = _fields(cls_r)
        fb_occ = sfft.rfft2(occ_r, s=self.shape)
        fb_target = sfft.rfft2(target_r, s=self.shape)
        # S(t) = sum_q occ_b(q) target_a(q + t) + target_b(q) occ_a(q + t)
        spec = np.conj(fb_occ) * self.fa_target + np.conj(fb_target) * self.fa_occ
        corr = sfft.irfft2(spec, s=self.shape)
        P, Q = self.shape
        out: list[_Hyp] = []
        work = corr.copy()
        for _ in range(k):
            idx = int(np.argmax(work))
            ky, kx = divmod(idx, Q)
            val = float(work[ky, kx])
            if not math.isfinite(val) or val <= 0:
                break
            ty = ky if ky < P - d else ky - P
            tx = kx if kx < Q - d else kx - Q
            out.append(_Hyp(yaw, float(tx + shift[0]), float(ty + shift[1]), val, "search"))
            work[max(0, ky - 3) : ky + 4, max(0, kx - 3) : kx + 4] = -np.inf
        return out


def _to_fine(h: _Hyp, f: int) -> _Hyp:
    """Coarse-pixel hypothesis to working-resolution pixels (coarse centre j is fine j f + (f-1)/2)."""
    c0 = (f - 1) / 2.0
    c, s = math.cos(h.yaw), math.sin(h.yaw)
    tx = f * h.tx + c0 - (c * c0 - s * c0)
    ty = f * h.ty + c0 - (s * c0 + c * c0)
    return _Hyp(h.yaw, tx, ty, h.score, h.source)


# ---------------------------------------------------------------------------------------------
# Refinement and verification
# ---------------------------------------------------------------------------------------------


def _icp(a: _View, b: _View, h: _Hyp, gate0: float, rng: np.random.Generator) -> _Hyp:
    """Trimmed point-to-point ICP of b's walls onto a's, starting at ``h`` (pixel index)."""
    if a.n_occ == 0 or b.n_occ == 0:
        return h
    pts = b.pts
    if len(pts) > 6000:
        pts = pts[rng.choice(len(pts), 6000, replace=False)]
    m = h.matrix()
    gate = max(gate0, 2.0)
    ha, wa = a.shape
    known_near = a.dist  # walls only exist in known space; gate on distance does the rest
    for it in range(30):
        q = pts @ m[:2, :2].T + m[:2, 2]
        xi = np.clip(np.rint(q[:, 0]).astype(np.int64), 0, wa - 1)
        yi = np.clip(np.rint(q[:, 1]).astype(np.int64), 0, ha - 1)
        inside = (q[:, 0] >= -0.5) & (q[:, 0] < wa - 0.5) & (q[:, 1] >= -0.5) & (q[:, 1] < ha - 0.5)
        near = inside & (known_near[yi, xi] <= gate)
        if int(near.sum()) < 6:
            break
        dist, idx = a.tree.query(q[near], distance_upper_bound=gate + 1.0)
        ok = np.isfinite(dist)
        if int(ok.sum()) < 6:
            break
        src = pts[near][ok]
        dst = a.pts[idx[ok]]
        dd = dist[ok]
        # trim the worst fifth: clutter and walls only one robot saw
        if len(dd) > 20:
            cut = np.quantile(dd, 0.8)
            keep = dd <= cut + 1e-9
            src, dst = src[keep], dst[keep]
        new = _kabsch(src, dst)
        step = np.abs(new - m).max()
        m = new
        if it >= 3:
            gate = max(2.0, gate * 0.7)
        if step < 1e-3 and gate <= 2.0:
            break
    p = from_matrix(m)
    return _Hyp(p.yaw, p.x, p.y, h.score, h.source)


def _kabsch(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (3x3) taking src points onto dst points."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    hmat = (src - ms).T @ (dst - md)
    u, _, vt = np.linalg.svd(hmat)
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[1] *= -1
        r = vt.T @ u.T
    t = md - r @ ms
    out = np.eye(3)
    out[:2, :2] = r
    out[:2, 2] = t
    return out


@dataclass
class _Score:
    agreement: float
    fit: float
    walls: int
    overlap: int
    inliers: int


def _verify(a: _View, b: _View, h: _Hyp) -> _Score:
    """Overlap agreement and wall fit of b placed on a by ``h``."""
    ha, wa = a.shape
    m = h.matrix()
    inv = np.linalg.inv(m)
    bw = cv2.warpAffine(
        b.cls, inv[:2], (wa, ha), flags=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=UNK_C
    )
    bknown = bw != UNK_C
    both = a.known & bknown
    n_both = int(both.sum())
    if n_both == 0:
        return _Score(0.0, 0.0, 0, 0, 0)
    agree = int((a.cls[both] == bw[both]).sum())
    bocc = (bw == OCC_C) & a.known
    aocc = a.occ & bknown
    n_b, n_a = int(bocc.sum()), int(aocc.sum())
    hit_b = int((a.dist[bocc] <= 1.5).sum())
    if n_a:
        dist_bw = _wall_distance(bw == OCC_C)
        hit_a = int((dist_bw[aocc] <= 1.5).sum())
    else:
        hit_a = 0
    fit_b = hit_b / n_b if n_b else 0.0
    fit_a = hit_a / n_a if n_a else 0.0
    fit = min(fit_a, fit_b)
    return _Score(agree / n_both, fit, min(n_a, n_b), n_both, hit_b)


# ---------------------------------------------------------------------------------------------
# The estimator
# ---------------------------------------------------------------------------------------------

_CACHE: OrderedDict[tuple[bytes, float], _View] = OrderedDict()
_CACHE_SIZE = 8


def _view(grid: OccupancyGrid, res: float) -> _View:
    key = (grid.digest(), res)
    v = _CACHE.get(key)
    if v is None:
        v = _View(grid, res)
        _CACHE[key] = v
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    else:
        _CACHE.move_to_end(key)
    return v


def _check_input(a: OccupancyGrid, b: OccupancyGrid, opt: EstimateOptions) -> str:
    for name, g in (("a", a), ("b", b)):
        if g.cells == 0:
            return f"map {name} is empty"
        if not (g.data >= 0).any():
            return f"map {name} is all unknown"
    ratio = max(a.resolution, b.resolution) / min(a.resolution, b.resolution)
    if ratio > opt.max_resolution_ratio:
        return (
            f"resolutions {a.resolution:g} and {b.resolution:g} m/cell differ {ratio:.1f}x "
            f"(at most {opt.max_resolution_ratio:g}x can be matched)"
        )
    return ""


def estimate_transform(
    a: OccupancyGrid,
    b: OccupancyGrid,
    *,
    min_confidence: float | None = None,
    min_agreement: float | None = None,
    prior: Pose2D | None = None,
    options: EstimateOptions | None = None,
    seed: int = 0,
) -> Estimate:
    """b's map frame expressed in a's map frame, with confidence and overlap agreement.

    ``prior`` (a previous answer, b in a) is refined first and kept as a candidate. Never raises
    for bad maps: empty, all-unknown, structureless, non-overlapping or incompatible maps give an
    estimate with ``accepted=False`` and the reason.
    """
    opt = options or EstimateOptions()
    min_conf = opt.min_confidence if min_confidence is None else min_confidence
    min_agr = opt.min_agreement if min_agreement is None else min_agreement
    problem = _check_input(a, b, opt)
    if problem:
        return rejected(problem)
    res = max(a.resolution, b.resolution)
    va, vb = _view(a, res), _view(b, res)
    for name, v in (("a", va), ("b", vb)):
        if v.n_occ < opt.min_walls:
            return rejected(f"map {name} has {v.n_occ} wall cells, too few to match (need {opt.min_walls})")
    rng = np.random.default_rng(seed)
    ctr_b = vb.centre()

    results: list[tuple[_Hyp, _Score, float]] = []

    def consider(hyps: list[_Hyp], gate0: float) -> None:
        for h in hyps:
            if any(_same(h, r[0], ctr_b, 2.0, 1.0) for r in results):
                continue
            refined = _icp(va, vb, h, gate0, rng)
            if any(_same(refined, r[0], ctr_b, 1.0, 0.5) for r in results):
                continue
            sc = _verify(va, vb, refined)
            results.append((refined, sc, _raw_conf(sc, opt)))

    def best_ok() -> bool:
        if not results:
            return False
        conf, agr = _final(results, ctr_b, opt)[1:3]
        return conf >= min_conf and agr >= min_agr

    if prior is not None:
        consider([_prior_hyp(a, b, va, vb, prior)], 4.0)
    if opt.use_features and not best_ok():
        consider(_feature_hyps(va, vb, rng), 4.0)
    f = _coarse_factor(va, vb, opt)
    if not best_ok():
        corr = _Correlator(va.coarse(f), vb.coarse(f))
        angles = _signature_angles(va, vb)
        hyps: list[_Hyp] = []
        for ang in angles:
            for dd in (-1.0, 0.0, 1.0):
                hyps += corr.peaks(ang + math.radians(dd), k=2)
        hyps.sort(key=lambda h: -h.score)
        consider([_to_fine(h, f) for h in _distinct(hyps, 8)], 1.5 * f + 2.0)
        if opt.exhaustive and not best_ok():
            hyps = []
            for deg in np.arange(-180.0, 180.0, 2.0):
                hyps += corr.peaks(math.radians(float(deg)), k=2)
            hyps.sort(key=lambda h: -h.score)
            consider([_to_fine(h, f) for h in _distinct(hyps, 10)], 1.5 * f + 2.0)
    if not results:
        return rejected("no candidate transform: the maps share no recognisable structure")
    best, conf, agr, sc, rival = _final(results, ctr_b, opt)
    t = _hyp_to_pose(best, va, vb)
    details = {"fit": sc.fit, "walls": sc.walls, "rival": rival, "candidates": len(results), "coarse": f}
    if sc.overlap == 0:
        return rejected("the maps do not overlap under any candidate", method=best.source, details=details)
    reason = ""
    if conf < min_conf:
        reason = f"confidence {conf:.2f} below {min_conf:.2f}"
        if rival > 0.0 and sc.fit > 0 and rival / sc.fit > 0.8:
            reason += " (another placement fits almost as well)"
        elif sc.walls < opt.support_walls:
            reason += f" (only {sc.walls} wall cells overlap)"
    elif agr < min_agr:
        reason = f"overlap agreement {agr:.2f} below {min_agr:.2f}"
    return Estimate(
        x=t.x,
        y=t.y,
        yaw=t.yaw,
        confidence=conf,
        agreement=agr,
        inliers=sc.inliers,
        accepted=not reason,
        reason=reason,
        method=best.source,
        overlap=sc.overlap,
        details=details,
    )


def _raw_conf(sc: _Score, opt: EstimateOptions) -> float:
    support = min(1.0, sc.walls / opt.support_walls)
    return sc.fit * support


def _final(
    results: list[tuple[_Hyp, _Score, float]], ctr_b: np.ndarray, opt: EstimateOptions
) -> tuple[_Hyp, float, float, _Score, float]:
    """Best candidate, its confidence (discounted by the best rival), agreement, score, rival fit."""
    ranked = sorted(results, key=lambda r: -r[2])
    best, sc, raw = ranked[0]
    rival = 0.0
    for h, _s, c in ranked[1:]:
        if not _same(best, h, ctr_b, opt.rival_cells, opt.rival_deg):
            rival = c
            break
    # a rival at 60% of the best costs nothing; one that fits as well halves... down to zero
    ratio = rival / raw if raw > 0 else 1.0
    distinct = float(np.clip((1.0 - ratio) / 0.4, 0.0, 1.0))
    return best, raw * distinct, sc.agreement, sc, rival


def _distinct(hyps: list[_Hyp], n: int) -> list[_Hyp]:
    out: list[_Hyp] = []
    for h in hyps:
        if all(not _same(h, o, np.zeros(2), 3.0, 3.0) for o in out):
            out.append(h)
        if len(out) >= n:
            break
    return out


def _coarse_factor(a: _View, b: _View, opt: EstimateOptions) -> int:
    side = max(*a.shape, *b.shape)
    f = max(1, math.ceil(side / opt.coarse_cells))
    cap = max(1, int(opt.max_coarse_m / a.res))
    return min(f, cap)


def _hyp_to_pose(h: _Hyp, a: _View, b: _View) -> Pose2D:
    """Pixel-index hypothesis to b's map frame in a's map frame."""
    m = a.g @ h.matrix() @ np.linalg.inv(b.g)
    return from_matrix(m)


def _prior_hyp(a: OccupancyGrid, b: OccupancyGrid, va: _View, vb: _View, prior: Pose2D) -> _Hyp:
    m = np.linalg.inv(va.g) @ to_matrix(prior) @ vb.g
    p = from_matrix(m)
    return _Hyp(p.yaw, p.x, p.y, 0.0, "prior")


__all__ = ["Estimate", "EstimateOptions", "compose", "estimate_transform", "inverse", "rejected"]
