"""Per-robot map version streams for the swarm: made once, cached on disk, sized by the real codecs.

A fleet of N robots either drives the simulator's building (``--sim SEED``: robot ``i`` of ``N`` is
:class:`~mapd.mapping.simrobot.SimRobot` ``(seed, index=i, robots=N)``, so the routes split the rooms
as the ``sim`` source does) or replays slices of one CARMEN log (``--log``: robot ``i`` replays
:func:`~mapd.mapping.replay.split_range` slice ``i`` of ``N`` from the slice's start, all robots at
once, so at a given moment robots stand where the log's robot stood at different times; the poses
are the log's corrected poses, unshifted). Robot ``i`` makes version 1 after its first scan and then
one version every ``period`` seconds (the ``sim`` source's ``emit_period``; log time for logs), up to
``duration``.

Each version is kept as its exact lossless keyframe (small, decodes to the very grid), so any codec's
payload for any (version, base) pair can be made later without replaying again. What goes on the air
is the size of the real signed :class:`~mapd.envelope.Envelope` around the real codec's payload
(:class:`Payloads`): encoded once per (robot stream, codec, version, base) and cached under the
cache directory, so the slow ``paper`` codec runs once per version ever.

Positions (x, y in the building's frame) are sampled every :data:`POSE_DT` seconds; after its last
version a robot stays where it stopped.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import msgpack
import numpy as np

from mapd.codec import decode, encode, get_codec
from mapd.envelope import Envelope
from mapd.grid import OCCUPIED_AT, OccupancyGrid, Pose2D
from mapd.identity import Identity

#: Seconds between recorded positions.
POSE_DT = 1.0
#: Bump when what a cached stream holds changes.
CACHE_FORMAT = 1


@dataclass
class RobotStream:
    """One robot's versions (when each was made, its exact grid as a lossless keyframe) and its path."""

    name: str
    key: str
    times: list[float]
    keyframes: list[bytes]
    poses: np.ndarray  # (T, 2): x, y every POSE_DT seconds from t = 0
    frame: Pose2D = field(default_factory=lambda: Pose2D(0.0, 0.0, 0.0))
    _grids: dict[int, OccupancyGrid] = field(default_factory=dict, repr=False)

    @property
    def versions(self) -> int:
        return len(self.times)

    def position(self, t: float) -> tuple[float, float]:
        k = min(max(0, int(t / POSE_DT)), len(self.poses) - 1)
        return float(self.poses[k, 0]), float(self.poses[k, 1])

    def grid(self, version: int) -> OccupancyGrid:
        """Version ``version`` (1-based), exact."""
        g = self._grids.get(version)
        if g is None:
            g = decode(self.keyframes[version - 1]).replace(robot=self.name, version=version)
            if len(self._grids) > 4:
                self._grids.pop(next(iter(self._grids)))
            self._grids[version] = g
        return g


@dataclass
class Building:
    """What blocks the radio: occupied cells of the building (walls, furniture) in its frame."""

    grid: OccupancyGrid

    @property
    def occupied(self) -> np.ndarray:
        return np.asarray(self.grid.data >= OCCUPIED_AT)


@dataclass
class Fleet:
    """The streams of one fleet and the building they move in."""

    robots: list[RobotStream]
    building: Building | None
    source: str


# --- making streams ----------------------------------------------------------------------------


def _keyframe(grid: OccupancyGrid) -> bytes:
    return encode(grid, "lossless")


def _sim_fleet(
    seed: int, n: int, period: float, duration: float, size: tuple[float, float], scan_rate: float
) -> tuple[list[tuple[list[float], list[bytes], np.ndarray, Pose2D]], OccupancyGrid]:
    from mapd.mapping import worldgen
    from mapd.mapping.simrobot import SimRobot

    world = worldgen.generate(seed, size[0], size[1], 0.05, 1.0)
    out = []
    for i in range(n):
        sim = SimRobot(world, seed=seed, index=i, robots=n, scan_rate=scan_rate)
        times: list[float] = []
        kfs: list[bytes] = []
        poses: list[tuple[float, float]] = [(sim.pose.x, sim.pose.y)]
        next_emit = 0.0
        while True:
            sim.step()
            while len(poses) * POSE_DT <= sim.time + 1e-9:
                poses.append((sim.pose.x, sim.pose.y))
            if sim.time >= next_emit - 1e-9:
                if sim.time > duration + 1e-9:
                    break
                times.append(round(sim.time, 6))
                kfs.append(_keyframe(sim.snapshot(version=len(times))))
                next_emit = len(times) * period
        out.append((times, kfs, np.asarray(poses, dtype=np.float64), sim.start))
    return out, world.grid


def _log_fleet(
    log: Path, n: int, period: float, duration: float
) -> tuple[list[tuple[list[float], list[bytes], np.ndarray, Pose2D]], OccupancyGrid]:
    from mapd.mapping.mapper import Mapper, MapperOptions, relative
    from mapd.mapping.replay import replay_scans

    out = []
    for i in range(n):
        mapper = Mapper(MapperOptions())
        times: list[float] = []
        kfs: list[bytes] = []
        poses: list[tuple[float, float]] = []
        frame: Pose2D | None = None
        t0 = 0.0
        due = 0.0
        for scan in replay_scans(log, robots=n, index=i):
            if frame is None:
                frame, t0 = scan.pose, scan.stamp
            t = scan.stamp - t0
            if t > duration + 1e-9:
                break
            mapper.integrate(scan.ranges, scan.angles, relative(frame, scan.pose))
            while len(poses) * POSE_DT <= t + 1e-9:
                poses.append((scan.pose.x, scan.pose.y))
            if t >= due - 1e-9:
                times.append(round(t, 6))
                kfs.append(_keyframe(mapper.snapshot(version=len(times))))
                while due <= t + 1e-9:
                    due += period
        if frame is None:
            raise ValueError(f"{log}: robot {i} of {n} has no scans")
        out.append((times, kfs, np.asarray(poses or [(frame.x, frame.y)], dtype=np.float64), frame))
    # The building: the whole log mapped in the log's world frame (where the poses are).
    whole = Mapper(MapperOptions())
    for scan in replay_scans(log):
        whole.integrate(scan.ranges, scan.angles, scan.pose)
    return out, whole.snapshot()


def load_fleet(
    *,
    cache: Path,
    n: int,
    period: float,
    duration: float,
    sim_seed: int | None = None,
    log: Path | None = None,
    size: tuple[float, float] = (30.0, 20.0),
    scan_rate: float = 1.0,
) -> Fleet:
    """The fleet's streams, from ``cache`` when made before with the same settings."""
    if (sim_seed is None) == (log is None):
        raise ValueError("give exactly one of sim_seed and log")
    if log is not None:
        src = f"log:{log.name}:{log.stat().st_size}"
        desc = f"log {log.name}"
    else:
        src = f"sim:{sim_seed}:{size[0]:g}x{size[1]:g}:{scan_rate:g}Hz"
        desc = f"sim seed {sim_seed}, {size[0]:g} x {size[1]:g} m"
    key = hashlib.sha256(f"{CACHE_FORMAT}|{src}|{n}|{period:g}|{duration:g}".encode()).hexdigest()[:16]
    path = cache / f"fleet-{key}.msgpack"
    doc = None
    if path.exists():
        try:
            doc = msgpack.unpackb(path.read_bytes(), raw=False)
        except (ValueError, msgpack.UnpackException):
            doc = None
    if doc is None:
        if log is not None:
            made, walls = _log_fleet(log, n, period, duration)
        else:
            assert sim_seed is not None
            made, walls = _sim_fleet(sim_seed, n, period, duration, size, scan_rate)
        doc = {
            "robots": [
                {"times": t, "keyframes": k, "poses": p.ravel().tolist(), "frame": list(f)}
                for t, k, p, f in made
            ],
            "walls": _keyframe(walls),
        }
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp")
        tmp.write_bytes(msgpack.packb(doc, use_bin_type=True))
        tmp.replace(path)
    robots = []
    for i, r in enumerate(doc["robots"]):
        poses = np.asarray(r["poses"], dtype=np.float64).reshape(-1, 2)
        robots.append(
            RobotStream(
                f"r{i}", f"{key}-{i}", list(r["times"]), list(r["keyframes"]), poses, Pose2D(*r["frame"])
            )
        )
    return Fleet(robots, Building(decode(doc["walls"])), desc)


# --- payload sizes -----------------------------------------------------------------------------


class Payloads:
    """Bytes on the air for one (robot, codec, version, base): the signed envelope's packed size.

    Encodes with the real codec the first time a pair is asked for and remembers the size in
    ``cache/sizes-<codec>.json`` (so the paper codec runs once per version, ever).
    """

    def __init__(self, cache: Path, codec: str) -> None:
        self.codec = codec
        self.uses_base = get_codec(codec).uses_base
        self.path = cache / f"sizes-{codec}.json"
        self._sizes: dict[str, int] = {}
        if self.path.exists():
            try:
                self._sizes = json.loads(self.path.read_text())
            except ValueError:
                self._sizes = {}
        self._dirty = 0
        self._identity = Identity.generate("r0")
        self.encodes = 0
        self.coded_bytes = 0

    def size(self, stream: RobotStream, version: int, base: int) -> int:
        """The packed, signed envelope of ``version`` against ``base`` (0: a keyframe)."""
        if not self.uses_base:
            base = 0
        k = f"{stream.key}:{version}:{base}"
        n = self._sizes.get(k)
        if n is None:
            grid = stream.grid(version)
            payload = encode(grid, self.codec, stream.grid(base) if base else None)
            env = Envelope(
                fleet="swarm", robot=self._identity.robot, version=version, base_version=base,
                codec=self.codec, width=grid.width, height=grid.height, resolution=grid.resolution,
                origin=grid.origin, payload=payload, stamp=grid.stamp, seq=version, frame_pose=stream.frame,
            )  # fmt: skip
            n = len(env.signed(self._identity).pack())
            self._sizes[k] = n
            self.encodes += 1
            self._dirty += 1
            if self._dirty >= 50:
                self.flush()
        return n

    def flush(self) -> None:
        if not self._dirty:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.path.exists():  # another run may have added sizes since: keep them too
            with contextlib.suppress(ValueError):
                self._sizes = {**json.loads(self.path.read_text()), **self._sizes}
        tmp = self.path.with_suffix(f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps(self._sizes))
        tmp.replace(self.path)
        self._dirty = 0
