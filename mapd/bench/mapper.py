"""Mapper benchmark: replay the shared CARMEN logs through mapd's mapper at real-time factor 0.

For each log it prints the scans, wall seconds, scans per second, the target time (intel: 910 scans
under 5 s; freiburg-079: 4,791 scans under 20 s) and seconds / target (below 1 meets it), and the
final map's occupied-cell F1 (one-cell tolerance) against the matching ``radish_derived`` reference
map, after moving the map into the log's world frame. Reading and parsing the log is included.
"seconds" is wall time; "cpu s" is this process's CPU time (the mapper is single-threaded, so it is
the one-core figure even when other work shares the machine).

Baseline rows, measured in the same run: the same scans ray-cast one beam at a time with
``skimage.draw.line`` (a per-beam loop over a well-kept library, on the first ``--baseline-scans``
scans) and the ratio of mapd's speed to it. A last row times the ``sim`` source's robot (lidar +
planner + mapper on a generated 30 x 20 m building) in sim seconds per wall second.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from mapd.bench.common import float_arg, int_arg
from mapd.tables import emit, table

HELP = "mapper speed on the intel and freiburg-079 logs (target: under 5 s / 20 s), beside a per-beam loop"
TARGETS = {"intel": 5.0, "freiburg-079": 20.0}
#: Longest sim row: an hour of sim time already takes minutes of wall time, and more is no better
#: a measure of speed.
MAX_SIM_SECONDS = 3600.0
#: The terminal's table.
COLUMNS = [
    ("what", "run", ""),
    ("scans", "scans", ""),
    ("seconds", "seconds", ".2f"),
    ("cpu_s", "cpu s", ".2f"),
    ("scans_per_s", "scans/s", ".0f"),
    ("target_s", "target s", ".0f"),
    ("vs_target", "s/target", ".2f"),
    ("f1", "F1 vs ref", ".3f"),
    ("note", "note", ""),
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", nargs="+", default=list(TARGETS), help="shared logs by short name")
    p.add_argument(
        "--baseline-scans", type=int_arg(1), default=100, help="scans for the per-beam baseline (default 100)"
    )
    p.add_argument(
        "--sim-seconds",
        type=float_arg(0.0, MAX_SIM_SECONDS),
        default=60.0,
        help=f"sim seconds for the sim row, at most {MAX_SIM_SECONDS:g} (default 60; 0: skip)",
    )


def _replay(path: Any) -> tuple[Any, float, float]:
    """Final map, wall seconds and CPU seconds of this process for a whole replay."""
    from mapd.errors import SourceError
    from mapd.mapping.replay import replay_log

    t0, c0 = time.perf_counter(), time.process_time()
    last = None
    for _stamp, grid in replay_log(path, every=1 << 30):
        last = grid
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    if last is None:  # a log without laser scans: nothing to time, and no map to score
        raise SourceError(f"{path}: no laser scans")
    return last, seconds, cpu


def _per_beam(scans: list[Any]) -> float:
    """Seconds for a per-beam skimage.draw.line ray caster with the same update rules."""
    import math

    import numpy as np
    from skimage.draw import line

    from mapd.mapping.mapper import MapperOptions, relative

    o = MapperOptions()
    res = o.resolution
    frame = scans[0].pose
    pad = 2000  # cells each way: room for any of these scans without growth
    lo = np.zeros((2 * pad, 2 * pad), dtype=np.float32)
    t0 = time.perf_counter()
    for s in scans:
        p = relative(frame, s.pose)
        r0, c0 = math.floor(p.y / res) + pad, math.floor(p.x / res) + pad
        free: set[tuple[int, int]] = set()
        hits: set[tuple[int, int]] = set()
        for rng, ang in zip(s.ranges, s.angles, strict=True):
            if not (0 < rng < (o.no_return or math.inf)):
                continue
            th = p.yaw + ang
            r1 = math.floor((p.y + rng * math.sin(th)) / res) + pad
            c1 = math.floor((p.x + rng * math.cos(th)) / res) + pad
            rr, cc = line(r0, c0, r1, c1)
            free.update(zip(rr[:-1].tolist(), cc[:-1].tolist(), strict=True))
            hits.add((r1, c1))
        free -= hits
        if free:
            fr, fc = np.array(list(free)).T
            lo[fr, fc] = np.clip(lo[fr, fc] + o.miss, o.clamp_min, o.clamp_max)
        if hits:
            hr, hc = np.array(list(hits)).T
            lo[hr, hc] = np.clip(lo[hr, hc] + o.hit, o.clamp_min, o.clamp_max)
    return time.perf_counter() - t0


def _mapd_on(scans: list[Any]) -> float:
    from mapd.mapping.mapper import Mapper, relative

    m = Mapper()
    frame = scans[0].pose
    t0 = time.perf_counter()
    for s in scans:
        m.integrate(s.ranges, s.angles, relative(frame, s.pose))
    return time.perf_counter() - t0


def _f1(name: str, grid: Any, path: Any) -> float:
    from mapd.codec import metrics
    from mapd.data import data_dir
    from mapd.grid.load import load_map
    from mapd.mapping.replay import first_pose, resample

    base = data_dir()
    ref_path = base / "maps" / "radish_derived" / name / f"{name}.yaml" if base else None
    pose = first_pose(path)
    if ref_path is None or not ref_path.exists() or pose is None:
        return float("nan")
    ref = load_map(ref_path)
    return metrics.occupied_f1(ref.data, resample(grid, pose, ref).data, tolerance=1)


def _sim_row(sim_seconds: float) -> dict[str, Any]:
    from mapd.mapping import worldgen
    from mapd.mapping.simrobot import SimRobot

    t0 = time.perf_counter()
    robot = SimRobot(worldgen.generate(7), seed=7)
    setup = time.perf_counter() - t0
    steps = round(sim_seconds / robot.dt)
    t0 = time.perf_counter()
    for _ in range(steps):
        robot.step()
    seconds = time.perf_counter() - t0
    snap = robot.snapshot()
    return {
        "what": "sim robot, 360 beams @ 5 Hz",
        "scans": steps,
        "seconds": seconds,
        "scans_per_s": steps / seconds,
        "note": f"{sim_seconds / seconds:.0f}x real time; setup {setup:.2f} s; "
        f"{snap.width}x{snap.height} map",
    }


def run(args: argparse.Namespace) -> int:
    from mapd.data import shared_log
    from mapd.errors import SourceError
    from mapd.mapping import carmen

    rows: list[dict[str, Any]] = []
    for name in args.log:
        path = shared_log(name)
        if path is None:
            raise SourceError(f"log '{name}' not found under the shared data folder (set MAPD_DATA)")
        grid, seconds, cpu = _replay(path)
        n = carmen.count_scans(path)
        target = TARGETS.get(name, float("nan"))
        rows.append(
            {
                "what": f"mapd {name}",
                "scans": n,
                "seconds": seconds,
                "cpu_s": cpu,
                "scans_per_s": n / seconds,
                "target_s": target,
                "vs_target": seconds / target,
                "f1": _f1(name, grid, path),
                "note": f"final map {grid.width}x{grid.height}",
            }
        )
        scans = []
        for s in carmen.read_scans(path):
            scans.append(s)
            if len(scans) >= args.baseline_scans:
                break
        ours = _mapd_on(scans)
        theirs = _per_beam(scans)
        rows.append(
            {
                "what": f"baseline per-beam skimage.draw.line, {name}",
                "scans": len(scans),
                "seconds": theirs,
                "scans_per_s": len(scans) / theirs,
                "note": f"mapd is {theirs / ours:.1f}x faster on the same {len(scans)} scans",
            }
        )
    if args.sim_seconds > 0:
        rows.append(_sim_row(args.sim_seconds))
    emit(rows, args.json, lambda: table(rows, COLUMNS))
    return 0
