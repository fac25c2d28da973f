"""Building the global map: every placed map resampled into one grid of the fleet frame.

:func:`merge` takes the maps and, for each, its map frame expressed in the fleet frame (meters and
radians, ``p_fleet = R(yaw) p_map + (x, y)``; ``None`` leaves a map out). Each grid's own origin,
yaw included, and resolution are honoured: a cell is placed where its centre lies in the fleet frame.
Resampling is nearest neighbour (OpenCV ``warpAffine``); a map finer than the global grid by 1.5x or
more is first pooled to the global resolution so that thin walls survive (a pooled cell is occupied
when half a fine cell's worth of it is, and known when half of it is known).

Modes:

* ``logodds`` (default): each known cell adds the log-odds of its occupancy, ``logit(p)`` with
  ``p = value / 100`` clamped to [0.01, 0.99]; unknown adds nothing. The result is
  ``round(100 * sigmoid(sum))``, saturated to 0 and 100 at the clamp, so one map merged alone comes back
  cell for cell (values 1 and 99 read as 0 and 100), agreeing maps reinforce, and a cell where two
  maps disagree evenly is 50 (known, undecided).
* ``occupied_wins``: the cell-wise maximum with unknown lowest (m-explore's compositor): any known
  beats unknown, occupied beats free.

The global grid has yaw 0 and lies on the fleet frame's cell lattice: its origin is a whole number
of cells from the fleet frame's origin, and its bounds are rounded out to blocks of ``chunk`` cells.
Passing the previous ``bounds`` makes them only ever grow. So a point of the fleet frame stays in
the same global cell however the maps grow, and the origin moves only when the map grows past a
block edge towards negative x or y (the fix for m-explore's drifting merged origin).

The blocks are deliberate, not slack: the daemon's global map is re-published at every merge while
the robots explore, and a new size or origin costs its consumers more than unknown cells do (Nav2's
static layer resizes its whole costmap when the map's size or origin changes; the live view sends
its edge tiles again). With blocks the size changes once per 64 cells of growth rather than at
nearly every merge, for at most 63 unknown cells beyond the maps on a side. A one-shot merge, with
no later merge to keep steady, can ask for a tight map with ``chunk=1``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from mapd.errors import FusionError, LimitError
from mapd.files import atomic_write_bytes
from mapd.fusion.transforms import transformed_corners, warp_matrix
from mapd.fusion.views import MAX_SIDE, resample_classes
from mapd.grid import DEFAULT_MAX_CELLS, OCCUPIED, UNKNOWN, OccupancyGrid, Pose2D

Mode = Literal["logodds", "occupied_wins"]
MODES: tuple[str, ...] = ("logodds", "occupied_wins")
#: ``owner`` value of a cell no map knows
NO_OWNER = 255

_P_MIN, _P_MAX = 0.01, 0.99
#: log-odds are summed as integers in 1/_Q steps (exact, fast); 100 * sigmoid moves at most 25 per
#: unit of log-odds, so the rounding moves a result by at most 0.2 and never changes it
_Q = 64.0
_L_SAT = math.log(_P_MAX / (1.0 - _P_MAX))
_SAT_Q = round(_L_SAT * _Q)


def _evidence_luts() -> tuple[np.ndarray, np.ndarray]:
    """Per int8 cell value (indexed by its uint8 bit pattern): quantised log-odds and |log-odds|."""
    v = np.arange(256, dtype=np.uint8).view(np.int8).astype(np.float64)
    p = np.clip(np.minimum(v, 100.0) / 100.0, _P_MIN, _P_MAX)
    lo = np.rint(np.log(p / (1.0 - p)) * _Q)
    lo[v < 0] = 0.0
    return lo.astype(np.int32), np.abs(lo).astype(np.uint16)


_LUT, _MAG = _evidence_luts()


def _occupancy_lut() -> np.ndarray:
    """Quantised summed log-odds in [-_SAT_Q, _SAT_Q] (offset by _SAT_Q) to occupancy 0..100."""
    q = np.arange(-_SAT_Q, _SAT_Q + 1, dtype=np.float64)
    out = np.rint(100.0 / (1.0 + np.exp(-q / _Q)))
    out[0], out[-1] = 0, OCCUPIED  # saturated: as sure as a lone map's free or occupied cell
    return out.astype(np.int8)


_OUT = _occupancy_lut()


@dataclass(frozen=True)
class Bounds:
    """A block of the fleet frame's cell lattice: columns ``[c0, c1)``, rows ``[r0, r1)``."""

    c0: int
    r0: int
    c1: int
    r1: int

    def union(self, other: Bounds) -> Bounds:
        return Bounds(
            min(self.c0, other.c0), min(self.r0, other.r0), max(self.c1, other.c1), max(self.r1, other.r1)
        )

    @property
    def width(self) -> int:
        return self.c1 - self.c0

    @property
    def height(self) -> int:
        return self.r1 - self.r0

    def origin(self, resolution: float) -> Pose2D:
        return Pose2D(self.c0 * resolution, self.r0 * resolution, 0.0)

    @staticmethod
    def of_grid(grid: OccupancyGrid) -> Bounds | None:
        """The lattice block a global grid covers, or None when it is not on the lattice."""
        r = grid.resolution
        c0, r0 = grid.origin.x / r, grid.origin.y / r
        if grid.origin.yaw != 0.0 or abs(c0 - round(c0)) > 1e-6 or abs(r0 - round(r0)) > 1e-6:
            return None
        return Bounds(round(c0), round(r0), round(c0) + grid.width, round(r0) + grid.height)


@dataclass(frozen=True)
class MergeResult:
    """The global grid, its lattice bounds, and per cell the index of the map that weighed most."""

    grid: OccupancyGrid
    bounds: Bounds
    owner: np.ndarray
    #: Maps OpenCV refused, left out of this merge: (index in the maps given, why).
    left_out: tuple[tuple[int, str], ...] = ()


def extent(
    maps: Sequence[OccupancyGrid], transforms: Sequence[Pose2D | None], resolution: float, chunk: int = 64
) -> Bounds | None:
    """Lattice block (rounded out to ``chunk`` cells) holding every placed map; None if none is."""
    pts = [transformed_corners(g, t) for g, t in zip(maps, transforms, strict=True) if t is not None]
    if not pts:
        return None
    allp = np.vstack(pts) / resolution
    if not np.all(np.isfinite(allp)) or np.abs(allp).max() > 2**40:
        raise FusionError("a transform places a map absurdly far from the fleet frame's origin")
    # A corner on a lattice line comes out a hair past it (320.00000000000006 cells), and rounding
    # out took it a whole block further: a map of whole blocks on block edges (the global map merged
    # again) grew by 64 unknown cells on a side. Within 1e-6 cells is on the line (as Bounds.of_grid).
    near = np.rint(allp)
    allp = np.where(np.abs(allp - near) <= 1e-6, near, allp)
    k = max(1, chunk)
    c0 = math.floor(float(allp[:, 0].min()) / k) * k
    r0 = math.floor(float(allp[:, 1].min()) / k) * k
    c1 = math.ceil(float(allp[:, 0].max()) / k) * k
    r1 = math.ceil(float(allp[:, 1].max()) / k) * k
    return Bounds(c0, r0, max(c1, c0 + k), max(r1, r0 + k))


def merge(
    maps: Sequence[OccupancyGrid],
    transforms: Sequence[Pose2D | None],
    mode: str = "logodds",
    *,
    resolution: float | None = None,
    bounds: Bounds | None = None,
    chunk: int = 64,
    frame_id: str = "fleet",
    max_cells: int = DEFAULT_MAX_CELLS,
) -> OccupancyGrid:
    """The global map of ``maps`` placed by ``transforms`` (each map frame in the fleet frame).

    See :func:`merge_with_owner` for the options.
    """
    return merge_with_owner(
        maps,
        transforms,
        mode,
        resolution=resolution,
        bounds=bounds,
        chunk=chunk,
        frame_id=frame_id,
        max_cells=max_cells,
    ).grid


def merge_with_owner(
    maps: Sequence[OccupancyGrid],
    transforms: Sequence[Pose2D | None],
    mode: str = "logodds",
    *,
    resolution: float | None = None,
    bounds: Bounds | None = None,
    chunk: int = 64,
    frame_id: str = "fleet",
    max_cells: int = DEFAULT_MAX_CELLS,
) -> MergeResult:
    """Merge, and say which map weighed most in each cell (``owner``; NO_OWNER where none knows).

    ``resolution`` defaults to the first placed map's; ``bounds`` (the previous global map's) is
    kept inside the result so the global map keeps its cells where they were. Raises :class:`FusionError` for an
    unknown mode or mismatched lists and :class:`LimitError` when the result would exceed
    ``max_cells``.
    """
    if mode not in MODES:
        raise FusionError(f"unknown merge mode '{mode}' (expected one of {', '.join(MODES)})")
    if len(maps) != len(transforms):
        raise FusionError(f"{len(maps)} maps but {len(transforms)} transforms")
    if len(maps) >= NO_OWNER:
        raise FusionError(f"at most {NO_OWNER - 1} maps can be merged at once")
    placed = [i for i, t in enumerate(transforms) if t is not None and maps[i].cells > 0]
    if resolution is None:
        resolution = maps[placed[0]].resolution if placed else 0.05
    if not (math.isfinite(resolution) and resolution > 0):
        raise FusionError(f"global resolution must be positive, got {resolution}")
    box = extent([maps[i] for i in placed], [transforms[i] for i in placed], resolution, chunk)
    if bounds is not None:
        box = bounds if box is None else box.union(bounds)
    if box is None:
        box = Bounds(0, 0, chunk, chunk)
    if box.width * box.height > max_cells or max(box.width, box.height) > MAX_SIDE:
        raise LimitError(
            f"the global map would be {box.width} x {box.height} cells, over the limit of "
            f"{max_cells} cells ({MAX_SIDE} a side); check the robots' poses"
        )
    h, w = box.height, box.width
    origin = box.origin(resolution)
    target = np.array(
        [
            [resolution, 0.0, origin.x + 0.5 * resolution],
            [0.0, resolution, origin.y + 0.5 * resolution],
            [0, 0, 1],
        ],
        dtype=np.float64,
    )
    owner = np.full((h, w), NO_OWNER, dtype=np.uint8)
    if mode == "logodds":
        total = np.zeros((h, w), dtype=np.int32)
        strength = np.zeros((h, w), dtype=np.uint16)
    else:
        best = np.full((h, w), UNKNOWN, dtype=np.int8)
    left_out: list[tuple[int, str]] = []
    for i in placed:
        t = transforms[i]
        assert t is not None
        try:
            src = _at_most_as_fine(maps[i], resolution)
        except cv2.error as exc:
            left_out.append((i, " ".join(str(exc).split())[-160:]))
            continue
        roi = _roi(src, t, box, resolution)
        if roi is None:
            continue
        c0, r0, c1, r1 = roi
        g_roi = target.copy()
        g_roi[0, 2] += c0 * resolution
        g_roi[1, 2] += r0 * resolution
        m = warp_matrix(src, t, g_roi)
        try:
            warped = cv2.warpAffine(
                src.data.view(np.uint8),
                m,
                (c1 - c0, r1 - r0),
                flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=255,
            )
        except cv2.error as exc:  # one map OpenCV cannot take must not stop the fleet's map
            left_out.append((i, " ".join(str(exc).split())[-160:]))
            continue
        sl = (slice(r0, r1), slice(c0, c1))
        if mode == "logodds":
            total[sl] += _LUT[warped]
            mag = _MAG[warped]
            # the strongest evidence owns a cell; a known cell with none (p = 0.5) still counts
            win = (mag > strength[sl]) | ((owner[sl] == NO_OWNER) & (warped < 128))
            np.maximum(strength[sl], mag, out=strength[sl])
            owner[sl][win] = i
        else:
            vals = warped.view(np.int8)
            vals = np.where(vals > OCCUPIED, OCCUPIED, vals).astype(np.int8)
            win = vals > best[sl]
            best[sl] = np.maximum(best[sl], vals)
            owner[sl][win] = i
    if mode == "logodds":
        data = _to_occupancy(total, owner != NO_OWNER)
    else:
        data = np.where(best < 0, UNKNOWN, best).astype(np.int8)
    grid = OccupancyGrid(data=data, resolution=resolution, origin=origin, frame_id=frame_id)
    return MergeResult(grid=grid, bounds=box, owner=owner, left_out=tuple(left_out))


def _to_occupancy(total: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Summed (quantised) log-odds to int8 occupancy; -1 where no map knows."""
    np.clip(total, -_SAT_Q, _SAT_Q, out=total)
    total += _SAT_Q
    out = _OUT[total]
    out[~known] = UNKNOWN
    return out


def _at_most_as_fine(grid: OccupancyGrid, resolution: float) -> OccupancyGrid:
    """``grid`` pooled to ``resolution`` when it is 1.5x finer or more (trinary; walls survive)."""
    if resolution / grid.resolution < 1.5:
        return grid
    cls = resample_classes(grid, resolution)
    lut = np.array([0, OCCUPIED, UNKNOWN], dtype=np.int8)
    return grid.replace(data=lut[cls], resolution=resolution)


def _roi(src: OccupancyGrid, t: Pose2D, box: Bounds, resolution: float) -> tuple[int, int, int, int] | None:
    """Cells of the global grid (relative to ``box``) that ``src`` can cover, or None."""
    corners = transformed_corners(src, t) / resolution
    c0 = max(0, math.floor(float(corners[:, 0].min())) - box.c0 - 1)
    r0 = max(0, math.floor(float(corners[:, 1].min())) - box.r0 - 1)
    c1 = min(box.width, math.ceil(float(corners[:, 0].max())) - box.c0 + 1)
    r1 = min(box.height, math.ceil(float(corners[:, 1].max())) - box.r0 + 1)
    if c1 <= c0 or r1 <= r0:
        return None
    return c0, r0, c1, r1


#: colours of the first robots' contributions in previews (RGB); later ones cycle
PALETTE = np.array(
    [
        [31, 119, 180],
        [214, 39, 40],
        [44, 160, 44],
        [148, 103, 189],
        [255, 127, 14],
        [23, 190, 207],
        [227, 119, 194],
        [140, 86, 75],
        [188, 189, 34],
        [127, 127, 127],
    ],
    dtype=np.float32,
)


#: Rows of the preview coloured at a time: the float temporaries of a whole 67 M-cell map took
#: 80 bytes a cell (5.6 GB); a band keeps them small beside the 3-byte-a-cell image.
COLOUR_BAND_ROWS = 256


def colour_image(result: MergeResult) -> np.ndarray:
    """RGB preview (row 0 at the top, like map_server images): unknown grey, free cells a light tint
    and occupied cells a dark shade of the colour of the map that weighed most there."""
    data, owner = result.grid.data, result.owner
    height = data.shape[0]
    out = np.empty((*data.shape, 3), dtype=np.uint8)
    for r0 in range(0, height, COLOUR_BAND_ROWS):
        r1 = min(height, r0 + COLOUR_BAND_ROWS)
        band, band_owner = data[r0:r1], owner[r0:r1]
        colours = PALETTE[np.where(band_owner == NO_OWNER, 0, band_owner) % len(PALETTE)]
        occ = (band.astype(np.float32).clip(0, 100) / 100.0)[..., None]
        free_tint = 255.0 - 0.25 * (255.0 - colours)
        wall_shade = 0.45 * colours
        rgb = free_tint * (1.0 - occ) + wall_shade * occ
        rgb[band < 0] = 205.0
        out[height - r1 : height - r0] = np.flipud(rgb.round().astype(np.uint8))
    return out


def save_png(result: MergeResult, path: str) -> None:
    """Write :func:`colour_image` as a PNG (raises FusionError when it cannot be written).

    Encoded in memory and written atomically: a full disk or a crash mid-write leaves the previous
    preview whole (a web page or viewer may be reading it), never a truncated PNG in its place.
    """
    import io

    from PIL import Image

    buf = io.BytesIO()
    try:
        Image.fromarray(colour_image(result), mode="RGB").save(buf, format="PNG")
    except (OSError, ValueError) as exc:
        raise FusionError(f"{path}: cannot write preview: {exc}") from None
    try:
        atomic_write_bytes(Path(path), buf.getvalue())
    except OSError as exc:
        # strerror, not str(exc): that names the hidden temp file, which means nothing to the user.
        raise FusionError(f"{path}: cannot write preview: {exc.strerror or exc}") from None
