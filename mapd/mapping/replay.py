"""Replaying a CARMEN log through the mapper, as one robot of several that share the log.

:func:`replay_log` runs a CARMEN log through the :class:`~mapd.mapping.mapper.Mapper` (the
``laserlog`` source, ``mapd replay`` and the benches use it) and yields numbered snapshots, by scan
count or by log time; :func:`split_range` is how a log is shared among ``robots`` replaying it, and
:func:`replay_scans` gives the scans of one robot's slice. A robot's map frame is its first laser
pose: :func:`first_pose` says where that sits in the log's world frame, and :func:`resample` puts a
robot's map onto a reference's cells, to compare the two in the fleet (world) frame.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator

import numpy as np

from mapd.errors import ConfigError, LimitError, SourceError
from mapd.grid import DEFAULT_MAX_CELLS, UNKNOWN, OccupancyGrid, Pose2D, inverse
from mapd.mapping import carmen
from mapd.mapping.mapper import Mapper, MapperOptions, relative, resolution_problem


def no_scan_lines(log: str | os.PathLike[str]) -> str:
    """Why a log with no scan line at all is no CARMEN log, in words (for the one error line)."""
    try:
        with open(log, "rb") as fh:
            head = fh.read(2)
    except OSError:
        head = b""
    if not head:
        return f"{log}: the log is empty"
    if os.fspath(log).endswith(".gz") and head != b"\x1f\x8b":
        return (
            f"{log}: not a CARMEN log (named .gz but not gzip-compressed, and no FLASER or ROBOTLASER1 line)"
        )
    return f"{log}: not a CARMEN log (no FLASER or ROBOTLASER1 line)"


def no_valid_scan(log: str | os.PathLike[str], part: str = "") -> str:
    """Why a log gave no scan to replay, in words: no scan line at all (:func:`no_scan_lines`), or
    scan lines that are all damaged (in ``part`` of it, a robot's slice, when given)."""
    lines = carmen.count_scans(log)
    if lines == 0:
        return no_scan_lines(log)
    return f"{log}: no valid scan{' in ' + part if part else ''} ({lines} scan line{'s' if lines != 1 else ''} in the log, none usable there)"


def split_range(n: int, robots: int, index: int, overlap: float = 0.2) -> range:
    """Scan indices robot ``index`` of ``robots`` replays: evenly spaced slices of equal length where
    consecutive slices share ``overlap`` of the whole log (two robots: the first and last 60 %)."""
    if robots < 1:
        raise ValueError("robots must be at least 1")
    if not 0 <= index < robots:
        raise ValueError(f"index {index} is not in 0..{robots - 1}")
    if not 0.0 <= overlap < 1.0:
        raise ValueError("overlap must lie in [0, 1)")
    if robots == 1:
        return range(n)
    span = min(1.0, (overlap * (robots - 1) + 1.0) / robots)
    length = round(span * n)
    start = round(index * (n - length) / (robots - 1))
    return range(start, min(n, start + length))


def replay_scans(
    path: str | os.PathLike[str],
    *,
    robots: int = 1,
    index: int = 0,
    overlap: float = 0.2,
    fov_deg: float = 180.0,
    stats: carmen.LogStats | None = None,
) -> Iterator[carmen.LaserScan]:
    """The scans robot ``index`` of ``robots`` replays (its slice of the log, see :func:`split_range`)."""
    picked = split_range(carmen.count_scans(path), robots, index, overlap) if robots > 1 else None
    for scan in carmen.read_scans(path, stats=stats, fov_deg=fov_deg):
        if picked is not None:
            if scan.index < picked.start:
                continue
            if scan.index >= picked.stop:
                return
        yield scan


def replay_log(
    path: str | os.PathLike[str],
    *,
    every: int = 10,
    every_s: float | None = None,
    resolution: float = 0.05,
    max_range: float | None = None,
    robots: int = 1,
    index: int = 0,
    overlap: float = 0.2,
    options: MapperOptions | None = None,
    robot: str = "",
    max_cells: int = DEFAULT_MAX_CELLS,
    stats: carmen.LogStats | None = None,
) -> Iterator[tuple[float, OccupancyGrid]]:
    """Replay a CARMEN log with corrected poses through the mapper, as robot ``index`` of ``robots``.

    Yields ``(log time in s, snapshot)`` every ``every`` scans and once more after the last scan, with
    versions 1, 2, ... With ``every_s``, snapshots go by log time instead of scan count: one at the
    first scan at or past each multiple of ``every_s`` seconds after the robot's first scan (a gap in
    the log longer than that gives one snapshot, not several). The map frame is the robot's first
    laser pose (see :func:`first_pose` for where that sits in the log's world frame). ``options``
    overrides ``resolution``/``max_range``; without it, a ``resolution`` :func:`resolution_problem`
    refuses or a ``max_range`` that is not positive raises ConfigError.
    Bad lines are skipped (logged and counted in ``stats``: pass one to several passes over the same
    log to log each kind of fault once). A log that ends early (a cut or damaged gzip stream) is
    replayed up to the cut, which is warned of once per ``stats``; a log that cannot be read, or has
    no scan before its cut, raises SourceError.
    """
    if every < 1:
        raise ValueError("every must be at least 1")
    if every_s is not None and not every_s > 0.0:
        raise ValueError("every_s must be positive")
    if options is None:
        # Said as a ConfigError, not pydantic's traceback: callers pass a user's numbers on.
        problem = resolution_problem(resolution)
        if problem is None and max_range is not None and not max_range > 0.0:
            problem = f"max_range {max_range:g} m is not positive"
        if problem is not None:
            raise ConfigError(problem)
    opts = options if options is not None else MapperOptions(resolution=resolution, max_range=max_range)
    mapper = Mapper(opts, max_cells=max_cells)
    frame: Pose2D | None = None
    version = 0
    pending = 0
    stamp = 0.0
    due = math.inf  # log time of the next snapshot when going by time
    for scan in replay_scans(path, robots=robots, index=index, overlap=overlap, stats=stats):
        if frame is None:
            frame = scan.pose
            if every_s is not None:
                due = scan.stamp + every_s
        stamp = scan.stamp
        try:
            mapper.integrate(scan.ranges, scan.angles, relative(frame, scan.pose))
        except LimitError as exc:
            raise SourceError(f"{path}: line {scan.line}: {exc}") from None
        pending += 1
        if every_s is None:
            now = pending >= every
        else:
            now = stamp >= due
            while due <= stamp:
                due += every_s
        if now:
            version += 1
            pending = 0
            yield stamp, mapper.snapshot(robot=robot, version=version, stamp=stamp)
    if pending:
        version += 1
        yield stamp, mapper.snapshot(robot=robot, version=version, stamp=stamp)


def first_pose(
    path: str | os.PathLike[str], *, robots: int = 1, index: int = 0, overlap: float = 0.2
) -> Pose2D | None:
    """Robot ``index``'s map frame in the log's world frame (its first laser pose), or None if no scan.

    Bad lines on the way are skipped without a word: the replay that reads them too reports them.
    """
    quiet = carmen.LogStats(quiet=True)
    for scan in replay_scans(path, robots=robots, index=index, overlap=overlap, stats=quiet):
        return scan.pose
    return None


def resample(grid: OccupancyGrid, pose: Pose2D, like: OccupancyGrid) -> OccupancyGrid:
    """``grid`` seen on ``like``'s cells: ``pose`` is where ``grid``'s map frame sits in ``like``'s frame.

    Nearest-neighbour lookup of every cell centre of ``like``; cells ``grid`` does not cover are unknown.
    Used to compare a robot's map with a reference in the fleet (world) frame.
    """
    grid_idx = np.indices(like.data.shape)
    rows, cols = grid_idx[0], grid_idx[1]
    wx, wy = like.cell_to_world(rows, cols)
    # World (like's frame) -> grid's map frame.
    inv = inverse(pose)
    c, s = math.cos(inv.yaw), math.sin(inv.yaw)
    mx = inv.x + c * wx - s * wy
    my = inv.y + s * wx + c * wy
    fr, fc = grid.world_to_cell(mx, my)
    r = np.floor(fr).astype(np.int64)
    k = np.floor(fc).astype(np.int64)
    inside = (r >= 0) & (r < grid.height) & (k >= 0) & (k < grid.width)
    out = np.full(like.data.shape, UNKNOWN, dtype=np.int8)
    out[inside] = grid.data[r[inside], k[inside]]
    return like.replace(data=out, robot=grid.robot, version=grid.version, stamp=grid.stamp)
