"""The runs ``mapd bench paper`` evaluates: a CARMEN log replayed by N robots, or N simulated robots.

A :class:`Run` holds what the paper's Figures 8 and 9 need:

* each robot's map stream, a snapshot every ``period`` seconds of log (or sim) time, in the robot's
  own map frame (its first pose), exactly what its daemon would send over the link;
* the global map: the whole fleet's scans mapped in one frame (the log's first laser pose, or the
  simulated world's frame), with the global map one period earlier as the base of its delta;
* every scan that went into the global map, with its pose in the global map's frame (the log's
  SLAM-corrected pose, or the simulator's true pose), from which Figure 9 picks its test poses.

With known poses, mapping every robot's scans in one frame is what the fleet's global map would be
if every map arrived exactly; doing it directly keeps resampling artefacts of a merge out of the
comparison between the original and the recovered maps.
"""

from __future__ import annotations

import collections
import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, cast

import numpy as np

from mapd.errors import SourceError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.mapping import mapper as mapping
from mapd.mapping import replay

if TYPE_CHECKING:
    from mapd.mapping.lidar import Lidar
    from mapd.mapping.simrobot import SimRobot

#: Readings at or beyond this are "no return" (the mapper's default; CARMEN logs use about 81.8 m).
MAX_RANGE = 80.0


@dataclass(frozen=True)
class Sample:
    """One scan of the run and its true pose in the global map's frame (meters, radians)."""

    truth: Pose2D
    ranges: np.ndarray
    angles: np.ndarray
    stamp: float


@dataclass
class Run:
    """Everything the paper evaluation measures, from one log or one simulation."""

    label: str
    #: Log (or sim) time of the run's first scan; figures count time from here.
    t0: float
    #: Robot name -> [(log time, snapshot)], a snapshot every period, in the robot's own frame.
    streams: dict[str, list[tuple[float, OccupancyGrid]]]
    global_map: OccupancyGrid
    #: The global map one period before the last (the base of its delta), None if there is only one.
    global_prev: OccupancyGrid | None
    samples: list[Sample]
    #: Each robot's map frame in the global map's frame.
    robot_frames: dict[str, Pose2D] = field(default_factory=dict)
    scans: int = 0
    #: What the samples' poses are: a log's SLAM-corrected poses, or the simulator's true ones.
    truth: str = "corrected pose"


def _progress(text: str) -> None:
    print(f"\r{text}", end="", file=sys.stderr, flush=True)


def log_run(path: Path, *, robots: int, period: float, limit: int | None, resolution: float) -> Run:
    """Replay ``path`` as ``robots`` robots (overlapping slices, see :func:`mapd.mapping.replay.split_range`)."""
    streams: dict[str, list[tuple[float, OccupancyGrid]]] = {}
    frames: dict[str, Pose2D] = {}
    world = replay.first_pose(path)
    if world is None:
        raise SourceError(f"{path}: no laser scans")
    for i in range(robots):
        name = f"robot{i}"
        snaps = replay.replay_log(
            path, every_s=period, resolution=resolution, robots=robots, index=i, robot=name
        )
        streams[name] = []
        for stamp, grid in itertools.islice(snaps, limit):
            streams[name].append((stamp, grid))
            _progress(f"replay {name}: {len(streams[name])} snapshots, log time {stamp:.0f} s")
        first = replay.first_pose(path, robots=robots, index=i)
        if not streams[name] or first is None:
            raise SourceError(f"{path}: robot {i} of {robots} gets no scans")
        frames[name] = mapping.relative(world, first)
    whole = replay.replay_log(path, every_s=period, resolution=resolution, robot="global")
    last = collections.deque(itertools.islice(whole, limit), maxlen=2)
    end = last[-1][0]
    samples = []
    for scan in replay.replay_scans(path):
        if scan.stamp > end:
            break
        samples.append(Sample(mapping.relative(world, scan.pose), scan.ranges, scan.angles, scan.stamp))
    print(file=sys.stderr)
    return Run(
        label=path.name,
        t0=samples[0].stamp,
        streams=streams,
        global_map=last[-1][1],
        global_prev=last[0][1] if len(last) == 2 else None,
        samples=samples,
        robot_frames=frames,
        scans=len(samples),
    )


class _ScanTap:
    """Stands in for a simulated robot's lidar and keeps the scan it returned last.

    :meth:`SimRobot.step` draws a scan and maps it in one call; the tap lets the global map and the
    localization test use exactly the scans the robot mapped with, noise and dropouts included.
    """

    def __init__(self, robot: SimRobot) -> None:
        self.inner = robot.lidar
        self.angles = self.inner.angles
        self.ranges = np.zeros(0)
        robot.lidar = cast("Lidar", self)

    def scan(self, pose: Pose2D, rng: np.random.Generator | None = None) -> np.ndarray:
        self.ranges = self.inner.scan(pose, rng)
        return self.ranges


def sim_run(seed: int, *, robots: int, period: float, duration: float, limit: int | None) -> Run:
    """``robots`` simulated robots sharing the generated building of ``seed`` for ``duration`` sim seconds."""
    from mapd.mapping import worldgen
    from mapd.mapping.simrobot import SimRobot

    world = worldgen.generate(seed)
    sims = [SimRobot(world, seed=seed, index=i, robots=robots) for i in range(robots)]
    taps = [_ScanTap(s) for s in sims]
    names = [f"robot{i}" for i in range(robots)]
    # The global map lives in the world frame: scans go in at the robots' true world poses.
    whole = mapping.Mapper(sims[0].mapper.options)
    streams: dict[str, list[tuple[float, OccupancyGrid]]] = {n: [] for n in names}
    last: collections.deque[OccupancyGrid] = collections.deque(maxlen=2)
    samples: list[Sample] = []
    steps = max(1, round(duration / sims[0].dt))
    due = period
    for k in range(1, steps + 1):
        for sim, tap in zip(sims, taps, strict=True):
            sim.step()
            whole.integrate(tap.ranges, tap.angles, sim.pose)
            samples.append(Sample(sim.pose, tap.ranges, tap.angles, sim.time))
        now = sims[0].time
        if now < due - 1e-9 and k < steps:
            continue
        while due <= now + 1e-9:
            due += period
        for name, sim in zip(names, sims, strict=True):
            version = len(streams[name]) + 1
            streams[name].append((now, sim.snapshot(robot=name, version=version)))
        last.append(whole.snapshot(robot="global", version=len(streams[names[0]]), stamp=now))
        _progress(f"sim: {now:.0f} of {steps * sims[0].dt:.0f} s simulated")
        if limit is not None and len(streams[names[0]]) >= limit:
            break
    print(file=sys.stderr)
    g = world.grid
    return Run(
        label=f"sim building seed {seed} ({g.width * g.resolution:.0f} x {g.height * g.resolution:.0f} m)",
        t0=0.0,
        streams=streams,
        global_map=last[-1],
        global_prev=last[0] if len(last) == 2 else None,
        samples=samples,
        robot_frames={n: s.start for n, s in zip(names, sims, strict=True)},
        scans=len(samples),
        truth="true pose",
    )
