"""Codec benchmark: size, speed and map quality of each codec on real maps, beside zstd -19 and brotli -11.

Ratio is cells / payload bytes (a raw nav_msgs cell is one byte). Payload bytes include mapd's
self-describing header; the baseline rows compress the raw cells alone. PSNR and SSIM are on the
map_server grey-level image (free 254, occupied 0, unknown 205; data range 255; SSIM 7x7 window)
over the whole grid. F1 is over occupied cells; "changed" is the share of known cells whose class
changes. Timings are wall-clock ms of one call (best of --repeat), all measured in this run.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import Any

from mapd import plugins
from mapd.bench.common import MAX_REPEAT, int_arg
from mapd.tables import emit, table

HELP = "codec size, speed and quality on the shared maps, beside zstd -19 and brotli -11"
BASELINES = ("zstd-19", "brotli-11")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--codec",
        nargs="+",
        type=plugins.name_type("codec", BASELINES),
        default=None,
        metavar="NAME",
        help="codecs to measure (default: every installed one)",
    )
    p.add_argument("--maps", type=Path, default=None, help="folder of map_server maps (default: shared data)")
    p.add_argument("--limit", type=int_arg(1), default=None, help="only the first N maps")
    p.add_argument(
        "--repeat",
        type=int_arg(1, MAX_REPEAT),
        default=1,
        help="time each call this many times, keep the best",
    )
    p.add_argument("--summary", action="store_true", help="print only the aggregate table")


def _baseline(name: str, cells: bytes) -> tuple[bytes, Any, Any]:
    if name == "zstd-19":
        import zstandard

        c = zstandard.ZstdCompressor(level=19)
        return c.compress(cells), (lambda: c.compress(cells)), zstandard.ZstdDecompressor().decompress
    import brotli

    return brotli.compress(cells, quality=11), (lambda: brotli.compress(cells, quality=11)), brotli.decompress


def _measure(name: str, label: str, grid: Any, repeat: int) -> dict[str, Any]:
    import numpy as np

    from mapd.bench.common import quality, timed
    from mapd.codec import decode, encode, get_codec

    row: dict[str, Any] = {"codec": name, "map": label, "cells": grid.cells}
    if name in BASELINES:
        cells = np.ascontiguousarray(grid.data).tobytes()
        payload, enc, dec = _baseline(name, cells)
        _, row["enc_ms"] = timed(enc, repeat)
        out, row["dec_ms"] = timed(lambda: dec(payload), repeat)
        exact = out == cells
        recovered = grid.data if exact else np.frombuffer(out, np.int8).reshape(grid.data.shape)
    else:
        codec = get_codec(name)
        payload, row["enc_ms"] = timed(lambda: encode(grid, name), repeat)
        stage = dict(getattr(codec, "last_timings", {}) or {})
        back, row["dec_ms"] = timed(lambda: decode(payload), repeat)
        stage.update(getattr(codec, "last_timings", {}) or {})
        row.update({k: float(v) for k, v in stage.items()})
        recovered = back.data
        exact = bool(np.array_equal(recovered, grid.data))
    row["bytes"] = len(payload)
    row["ratio"] = grid.cells / len(payload)
    row["bpc"] = 8.0 * len(payload) / grid.cells
    row.update(quality(grid.data, recovered, exact), exact=exact)
    return row


def _aggregate(rows: list[dict[str, Any]], codec: str, zstd_total: int, largest: str) -> dict[str, Any]:
    mine = [r for r in rows if r["codec"] == codec]
    cells = sum(r["cells"] for r in mine)
    nbytes = sum(r["bytes"] for r in mine)
    finite = [r["psnr"] for r in mine if math.isfinite(r["psnr"])]
    agg: dict[str, Any] = {
        "codec": codec,
        "maps": len(mine),
        "cells": cells,
        "bytes": nbytes,
        "ratio": cells / nbytes,
        "vs_zstd": (cells / nbytes) / (cells / zstd_total) if zstd_total else math.nan,
        "bpc": 8.0 * nbytes / cells,
        "enc_ms": sum(r["enc_ms"] for r in mine) / len(mine),
        "dec_ms": sum(r["dec_ms"] for r in mine) / len(mine),
        "psnr": (sum(finite) / len(finite)) if finite else math.inf,
        "ssim": sum(r["ssim"] for r in mine) / len(mine),
        "f1": sum(r["f1"] for r in mine) / len(mine),
        "changed": sum(r["changed"] for r in mine) / len(mine),
        "exact": all(r["exact"] for r in mine),
    }
    big = next((r for r in mine if r["map"] == largest), None)
    zbig = next((r for r in rows if r["codec"] == "zstd-19" and r["map"] == largest), None)
    if big and zbig:
        agg["largest_enc_vs_zstd_enc"] = big["enc_ms"] / zbig["enc_ms"]
        agg["largest_dec_vs_zstd_enc"] = big["dec_ms"] / zbig["enc_ms"]
    for k in sorted({k for r in mine for k in r if k.endswith("_ms") and k not in ("enc_ms", "dec_ms")}):
        agg[k] = sum(r.get(k, 0.0) for r in mine) / len(mine)
    return agg


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from mapd import plugins
    from mapd.bench.common import input_maps
    from mapd.errors import MapdError

    codecs = args.codec or plugins.names("codec")
    usable = []
    for name in codecs:
        if name in BASELINES:
            continue
        try:
            plugins.load("codec", name)
            usable.append(name)
        except MapdError as exc:
            if args.codec:
                raise
            print(f"note: skipping codec {name}: {exc}", file=sys.stderr)
    from mapd.codec.api import warm_up

    for name in usable:
        warm_up(name)  # one-time costs (numba's compile, the model's load) stay out of the timings
    order = [*usable, *BASELINES]
    rows: list[dict[str, Any]] = []
    maps = list(input_maps(args.maps, args.limit))
    largest = max(maps, key=lambda m: m[1].cells)[0]
    for label, grid in tqdm(maps, desc="maps", unit="map", file=sys.stderr, disable=None):
        for name in order:
            rows.append(_measure(name, label, grid, args.repeat))
    zstd_total = sum(r["bytes"] for r in rows if r["codec"] == "zstd-19")
    summary = [_aggregate(rows, name, zstd_total, largest) for name in order]
    doc = {"maps": len(maps), "largest": largest, "rows": rows, "aggregate": summary}
    emit(doc, args.json, lambda: _text(rows, summary, largest, len(maps), per_map=not args.summary))
    return 0


def _text(
    rows: list[dict[str, Any]], summary: list[dict[str, Any]], largest: str, maps: int, *, per_map: bool
) -> str:
    """The terminal's tables: every (map, codec) row unless only the summary is asked for, then the
    aggregate per codec."""
    map_cols = [
        ("map", "map", ""),
        ("codec", "codec", ""),
        ("cells", "cells", ""),
        ("bytes", "bytes", ""),
        ("ratio", "ratio", ".1f"),
        ("bpc", "bits/cell", ".4f"),
        ("enc_ms", "enc ms", ".1f"),
        ("dec_ms", "dec ms", ".1f"),
        ("psnr", "PSNR dB", ".2f"),
        ("ssim", "SSIM", ".4f"),
        ("f1", "occ F1", ".4f"),
        ("changed", "changed", ".4f"),
    ]
    extra = sorted({k for r in rows for k in r if k.endswith("_ms") and k not in ("enc_ms", "dec_ms")})
    map_cols += [(k, k.replace("_ms", " ms"), ".1f") for k in extra]
    agg_cols = [
        ("codec", "codec", ""),
        ("maps", "maps", ""),
        ("cells", "cells", ""),
        ("bytes", "bytes", ""),
        ("ratio", "ratio", ".1f"),
        ("vs_zstd", "x zstd-19", ".2f"),
        ("bpc", "bits/cell", ".4f"),
        ("enc_ms", "mean enc ms", ".1f"),
        ("dec_ms", "mean dec ms", ".1f"),
        ("largest_enc_vs_zstd_enc", "largest: enc/zstd enc", ".2f"),
        ("largest_dec_vs_zstd_enc", "largest: dec/zstd enc", ".2f"),
        ("psnr", "PSNR dB", ".2f"),
        ("ssim", "SSIM", ".4f"),
        ("f1", "occ F1", ".4f"),
        ("changed", "changed", ".4f"),
    ]
    agg_cols += [(k, k.replace("_ms", " ms"), ".1f") for k in extra]
    lines = [table(rows, map_cols), ""] if per_map else []
    lines.append(f"aggregate over {maps} maps (ratio = total cells / total bytes; largest map: {largest})")
    lines.append(table(summary, agg_cols))
    return "\n".join(lines)
