"""Helpers shared by the benchmarks: input maps, timing, and plain-text tables."""

from __future__ import annotations

import itertools
import json
import math
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from mapd.data import data_dir, map_label, shared_maps
from mapd.errors import MapFileError
from mapd.grid import OccupancyGrid, Pose2D, load_map

T = TypeVar("T")


def timed(fn: Callable[[], T], repeat: int = 1) -> tuple[T, float]:
    """Run ``fn`` ``repeat`` times; return its last result and the best wall time in ms."""
    best = math.inf
    result: Any = None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, 1000.0 * (time.perf_counter() - t0))
    return result, best


def synthetic_maps(count: int = 6, seed: int = 0) -> list[tuple[str, OccupancyGrid]]:
    """Plausible indoor maps made from a seed, for machines without the shared data."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(count):
        h, w = int(rng.integers(200, 700)), int(rng.integers(200, 700))
        d = np.full((h, w), -1, dtype=np.int8)
        # Rooms on a jittered grid, joined by doors: free inside, walls around.
        rooms_y = np.linspace(10, h - 10, int(rng.integers(2, 5)) + 1).astype(int)
        rooms_x = np.linspace(10, w - 10, int(rng.integers(2, 5)) + 1).astype(int)
        for r0, r1 in itertools.pairwise(rooms_y):
            for c0, c1 in itertools.pairwise(rooms_x):
                if rng.random() < 0.2:
                    continue
                d[r0:r1, c0:c1] = 0
                d[r0, c0:c1] = d[r1 - 1, c0:c1] = 100
                d[r0:r1, c0] = d[r0:r1, c1 - 1] = 100
                dr = int(rng.integers(r0 + 3, max(r0 + 4, r1 - 6)))
                d[dr : dr + 4, c0] = 0
                dc = int(rng.integers(c0 + 3, max(c0 + 4, c1 - 6)))
                d[r0, dc : dc + 4] = 0
        noise = rng.random((h, w)) < 0.003
        d[noise & (d == 0)] = 100
        out.append((f"synthetic/{i}", OccupancyGrid(d, 0.05, Pose2D(-w * 0.025, -h * 0.025, 0.0))))
    return out


def input_maps(maps_dir: Path | None, limit: int | None = None) -> Iterator[tuple[str, OccupancyGrid]]:
    """Maps to benchmark: every YAML under ``maps_dir`` (default: the shared data), else synthetic."""
    if maps_dir is None and data_dir() is None:
        print("note: no shared data (MAPD_DATA); using synthetic maps", file=sys.stderr)
        yield from synthetic_maps()[:limit]
        return
    paths = shared_maps(maps_dir)
    if not paths:
        raise MapFileError(f"{maps_dir or data_dir()}: no map_server YAML files found")
    for p in paths[:limit]:
        yield map_label(p), load_map(p)


def fmt(v: Any, spec: str = "") -> str:
    if isinstance(v, float):
        if math.isinf(v):
            return "inf"
        if math.isnan(v):
            return "-"
        return format(v, spec or ".3g")
    return str(v)


def table(rows: Sequence[dict[str, Any]], columns: Sequence[tuple[str, str, str]]) -> str:
    """Render rows as an aligned text table. ``columns`` holds (key, title, format spec)."""
    cells = [[title for _, title, _ in columns]]
    for r in rows:
        cells.append([fmt(r.get(k, ""), spec) for k, _, spec in columns])
    widths = [max(len(row[i]) for row in cells) for i in range(len(columns))]
    lines = []
    for n, row in enumerate(cells):
        parts = [row[0].ljust(widths[0])] + [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        lines.append("  ".join(parts))
        if n == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def dump_json(obj: Any) -> str:
    """JSON with inf/nan written as strings, so any JSON reader takes it."""

    def clean(x: Any) -> Any:
        if isinstance(x, float) and not math.isfinite(x):
            return str(x)
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items()}
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        return x

    return json.dumps(clean(obj), indent=2)
