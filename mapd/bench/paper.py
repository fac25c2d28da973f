"""Paper benchmark: the Zhang & Deng (2024) evaluation, Figures 7, 8a, 8b and 9, on a log or a simulation.

``mapd bench paper --log LOG | --sim SEED --out DIR`` writes ``DIR/report.md`` (the paper's numbers
beside ours, the settings and the command), the figures as PNG files, ``results.json``,
``updates.csv`` (one row per map update and codec) and ``poses.csv`` (one row per test pose).

Figure 8a: every robot's map, a snapshot every ``--period`` seconds of log time, is coded by each
codec: ``paper`` (the paper's CNN + Huffman codec, lossy), ``lossless`` (mapd's, whole map),
``lossless+delta`` (against the robot's previous snapshot, as a daemon sends it), ``pooled+delta``
(mapd's lossy ``pooled`` codec, likewise) and ``zstd-19`` (the raw int8 cells at level 19). Per
update: compression ratio (raw cells, one byte each, over bytes) and rate (1 - bytes / raw bytes,
the paper's "compression rate"); the recovered map's PSNR and SSIM against the original
(map_server grey levels, data range 255, SSIM 7x7), occupied-cell F1 and the share of known cells
that change class. Payload bytes include mapd's header.

Figure 8b: the bits per second each codec needs if every robot sends one update per period, beside
the raw map's, against the paper's 12.5 kb/s UWB budget; the transfer time of each update at
12.5 kb/s and its measured decode time.

Figure 9: ``--poses`` poses (default 28, the paper's count) spread over the map, localized from a
perturbed start in the original global map and in each codec's recovered global map
(:mod:`mapd.bench.paper_localize`).
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapd.bench import paper_global, paper_report
from mapd.bench.common import UWB_BPS, float_arg, int_arg, quality, timed
from mapd.bench.paper_report import ROWS
from mapd.grid import MIN_RESOLUTION
from mapd.tables import emit

if TYPE_CHECKING:
    import numpy as np

    from mapd.bench.paper_data import Run
    from mapd.bench.paper_global import Recovered
    from mapd.grid import OccupancyGrid

HELP = "the paper's Figures 7, 8a, 8b and 9 on a log or a simulation: report.md and PNG figures"
#: Most robots sharing the run.
MAX_ROBOTS = 16
#: Longest simulation (sim seconds): the default 300 takes about 2 minutes, an hour about 25.
MAX_SIM_SECONDS = 3600.0
#: Updates at most once a second of log time: each is coded by every row, so a shorter period
#: multiplies the work (1e-9 s ran for ever), and at most once an hour (a period past the run's end
#: leaves it with no update).
PERIOD_S = float_arg(1.0, 3600.0)
#: The finest cells a map file may hold (and the mapper makes) to a metre, for --log.
RESOLUTION_M = float_arg(MIN_RESOLUTION, 1.0)


def add_arguments(p: argparse.ArgumentParser) -> None:
    src = p.add_mutually_exclusive_group()
    src.add_argument("--log", type=Path, default=None, help="CARMEN log (default: the shared intel log)")
    src.add_argument(
        "--sim", type=int_arg(0), default=None, metavar="SEED", help="simulate a building instead (SEED >= 0)"
    )
    p.add_argument(
        "--robots",
        type=int_arg(1, MAX_ROBOTS),
        default=2,
        help=f"robots sharing the run, 1 to {MAX_ROBOTS} (default 2, as the paper)",
    )
    p.add_argument("--out", type=Path, required=True, help="folder for report.md and the figures")
    p.add_argument("--period", type=PERIOD_S, default=30.0, help="seconds of log time between updates (30)")
    p.add_argument("--poses", type=int, default=28, help="test poses for Figure 9 (default 28, as the paper)")
    # Checked while parsing: numpy refuses a negative seed only after the whole run, at Figure 9.
    p.add_argument("--seed", type=int_arg(0), default=0, help="seed of the perturbed starts (default 0)")
    p.add_argument(
        "--duration",
        type=float_arg(1.0, MAX_SIM_SECONDS),
        default=300.0,
        help=f"sim seconds to simulate (--sim), 1 to {MAX_SIM_SECONDS:g} (300)",
    )
    p.add_argument(
        "--limit", type=int_arg(1), default=None, help="stop each map stream after N updates (quick runs)"
    )
    p.add_argument(
        "--resolution", type=RESOLUTION_M, default=0.05, help="map resolution in m for --log (0.05)"
    )


def command_line(args: argparse.Namespace) -> str:
    """The command that reproduces this run, every setting spelled out."""
    src = f"--sim {args.sim} --duration {args.duration:g}" if args.sim is not None else f"--log {args.log}"
    parts = [f"mapd bench paper {src} --robots {args.robots} --period {args.period:g}"]
    parts.append(f"--poses {args.poses} --seed {args.seed}")
    if args.sim is None:
        parts.append(f"--resolution {args.resolution:g}")
    if args.limit is not None:
        parts.append(f"--limit {args.limit}")
    parts.append(f"--out {args.out}")
    return " ".join(parts)


def _check(args: argparse.Namespace) -> None:
    from mapd.data import shared_log
    from mapd.errors import ConfigError

    # The other numbers are bounded while parsing (add_arguments).
    if args.sim is None and args.log is None:
        args.log = shared_log("intel")
        if args.log is None:
            raise ConfigError("no --log or --sim given and no shared intel log found (set MAPD_DATA)")
    if args.poses < 1:
        raise ConfigError("--poses must be at least 1")


class Coder:
    """Codes one map with one row's codec, decodes it, times both and measures what came back."""

    def __init__(self) -> None:
        import zstandard

        self.zc = zstandard.ZstdCompressor(level=19)
        self.zd = zstandard.ZstdDecompressor()

    def __call__(
        self, row: str, grid: OccupancyGrid, base: OccupancyGrid | None
    ) -> tuple[dict[str, Any], np.ndarray]:
        import numpy as np

        from mapd.codec import decode, encode, read_header

        if row == "zstd-19":
            raw = np.ascontiguousarray(grid.data).tobytes()
            packed, enc_ms = timed(lambda: self.zc.compress(raw))
            back, dec_ms = timed(lambda: self.zd.decompress(packed))
            cells = np.frombuffer(back, np.int8).reshape(grid.data.shape)
            nbytes, delta = len(packed), False
        else:
            use = base if row.endswith("+delta") else None
            codec = row.removesuffix("+delta")
            payload, enc_ms = timed(lambda: encode(grid, codec, base=use))
            out, dec_ms = timed(lambda: decode(payload, base=use))
            cells, nbytes, delta = out.data, len(payload), read_header(payload).delta
        exact = bool(np.array_equal(cells, grid.data))
        measured = quality(grid.data, cells, exact)
        rec = {
            "bytes": nbytes,
            "delta": delta,
            "enc_ms": enc_ms,
            "dec_ms": dec_ms,
            "exact": exact,
            **measured,
        }
        return rec, cells


def fig8_updates(run: Run, coder: Coder, period: float) -> tuple[list[dict[str, Any]], Recovered]:
    """One record per robot update and row: size, rate, quality, bit/s, transfer and codec times.

    Also the recovered cells of every update a row did not reproduce exactly, for Figure 7.
    """
    out: list[dict[str, Any]] = []
    recovered: Recovered = {}
    for name, snaps in run.streams.items():
        prev: OccupancyGrid | None = None
        for k, (stamp, grid) in enumerate(snaps):
            for row in ROWS:
                rec, cells = coder(row, grid, prev)
                if not rec["exact"]:
                    recovered.setdefault((name, k), {})[row] = cells
                b, c = rec["bytes"], grid.cells
                rec.update(robot=name, row=row, t=stamp - run.t0, version=grid.version, cells=c)
                rec.update(ratio=c / b, rate=1.0 - b / c, bps=8 * b / period, raw_bps=8 * c / period)
                rec["transfer_s"] = 8 * b / UWB_BPS
                out.append(rec)
            prev = grid
            print(f"\rfig 8: {name} update {k + 1}/{len(snaps)}", end="", file=sys.stderr, flush=True)
        print(file=sys.stderr)
    return out, recovered


def _mean(vals: list[float]) -> float:
    return sum(vals) / len(vals) if vals else math.nan


def fig8_summary(updates: list[dict[str, Any]], period: float) -> list[dict[str, Any]]:
    """Per row: totals and means over every robot's updates (PSNR over the finite values)."""
    rows = []
    for row in ROWS:
        u = [r for r in updates if r["row"] == row]
        cells, nbytes = sum(r["cells"] for r in u), sum(r["bytes"] for r in u)
        robots = sorted({r["robot"] for r in u})
        finite = [r["psnr"] for r in u if math.isfinite(r["psnr"])]
        per_robot = [_mean([r["bps"] for r in u if r["robot"] == n]) for n in robots]
        fleet = sum(per_robot)
        rows.append(
            {
                "row": row,
                "updates": len(u),
                "deltas": sum(bool(r["delta"]) for r in u),
                "cells": cells,
                "bytes": nbytes,
                "ratio": cells / nbytes,
                "rate": 1.0 - nbytes / cells,
                "max_rate": max(r["rate"] for r in u),
                "psnr": _mean(finite) if finite else math.inf,
                "min_psnr": min(r["psnr"] for r in u),
                "ssim": _mean([r["ssim"] for r in u]),
                "f1": _mean([r["f1"] for r in u]),
                "changed": _mean([r["changed"] for r in u]),
                "exact": all(r["exact"] for r in u),
                "raw_bps": _mean([r["raw_bps"] for r in u]),
                "bps": _mean([r["bps"] for r in u]),
                "max_bps": max(r["bps"] for r in u),
                "fleet_bps": fleet,
                "uwb_share": fleet / UWB_BPS,
                "transfer_s": _mean([r["transfer_s"] for r in u]),
                "max_transfer_s": max(r["transfer_s"] for r in u),
                "enc_ms": _mean([r["enc_ms"] for r in u]),
                "dec_ms": _mean([r["dec_ms"] for r in u]),
                "max_dec_ms": max(r["dec_ms"] for r in u),
                # Every robot's updates fit when the fleet's mean rate and the largest update both fit.
                "fits": fleet <= UWB_BPS and max(r["transfer_s"] for r in u) <= period,
            }
        )
    return rows


def recovered_global(run: Run, coder: Coder) -> tuple[dict[str, OccupancyGrid], list[dict[str, Any]]]:
    """The original global map and each row's recovered copy, with the size and quality of each."""
    g = run.global_map
    maps = {"original": g}
    rows = []
    for row in ROWS:
        rec, cells = coder(row, g, run.global_prev)
        maps[row] = g.replace(data=cells)
        rows.append({"row": row, "cells": g.cells, "ratio": g.cells / rec["bytes"], **rec})
    return maps, rows


def _torch_threads() -> int | None:
    torch = sys.modules.get("torch")
    return int(torch.get_num_threads()) if torch is not None else None


def run(args: argparse.Namespace) -> int:
    from mapd import __version__
    from mapd.bench import paper_data, paper_localize
    from mapd.codec.api import warm_up
    from mapd.errors import ConfigError

    _check(args)
    t_start = time.perf_counter()
    try:
        args.out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"{args.out}: cannot create the output folder: {exc.strerror}") from None
    if args.sim is not None:
        the_run = paper_data.sim_run(
            args.sim, robots=args.robots, period=args.period, duration=args.duration, limit=args.limit
        )
    else:
        the_run = paper_data.log_run(
            args.log, robots=args.robots, period=args.period, limit=args.limit, resolution=args.resolution
        )
    for name in ("paper", "lossless"):  # one-time costs (JIT cache, model loading) stay out of timings
        warm_up(name)
    coder = Coder()
    updates, recovered = fig8_updates(the_run, coder, args.period)
    summary = fig8_summary(updates, args.period)
    global7 = paper_global.fig7(the_run, recovered, ROWS)
    maps, global_rows = recovered_global(the_run, coder)
    fig9 = paper_localize.evaluate(maps, the_run.samples, args.poses, args.seed, the_run.truth)
    g = the_run.global_map
    results: dict[str, Any] = {
        "command": command_line(args),
        "source": the_run.label,
        "mapd": __version__,
        "settings": {
            "robots": args.robots,
            "period_s": args.period,
            "poses": args.poses,
            "seed": args.seed,
            "limit": args.limit,
            "duration_s": args.duration if args.sim is not None else None,
            "resolution": g.resolution,
            "uwb_bps": UWB_BPS,
            "start_offset": [paper_localize.MAX_OFFSET_M, paper_localize.MAX_OFFSET_DEG],
            "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
            "torch_threads": _torch_threads(),
        },
        "run": {
            "clock": "sim time" if args.sim is not None else "log time",
            "scans": the_run.scans,
            "log_seconds": the_run.samples[-1].stamp - the_run.t0,
            "updates_per_robot": {n: len(s) for n, s in the_run.streams.items()},
            "robot_frames": {n: list(p) for n, p in the_run.robot_frames.items()},
            "global_map": [g.width, g.height],
            "global_known_cells": g.cells - g.counts()["unknown"],
        },
        "fig8": {"summary": summary, "updates": updates, "global": global_rows},
        "fig7": {k: v for k, v in global7.items() if k != "maps"},
        "fig9": {
            "rows": fig9["rows"],
            "poses": fig9["poses"],
            "picked": len(fig9["poses"]),
            "truth": the_run.truth,
        },
        "paper": paper_report.PAPER,
    }
    results["date"] = datetime.date.today().isoformat()
    results["wall_s"] = time.perf_counter() - t_start
    paper_report.write(args.out, results, maps, fig9, global7)
    emit(
        results, args.json, lambda: f"{paper_report.text_summary(results)}\nreport: {args.out / 'report.md'}"
    )
    return 0
