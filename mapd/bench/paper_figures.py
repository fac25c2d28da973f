"""The figures of ``mapd bench paper``: Figure 8a, 8b and 9 equivalents, as PNG files (matplotlib, Agg).

Figure 7 (global maps fused with and without compression) is drawn by :mod:`mapd.bench.paper_global`.

Colours are the demo's (:data:`mapd.demo.report.COLOURS`), one per codec; line styles tell robots
apart. The paper's reported values are drawn as dotted reference lines where a figure has one.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mapd.demo.report import COLOURS
from mapd.files import atomic_write_via

if TYPE_CHECKING:
    from matplotlib.axes import Axes

    from mapd.grid import OccupancyGrid

STYLES = ("-", "--", ":", "-.")
FILES = ("fig8a_quality.png", "fig8b_bandwidth.png", "fig9_poses.png", "fig9_errors.png")


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _colour(i: int) -> np.ndarray:
    return COLOURS[i % len(COLOURS)] / 255.0


def _series(updates: list[dict[str, Any]], row: str, robot: str, key: str) -> tuple[np.ndarray, np.ndarray]:
    u = [r for r in updates if r["row"] == row and r["robot"] == robot]
    return np.array([r["t"] for r in u]), np.array([float(r[key]) for r in u])


def fig8a(path: Path, results: dict[str, Any], rows: tuple[str, ...]) -> None:
    """Compression ratio, PSNR and SSIM of every update, per codec and robot."""
    plt = _plt()
    updates = results["fig8"]["updates"]
    robots = sorted({r["robot"] for r in updates})
    paper = results["paper"]
    fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    for i, row in enumerate(rows):
        for j, robot in enumerate(robots):
            kw = {"color": _colour(i), "ls": STYLES[j % len(STYLES)], "marker": "o", "ms": 2.5}
            label = f"{row} ({robot})"
            t, ratio = _series(updates, row, robot, "ratio")
            axes[0].plot(t, ratio, label=label, **kw)
            t, psnr = _series(updates, row, robot, "psnr")
            if np.isfinite(psnr).any():
                axes[1].plot(t[np.isfinite(psnr)], psnr[np.isfinite(psnr)], label=label, **kw)
            t, ssim = _series(updates, row, robot, "ssim")
            axes[2].plot(t, ssim, label=label, **kw)
    axes[0].set_yscale("log")
    axes[0].set_ylabel("compression ratio\n(raw cells : bytes)")
    axes[0].set_title(f"Figure 8a equivalent: every map update of {results['source']}")
    axes[0].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[1].axhline(paper["psnr"], color="k", ls=":", label=f"paper, mean {paper['psnr']} dB")
    axes[1].set_ylabel("PSNR dB (lossy only;\nexact maps are inf)")
    axes[1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    axes[2].axhline(paper["ssim"], color="k", ls=":", label=f"paper, mean {paper['ssim']}")
    axes[2].set_ylabel("SSIM (7x7)")
    axes[2].set_xlabel(f"{results['run']['clock']} (s)")
    axes[2].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write_via(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def fig8b(path: Path, results: dict[str, Any], rows: tuple[str, ...]) -> None:
    """Bit/s per update beside the raw map's and the UWB budget; transfer and decode time per update."""
    plt = _plt()
    updates = results["fig8"]["updates"]
    summary = results["fig8"]["summary"]
    robots = sorted({r["robot"] for r in updates})
    paper = results["paper"]
    uwb = results["settings"]["uwb_bps"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 8))
    for j, robot in enumerate(robots):
        t, raw = _series(updates, rows[0], robot, "raw_bps")
        a1.plot(t, raw, color="0.4", ls=STYLES[j % len(STYLES)], label=f"raw cells ({robot})")
        for i, row in enumerate(rows):
            t, bps = _series(updates, row, robot, "bps")
            a1.plot(
                t,
                bps,
                color=_colour(i),
                ls=STYLES[j % len(STYLES)],
                marker="o",
                ms=2.5,
                label=f"{row} ({robot})",
            )
    a1.axhline(uwb, color="k", lw=1.5, label=f"UWB budget {uwb / 1000:g} kb/s")
    a1.axhline(paper["raw_bps"], color="0.4", ls=":", label=f"paper raw {paper['raw_bps'] / 1000:g} kb/s")
    a1.axhline(paper["bps"], color="k", ls=":", label=f"paper compressed {paper['bps']:g} bit/s")
    a1.set_yscale("log")
    a1.set_xlabel(f"{results['run']['clock']} (s)")
    a1.set_ylabel(f"bit/s for one update every {results['settings']['period_s']:g} s")
    a1.set_title("Figure 8b equivalent: bandwidth each robot needs")
    a1.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    a1.grid(alpha=0.3)
    x = np.arange(len(rows))
    by_row = {r["row"]: r for r in summary}
    transfer = [by_row[r]["transfer_s"] for r in rows]
    decode = [by_row[r]["dec_ms"] / 1000.0 for r in rows]
    b1 = a2.bar(
        x - 0.2, transfer, 0.4, color=[_colour(i) for i in range(len(rows))], label="transfer at 12.5 kb/s"
    )
    b2 = a2.bar(x + 0.2, decode, 0.4, color="0.6", label="decode (measured)")
    a2.bar_label(b1, fmt="%.2g s", fontsize=7)
    a2.bar_label(b2, fmt="%.2g s", fontsize=7)
    a2.set_xticks(x, rows)
    a2.set_yscale("log")
    a2.set_ylabel("seconds per update (mean)")
    a2.legend(fontsize=7)
    a2.grid(alpha=0.3, axis="y")
    fig.tight_layout()
    atomic_write_via(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def _map_axes(ax: Axes, grid: OccupancyGrid) -> None:
    x0, y0 = grid.origin.x, grid.origin.y
    extent = (x0, x0 + grid.width * grid.resolution, y0, y0 + grid.height * grid.resolution)
    ax.imshow(grid.to_image(), cmap="gray", vmin=0, vmax=255, extent=extent, interpolation="nearest")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def fig9_poses(path: Path, grid: OccupancyGrid, fig9: dict[str, Any], lossy: str) -> None:
    """The global map, the test poses, the perturbed starts and where the lossy map put each scan."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 9))
    _map_axes(ax, grid)
    truth = fig9["truth"]
    starts = np.array([[p["x"] + p["start_dx"], p["y"] + p["start_dy"]] for p in fig9["poses"]]).reshape(
        -1, 2
    )
    ax.quiver(
        truth[:, 0],
        truth[:, 1],
        np.cos(truth[:, 2]),
        np.sin(truth[:, 2]),
        color="tab:green",
        width=0.004,
        label=fig9["truth_label"],
    )
    ax.plot(starts[:, 0], starts[:, 1], "x", color="tab:orange", ms=5, label="perturbed start")
    for name, style in ((fig9["original"], "o"), (lossy, "+")):
        est = fig9["found"][name]
        ax.plot(est[:, 0], est[:, 1], style, mfc="none", ms=8, label=f"localized in {name} map")
    for j, (x, y) in enumerate(truth[:, :2]):
        ax.annotate(str(j), (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_title(f"Figure 9 equivalent: {len(truth)} test poses on the global map")
    ax.legend(fontsize=7, loc="best")
    fig.tight_layout()
    atomic_write_via(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def fig9_errors(path: Path, fig9: dict[str, Any], paper: dict[str, Any]) -> None:
    """Distributions of |x|, |y| and |yaw| errors per map, against the original map and the truth."""
    from mapd.bench.paper_localize import pose_errors

    plt = _plt()
    found, truth, original = fig9["found"], fig9["truth"], fig9["original"]
    groups: list[tuple[str, np.ndarray]] = []
    for name, est in found.items():
        if name != original:
            groups.append((f"{name}\nvs original", pose_errors(est, found[original])))
    for name, est in found.items():
        groups.append((f"{name}\nvs {fig9['truth_label']}", pose_errors(est, truth)))
    fig, axes = plt.subplots(3, 1, figsize=(10, 9), sharex=True)
    scale = (100.0, 100.0, math.degrees(1.0))
    refs = (paper["loc_x_cm"], paper["loc_y_cm"], paper["loc_yaw_deg"])
    for k, (ax, title) in enumerate(
        zip(axes, ("|x| error (cm)", "|y| error (cm)", "|yaw| error (deg)"), strict=True)
    ):
        data = [np.abs(err[:, k]) * scale[k] for _, err in groups]
        ax.boxplot(data, showmeans=True, whis=(0, 100))
        for i, d in enumerate(data):
            jitter = np.linspace(-0.15, 0.15, len(d)) if len(d) > 1 else np.zeros(len(d))
            ax.plot(i + 1 + jitter, d, ".", color="tab:blue", ms=3, alpha=0.6)
        ax.axhline(refs[k], color="k", ls=":", label=f"paper, mean {refs[k]}")
        ax.set_ylabel(title)
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3, axis="y")
    axes[-1].set_xticks(range(1, len(groups) + 1), [g for g, _ in groups], fontsize=7)
    axes[0].set_title(
        "Figure 9 equivalent: localization error per test pose (box: quartiles, range; triangle: mean)"
    )
    fig.tight_layout()
    atomic_write_via(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def write_all(
    out: Path,
    results: dict[str, Any],
    maps: dict[str, OccupancyGrid],
    fig9: dict[str, Any],
    rows: tuple[str, ...],
) -> list[Path]:
    """Draw every figure into ``out``; returns their paths (see :data:`FILES`)."""
    paths = [out / f for f in FILES]
    fig8a(paths[0], results, rows)
    fig8b(paths[1], results, rows)
    fig9_poses(paths[2], maps[fig9["original"]], fig9, rows[0])
    fig9_errors(paths[3], fig9, results["paper"])
    return paths
