"""Maps in the making for ``mapd train``: snapshots replayed from CARMEN logs and simulator runs.

The paper trains on 2,800 maps Gmapping saved *while* mapping, so most of its training maps are
unfinished: ragged frontiers, unknown holes, walls seen from one side. ``mapd train`` can add such
maps beside the finished ones:

* **Logs** (``--snapshots-log``): a CARMEN log with corrected poses replayed through mapd's mapper
  (:func:`mapd.mapping.replay.replay_log`, one robot, the whole log), a snapshot every
  ``--snapshot-every`` scans and one after the last scan, as a Gmapping run saves its map.
* **Simulator** (``--snapshots-sim``): one simulated robot driving through the generated building of
  a seed (:mod:`mapd.mapping.worldgen`, :class:`mapd.mapping.simrobot.SimRobot`) for ``--sim-scans``
  scans, a snapshot every ``--snapshot-every`` scans.

Snapshots are cached on disk (``--cache``, default ``$MAPD_CACHE`` or ``~/.cache/mapd``) under a key
of everything that decides them (the log's sha256, the seed, the cadence, the resolution and
:data:`CACHE_VERSION`), so a second run loads them instead of replaying. They all go to training;
validation stays on held-out finished maps.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sys
import zipfile
import zlib
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapd.errors import ConfigError
from mapd.grid import OccupancyGrid

#: Bump when the mapper or simulator changes what a snapshot holds; old cache entries are then ignored.
CACHE_VERSION = 1

logger = logging.getLogger(__name__)

#: How many times a snapshot set was actually replayed (not loaded from the cache) in this process.
REPLAYS = {"log": 0, "sim": 0}


@dataclass(frozen=True)
class SnapshotSpec:
    """Which maps in the making to train on (recorded in model.json and the card)."""

    logs: tuple[Path, ...] = ()
    sims: tuple[int, ...] = ()
    every: int = 100
    sim_scans: int = 1500
    resolution: float = 0.05
    cache: Path | None = None

    def __bool__(self) -> bool:
        return bool(self.logs or self.sims)

    def check(self) -> None:
        if self.every < 1:
            raise ConfigError(f"--snapshot-every must be at least 1 scan, got {self.every}")
        if self.sim_scans < 1:
            raise ConfigError(f"--sim-scans must be at least 1, got {self.sim_scans}")
        if not 0 < self.resolution <= 1.0:
            raise ConfigError(f"snapshot resolution must lie in (0, 1] m, got {self.resolution}")
        for path in self.logs:
            if not path.is_file():
                raise ConfigError(f"--snapshots-log {path}: no such file")
        check_cache(self.cache)


def default_cache() -> Path:
    """``$MAPD_CACHE``, else ``$XDG_CACHE_HOME/mapd``, else ``~/.cache/mapd``."""
    if os.environ.get("MAPD_CACHE"):
        return Path(os.environ["MAPD_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "mapd"


def check_cache(cache: Path | None) -> Path:
    """The snapshot cache (``cache``, else :func:`default_cache`) with its folders created.

    Called before any snapshot is made, so a cache that cannot be one (a regular file, a path
    through one) is one :class:`ConfigError` line, not a failure after minutes of replaying.
    """
    root = cache or default_cache()
    what = f"--cache {root}" if cache else f"snapshot cache {root} (set --cache or $MAPD_CACHE)"
    try:
        for folder in (root, root / "snapshots"):
            if folder.exists() and not folder.is_dir():
                raise ConfigError(f"{what}: {folder} is not a folder")
        (root / "snapshots").mkdir(parents=True, exist_ok=True)
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        raise ConfigError(
            f"{what}: cannot make the folder ({getattr(exc, 'strerror', None) or exc})"
        ) from None
    return root


def _file_sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _cached(
    kind: str, label: str, key: dict[str, Any], cache: Path, make: Callable[[], list[OccupancyGrid]]
) -> tuple[list[OccupancyGrid], Path]:
    """Load the snapshots for ``key`` from ``cache``, or make and store them."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]
    path = cache / "snapshots" / f"{label}-{digest}.npz"
    if path.is_file():
        cached = _load(path)
        if cached is not None:
            return cached, path
    REPLAYS[kind] += 1
    grids = make()
    tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
    res = grids[0].resolution if grids else 0.05
    arrays: dict[str, Any] = {f"m{i:04d}": g.data for i, g in enumerate(grids)}
    arrays.update(count=np.int64(len(grids)), resolution=np.float64(res))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(tmp, **arrays)
        tmp.replace(path)  # atomic: a concurrent run sees the whole file or none
    except OSError as exc:
        # The cache only saves time: the snapshots are made, so training goes on without it.
        with suppress(OSError):
            tmp.unlink(missing_ok=True)
        logger.warning(
            "cannot write the snapshot cache %s (%s); carrying on without it", path, exc.strerror or exc
        )
    return grids, path


def _load(path: Path) -> list[OccupancyGrid] | None:
    """The snapshots cached in ``path``; None, with one warning, when the file cannot be read whole.

    A cache file can be damaged (a full disk, a crash of an older mapd, a hand edit); it is then a
    cache miss: the snapshots are made again and the file rewritten.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            count = int(z["count"])
            res = float(z["resolution"])
            if not 0 <= count <= len(z.files):
                raise ValueError(f"count {count} for {len(z.files)} arrays")
            return [OccupancyGrid(z[f"m{i:04d}"], res) for i in range(count)]
    except (
        OSError,
        EOFError,
        ValueError,
        TypeError,
        KeyError,
        OverflowError,
        MemoryError,
        zipfile.BadZipFile,
        zlib.error,
    ) as exc:
        logger.warning(
            "snapshot cache %s is damaged (%s: %s); making the snapshots again", path, type(exc).__name__, exc
        )
        return None


def log_snapshots(
    log: Path, every: int, resolution: float = 0.05, cache: Path | None = None
) -> tuple[list[OccupancyGrid], Path]:
    """Snapshots of ``log`` replayed by one robot, every ``every`` scans and after the last one."""
    from mapd.mapping import replay

    key = {"v": CACHE_VERSION, "kind": "log", "sha256": _file_sha256(log), "every": every, "res": resolution}

    def make() -> list[OccupancyGrid]:
        out = []
        for _, grid in replay.replay_log(log, every=every, resolution=resolution, robot="snapshots"):
            out.append(grid)
            print(f"\rsnapshots {log.name}: {len(out)}", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
        return out

    label = log.name.split(".")[0]
    return _cached("log", label, key, cache or default_cache(), make)


def sim_snapshots(
    seed: int, every: int, scans: int, cache: Path | None = None
) -> tuple[list[OccupancyGrid], Path]:
    """Snapshots of one simulated robot in the building of ``seed``: every ``every`` of ``scans`` scans."""
    key = {"v": CACHE_VERSION, "kind": "sim", "seed": seed, "every": every, "scans": scans}

    def make() -> list[OccupancyGrid]:
        from mapd.mapping import worldgen
        from mapd.mapping.simrobot import SimRobot

        robot = SimRobot(worldgen.generate(seed), seed=seed)
        out: list[OccupancyGrid] = []
        for k in range(1, scans + 1):
            robot.step()
            if k % every == 0 or k == scans:
                out.append(robot.snapshot(robot="snapshots", version=len(out) + 1))
                print(f"\rsnapshots sim {seed}: {len(out)}", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
        return out

    return _cached("sim", f"sim{seed}", key, cache or default_cache(), make)


def snapshot_maps(spec: SnapshotSpec) -> tuple[list[tuple[str, OccupancyGrid]], dict[str, Any]]:
    """Every snapshot of ``spec`` as (label, grid), and the recipe to record in model.json."""
    spec.check()
    out: list[tuple[str, OccupancyGrid]] = []
    sources = []
    for log in spec.logs:
        grids, _ = log_snapshots(log, spec.every, spec.resolution, spec.cache)
        name = log.name.split(".")[0]
        out += [(f"snapshots/{name}/{i + 1:04d}", g) for i, g in enumerate(grids)]
        sources.append({"log": log.name, "sha256": _file_sha256(log), "snapshots": len(grids)})
    for seed in spec.sims:
        grids, _ = sim_snapshots(seed, spec.every, spec.sim_scans, spec.cache)
        out += [(f"snapshots/sim{seed}/{i + 1:04d}", g) for i, g in enumerate(grids)]
        sources.append({"sim_seed": seed, "scans": spec.sim_scans, "snapshots": len(grids)})
    recipe = {
        "every_scans": spec.every,
        "sim_scans": spec.sim_scans,
        "resolution": spec.resolution,
        "sources": sources,
        "snapshots": len(out),
        "cells": int(sum(g.cells for _, g in out)),
    }
    return out, recipe


def describe(recipe: dict[str, Any]) -> str:
    """One line for the model card: where the snapshots came from."""
    parts = []
    for s in recipe.get("sources", []):
        if "log" in s:
            parts.append(f"log `{s['log']}` ({s['snapshots']})")
        else:
            parts.append(f"sim building seed {s['sim_seed']}, {s['scans']} scans ({s['snapshots']})")
    return (
        f"{recipe['snapshots']} snapshots of maps in the making, one every {recipe['every_scans']} scans"
        f" (and after the last): {', '.join(parts)}"
    )


__all__ = [
    "CACHE_VERSION",
    "REPLAYS",
    "SnapshotSpec",
    "check_cache",
    "default_cache",
    "describe",
    "log_snapshots",
    "sim_snapshots",
    "snapshot_maps",
]
