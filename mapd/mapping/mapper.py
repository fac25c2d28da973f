"""The log-odds occupancy-grid mapper shared by every source that makes maps.

:class:`Mapper` takes 2D scans (ranges, beam angles, sensor pose in the map frame) and keeps a
log-odds grid. Each scan is ray-cast in one go with numpy: every beam is sampled once per cell along
its major axis (a DDA), the cells a scan sees free get ``miss`` once, the cells it hits get ``hit``
once (a hit wins over a miss in the same scan), and both are clamped. Nothing loops over cells in
Python.

Readings: NaN, zero or negative ranges are ignored; ``inf`` or anything at or above ``no_return``
means "no return" and, with ``clear_no_return``, clears free space up to ``max_range``; a finite
reading beyond ``max_range`` clears free space up to ``max_range`` and marks no hit, as gmapping's
``maxUrange`` does.

The grid grows as the robot sees new space: the internal buffer is enlarged in generous steps, and
each snapshot covers exactly the cells observed so far, so its width, height and origin change only
when the robot sees beyond the old bounds. Origins stay on the same cell lattice, so consecutive
versions line up cell for cell. Snapshots are thresholded to -1/0/100 like gmapping's ``/map``.

Replaying a CARMEN log through the mapper, as one of several robots sharing it, is
:mod:`mapd.mapping.replay`.
"""

from __future__ import annotations

import argparse
import decimal
import itertools
import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from mapd.errors import LimitError
from mapd.grid import (
    DEFAULT_MAX_CELLS,
    FREE,
    MIN_RESOLUTION,
    OCCUPIED,
    UNKNOWN,
    OccupancyGrid,
    Pose2D,
    compose,
    inverse,
)

#: Cells added on each side when the buffer must grow (so growth is rare, not once per scan).
GROW_MARGIN_CELLS = 160
#: Most ray samples handled at once; longer scans are cast in several chunks.
MAX_SAMPLES = 1 << 20
#: Coarsest cells the mapper makes (m): a 10 m cell no longer shows a building's rooms.
MAX_MAPPER_RESOLUTION = 10.0


def _dda_cells(
    sc: float, sr: float, ec: np.ndarray, er: np.ndarray, steps: np.ndarray, w: int, h: int
) -> np.ndarray:
    """Flat buffer indices of the cells from (sr, sc) towards each (er, ec), ``steps`` samples each."""
    total = int(steps.sum())
    beam = np.repeat(np.arange(steps.size), steps)
    first = np.cumsum(steps) - steps
    k = np.arange(total, dtype=np.float64) - np.repeat(first, steps)
    t = k / np.repeat(np.maximum(steps, 1), steps)
    fc = np.floor(sc + t * (ec - sc)[beam]).astype(np.int64)
    fr = np.floor(sr + t * (er - sr)[beam]).astype(np.int64)
    np.clip(fc, 0, w - 1, out=fc)
    np.clip(fr, 0, h - 1, out=fr)
    out: np.ndarray = fr * w + fc
    return out


def logit(p: float) -> float:
    """Log-odds of a probability."""
    return math.log(p / (1.0 - p))


#: The largest log-odds a mapper option may hold (p = 1 - 4e-44: certain).
MAX_LOG_ODDS = 100.0


class MapperOptions(BaseModel):
    """Mapper parameters; sources that map take these keys in their own config table."""

    model_config = ConfigDict(extra="forbid")

    # (bounds: finer than MIN_RESOLUTION cannot be read back from its own file; log-odds past
    # MAX_LOG_ODDS are certainty already, and overflowed the float32 cells)
    resolution: float = Field(
        default=0.05, ge=MIN_RESOLUTION, le=MAX_MAPPER_RESOLUTION, description="meters per cell"
    )
    hit: float = Field(
        default=0.85, gt=0.0, le=MAX_LOG_ODDS, description="log-odds added to a cell a beam ends in"
    )
    miss: float = Field(
        default=-0.4, lt=0.0, ge=-MAX_LOG_ODDS, description="log-odds added to a cell a beam passes"
    )
    clamp_min: float = Field(
        default=-2.0, lt=0.0, ge=-MAX_LOG_ODDS, description="lowest log-odds a cell may hold"
    )
    clamp_max: float = Field(
        default=3.5, gt=0.0, le=MAX_LOG_ODDS, description="highest log-odds a cell may hold"
    )
    max_range: float | None = Field(
        default=None, gt=0.0, description="usable range in m: longer beams clear up to here, no hit"
    )
    no_return: float | None = Field(
        default=80.0, gt=0.0, description="readings at or above this (m) mean no return (inf always does)"
    )
    clear_no_return: bool = Field(
        default=False, description="clear free space along no-return beams up to max_range"
    )
    occupied_thresh: float = Field(default=0.65, gt=0.0, lt=1.0, description="p above this: occupied")
    free_thresh: float = Field(default=0.5, gt=0.0, lt=1.0, description="p below this: free")

    @model_validator(mode="after")
    def _check(self) -> MapperOptions:
        if self.free_thresh > self.occupied_thresh:
            raise ValueError("free_thresh must not be above occupied_thresh")
        if self.clear_no_return and self.max_range is None:
            raise ValueError("clear_no_return needs a finite max_range")
        return self


def resolution_problem(resolution: float) -> str | None:
    """Why a user's ``resolution`` (m/cell) cannot be mapped, in one line; None if it is fine.

    Finer than :data:`mapd.grid.MIN_RESOLUTION` is refused too (beyond :class:`MapperOptions`'s
    bounds): such a map could not be read back from its own file, and a tiny resolution only ends
    in a growth error with numbers hundreds of digits long.
    """
    if MIN_RESOLUTION <= resolution <= MAX_MAPPER_RESOLUTION:  # NaN fails the comparison
        return None
    return f"resolution {resolution:g} m/cell is not within [{MIN_RESOLUTION:g}, {MAX_MAPPER_RESOLUTION:g}]"


def resolution_arg(text: str) -> float:
    """An argparse ``type=`` for a mapper's ``--resolution`` (see :func:`resolution_problem`),
    checked while parsing so that a bad value is one usage line before any log is read."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number of meters per cell") from None
    problem = resolution_problem(value)
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return value


def _compact(n: int) -> str:
    """``n`` in full while it is short, else as ``1.25e+304``: a runaway pose must not print a
    number hundreds of digits long (Decimal formats any int; a float would overflow)."""
    return str(n) if abs(n) < 10**12 else format(decimal.Decimal(n), ".3g")


def relative(frame: Pose2D, pose: Pose2D) -> Pose2D:
    """``pose`` (in the parent frame) expressed in ``frame``."""
    return compose(inverse(frame), pose)


class Mapper:
    """A growing log-odds occupancy grid fed with 2D scans, in one map frame."""

    def __init__(self, options: MapperOptions | None = None, *, max_cells: int = DEFAULT_MAX_CELLS) -> None:
        self.options = options if options is not None else MapperOptions()
        self.max_cells = max_cells
        o = self.options
        self._res = float(o.resolution)
        self._occ_lo = logit(o.occupied_thresh)
        self._free_lo = logit(o.free_thresh)
        self._lo = np.zeros((0, 0), dtype=np.float32)
        self._scratch = np.zeros((0, 0), dtype=np.bool_)
        self._seen = np.zeros((0, 0), dtype=np.bool_)
        # Frame cell (row, col) of buffer cell (0, 0).
        self._off = (0, 0)
        # Observed bounds in frame cells, half-open: row0, row1, col0, col1; None before the first scan.
        self._bounds: tuple[int, int, int, int] | None = None
        self.scans = 0

    # -- state ----------------------------------------------------------------------------------------
    @property
    def resolution(self) -> float:
        return self._res

    @property
    def bounds(self) -> tuple[int, int, int, int] | None:
        """Observed cells as frame-cell bounds (row0, row1, col0, col1), half-open."""
        return self._bounds

    def logodds(self) -> np.ndarray:
        """The log-odds of the observed region (a copy, float32, row 0 at the snapshot origin)."""
        if self._bounds is None:
            return np.zeros((0, 0), dtype=np.float32)
        r0, r1, c0, c1 = self._bounds
        dr, dc = self._off
        return self._lo[r0 - dr : r1 - dr, c0 - dc : c1 - dc].copy()

    # -- growth ---------------------------------------------------------------------------------------
    def _ensure(self, r0: int, r1: int, c0: int, c1: int) -> None:
        """Make the buffer hold frame cells rows [r0, r1) and cols [c0, c1)."""
        h, w = self._lo.shape
        dr, dc = self._off
        if h and r0 >= dr and r1 <= dr + h and c0 >= dc and c1 <= dc + w:
            return
        if h:
            r0, r1 = min(r0, dr), max(r1, dr + h)
            c0, c1 = min(c0, dc), max(c1, dc + w)
        m = GROW_MARGIN_CELLS
        nr0, nr1, nc0, nc1 = r0 - m, r1 + m, c0 - m, c1 + m
        cells = (nr1 - nr0) * (nc1 - nc0)
        needed = (r1 - r0) * (c1 - c0)
        if needed > self.max_cells:
            raise LimitError(
                f"map would grow to {_compact(r1 - r0)} x {_compact(c1 - c0)} = {_compact(needed)} "
                f"cells, over the limit of {self.max_cells} cells"
            )
        if cells > self.max_cells:
            nr0, nr1, nc0, nc1 = r0, r1, c0, c1
        lo = np.zeros((nr1 - nr0, nc1 - nc0), dtype=np.float32)
        if h:
            lo[dr - nr0 : dr - nr0 + h, dc - nc0 : dc - nc0 + w] = self._lo
        self._lo = lo
        self._scratch = np.zeros(lo.shape, dtype=np.bool_)
        self._seen = np.zeros(lo.shape, dtype=np.bool_)
        self._off = (nr0, nc0)

    # -- integration ----------------------------------------------------------------------------------
    def integrate(self, ranges: np.ndarray, angles: np.ndarray, pose: Pose2D) -> int:
        """Ray-cast one scan taken at sensor ``pose`` (map frame); returns the number of beams used.

        Raises :class:`LimitError` (and changes nothing) when the scan would grow the grid past
        ``max_cells``, and :class:`ValueError` when the arrays do not match or the pose is not finite.
        """
        r = np.asarray(ranges, dtype=np.float64).ravel()
        a = np.asarray(angles, dtype=np.float64).ravel()
        if r.shape != a.shape:
            raise ValueError(f"{r.size} ranges but {a.size} angles")
        if not all(math.isfinite(v) for v in pose):
            raise ValueError(f"sensor pose is not finite: {tuple(pose)}")
        o = self.options
        max_range = math.inf if o.max_range is None else float(o.max_range)
        with np.errstate(invalid="ignore"):
            valid = np.isfinite(a) & (r > 0.0)  # NaN compares False: dropped here
            no_ret = valid & (np.isinf(r) | ((r >= o.no_return) if o.no_return is not None else False))
            hit = valid & ~no_ret & (r <= max_range)
            free_len = np.where(valid & ~no_ret, np.minimum(r, max_range), 0.0)
        if o.clear_no_return:
            free_len = np.where(no_ret, max_range, free_len)
        used = free_len > 0.0
        if not used.any():
            self.scans += 1
            return 0
        res = self._res
        th = pose.yaw + a[used]
        hits = hit[used]
        # Continuous frame-cell coordinates (x -> col, y -> row) of the sensor and the beam ends.
        sc, sr = pose.x / res, pose.y / res
        with np.errstate(over="ignore", invalid="ignore"):
            length = free_len[used] / res
            ec = sc + length * np.cos(th)
            er = sr + length * np.sin(th)
        if not (math.isfinite(sc) and math.isfinite(sr) and np.isfinite(ec).all() and np.isfinite(er).all()):
            # A finite range or pose so large that it overflows in cells: no grid could hold it.
            raise LimitError(f"scan reaches past any grid: sensor at {pose.x:g}, {pose.y:g} m")
        r0 = math.floor(min(sr, float(er.min())))
        r1 = math.floor(max(sr, float(er.max()))) + 1
        c0 = math.floor(min(sc, float(ec.min())))
        c1 = math.floor(max(sc, float(ec.max()))) + 1
        self._ensure(r0, r1, c0, c1)
        dr, dc = self._off
        h, w = self._lo.shape
        sc_b, sr_b = sc - dc, sr - dr
        ec_b, er_b = ec - dc, er - dr

        hc = np.clip(np.floor(ec_b[hits]).astype(np.int64), 0, w - 1)
        hr = np.clip(np.floor(er_b[hits]).astype(np.int64), 0, h - 1)
        hit_idx = hr * w + hc

        # DDA: one sample per cell along each beam's major axis, the end cell excluded. Beams are
        # taken in chunks of at most MAX_SAMPLES samples so that one long scan cannot allocate much.
        steps = np.ceil(np.maximum(np.abs(ec_b - sc_b), np.abs(er_b - sr_b))).astype(np.int64)
        chunk_of = (np.cumsum(steps) - 1) // MAX_SAMPLES
        cuts = np.flatnonzero(np.diff(chunk_of)) + 1
        bounds = [0, *cuts.tolist(), steps.size]
        lo = self._lo.reshape(-1)
        scratch = self._scratch.reshape(-1)
        seen = self._seen.reshape(-1)
        several = len(bounds) > 2
        scratch[hit_idx] = True
        missed: list[np.ndarray] = []
        for i0, i1 in itertools.pairwise(bounds):
            free_idx = _dda_cells(sc_b, sr_b, ec_b[i0:i1], er_b[i0:i1], steps[i0:i1], w, h)
            free_idx = free_idx[~scratch[free_idx]]
            if several:
                # Across chunks, a cell must still get one miss per scan.
                free_idx = free_idx[~seen[free_idx]]
                seen[free_idx] = True
            # Fancy-index += applies once per distinct cell: one miss/hit per cell per scan.
            lo[free_idx] += np.float32(o.miss)
            missed.append(free_idx)
        scratch[hit_idx] = False
        lo[hit_idx] += np.float32(o.hit)
        touched = np.concatenate([*missed, hit_idx])
        if several:
            seen[touched] = False
        lo[touched] = np.clip(lo[touched], o.clamp_min, o.clamp_max)

        if self._bounds is None:
            self._bounds = (r0, r1, c0, c1)
        else:
            b = self._bounds
            self._bounds = (min(b[0], r0), max(b[1], r1), min(b[2], c0), max(b[3], c1))
        self.scans += 1
        return int(used.sum())

    # -- output ---------------------------------------------------------------------------------------
    def threshold(self, lo: np.ndarray) -> np.ndarray:
        """-1/0/100 cells from log-odds: above the occupied threshold 100, below the free one 0."""
        out = np.full(lo.shape, UNKNOWN, dtype=np.int8)
        out[lo > self._occ_lo] = OCCUPIED
        out[lo < self._free_lo] = FREE
        return out

    def snapshot(
        self, *, robot: str = "", version: int = 0, stamp: float = 0.0, frame_id: str = "map"
    ) -> OccupancyGrid:
        """The observed region as a thresholded :class:`OccupancyGrid` (1x1 unknown before any scan)."""
        if self._bounds is None:
            return OccupancyGrid(
                data=np.full((1, 1), UNKNOWN, dtype=np.int8), resolution=self._res, frame_id=frame_id,
                robot=robot, version=version, stamp=stamp,
            )  # fmt: skip
        r0, _r1, c0, _c1 = self._bounds
        return OccupancyGrid(
            data=self.threshold(self.logodds()),
            resolution=self._res,
            origin=Pose2D(c0 * self._res, r0 * self._res, 0.0),
            frame_id=frame_id,
            robot=robot,
            version=version,
            stamp=stamp,
        )
