"""Score model folders on held-out maps in the making and held-out finished maps.

``python -m mapd.train.heldout MODEL_DIR [MODEL_DIR ...] [--log LOG] [--maps DIR] [--json FILE]``

* **Growing maps**: the held-out log replayed exactly as ``mapd bench paper`` replays it for
  Figure 8a: ``--robots`` robots (default 2, overlapping slices of the log), each robot's map a
  snapshot every ``--period`` seconds of log time (default 30) in its own frame. So paper-v3 scores
  here what the benchmark reports per robot (29.11 dB on the Intel log). The snapshots are cached
  like the training snapshots (:mod:`mapd.train.snapshots`).
* **Finished maps**: the validation split of ``mapd train`` (by place, ``--val-fraction`` 0.2) over
  ``--maps``, the maps no recipe trains on.

Both through the real codec API, with the card's metrics (:func:`mapd.train.card.summarize`):
ratio (cells / payload bytes), mean PSNR over maps (finite values), mean SSIM, occupied F1, changed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

from mapd.errors import MapdError
from mapd.grid import OccupancyGrid
from mapd.train.card import evaluate_grids, evaluate_maps, summarize
from mapd.train.data import split_maps
from mapd.train.snapshots import _cached, _file_sha256, check_cache, default_cache


def growing_maps(
    log: Path, *, robots: int = 2, period: float = 30.0, resolution: float = 0.05, cache: Path | None = None
) -> list[tuple[str, OccupancyGrid]]:
    """Every robot's map stream of ``log`` as ``mapd bench paper`` replays it (Figure 8a's updates)."""
    from mapd.mapping import replay

    out: list[tuple[str, OccupancyGrid]] = []
    sha = _file_sha256(log)
    for i in range(robots):
        key = {"v": 1, "kind": "bench", "sha256": sha, "robots": robots, "index": i, "period": period}
        key["res"] = resolution

        def make(i: int = i) -> list[OccupancyGrid]:
            snaps = replay.replay_log(
                log, every_s=period, resolution=resolution, robots=robots, index=i, robot=f"robot{i}"
            )
            return [g for _, g in snaps]

        label = f"{log.name.split('.')[0]}-robot{i}of{robots}"
        grids, _ = _cached("log", label, key, cache or default_cache(), make)
        out += [(f"robot{i}/{k + 1:03d}", g) for k, g in enumerate(grids)]
    return out


def held_out_finished(maps: Path, val_fraction: float = 0.2) -> tuple[list[Path], Path]:
    """The validation split of ``mapd train`` over ``maps`` (and the root labels are relative to)."""
    from mapd.data import shared_maps

    paths = shared_maps(maps)
    root = maps / "maps" if (maps / "maps").is_dir() else maps
    return split_maps(paths, val_fraction)[1], root


def score(
    model_dir: Path, growing: list[tuple[str, OccupancyGrid]], finished: list[Path], root: Path
) -> dict[str, Any]:
    """One model on both sets: the card's summary of each, and the seconds it took."""
    t0 = time.perf_counter()
    g = summarize(evaluate_grids(model_dir, growing))
    f = summarize(evaluate_maps(model_dir, finished, root))
    return {"model": str(model_dir), "growing": g, "finished": f, "seconds": time.perf_counter() - t0}


def table(results: list[dict[str, Any]]) -> str:
    """A markdown table: per model, ratio / PSNR / SSIM / F1 / changed on both sets."""
    head = (
        "| model | growing: ratio | PSNR dB | SSIM | F1 | changed | finished: ratio | PSNR dB | SSIM | F1 |"
        " changed |\n|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    rows = [head]
    for r in results:
        cells = [Path(r["model"]).name]
        for key in ("growing", "finished"):
            s = r[key]
            cells += [
                f"{s['ratio']:.1f}",
                f"{s['psnr_mean']:.2f}",
                f"{s['ssim_mean']:.4f}",
                f"{s['f1_mean']:.4f}",
                f"{s['changed_mean']:.4f}",
            ]
        rows.append("| " + " | ".join(cells) + " |")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    from mapd.data import data_dir, shared_log

    p = argparse.ArgumentParser(prog="python -m mapd.train.heldout", description=__doc__.split("\n\n")[0])
    p.add_argument("models", type=Path, nargs="+", help="model folders (weights.npz + model.json)")
    p.add_argument(
        "--log", type=Path, default=None, help="held-out CARMEN log (default: the shared intel log)"
    )
    p.add_argument("--maps", type=Path, default=None, help="finished maps (default: the shared maps)")
    p.add_argument("--robots", type=int, default=2, help="robots sharing the log (default 2, as bench paper)")
    p.add_argument("--period", type=float, default=30.0, help="seconds of log time between maps (30)")
    p.add_argument("--val-fraction", type=float, default=0.2, help="as mapd train (default 0.2)")
    p.add_argument("--cache", type=Path, default=None, help="snapshot cache (default ~/.cache/mapd)")
    p.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = p.parse_args(argv)
    log = args.log or shared_log("intel")
    base = data_dir()
    maps = args.maps or (base / "maps" if base else None)
    if log is None or maps is None:
        print("no --log/--maps given and no shared data found (set MAPD_DATA)", file=sys.stderr)
        return 2
    try:
        check_cache(args.cache)  # before the replay, not after it
    except MapdError as exc:
        print(exc, file=sys.stderr)
        return 2
    growing = growing_maps(log, robots=args.robots, period=args.period, cache=args.cache)
    finished, root = held_out_finished(maps, args.val_fraction)
    print(
        f"growing: {len(growing)} maps of {log.name}; finished: {len(finished)} held-out maps",
        file=sys.stderr,
    )
    results = []
    for m in args.models:
        results.append(score(m, growing, finished, root))
        print(f"{m}: {results[-1]['seconds']:.0f} s", file=sys.stderr)
    print(table(results))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2, default=str) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
