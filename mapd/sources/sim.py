"""``sim``: the embedded default source. A generated (or loaded) building, a robot, a lidar, a mapper.

Each daemon simulates ONE robot: ``robots = N`` and ``index = i`` make it robot ``i`` of a fleet of
``N``; N daemons given the same ``seed`` simulate the same building and split its rooms between them,
each deterministically and without talking to the others. The robot drives its route, scans at
``scan_rate`` Hz of sim time and maps with :mod:`mapd.mapping.mapper`; a snapshot is emitted after the first
scan and then every ``emit_period`` sim seconds. ``realtime`` is the real-time factor (sim seconds
per wall second; 1 is live-like, 0 runs as fast as possible). The defaults (5x real time, a version
every 5 sim seconds) suit the two-robot demo: two robots map about 95 % of the default 30 x 20 m building
in about 180 sim seconds (seed 7), under 40 s of wall time, at about 5 % of one core each.

Frames: each robot's map frame is its start pose. The fleet frame is the simulated world's frame
(origin at the building's lower-left outer corner, or the loaded map's frame); :meth:`start_pose`
gives the robot's map frame in it, for evaluation and known-pose fusion.

Example ``config.toml`` table::

    [source.sim]
    seed = 7
    robots = 2
    index = 0
    realtime = 5.0        # sim seconds per wall second (1: live-like, 0: flat out)
    emit_period = 5.0     # sim seconds between map versions
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from pydantic import Field, PrivateAttr, field_validator

from mapd.errors import LimitError, MapFileError, SourceError
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.grid.load import load_map
from mapd.mapping.mapper import MapperOptions, relative
from mapd.sources.base import FleetSliceOptions, MapSource, SourceContext, SourceOptions, is_pose

if TYPE_CHECKING:
    from mapd.config import MapdConfig
    from mapd.mapping.simrobot import SimRobot

log = logging.getLogger(__name__)

#: When pacing falls further behind than this (wall seconds), the schedule restarts from now.
MAX_BEHIND_S = 1.0


class SimOptions(FleetSliceOptions, MapperOptions):
    """``[source.sim]``: the world, the fleet slot, the robot, its lidar, pacing, and mapper keys."""

    seed: int = Field(
        default=0, ge=0, lt=1 << 63, description="world and noise seed; the same seed gives the same building"
    )
    world: Path | None = Field(
        default=None,
        description="map_server YAML to use as the world (relative: to the data folder, else the config's)",
    )
    width_m: float = Field(default=30.0, ge=6.0, le=500.0, description="generated building width")
    height_m: float = Field(default=20.0, ge=6.0, le=500.0, description="generated building depth")
    world_resolution: float = Field(default=0.05, ge=0.01, le=0.5, description="generated world m/cell")
    clutter: float = Field(default=1.0, ge=0.0, le=5.0, description="furniture per room, relative")
    start: list[float] | Literal["auto", "random"] = Field(
        default="auto", description="[x, y, yaw] in the world frame, 'auto' (spread out) or 'random'"
    )
    speed: float = Field(default=0.8, gt=0.0, le=5.0, description="m/s")
    turn_rate: float = Field(default=1.5, gt=0.0, le=10.0, description="rad/s")
    radius: float = Field(default=0.25, gt=0.0, le=2.0, description="robot radius, m")
    scan_rate: float = Field(default=5.0, gt=0.0, le=50.0, description="scans per sim second")
    beams: int = Field(default=360, ge=1, le=8192, description="lidar beams per scan")
    fov_deg: float = Field(default=360.0, gt=0.0, le=360.0, description="lidar field of view")
    lidar_range: float = Field(default=12.0, gt=0.0, le=100.0, description="lidar max range, m")
    noise_std: float = Field(default=0.01, ge=0.0, le=1.0, description="range noise sigma, m")
    dropout: float = Field(default=0.01, ge=0.0, lt=1.0, description="share of beams with no return")
    # at least 10 ms: a period below the clock's resolution never moved the next emit on (a hang)
    emit_period: float = Field(default=5.0, ge=0.01, description="sim seconds between map versions")
    realtime: float = Field(
        default=5.0, ge=0.0, description="sim seconds per wall second (1: live-like, 0: flat out)"
    )
    duration: float | None = Field(default=None, gt=0.0, description="stop after this many sim seconds")
    #: The world map :meth:`check_with_config` loaded, with its path and the cell limit it was read
    #: under, until the source these options start takes it (:meth:`take_world`): the daemon checks
    #: its config, then starts the source with the same options, and read the map twice (a large
    #: map_server world, twice the seconds and, while both were held, twice the memory).
    _checked_world: tuple[Path, int, OccupancyGrid] | None = PrivateAttr(default=None)

    @field_validator("start")
    @classmethod
    def _check_start(cls, v: list[float] | str) -> list[float] | str:
        if isinstance(v, list) and not is_pose(v):
            raise ValueError("start must be [x, y, yaw] (m, m, rad), 'auto' or 'random'")
        return v

    def check_with_config(self, cfg: MapdConfig) -> None:
        """ValueError for a world the source could not build at start: ``world`` missing or not a
        map within ``limits.max_cells``, or a generated building of more cells than that."""
        ctx = SourceContext.of(cfg)
        self._checked_world = None
        if self.world is not None:
            path = ctx.resolve(self.world)
            try:
                grid = load_map(path, max_cells=ctx.max_cells)
            except (MapFileError, LimitError) as exc:
                raise ValueError(f"world: {exc}") from None
            self._checked_world = (path, ctx.max_cells, grid)
        elif (cells := generated_cells(self)) > ctx.max_cells:
            raise ValueError(
                f"width_m: a {self.width_m} x {self.height_m} m building at {self.world_resolution} "
                f"m/cell has {int(cells)} cells, over limits.max_cells ({ctx.max_cells})"
            )

    def take_world(self, path: Path, max_cells: int) -> OccupancyGrid | None:
        """The world map :meth:`check_with_config` loaded from ``path`` under ``max_cells``, handed
        over once (not kept here as well); None when it loaded none, or another path or limit."""
        held, self._checked_world = self._checked_world, None
        if held is not None and held[0] == path and held[1] == max_cells:
            return held[2]
        return None


def generated_cells(o: SimOptions) -> float:
    """How many cells the generated building of ``o`` has (margin included)."""
    from mapd.mapping.worldgen import MARGIN

    return (o.width_m + 2 * MARGIN) * (o.height_m + 2 * MARGIN) / o.world_resolution**2


class SimSource(MapSource):
    """Simulated robot ``index`` of ``robots`` mapping a generated or loaded building."""

    name = "sim"
    Options = SimOptions

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, SimOptions)
        self.opts: SimOptions = self.options
        self._sim: SimRobot | None = None  # built lazily: world generation and planning take a moment
        self._versions = 0
        self._late = 0.0
        self._slips = 0
        self._pose: StampedPose | None = None

    @property
    def sim(self) -> SimRobot:
        """The simulated robot (built on first use)."""
        if self._sim is None:
            self._sim = self._build()
        return self._sim

    # -- construction --------------------------------------------------------------------------------
    def _world_path(self) -> Path:
        assert self.opts.world is not None
        return self.ctx.resolve(self.opts.world)

    def _build(self) -> SimRobot:
        from mapd.mapping import worldgen
        from mapd.mapping.simrobot import SimRobot

        o = self.opts
        if o.world is not None:
            path = self._world_path()
            grid = o.take_world(path, self.ctx.max_cells)  # read by the config's check already?
            if grid is None:
                try:
                    grid = load_map(path, max_cells=self.ctx.max_cells)
                except (MapFileError, LimitError) as exc:
                    raise SourceError(f"sim world: {exc}") from None
            world = worldgen.from_map(grid, seed=o.seed)
        else:
            cells = generated_cells(o)
            if cells > self.ctx.max_cells:
                raise SourceError(
                    f"sim world of {o.width_m} x {o.height_m} m at {o.world_resolution} m/cell has "
                    f"{int(cells)} cells, over the limit of {self.ctx.max_cells}"
                )
            world = worldgen.generate(o.seed, o.width_m, o.height_m, o.world_resolution, o.clutter)
        start: Pose2D | str = Pose2D(*o.start) if isinstance(o.start, list) else o.start
        mapper = MapperOptions.model_validate({k: getattr(o, k) for k in MapperOptions.model_fields})
        try:
            return SimRobot(
                world,
                seed=o.seed,
                index=o.index,
                robots=o.robots,
                start=start,
                mapper=mapper,
                lidar={
                    "beams": o.beams,
                    "fov_deg": o.fov_deg,
                    "max_range": o.lidar_range,
                    "noise_std": o.noise_std,
                    "dropout": o.dropout,
                },
                speed=o.speed,
                turn_rate=o.turn_rate,
                scan_rate=o.scan_rate,
                radius=o.radius,
                max_cells=self.ctx.max_cells,
            )
        except ValueError as exc:
            raise SourceError(f"sim: {exc}") from None

    # -- the stream ----------------------------------------------------------------------------------
    def start_pose(self) -> Pose2D:
        """This robot's map frame (its start pose) in the fleet frame, the simulated world's frame."""
        return self.sim.start

    def pose(self) -> StampedPose | None:
        """The simulated robot's pose in its map frame (its start pose), stamped at the last step."""
        return self._pose

    def _emit(self) -> OccupancyGrid:
        self._versions += 1
        return self.sim.snapshot(robot=self.ctx.robot, version=self._versions)

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        """Drive, scan and map; yield a version after the first scan and every ``emit_period``."""
        o = self.opts
        sim = await asyncio.to_thread(lambda: self.sim)
        loop = asyncio.get_running_loop()
        wall0 = loop.time()
        sim0 = sim.time
        next_emit: float | None = None
        pending = False
        while o.duration is None or sim.time < sim0 + o.duration - 1e-9:
            # driving, ray-casting and mapping a scan, and copying a snapshot, are CPU work: on a
            # worker thread, one at a time; only the pacing stays on the loop
            await asyncio.to_thread(sim.step)
            self._pose = StampedPose(relative(sim.start, sim.pose), time.time())
            pending = True
            if next_emit is None or sim.time >= next_emit - 1e-9:
                next_emit = (sim.time if next_emit is None else next_emit) + o.emit_period
                while next_emit <= sim.time + 1e-9:
                    next_emit += o.emit_period
                pending = False
                yield await asyncio.to_thread(self._emit)
            if o.realtime > 0:
                delay = wall0 + (sim.time - sim0) / o.realtime - loop.time()
                if delay < -MAX_BEHIND_S:
                    # Stalled (a slow consumer, a busy CPU): carry on from now instead of racing to
                    # catch up, which would burn a core in a burst.
                    self._slips += 1
                    wall0 -= delay
                    delay = 0.0
                self._late = max(0.0, -delay)
                await asyncio.sleep(max(delay, 0.0))
        if pending:
            yield await asyncio.to_thread(self._emit)

    def stats(self) -> dict[str, int | float | str]:
        if self._sim is None:
            return {"versions": self._versions}
        s = self._sim
        return {
            "versions": self._versions,
            "sim_time_s": round(s.time, 3),
            "scans": s.mapper.scans,
            "distance_m": round(s.distance, 2),
            "goals_reached": s.goals_reached,
            "behind_realtime_s": round(self._late, 3),
            "realtime_slips": self._slips,
        }
