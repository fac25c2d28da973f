"""Figure 7 as the paper made it: global maps fused with and without compressed communication.

The paper measures its headline PSNR and SSIM on **global maps**: one robot (the receiver) fuses
its own exact map with the others' maps as they arrive, compressed and recovered, and that global
map is compared with the one fused from every robot's exact map, every period from the start of
mapping to the end. Here robot 0 is the receiver. At each of its snapshots, every other robot's
latest snapshot at that time is taken as sent (each codec's recovered copy, from Figure 8's
updates) and all are merged with the run's known frames (:func:`mapd.fusion.merge.merge`, log-odds);
PSNR and SSIM compare the two global maps (map_server grey levels, :mod:`mapd.codec.metrics`).
In a global map the receiver's own part and the cells it knows too are exact, which alone raises
PSNR over the per-robot figures of Figure 8a.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

from mapd.files import atomic_write_via

if TYPE_CHECKING:
    from pathlib import Path

    import numpy as np

    from mapd.bench.paper_data import Run
    from mapd.grid import OccupancyGrid

#: Recovered cells of each update: (robot, snapshot index) -> row -> cells (exact rows leave it out).
Recovered = dict[tuple[str, int], dict[str, "np.ndarray"]]


def _latest(snaps: list[tuple[float, OccupancyGrid]], t: float) -> int | None:
    """Index of the last snapshot at or before ``t``, or None."""
    found = None
    for k, (stamp, _) in enumerate(snaps):
        if stamp <= t:
            found = k
    return found


def fig7(run: Run, recovered: Recovered, rows: tuple[str, ...]) -> dict[str, Any]:
    """Per receiver snapshot: the exact global map's size and each row's PSNR/SSIM against it.

    Returns ``{"receiver", "steps": [{"t", "known", row: {"psnr", "ssim"}}], "global": {row: means}}``
    plus, under ``"maps"``, the exact and per-row global maps of every step (for the figure; not JSON).
    """
    from mapd.codec.metrics import psnr, ssim
    from mapd.fusion.merge import merge

    names = sorted(run.streams)
    receiver = names[0]
    steps: list[dict[str, Any]] = []
    maps: list[dict[str, OccupancyGrid]] = []
    resolution = run.global_map.resolution
    for stamp, _ in run.streams[receiver]:
        chosen = {r: _latest(run.streams[r], stamp) for r in names}
        present = [r for r in names if chosen[r] is not None]
        frames = [run.robot_frames.get(r) for r in present]
        exact_maps = [run.streams[r][chosen[r]][1] for r in present]  # type: ignore[index]
        exact = merge(exact_maps, frames, resolution=resolution)
        step: dict[str, Any] = {
            "t": stamp - run.t0,
            "robots": len(present),
            "known": int((exact.data >= 0).sum()),
        }
        step_maps = {"exact": exact}
        for row in rows:
            sent = []
            for r, g in zip(present, exact_maps, strict=True):
                cells = recovered.get((r, chosen[r]), {}).get(row)  # type: ignore[arg-type]
                sent.append(g if r == receiver or cells is None else g.replace(data=cells))
            fused = merge(sent, frames, resolution=resolution)
            if fused.data.shape != exact.data.shape:
                raise ValueError(f"fig 7: {row} global map is {fused.data.shape}, exact {exact.data.shape}")
            step[row] = {"psnr": psnr(exact.data, fused.data), "ssim": ssim(exact.data, fused.data)}
            step_maps[row] = fused
        steps.append(step)
        maps.append(step_maps)
    summary = {}
    for row in rows:
        ps = [s[row]["psnr"] for s in steps if math.isfinite(s[row]["psnr"])]
        ss = [s[row]["ssim"] for s in steps]
        summary[row] = {
            "psnr": sum(ps) / len(ps) if ps else math.inf,
            "ssim": sum(ss) / len(ss) if ss else math.nan,
            "exact_steps": sum(not math.isfinite(s[row]["psnr"]) for s in steps),
        }
    return {"receiver": receiver, "steps": steps, "global": summary, "maps": maps}


def figure(path: Path, fig7_result: dict[str, Any], lossy: str, columns: int = 6) -> None:
    """``fig7_global.png``: the global map without (top) and with ``lossy`` compression (bottom)."""
    from mapd.bench.paper_figures import _map_axes, _plt

    plt = _plt()
    maps = fig7_result["maps"]
    steps = fig7_result["steps"]
    n = len(maps)
    picks = sorted({round(i * (n - 1) / max(1, columns - 1)) for i in range(min(columns, n))})
    fig, axes = plt.subplots(2, len(picks), figsize=(max(7.0, 2.6 * len(picks)), 5.6), squeeze=False)
    for j, k in enumerate(picks):
        for i, key in enumerate(("exact", lossy)):
            ax = axes[i][j]
            _map_axes(ax, maps[k][key])
            title = f"t = {steps[k]['t']:.0f} s"
            if key != "exact":
                title += f"\n{steps[k][lossy]['psnr']:.1f} dB, SSIM {steps[k][lossy]['ssim']:.3f}"
            ax.set_title(title, fontsize=8)
        axes[0][0].set_ylabel("without compression", fontsize=9)
        axes[1][0].set_ylabel(f"with {lossy}", fontsize=9)
    fig.suptitle(
        f"Figure 7: global map at robot '{fig7_result['receiver']}' (own map exact, peers' maps as {lossy} "
        "recovers them)",
        fontsize=9,
    )
    fig.tight_layout()
    atomic_write_via(path, lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)
