"""Helpers shared by the benchmarks: input maps, timing and map quality (tables and JSON are
:mod:`mapd.tables`)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from mapd.data import data_dir, map_label, shared_maps
from mapd.errors import MapFileError
from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map
from mapd.mapping.synthetic import indoor_maps

if TYPE_CHECKING:
    import numpy as np

T = TypeVar("T")

#: The paper's UWB link budget (Zhang & Deng 2024): 12.5 kb/s.
UWB_BPS = 12_500.0

#: The link rates a UWB link may be given (``[transports.uwb] link_rate_bps``): at least two
#: 224-byte frames (the default ``max_frame``) a second, the pacer's burst, and at most 10 Mb/s.
UWB_MIN_BPS = 2 * 224 * 8
UWB_MAX_BPS = 10_000_000

#: The largest seed taken anywhere: numpy, torch and the simulator's ``[source.sim] seed`` take
#: seeds below 2**63.
MAX_SEED = 2**63 - 1

#: The most robots one simulated building (or shared log) is split among: ``[source.sim] robots``.
MAX_SIM_ROBOTS = 64

#: The most timing repeats a bench takes: its run grows with them, and a best (or median) of
#: a thousand is as good as any.
MAX_REPEAT = 1000

#: The longest a command may be asked to run for, in wall seconds: a day; longer is a typo.
DAY_S = 86_400.0

#: The metrics of a map that came back exact: identical images have an infinite PSNR and an SSIM
#: of exactly 1 by definition, which computing them would only blur with rounding.
EXACT = {"psnr": math.inf, "ssim": 1.0, "f1": 1.0, "changed": 0.0}


def int_arg(low: int, high: int | None = None) -> Callable[[str], int]:
    """An argparse ``type=`` for an integer in [``low``, ``high``]: a bad value is one usage line
    before any work, where the bench would fail much later (or never stop)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
        if value < low or (high is not None and value > high):
            bounds = f"at least {low}" if high is None else f"within {low}..{high}"
            raise argparse.ArgumentTypeError(f"{value} is not {bounds}")
        return value

    return parse


def float_arg(low: float, high: float) -> Callable[[str], float]:
    """An argparse ``type=`` for a finite number in [``low``, ``high``] (NaN and inf are refused)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None
        if not low <= value <= high:  # NaN fails the comparison too
            raise argparse.ArgumentTypeError(f"{text} is not within [{low:g}, {high:g}]")
        return value

    return parse


def resolution_arg(text: str) -> float:
    """An argparse ``type=`` for a mapper's ``--resolution`` (see
    :func:`mapd.mapping.mapper.resolution_arg`), imported only when the option is given: the
    mapper's import (pydantic) would slow every ``mapd`` command's start by about 0.3 s."""
    from mapd.mapping.mapper import resolution_arg as parse

    return parse(text)


def timed(fn: Callable[[], T], repeat: int = 1) -> tuple[T, float]:
    """Run ``fn`` ``repeat`` times; return its last result and the best wall time in ms."""
    best = math.inf
    result: Any = None
    for _ in range(max(1, repeat)):
        t0 = time.perf_counter()
        result = fn()
        best = min(best, 1000.0 * (time.perf_counter() - t0))
    return result, best


def input_maps(maps_dir: Path | None, limit: int | None = None) -> Iterator[tuple[str, OccupancyGrid]]:
    """Maps to benchmark: every YAML under ``maps_dir`` (default: the shared data), else synthetic."""
    if maps_dir is None and data_dir() is None:
        print("note: no shared data (MAPD_DATA); using synthetic maps", file=sys.stderr)
        yield from indoor_maps()[:limit]
        return
    paths = shared_maps(maps_dir)
    if not paths:
        raise MapFileError(f"{maps_dir or data_dir()}: no map_server YAML files found")
    for p in paths[:limit]:
        yield map_label(p), load_map(p)


def quality(original: np.ndarray, recovered: np.ndarray, exact: bool) -> dict[str, float]:
    """PSNR, SSIM, occupied F1 and class change of ``recovered`` (see :mod:`mapd.codec.metrics`);
    :data:`EXACT` when the caller found it identical to ``original``."""
    if exact:
        return dict(EXACT)
    from mapd.codec import metrics  # scipy and scikit-image: only when a map came back changed

    return metrics.quality(original, recovered)
