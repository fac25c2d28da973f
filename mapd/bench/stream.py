"""Map-stream benchmark: what it costs to send every version of a growing map, whole or as deltas.

A CARMEN log is replayed through the log-odds mapper (:func:`mapd.mapping.replay.replay_log`) and a
snapshot is taken every ``--every`` scans. Each snapshot is encoded with each codec twice: as a
whole map, and against the previous snapshot as base (``encode(grid, codec, base=prev)``; the codec
decides whether the delta pays, so "delta" rows may hold some whole maps, counted in "deltas"). The
first snapshot has no base and is sent whole in every row. Every payload is decoded again and
checked cell for cell (column "exact"): against the snapshot for lossless codecs, against the
codec's own rendering of it (``held``) for lossy codecs that take a base, such as ``pooled``;
lossy codecs without a base are not checked.

Baselines, in the same run: zstd -19 of each snapshot's raw int8 cells, and zstd -19 of the
cell-wise difference between consecutive snapshots. The difference is taken on the new snapshot's
extent: the previous snapshot is placed by its origin (the mapper keeps origins on one cell
lattice), cells it does not cover count as unknown (-1), and new minus old is stored as int8
(wrapping). Where two snapshots cannot be aligned cell for cell, the baseline sends the whole map.

Ratio is total raw cells (one byte each) over total bytes; bit/s spreads the bytes over the log's own
duration (first scan to last snapshot) and is compared with the paper's UWB budget of 12.5 kb/s.
Payload bytes include mapd's header; the zstd rows compress cells alone. Times are wall-clock ms per
payload (mean); each codec is warmed up on a tiny grid first, so one-time JIT loading is not counted.
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mapd.bench.common import UWB_BPS, int_arg, resolution_arg, timed
from mapd.tables import emit, table

if TYPE_CHECKING:
    import numpy as np

    from mapd.grid import OccupancyGrid

HELP = "replay a log: whole and delta payloads per snapshot, beside zstd -19 of snapshots and differences"
#: The terminal's table.
COLUMNS = [
    ("row", "payloads", ""),
    ("snapshots", "snapshots", ""),
    ("deltas", "deltas", ""),
    ("bytes", "bytes", ""),
    ("ratio", "ratio", ".1f"),
    ("mean_bytes", "mean B", ".0f"),
    ("max_bytes", "max B", ""),
    ("bps", "bit/s", ".1f"),
    ("uwb_share", "of 12.5 kb/s", ".2%"),  # (the JSON keeps the fraction)
    ("vs_zstd_diff", "x zstd-19 diff", ".2f"),
    ("enc_ms", "enc ms", ".1f"),
    ("dec_ms", "dec ms", ".1f"),
    ("exact", "exact", ""),
]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", type=Path, default=None, help="CARMEN log (default: the shared intel log)")
    p.add_argument("--every", type=int_arg(1), default=10, help="take a snapshot every N scans (default 10)")
    p.add_argument("--codec", nargs="+", default=["lossless"], metavar="NAME", help="codecs to measure")
    p.add_argument(
        "--resolution", type=resolution_arg, default=0.05, help="map resolution in m (default 0.05)"
    )
    p.add_argument("--limit", type=int_arg(1), default=None, help="stop after N snapshots (quick runs)")


def _aligned_previous(prev: OccupancyGrid, grid: OccupancyGrid) -> np.ndarray | None:
    """``prev``'s cells on ``grid``'s extent (unknown where ``prev`` has none), or None if unaligned."""
    import numpy as np

    from mapd.codec.lossless import alignment

    off = alignment(grid.resolution, grid.origin, prev)
    if off is None:
        return None
    off_r, off_c = off
    out = np.full(grid.data.shape, -1, dtype=np.int8)
    r0, c0 = max(0, -off_r), max(0, -off_c)
    r1 = min(grid.height, prev.height - off_r)
    c1 = min(grid.width, prev.width - off_c)
    if r1 > r0 and c1 > c0:
        out[r0:r1, c0:c1] = prev.data[r0 + off_r : r1 + off_r, c0 + off_c : c1 + off_c]
    return out


class _Row:
    """Running totals of one row of the table."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.count = 0
        self.deltas = 0
        self.bytes = 0
        self.max_bytes = 0
        self.enc_ms = 0.0
        self.dec_ms = 0.0
        self.exact = True

    def add(
        self, nbytes: int, enc_ms: float, dec_ms: float, *, delta: bool = False, exact: bool = True
    ) -> None:
        self.count += 1
        self.deltas += int(delta)
        self.bytes += nbytes
        self.max_bytes = max(self.max_bytes, nbytes)
        self.enc_ms += enc_ms
        self.dec_ms += dec_ms
        self.exact = self.exact and exact

    def result(self, cells: int, duration: float, zstd_diff_bytes: int) -> dict[str, Any]:
        bps = 8.0 * self.bytes / duration if duration > 0 else float("inf")
        return {
            "row": self.name,
            "snapshots": self.count,
            "deltas": self.deltas,
            "bytes": self.bytes,
            "ratio": cells / self.bytes if self.bytes else float("inf"),
            "mean_bytes": self.bytes / max(1, self.count),
            "max_bytes": self.max_bytes,
            "bps": bps,
            "uwb_share": bps / UWB_BPS,
            "vs_zstd_diff": zstd_diff_bytes / self.bytes if self.bytes else float("inf"),
            "enc_ms": self.enc_ms / max(1, self.count),
            "dec_ms": self.dec_ms / max(1, self.count),
            "exact": self.exact,
        }


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import zstandard

    from mapd.codec import decode, encode, get_codec, read_header
    from mapd.codec.api import warm_up
    from mapd.data import shared_log
    from mapd.errors import SourceError
    from mapd.mapping import replay

    log = args.log if args.log is not None else shared_log("intel")
    if log is None:
        raise SourceError("no log given and no shared intel log found (set MAPD_DATA or pass --log)")
    first = next(iter(replay.replay_scans(log)), None)
    if first is None:
        raise SourceError(f"{log}: no laser scans")
    codecs = list(dict.fromkeys(args.codec))
    impls = {name: get_codec(name) for name in codecs}
    for name in codecs:  # one-time costs (JIT cache loading, model files) stay out of the timings
        warm_up(name)
    rows: dict[str, _Row] = {}
    for name in codecs:
        rows[f"{name} whole"] = _Row(f"{name} whole")
        rows[f"{name} delta"] = _Row(f"{name} delta")
    rows["zstd-19 whole"] = _Row("zstd-19 whole")
    rows["zstd-19 diff"] = _Row("zstd-19 diff")
    zc = zstandard.ZstdCompressor(level=19)
    zd = zstandard.ZstdDecompressor()
    cells = 0
    last_stamp = first.stamp
    prev: OccupancyGrid | None = None
    snaps = replay.replay_log(log, every=args.every, resolution=args.resolution)
    for n, (stamp, grid) in enumerate(snaps):
        if args.limit is not None and n >= args.limit:
            break
        last_stamp = stamp
        cells += grid.cells
        for name in codecs:
            impl = impls[name]
            pairs: tuple[tuple[str, OccupancyGrid | None], ...] = (("whole", None), ("delta", prev))
            for kind, base in pairs:
                payload, enc_ms = timed(partial(encode, grid, name, base=base))
                back, dec_ms = timed(partial(decode, payload, base=base))
                # What the sender holds the receiver must get: the map itself, or a lossy codec's
                # own rendering of it when that depends on the map alone (``uses_base``).
                exact = back.same_map(impl.held(grid)) if impl.lossless or impl.uses_base else True
                is_delta = read_header(payload).delta
                rows[f"{name} {kind}"].add(len(payload), enc_ms, dec_ms, delta=is_delta, exact=exact)
        raw = np.ascontiguousarray(grid.data).tobytes()
        z, enc_ms = timed(partial(zc.compress, raw))
        _, dec_ms = timed(partial(zd.decompress, z))
        rows["zstd-19 whole"].add(len(z), enc_ms, dec_ms)
        old = _aligned_previous(prev, grid) if prev is not None else None
        if old is None:
            rows["zstd-19 diff"].add(len(z), enc_ms, dec_ms)
        else:
            diff = (grid.data.astype(np.int16) - old).astype(np.int8).tobytes()
            zdiff, enc_ms = timed(partial(zc.compress, diff))
            _, dec_ms = timed(partial(zd.decompress, zdiff))
            rows["zstd-19 diff"].add(len(zdiff), enc_ms, dec_ms, delta=True)
        prev = grid
        print(f"\rsnapshot {n + 1}", end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    if prev is None:
        raise SourceError(f"{log}: the replay gave no snapshot")
    duration = last_stamp - first.stamp
    zdiff_bytes = rows["zstd-19 diff"].bytes
    results = [r.result(cells, duration, zdiff_bytes) for r in rows.values()]
    info = {
        "log": str(log),
        "every": args.every,
        "snapshots": rows["zstd-19 whole"].count,
        "duration_s": duration,
        "raw_cells": cells,
        "uwb_bps": UWB_BPS,
        "last_map": [prev.height, prev.width],
    }
    last = prev
    emit({**info, "rows": results}, args.json, lambda: _text(log, info, last, results))
    return 0


def _text(log: Path, info: dict[str, Any], last: OccupancyGrid, results: list[dict[str, Any]]) -> str:
    """The terminal's table, one row per kind of payload, under a line about the replay."""
    head = (
        f"{log.name}: {info['snapshots']} snapshots every {info['every']} scans over "
        f"{info['duration_s']:.0f} s of log, {info['raw_cells']} raw cells in all, last map "
        f"{last.width}x{last.height}"
    )
    return f"{head}\n{table(results, COLUMNS)}"
