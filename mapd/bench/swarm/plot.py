"""The swarm bench's picture (``--plot``): p95 staleness against range, or fleet size, beside the bound.

One line per combination of the real protocol's settings, and one dashed line per schedule of the
all-knowing bound (``--bound``): how far the protocol is from what the channel allows reads off
the gap between them. The x axis is the radio range when a run swept several (``--range 40 30
20``; *all in range* stands left of the longest), else the fleet size. With several seeds each
point is their mean and a bar spans the seeds' lowest to highest. ``--target`` draws the goal as a
horizontal line.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

from mapd.errors import ConfigError
from mapd.files import atomic_write_bytes

#: Colours per line of the real protocol, and per bound schedule (matplotlib's tab10 order).
_REAL = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2")
_BOUND = {"turns": "#7f7f7f", "one": "#ff7f0e", "reuse": "#bcbd22", "reach": "#17becf"}


def _x_axis(rows: list[dict[str, Any]]) -> tuple[str, list[Any]]:
    ranges = sorted({r["range_m"] for r in rows}, key=lambda v: -v)  # all in range (inf) first
    if len(ranges) > 1:
        return "range_m", ranges
    return "robots", sorted({r["robots"] for r in rows})


def _label(v: Any, key: str) -> str:
    if key == "range_m":
        return "all in range" if math.isinf(v) else f"{v:g}"
    return str(v)


def _points(
    rows: list[dict[str, Any]], key: str, xs: list[Any]
) -> tuple[list[int], list[float], list[float], list[float]]:
    """(x positions, means, lows, highs) of p95 in periods, over the rows' seeds at each x."""
    pos, mean, low, high = [], [], [], []
    for i, x in enumerate(xs):
        vals = [r["stale_p95_periods"] for r in rows if r[key] == x and r.get("seed") != "mean"]
        if not vals:
            continue
        pos.append(i)
        mean.append(sum(vals) / len(vals))
        low.append(min(vals))
        high.append(max(vals))
    return pos, mean, low, high


def plot(
    path: Path,
    rows: list[dict[str, Any]],
    bounds: list[dict[str, Any]],
    *,
    settings: tuple[str, ...],
    title: str,
    target: float | None = None,
) -> None:
    """Write the picture to ``path`` (PNG). ``rows`` and ``bounds`` are the bench's, seeds and means
    alike (means are recomputed from the seeds' rows); ``settings`` are the row keys that may tell
    two lines of the real protocol apart."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    key, xs = _x_axis(rows)
    keys = tuple(k for k in ("robots", *settings) if k != key)  # one line per fleet size too
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in keys), []).append(r)
    varying = [(i, k) for i, k in enumerate(keys) if len({g[i] for g in groups}) > 1]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for n, (setting, grows) in enumerate(groups.items()):
        pos, mean, low, high = _points(grows, key, xs)
        extra = ", ".join(f"{k} {_label(setting[i], k)}" for i, k in varying)
        err = [
            [m - lo for m, lo in zip(mean, low, strict=True)],
            [h - m for m, h in zip(mean, high, strict=True)],
        ]
        ax.errorbar(
            pos, mean, yerr=err, color=_REAL[n % len(_REAL)], marker="o", capsize=3, lw=2,
            label="real protocol" + (f" ({extra})" if extra else ""),
        )  # fmt: skip
    fleets = sorted({b["robots"] for b in bounds}) if key != "robots" else [None]
    for mode, colour in _BOUND.items():
        for fleet in fleets:
            brows = [b for b in bounds if b["senders"] == mode and fleet in (None, b["robots"])]
            pos, mean, _, _ = _points(brows, key, xs)
            if pos:
                more = f" ({fleet} robots)" if len(fleets) > 1 else ""
                ax.plot(pos, mean, "--", color=colour, marker=".", label=f"bound: {mode}{more}")
    if target is not None:
        ax.axhline(target, color="k", lw=1, ls=":", label=f"target: {target:g} periods")
    ax.set_xticks(range(len(xs)), [_label(x, key) for x in xs])
    ax.set_xlabel("radio range (m)" if key == "range_m" else "robots")
    ax.set_ylabel("p95 staleness (periods)")
    ax.set_ylim(bottom=0)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110)
    plt.close(fig)
    try:  # (the bench made the folder before its runs)
        atomic_write_bytes(path, png.getvalue())
    except OSError as exc:
        raise ConfigError(f"{path}: cannot write the plot: {exc.strerror or exc}") from None
