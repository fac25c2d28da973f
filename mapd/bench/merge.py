"""Map-merge accuracy against the m-explore-style baseline, and the speed of merging big maps.

Pairs: two overlapping crops of one real shared map, the second turned by a random angle
(nearest-neighbour resampling) and shifted, and degraded like another robot's map of the same place
(unexplored patches, walls thicker or thinner in places, speckle). Overlap is what the two maps share:
cells known in both under the true transform, over the known cells of the smaller map; targets are
drawn evenly from 15% to 80% and a pair is kept when its measured overlap is within 0.1 of its target.
Real pairs: every radish_derived *_part1 / *_part2 pair (one world frame, so the truth is known),
with the second turned and both re-origined to hide it.

Success: accepted, translation error at most 2 cells (measured at the centre of the second map, in
its cells) and yaw error at most 1 degree. "wrong" counts accepted estimates more than 5 cells off.
The baseline does what m-explore's map_merge does (AKAZE, ratio-test matching, estimateAffinePartial2D
RANSAC, confidence = inliers / (8 + 0.3 * matches), accepted at 1.0); see mapd.fusion.mexplore.

The last rows time merging 4 maps of 2000 x 2000 cells (real maps padded or cropped to that size,
placed within 25 m of each other) into the global map, against a plain numpy copy of the 4 maps.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from mapd.bench.common import MAX_REPEAT, int_arg
from mapd.tables import emit

HELP = "map-merge success rate vs the m-explore baseline, by overlap; merge speed"

BUCKETS = [(0.15, 0.25), (0.25, 0.40), (0.40, 0.60), (0.60, 0.80)]
#: Largest side of the speed rows' maps: 4 maps of 4096 x 4096 cells are 64 MiB of cells, and turned
#: and spread over 25 m their global map (about 6800 cells a side) still fits the daemon's
#: DEFAULT_MAX_CELLS; a larger side only asks for gigabytes.
MAX_MERGE_SIZE = 4096
#: Most synthetic pairs: each takes a second or two to build and place (the docs' runs use 200).
MAX_PAIRS = 10_000


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--pairs",
        type=int_arg(0, MAX_PAIRS),
        default=60,
        help=f"synthetic pairs, 0 to {MAX_PAIRS} (default 60)",
    )
    p.add_argument("--seed", type=int_arg(0), default=1, help="random seed, 0 or more (default 1)")
    p.add_argument("--no-real", action="store_true", help="skip the real radish part1/part2 pairs")
    p.add_argument(
        "--merge-size",
        type=int_arg(16, MAX_MERGE_SIZE),
        default=2000,
        help=f"side of the 4 maps in the speed rows, 16 to {MAX_MERGE_SIZE} cells (default 2000)",
    )
    p.add_argument(
        "--repeat",
        type=int_arg(1, MAX_REPEAT),
        default=3,
        help="timing repeats for the speed rows (median)",
    )
    p.add_argument(
        "--only",
        type=int_arg(1),  # pair numbers count from 1; the top is checked once the pairs are built
        nargs="+",
        metavar="N",
        help="evaluate only these pairs (numbered as the progress lines print them) and skip the speed rows",
    )


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mapd.data import data_dir, shared_maps
    from mapd.errors import FusionError

    root = data_dir()
    if root is None:
        raise FusionError(
            "shared data folder not found: set MAPD_DATA or place ../shared/data beside the checkout"
        )
    sources = [p for p in shared_maps(root) if "_part" not in p.stem]
    if not sources:  # the pairs and the speed rows are all drawn from these
        raise FusionError(f"{root}: no map_server maps to build pairs from")
    pairs = build_pairs(root, args.pairs, args.seed, real=not args.no_real)
    chosen = set(args.only or range(1, len(pairs) + 1))
    if not chosen <= set(range(1, len(pairs) + 1)):
        raise FusionError(f"--only takes pair numbers from 1 to {len(pairs)}")
    records: list[dict[str, Any]] = []
    for i, (kind, pair) in enumerate(pairs):
        if i + 1 not in chosen:
            continue
        records.append({"pair": i + 1, **_evaluate(kind, pair)})
        if not args.json:
            r = records[-1]
            m = r["mapd"]
            why = "" if m["success"] else f"  ({_miss(m)})"
            print(
                f"  [{i + 1}/{len(pairs)}] {r['label']:<32} overlap {r['overlap']:.2f}  mapd "
                f"{'ok ' if m['success'] else '-- '}  m-explore {'ok' if r['baseline']['success'] else '--'}{why}",
                file=sys.stderr,
                flush=True,
            )
    # the speed maps have their own random stream, so --only and --no-real leave them unchanged
    rng = np.random.default_rng(args.seed + 1_000_003)
    speed = None if args.only else _speed(sources, args.merge_size, args.repeat, rng)
    rows = _rows(records)
    doc = {
        "bench": "merge",
        "seed": args.seed,
        "pairs": len(records),
        "success_rule": "accepted, translation error <= 2 cells at b's centre, yaw error <= 1 deg",
        "rows": rows,
        "speed": speed,
        "records": records,
    }
    emit(doc, args.json, lambda: _text(doc))
    return 0


def build_pairs(root: Path, n: int, seed: int, *, real: bool = True) -> list[tuple[str, Any]]:
    """The bench's pairs: ``n`` synthetic ones from the shared maps (overlap targets spread evenly
    over 15-80 %), then the real radish part1/part2 pairs with their poses hidden. The same
    ``seed`` gives the same pairs, so a miss can be re-run alone (``--only``)."""
    import numpy as np

    from mapd.data import map_label, shared_maps
    from mapd.fusion import synth
    from mapd.grid.load import load_map

    paths = shared_maps(root)
    sources = [p for p in paths if "_part" not in p.stem]
    rng = np.random.default_rng(seed)
    cache: dict[Path, Any] = {}
    pairs: list[tuple[str, Any]] = []
    for k in range(n):
        target = 0.15 + 0.65 * (k + float(rng.uniform())) / max(n, 1)
        for _ in range(20):
            path = sources[int(rng.integers(len(sources)))]
            if path not in cache:
                cache[path] = load_map(path)
            pair = synth.make_pair(cache[path], target, rng, label=map_label(path))
            if pair is not None:
                pairs.append(("synthetic", pair))
                break
    if real:
        for p1 in (p for p in paths if p.stem.endswith("_part1")):
            p2 = (
                p1.parent.parent
                / p1.parent.name.replace("_part1", "_part2")
                / (p1.stem.replace("_part1", "_part2") + ".yaml")
            )
            if p2.exists():
                pairs.append(
                    ("real", synth.hide_pose(load_map(p1), load_map(p2), rng, label=p1.parent.name[:-6]))
                )
    return pairs


def _evaluate(kind: str, pair: Any) -> dict[str, Any]:
    import numpy as np

    from mapd.fusion import mexplore
    from mapd.fusion.estimate import estimate_transform
    from mapd.fusion.transforms import to_matrix

    b = pair.b
    cx, cy = b.cell_to_world(np.array([b.height / 2.0]), np.array([b.width / 2.0]))
    centre = np.array([float(cx[0]), float(cy[0]), 1.0])
    truth = to_matrix(pair.truth)

    def errors(m: np.ndarray) -> tuple[float, float]:
        dp = (m @ centre - truth @ centre)[:2]
        dyaw = math.remainder(math.atan2(m[1, 0], m[0, 0]) - pair.truth.yaw, 2 * math.pi)
        return float(np.hypot(*dp)) / b.resolution, abs(math.degrees(dyaw))

    t0 = time.perf_counter()
    est = estimate_transform(pair.a, b)
    t_ours = time.perf_counter() - t0
    t0 = time.perf_counter()
    base = mexplore.estimate(pair.a, b)
    t_base = time.perf_counter() - t0
    out: dict[str, Any] = {"kind": kind, "label": pair.label, "overlap": round(pair.overlap, 4)}
    for name, m, accepted, conf, secs, extra in (
        ("mapd", to_matrix(est.transform), est.accepted, est.confidence, t_ours, {"reason": est.reason}),
        ("baseline", base.matrix, base.accepted, base.confidence, t_base, {}),
    ):
        e_cells, e_deg = errors(m)
        out[name] = {
            "accepted": bool(accepted),
            "confidence": round(float(conf), 4),
            "err_cells": round(e_cells, 3),
            "err_deg": round(e_deg, 3),
            "success": bool(accepted and e_cells <= 2.0 and e_deg <= 1.0),
            "wrong": bool(accepted and e_cells > 5.0),
            "seconds": round(secs, 4),
            **extra,
        }
    return out


def _group(records: list[dict[str, Any]], name: str, method: str) -> dict[str, Any]:
    n = len(records)
    res = [r[method] for r in records]
    acc = [x for x in res if x["accepted"]]
    return {
        "group": name,
        "method": "mapd" if method == "mapd" else "m-explore",
        "pairs": n,
        "success": sum(x["success"] for x in res) / n if n else None,
        "accepted": len(acc) / n if n else None,
        "wrong": sum(x["wrong"] for x in res),
        "median_err_cells": statistics.median(x["err_cells"] for x in acc) if acc else None,
        "median_err_deg": statistics.median(x["err_deg"] for x in acc) if acc else None,
        "mean_seconds": statistics.fmean(x["seconds"] for x in res) if res else None,
    }


def _rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    groups: list[tuple[str, list[dict[str, Any]]]] = []
    synth = [r for r in records if r["kind"] == "synthetic"]
    for lo, hi in BUCKETS:
        first, last = lo == BUCKETS[0][0], hi == BUCKETS[-1][1]
        sel = [r for r in synth if (first or lo <= r["overlap"]) and (last or r["overlap"] < hi)]
        groups.append((f"synthetic {lo:.0%}-{hi:.0%}", sel))
    groups.append(("real part1/part2", [r for r in records if r["kind"] == "real"]))
    groups.append(("all, overlap >= 40%", [r for r in records if r["overlap"] >= 0.4]))
    groups.append(("all, overlap < 40%", [r for r in records if r["overlap"] < 0.4]))
    rows = []
    for name, sel in groups:
        for method in ("mapd", "baseline"):
            rows.append(_group(sel, name, method))
    return rows


def _speed(sources: list[Path], size: int, repeat: int, rng: Any) -> dict[str, Any]:
    import numpy as np

    from mapd.fusion.merge import merge_with_owner
    from mapd.grid import UNKNOWN, Pose2D
    from mapd.grid.load import load_map

    big = sorted(sources, key=lambda p: p.stat().st_size, reverse=True)[:4]
    maps = []
    for i, path in enumerate(big):
        g = load_map(path)
        data = np.full((size, size), UNKNOWN, dtype=np.int8)
        h, w = min(size, g.height), min(size, g.width)
        data[:h, :w] = g.data[:h, :w]
        # 5 cm cells (so that the global map is 2000-cell maps at its own resolution), and each
        # robot's map frame at its map's centre, as for a robot that started mid-map
        half = -0.5 * size * 0.05
        maps.append(g.replace(data=data, robot=f"r{i}", resolution=0.05, origin=Pose2D(half, half, 0.0)))
    poses = [Pose2D(0.0, 0.0, 0.0)] + [
        Pose2D(
            float(rng.uniform(-25, 25)), float(rng.uniform(-25, 25)), float(rng.uniform(-math.pi, math.pi))
        )
        for _ in range(len(maps) - 1)  # a data folder may hold fewer than 4 maps
    ]

    def timed(fn: Any) -> float:
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return statistics.median(times)

    copy_s = timed(lambda: [m.data.copy() for m in maps])
    out: dict[str, Any] = {"maps": len(maps), "size": size, "numpy_copy_s": copy_s}
    for mode in ("logodds", "occupied_wins"):
        secs = timed(lambda mode=mode: merge_with_owner(maps, poses, mode))
        res = merge_with_owner(maps, poses, mode)
        out[mode] = {
            "seconds": secs,
            "ratio_to_copy": secs / copy_s if copy_s > 0 else None,
            "cells": res.grid.cells,
        }
    return out


def _miss(m: dict[str, Any]) -> str:
    """Why an estimate is not a success, in a few words."""
    if not m["accepted"]:
        return f"declined: {m['reason']}"
    return (
        f"accepted {m['err_cells']:.1f} cells / {m['err_deg']:.2f} deg off, confidence {m['confidence']:.2f}"
    )


def _fmt(v: Any, spec: str, none: str = "-") -> str:
    return none if v is None else format(v, spec)


def _text(doc: dict[str, Any]) -> str:
    """The terminal's summary: success by group and method, the headline comparison, merge speed."""
    lines = [f"mapd bench merge: {doc['pairs']} pairs (seed {doc['seed']}); success = {doc['success_rule']}"]
    head = f"{'group':<24} {'method':<10} {'pairs':>5} {'success':>8} {'accepted':>8} {'wrong':>5} {'med err':>8} {'med yaw':>8} {'mean s':>7}"
    lines += [head, "-" * len(head)]
    for r in doc["rows"]:
        lines.append(
            f"{r['group']:<24} {r['method']:<10} {r['pairs']:>5} {_fmt(r['success'], '8.0%'):>8} "
            f"{_fmt(r['accepted'], '8.0%'):>8} {r['wrong']:>5} {_fmt(r['median_err_cells'], '8.2f'):>8} "
            f"{_fmt(r['median_err_deg'], '8.2f'):>8} {_fmt(r['mean_seconds'], '7.2f'):>7}"
        )
    rows = {(r["group"], r["method"]): r for r in doc["rows"]}
    for g in ("all, overlap >= 40%", "all, overlap < 40%"):
        ours, base = rows[(g, "mapd")]["success"], rows[(g, "m-explore")]["success"]
        if ours is not None and base is not None:
            lines.append(f"{g}: mapd {ours:.0%} vs m-explore {base:.0%} ({100 * (ours - base):+.0f} points)")
    s = doc["speed"]
    if s is not None:
        lines.append(
            f"merge {s['maps']} maps of {s['size']}x{s['size']} cells (baseline: numpy copy of the maps, {1000 * s['numpy_copy_s']:.1f} ms):"
        )
        for mode in ("logodds", "occupied_wins"):
            m = s[mode]
            lines.append(
                f"  {mode:<14} {m['seconds']:.3f} s  ({_fmt(m['ratio_to_copy'], '.0f')}x the copy)  global map {m['cells']} cells"
            )
    return "\n".join(lines)
