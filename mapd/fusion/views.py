"""A map prepared for matching: classes at a working resolution, wall faces, distance fields.

Matching works on *pixel index* coordinates of a working grid (column, row; cell centres at
integers). :class:`MapView` builds, once per map version and resolution, what the candidate search
and the refinement need, and :func:`view` keeps the last few in a small cache (the worker matches the
same maps again and again as only one of them changes).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict

import cv2
import numpy as np
from scipy.spatial import cKDTree

from mapd.fusion.transforms import to_matrix
from mapd.grid import OCCUPIED_AT, OccupancyGrid

FREE_C, OCC_C, UNK_C = 0, 1, 2
#: SIFT draws a map of at most this many cells (a bigger one shrunk by a whole factor): its
#: pyramid costs about 250 bytes a cell, so this bounds it near 250 MB.
FEATURE_CELLS = 1 << 20
#: OpenCV's remap and warp work on images up to this many cells a side.
MAX_SIDE = 32000
#: Evidence weights: the log-likelihood ratio of a wall that meets / misses the other map's walls
#: when the placement is right (95% of walls meet) against a chance placement (40% meet).
MEET_WEIGHT = math.log(0.95 / 0.4)
MISS_WEIGHT = math.log(0.05 / 0.6)
#: known cells near walls sampled per map for the cheap agreement check of candidates
KNOWN_SAMPLE = 4000
#: Free-space evidence: the log-likelihood ratio of a cell known in both maps whose class agrees /
#: disagrees, for a right placement (98 % of such cells agree in degraded copies of one place)
#: against a wrong one that fits the walls well (95 %: its free space lies on free space too,
#: except where it runs into the other map's walls).
AGREE_WEIGHT = math.log(0.98 / 0.95)
DISAGREE_WEIGHT = math.log(0.02 / 0.05)
#: neighbouring cells agree or disagree together (a wall seen thicker is thicker over a stretch):
#: this many count as one observation
FREE_CELLS = 4.0


def resample_classes(grid: OccupancyGrid, res: float) -> np.ndarray:
    """Cell classes of ``grid`` at resolution ``res`` >= its own.

    Pooling keeps thin walls: a coarse cell is a wall when at least half a fine cell's worth of it
    is occupied, and known when half of it is known.
    """
    d = grid.data
    cls = np.full(d.shape, UNK_C, dtype=np.uint8)
    cls[d >= 0] = FREE_C
    cls[d >= OCCUPIED_AT] = OCC_C
    k = res / grid.resolution
    if abs(k - 1.0) < 1e-9:
        return cls
    occ_f = _pool((cls == OCC_C).astype(np.float32), k)
    known_f = _pool((cls != UNK_C).astype(np.float32), k)
    out = np.full(occ_f.shape, UNK_C, dtype=np.uint8)
    out[known_f >= 0.5] = FREE_C
    out[occ_f >= 0.5 / (k * k)] = OCC_C
    return out


def _pool(img: np.ndarray, k: float) -> np.ndarray:
    """Area-average by a factor ``k``: output cell j covers input cells [j k, (j + 1) k) exactly."""
    h, w = img.shape
    # The output size as OpenCV rounds it (w * (1 / k), not w / k): at k = 5.999999999999999 a map 3
    # cells wide rounds to 1 one way and to 0 the other, and OpenCV refused it (!dsize.empty()).
    if round(w * (1.0 / k)) < 1 or round(h * (1.0 / k)) < 1:
        return np.full((1, 1), float(img.mean()), dtype=np.float32)
    # with fx/fy (no dsize) OpenCV keeps the exact scale and only rounds the output size
    return cv2.resize(img, None, fx=1.0 / k, fy=1.0 / k, interpolation=cv2.INTER_AREA)


def wall_faces(cls: np.ndarray) -> np.ndarray:
    """Wall surface cells: occupied, not lone speckle, and not inside a thick wall.

    The inside of a thick wall carries no position information; using only its faces keeps the
    refinement and the wall fit sharp on thick-walled maps. A wall cell needs another occupied cell
    within two cells, so dotted walls from sparse scans survive and lone speckle does not.
    """
    occ = (cls == OCC_C).astype(np.uint8)
    near = cv2.filter2D(occ, cv2.CV_16S, np.ones((5, 5), np.float32), borderType=cv2.BORDER_CONSTANT)
    inside = cv2.erode(occ, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return (occ > 0) & (near - occ > 0) & (inside == 0)


def wall_distance(walls: np.ndarray) -> np.ndarray:
    """Euclidean distance (cells, float32) to the nearest wall cell; 1e6 everywhere if none."""
    if not walls.any():
        return np.full(walls.shape, 1e6, dtype=np.float32)
    return cv2.distanceTransform((~walls).astype(np.uint8), cv2.DIST_L2, 5)


def score_fields(
    cls: np.ndarray, sigma: float = 1.0, free_weight: float = 0.5, dist: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(walls, target) float32 images for the correlation search.

    ``target`` is a wall likelihood (a Gaussian of the distance to the nearest wall) minus
    ``free_weight`` where the map is plainly free (known free, farther than 2.5 cells from a wall):
    a wall of the other map landing there is evidence against the placement. ``dist`` is
    :func:`wall_distance` of ``cls``'s walls when the caller has it already (the search fields share
    one).
    """
    walls = cls == OCC_C
    if dist is None:
        dist = wall_distance(walls)
    like = np.exp(-(dist.astype(np.float32) ** 2) / (2.0 * sigma**2))
    free_far = (cls == FREE_C) & (dist > 2.5)
    return walls.astype(np.float32), (like - free_weight * free_far).astype(np.float32)


def evidence_field(cls: np.ndarray, tol: float = 1.0, dist: np.ndarray | None = None) -> np.ndarray:
    """Per-cell evidence (float32) of a wall of the other map landing there: ``MEET_WEIGHT``
    within ``tol`` cells of a wall, ``MISS_WEIGHT`` where the map knows the place farther from any
    wall, 0 where it is unknown. Correlated with the other map's walls, this is the wall evidence
    that the full check counts (:func:`mapd.fusion.refine.evidence`), at the search's resolution."""
    if dist is None:
        dist = wall_distance(cls == OCC_C)
    near = dist <= tol
    out = np.where(near, np.float32(MEET_WEIGHT), np.float32(0.0))
    out[~near & (cls != UNK_C)] = MISS_WEIGHT
    return out.astype(np.float32)


def free_fields(
    cls: np.ndarray, clear: float = 1.5, dist: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(free, clear) float32 masks for the free-space correlation: cells known free, and those of
    them farther than ``clear`` cells from any wall (a wall of the other map landing beside a wall
    is a wall seen thicker, not a contradiction)."""
    free = cls == FREE_C
    if dist is None:
        dist = wall_distance(cls == OCC_C)
    far = free & (dist > clear)
    return free.astype(np.float32), far.astype(np.float32)


class Coarse:
    """A map pooled by an integer factor ``f`` for the correlation search (walls win)."""

    def __init__(self, cls: np.ndarray, walls: np.ndarray, f: int) -> None:
        self.f = f
        if f == 1:
            wall = walls
            known = cls != UNK_C
        else:
            wall = _pool(walls.astype(np.float32), f) > 0.0
            known = (_pool((cls != UNK_C).astype(np.float32), f) >= 0.3) | wall
        self.cls: np.ndarray = np.full(wall.shape, UNK_C, dtype=np.uint8)
        self.cls[known] = FREE_C
        self.cls[wall] = OCC_C
        dist = wall_distance(self.cls == OCC_C)
        self.walls, self.target = score_fields(self.cls, dist=dist)
        self.evidence = evidence_field(self.cls, dist=dist)
        self.free, self.clear = free_fields(self.cls, dist=dist)


class MapView:
    """One map at the working resolution ``res``, with what matching needs (built lazily)."""

    def __init__(self, grid: OccupancyGrid, res: float) -> None:
        self.res = res
        self.cls = resample_classes(grid, res)
        self.walls = wall_faces(self.cls)
        self.known = self.cls != UNK_C
        self.n_walls = int(self.walls.sum())
        self.n_known = int(self.known.sum())
        #: pixel index -> map frame
        self.g = to_matrix(grid.origin) @ np.array(
            [[res, 0.0, 0.5 * res], [0.0, res, 0.5 * res], [0.0, 0.0, 1.0]]
        )
        self.dist = wall_distance(self.walls)
        ys, xs = np.nonzero(self.walls)
        self.pts = np.column_stack([xs, ys]).astype(np.float64)
        self._tree: cKDTree | None = None
        self._coarse: dict[int, Coarse] = {}
        self._features: tuple[np.ndarray, np.ndarray] | None = None
        self._hist: np.ndarray | None = None
        self._normals: tuple[np.ndarray, np.ndarray] | None = None
        self._field: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._centre: np.ndarray | None = None
        self._known_sample: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.cls.shape[0]), int(self.cls.shape[1]))

    @property
    def tree(self) -> cKDTree:
        """KD-tree of the wall cells (pixel index)."""
        if self._tree is None:
            self._tree = cKDTree(self.pts)
        return self._tree

    def coarse(self, f: int) -> Coarse:
        if f not in self._coarse:
            self._coarse[f] = Coarse(self.cls, self.walls, f)
        return self._coarse[f]

    def centre(self) -> np.ndarray:
        """Centroid of the known cells (pixel index): where transform differences are measured."""
        if self._centre is None:
            ys, xs = np.nonzero(self.known[::4, ::4])
            if len(xs) == 0:
                self._centre = np.array([self.cls.shape[1] / 2.0, self.cls.shape[0] / 2.0])
            else:
                self._centre = np.array([xs.mean() * 4.0, ys.mean() * 4.0])
        return self._centre

    def known_sample(self) -> tuple[np.ndarray, np.ndarray]:
        """About ``KNOWN_SAMPLE`` known cells within 4 cells of a wall, spread evenly: (N, 2) pixel
        index and their classes. Near walls is where a wrong placement shows (free space on the
        other map's walls); open floor agrees with open floor anywhere."""
        if self._known_sample is None:
            ys, xs = np.nonzero(self.known & (self.dist <= 4.0))
            step = max(1, len(xs) // KNOWN_SAMPLE)
            ys, xs = ys[::step], xs[::step]
            self._known_sample = (np.column_stack([xs, ys]).astype(np.float64), self.cls[ys, xs])
        return self._known_sample

    def field(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Distance to the nearest wall (capped at 30 cells) and its gradient (per cell)."""
        if self._field is None:
            d = np.minimum(self.dist, 30.0).astype(np.float32)
            gx = cv2.Sobel(d, cv2.CV_32F, 1, 0, ksize=3) / 8.0
            gy = cv2.Sobel(d, cv2.CV_32F, 0, 1, ksize=3) / 8.0
            self._field = (d, gx, gy)
        return self._field

    def orientation_hist(self) -> np.ndarray:
        """Wall-orientation histogram (mod 180 degrees, 1 degree bins)."""
        if self._hist is None:
            self._hist, self._normals = orientation(self.walls)
        return self._hist

    def normals(self) -> tuple[np.ndarray, np.ndarray]:
        """(cos 2 phi, sin 2 phi) of each wall cell's normal direction phi (0 elsewhere)."""
        if self._normals is None:
            self._hist, self._normals = orientation(self.walls)
        return self._normals

    def features(self) -> tuple[np.ndarray, np.ndarray]:
        """SIFT keypoints (N, 2) in pixel index, and their descriptors."""
        if self._features is None:
            self._features = sift_features(self.cls)
        return self._features


def orientation(walls: np.ndarray, bins: int = 180) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
    """Wall orientations from the structure tensor: their histogram (mod 180 degrees, 1 degree
    bins) and, per wall cell, (cos 2 phi, sin 2 phi) of the normal direction phi.

    The tensor is averaged over a few cells, so the staircase of a wall drawn at an odd angle (a
    map made at another heading) reads as the wall's angle, not as 0 or 45 degrees.
    """
    img = cv2.GaussianBlur(walls.astype(np.float32), (0, 0), 1.0)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    jxx = cv2.GaussianBlur(gx * gx, (0, 0), 3.0)
    jyy = cv2.GaussianBlur(gy * gy, (0, 0), 3.0)
    jxy = cv2.GaussianBlur(gx * gy, (0, 0), 3.0)
    coherence = np.sqrt((jxx - jyy) ** 2 + 4.0 * jxy**2)
    sel = walls & (coherence > 1e-4)
    c2 = np.zeros(walls.shape, np.float32)
    s2 = np.zeros(walls.shape, np.float32)
    c2[sel] = (jxx - jyy)[sel] / coherence[sel]
    s2[sel] = 2.0 * jxy[sel] / coherence[sel]
    ang = np.mod(0.5 * np.arctan2(s2[sel], c2[sel]), math.pi)
    hist, _ = np.histogram(ang, bins=bins, range=(0.0, math.pi), weights=coherence[sel])
    k = np.array([0.25, 0.5, 1.0, 0.5, 0.25])
    padded = np.concatenate([hist[-2:], hist, hist[:2]])
    return np.convolve(padded, k, mode="valid"), (c2, s2)


def sift_features(
    cls: np.ndarray, n: int = 1500, max_cells: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of the map drawn as an image (walls dark, unknown grey).

    A map of more than ``max_cells`` (default :data:`FEATURE_CELLS`) cells is drawn shrunk by a
    whole factor first: SIFT doubles the image and keeps a float pyramid of it, about 250 bytes a
    cell. Features only propose placements, which are refined on the whole map; on large maps the
    shrunk drawing proposes the true one as the whole did (tests/fusion/test_fusion_hostile.py).
    Keypoints are given in ``cls``'s pixel index either way.
    """
    img: np.ndarray = np.full(cls.shape, 128, dtype=np.uint8)
    img[cls == FREE_C] = 255
    img[cls == OCC_C] = 0
    cap = FEATURE_CELLS if max_cells is None else max_cells
    k = max(1, math.ceil(math.sqrt(cls.size / max(1, cap)) - 1e-9))
    if k > 1:
        h, w = (cls.shape[0] // k) * k, (cls.shape[1] // k) * k
        img = cv2.resize(img[:h, :w], (w // k, h // k), interpolation=cv2.INTER_AREA)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    kps, desc = cv2.SIFT.create(nfeatures=n).detectAndCompute(img, None)
    if desc is None or len(kps) == 0:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    # a shrunk pixel j covers pixels jk .. jk + k - 1: its centre is at jk + (k - 1) / 2
    pts = np.array([kp.pt for kp in kps], dtype=np.float64) * k + (k - 1) / 2.0
    return pts, desc


_CACHE: OrderedDict[tuple[bytes, float], MapView] = OrderedDict()
#: a prepared 2000 x 2000 map holds about 80 MB, so only the last few are kept
_CACHE_SIZE = 4
_LOCK = threading.Lock()


def view(grid: OccupancyGrid, res: float) -> MapView:
    """The prepared view of ``grid`` at ``res``, cached by map digest and resolution."""
    key = (grid.digest(), res)
    with _LOCK:
        v = _CACHE.get(key)
        if v is not None:
            _CACHE.move_to_end(key)
            return v
    v = MapView(grid, res)
    with _LOCK:
        _CACHE[key] = v
        while len(_CACHE) > _CACHE_SIZE:
            _CACHE.popitem(last=False)
    return v
