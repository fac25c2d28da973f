"""``laserlog``: replay a CARMEN log with corrected poses through the mapper, as one robot of K.

The log (gzip or plain) is read one line at a time. ``robots = K`` with ``index = i`` replays robot
``i``'s slice of the log (:func:`mapd.mapping.replay.split_range`: equal, evenly spaced slices where
neighbours share ``overlap`` of the log; for two robots, the first and the last 60 %), which is how
the paper's two-robot experiment runs on real data. A snapshot is emitted every ``every`` scans
and/or every ``every_s`` seconds of log time, and once more after the last scan; then the stream
ends. ``realtime`` paces the replay: 1.0 replays at the speed it was recorded, 0 as fast as
possible.

Frames: each robot's map frame is its first laser pose. The fleet frame is the log's world frame
(the frame of the corrected poses, in which ``../shared/data/maps/radish_derived`` maps are drawn);
:meth:`start_pose` is the robot's map frame in it, for evaluation and known-pose fusion.

Bad lines (wrong field count, NaN or negative ranges, unknown message types) are skipped, logged
once per kind with file and line, and counted in :meth:`stats`. A log that ends early (a gzip log
cut short by a power loss or an interrupted copy, or damaged part-way) is replayed up to the cut and
then ends as at the log's end, with one warning that is also :meth:`stats`' ``last_error``: the
scans before the cut are good data, and ending with an error would stop the daemon (and a
supervisor restarting it would replay the same scans again and again). A log with no scan before
the cut is one SourceError.

Example ``config.toml`` table::

    [source.laserlog]
    log = "logs/intel-corrected.log.gz"   # relative paths: to the shared data folder
    every = 10
    realtime = 1.0
    robots = 2
    index = 0
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, model_validator

from mapd.errors import LimitError, SourceError
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.mapping import carmen
from mapd.mapping.mapper import Mapper, MapperOptions, relative
from mapd.mapping.replay import first_pose, no_valid_scan, replay_scans
from mapd.sources.base import FleetSliceOptions, MapSource, SourceContext, SourceOptions

if TYPE_CHECKING:
    from mapd.config import MapdConfig

log = logging.getLogger(__name__)

#: When pacing falls further behind than this (wall seconds), the schedule restarts from now.
MAX_BEHIND_S = 1.0
#: Longest wall-clock wait for one scan. A later timestamp (a gap in the log, or a corrupt stamp
#: years ahead) is replayed as this long a pause, so one bad line cannot stall the source for ever.
MAX_GAP_S = 60.0


class LaserLogOptions(FleetSliceOptions, MapperOptions):
    """``[source.laserlog]``: the log, the fleet slot, when to emit, pacing, and mapper keys."""

    log: Path = Field(
        default=Path("logs/intel-corrected.log.gz"),
        description="CARMEN log, gzip or plain (relative: to the shared data folder, else the config's)",
    )
    every: int | None = Field(default=10, ge=1, description="emit a snapshot every N scans")
    every_s: float | None = Field(default=None, gt=0.0, description="emit a snapshot every T s of log time")
    realtime: float = Field(default=1.0, ge=0.0, description="replay speed: 1.0 as recorded, 0 flat out")
    overlap: float = Field(default=0.2, ge=0.0, lt=1.0, description="share of the log neighbours share")
    fov_deg: float = Field(default=180.0, gt=0.0, le=360.0, description="FLASER field of view")

    @model_validator(mode="after")
    def _check(self) -> LaserLogOptions:
        if self.every is None and self.every_s is None:
            raise ValueError("set every (scans) or every_s (log seconds), or both")
        return self

    def check_with_config(self, cfg: MapdConfig) -> None:
        """ValueError for a log the replay could not open at start (missing, not a regular file,
        unreadable, damaged before its first scan), looked up as the source will."""
        path = SourceContext.of(cfg).resolve(self.log)
        try:
            # the first scan only (the generator, dropped here, closes the file)
            first = next(carmen.read_scans(path, stats=carmen.LogStats(quiet=True)), None)
            if first is None:  # a text file, say: the source ran with no map, and said "finished"
                raise SourceError(no_valid_scan(path))
        except (SourceError, LimitError) as exc:  # (LimitError: a gzip bomb, carmen.MAX_GZIP_RATIO)
            raise ValueError(f"log: {exc}") from None


class LaserLogSource(MapSource):
    """Robot ``index`` of ``robots`` replaying its slice of a CARMEN log through the mapper."""

    name = "laserlog"
    Options = LaserLogOptions

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, LaserLogOptions)
        self.opts: LaserLogOptions = self.options
        self.log_stats = carmen.LogStats()
        self._start: Pose2D | None = None
        self._versions = 0
        self._scans = 0
        self._limit_skips = 0
        self._late = 0.0
        self._gap_logged = False
        self._pose: StampedPose | None = None

    @property
    def path(self) -> Path:
        """The log file, a relative one resolved by :meth:`SourceContext.resolve`."""
        return self.ctx.resolve(self.opts.log)

    def start_pose(self) -> Pose2D | None:
        """Robot's map frame (its first laser pose) in the log's world frame, the fleet frame."""
        if self._start is None:
            o = self.opts
            self._start = first_pose(self.path, robots=o.robots, index=o.index, overlap=o.overlap)
        return self._start

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        """Replay the slice; yield snapshots; end after the last scan."""
        o = self.opts
        mapper = Mapper(MapperOptions.model_validate({k: getattr(o, k) for k in MapperOptions.model_fields}))
        mapper.max_cells = self.ctx.max_cells
        path = self.path
        if not path.exists():
            raise SourceError(f"{path}: no such log file")
        scans = replay_scans(
            path, robots=o.robots, index=o.index, overlap=o.overlap, fov_deg=o.fov_deg, stats=self.log_stats
        )
        loop = asyncio.get_running_loop()
        wall0 = loop.time()
        log_t0: float | None = None
        last_emit_t: float | None = None
        pending = 0
        frame: Pose2D | None = None
        stamp = 0.0
        it = iter(scans)
        while True:
            # Reading, inflating and parsing the log, ray-casting a scan and copying a snapshot are
            # CPU work: each runs on a worker thread, one at a time; only the pacing stays here.
            scan = await asyncio.to_thread(next, it, None)
            if scan is None:
                break
            if frame is None:
                frame, log_t0, last_emit_t = scan.pose, scan.stamp, scan.stamp
                self._start = scan.pose
            assert log_t0 is not None and last_emit_t is not None
            if o.realtime > 0:
                delay = wall0 + max(0.0, scan.stamp - log_t0) / o.realtime - loop.time()
                if delay < -MAX_BEHIND_S:
                    # Stalled (a slow consumer, a busy CPU): carry on from now, no burst to catch up.
                    wall0 -= delay
                    delay = 0.0
                elif delay > MAX_GAP_S:
                    if not self._gap_logged:
                        log.warning(
                            "%s: line %d: log time jumps %.3g s ahead; pausing %.0f s instead "
                            "(further jumps are not logged)", path, scan.line, delay * o.realtime, MAX_GAP_S,
                        )  # fmt: skip
                        self._gap_logged = True
                    wall0 -= delay - MAX_GAP_S
                    delay = MAX_GAP_S
                self._late = max(0.0, -delay)
                await asyncio.sleep(max(delay, 0.0))
            here = relative(frame, scan.pose)
            # stamped on the wall clock: a replayed log's own times are years old
            self._pose = StampedPose(here, time.time())
            try:
                await asyncio.to_thread(mapper.integrate, scan.ranges, scan.angles, here)
            except LimitError as exc:
                self._limit_skips += 1
                self.log_stats.skip(f"{path}: line {scan.line}", str(exc))
                continue
            self._scans += 1
            stamp = scan.stamp
            pending += 1
            due = o.every is not None and pending >= o.every
            due = due or (o.every_s is not None and scan.stamp - last_emit_t >= o.every_s)
            if due:
                pending = 0
                last_emit_t = scan.stamp
                yield await asyncio.to_thread(self._snapshot, mapper, scan.stamp)
        if pending:
            yield await asyncio.to_thread(self._snapshot, mapper, stamp)
        if frame is None:  # not one scan replayed: one error, not a source that ran with no map
            part = f"robot {o.index + 1} of {o.robots}'s part" if o.robots > 1 else ""
            raise SourceError(await asyncio.to_thread(no_valid_scan, path, part))

    def pose(self) -> StampedPose | None:
        """The robot's pose in its map frame at the last replayed scan."""
        return self._pose

    def _snapshot(self, mapper: Mapper, stamp: float) -> OccupancyGrid:
        self._versions += 1
        return mapper.snapshot(robot=self.ctx.robot, version=self._versions, stamp=stamp)

    def stats(self) -> dict[str, int | float | str]:
        st = self.log_stats
        return {
            "versions": self._versions,
            "scans": self._scans,
            "skipped_lines": st.skipped,
            "ignored_messages": st.ignored,
            "last_error": st.last_error,
            "behind_realtime_s": round(self._late, 3),
        }
