"""``report.md``, the data files and the terminal summary of ``mapd bench paper``.

The report puts the paper's reported numbers (:data:`PAPER`) beside this run's for each figure, and
states the command, the settings and the choices the evaluation makes.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Any

from mapd.errors import MapdError
from mapd.files import atomic_write_bytes
from mapd.grid import OccupancyGrid
from mapd.tables import dump_json, md_table, table

#: Rows of Figure 8, in order: the paper's codec, mapd's, mapd's as a delta stream, and zstd -19.
#: ``mapd bench paper`` measures these and every table and figure of the report shows them.
ROWS = ("paper", "lossless", "lossless+delta", "pooled+delta", "zstd-19")

#: What Zhang & Deng (Sensors 2024) report: Fig. 8a (mean PSNR, SSIM; "compression rate up to 99 %"),
#: Fig. 8b (bandwidth without and with compression, UWB budget) and Fig. 9 (28 poses, mean errors).
PAPER: dict[str, float] = {
    "psnr": 50.649,
    "ssim": 0.975,
    "max_rate": 0.99,
    "raw_bps": 124_700.0,
    "bps": 720.4,
    "uwb_bps": 12_500.0,
    "poses": 28,
    "loc_x_cm": 3.59,
    "loc_y_cm": 3.43,
    "loc_yaw_deg": 0.72,
}


def _pct(v: float) -> str:
    return f"{100 * v:.2f} %" if math.isfinite(v) else "-"


def _psnr(v: float) -> str:
    return "inf (exact)" if math.isinf(v) else f"{v:.2f}"


def _loc(row: dict[str, Any] | None) -> str:
    if not row:
        return "-"
    return f"{row['mean_x_cm']:.2f} / {row['mean_y_cm']:.2f} / {row['mean_yaw_deg']:.2f}"


def summary_rows(results: dict[str, Any]) -> list[dict[str, str]]:
    """The headline table: one line per claim, the paper's value and each codec's here."""
    s = {r["row"]: r for r in results["fig8"]["summary"]}
    g = results["fig7"]["global"]
    loc = {(r["map"], r["against"]): r for r in results["fig9"]["rows"]}
    truth = results["fig9"]["truth"]
    p = PAPER

    def line(what: str, paper: str, cell: Any) -> dict[str, str]:
        return {"what": what, "claim": paper, **{row: cell(row) for row in ROWS}}

    return [
        line(
            "global map: mean PSNR dB / SSIM (Fig. 7, the paper's measure)",
            f"{p['psnr']} / {p['ssim']}",
            lambda r: f"{_psnr(g[r]['psnr'])} / {g[r]['ssim']:.4f}",
        ),
        line("each robot's map: mean PSNR dB (Fig. 8a)", "-", lambda r: _psnr(s[r]["psnr"])),
        line("each robot's map: mean SSIM", "-", lambda r: f"{s[r]['ssim']:.4f}"),
        line(
            "occupied F1 / known cells changed", "-", lambda r: f"{s[r]['f1']:.3f} / {_pct(s[r]['changed'])}"
        ),
        line(
            "compression rate: all updates (best)",
            "up to 99 %",
            lambda r: f"{_pct(s[r]['rate'])} ({_pct(s[r]['max_rate'])})",
        ),
        line("compression ratio", "-", lambda r: f"{s[r]['ratio']:.1f}"),
        line(
            "bit/s per robot, mean (Fig. 8b)",
            f"{p['bps']:g} (raw {p['raw_bps'] / 1000:g} k)",
            lambda r: f"{s[r]['bps']:.0f} (raw {s[r]['raw_bps'] / 1000:.1f} k)",
        ),
        line(
            "fleet's share of 12.5 kb/s",
            f"{_pct(p['bps'] / p['uwb_bps'])} (one robot)",
            lambda r: _pct(s[r]["uwb_share"]),
        ),
        line(
            "transfer / decode per update",
            "-",
            lambda r: f"{s[r]['transfer_s']:.2f} s / {s[r]['dec_ms']:.3g} ms",
        ),
        line(
            "localization vs original map: mean abs x, y cm, yaw deg (Fig. 9)",
            f"{p['loc_x_cm']} / {p['loc_y_cm']} / {p['loc_yaw_deg']}",
            lambda r: _loc(loc.get((r, "original map"))),
        ),
        line(f"localization vs {truth}", "-", lambda r: _loc(loc.get((r, truth)))),
    ]


SUMMARY_COLS = [("what", "", ""), ("claim", "paper, as reported", "")] + [(r, r, "") for r in ROWS]

FIG8A_COLS = [
    ("row", "codec", ""),
    ("updates", "updates", ""),
    ("deltas", "deltas", ""),
    ("bytes", "bytes", ""),
    ("ratio", "ratio", ".1f"),
    ("rate", "rate", ".4f"),
    ("max_rate", "best rate", ".4f"),
    ("psnr", "mean PSNR dB", ".2f"),
    ("min_psnr", "min PSNR dB", ".2f"),
    ("ssim", "mean SSIM", ".4f"),
    ("f1", "occ. F1", ".4f"),
    ("changed", "changed", ".4f"),
    ("exact", "exact", ""),
]
FIG8B_COLS = [
    ("row", "codec", ""),
    ("raw_bps", "raw bit/s", ".0f"),
    ("bps", "bit/s", ".1f"),
    ("max_bps", "max bit/s", ".1f"),
    ("fleet_bps", "fleet bit/s", ".1f"),
    ("uwb_share", "of 12.5 kb/s", ".4f"),
    ("transfer_s", "transfer s", ".3f"),
    ("max_transfer_s", "max transfer s", ".3f"),
    ("enc_ms", "enc ms", ".1f"),
    ("dec_ms", "dec ms", ".1f"),
    ("max_dec_ms", "max dec ms", ".1f"),
    ("fits", "fits", ""),
]
GLOBAL_COLS = [
    ("row", "codec", ""),
    ("cells", "cells", ""),
    ("bytes", "bytes", ""),
    ("delta", "delta", ""),
    ("ratio", "ratio", ".1f"),
    ("psnr", "PSNR dB", ".2f"),
    ("ssim", "SSIM", ".4f"),
    ("f1", "occ. F1", ".4f"),
    ("changed", "changed", ".4f"),
]
FIG9_COLS = [
    ("map", "map", ""),
    ("against", "against", ""),
    ("poses", "poses", ""),
    ("mean_x_cm", "mean x cm", ".2f"),
    ("mean_y_cm", "mean y cm", ".2f"),
    ("mean_yaw_deg", "mean yaw deg", ".3f"),
    ("median_x_cm", "median x", ".2f"),
    ("median_y_cm", "median y", ".2f"),
    ("p95_x_cm", "p95 x", ".2f"),
    ("p95_y_cm", "p95 y", ".2f"),
    ("p95_yaw_deg", "p95 yaw", ".3f"),
    ("max_x_cm", "max x", ".2f"),
    ("max_y_cm", "max y", ".2f"),
    ("max_yaw_deg", "max yaw", ".3f"),
    ("score", "mean score", ".3f"),
]


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    fields: list[str] = list(dict.fromkeys(k for r in rows for k in r))
    text = io.StringIO(newline="")
    w = csv.DictWriter(text, fieldnames=fields)
    w.writeheader()
    w.writerows(rows)
    atomic_write_bytes(path, text.getvalue().encode())


def markdown(results: dict[str, Any], figures: list[Path]) -> str:
    """The whole report.md."""
    st, rn, f8 = results["settings"], results["run"], results["fig8"]
    ups = ", ".join(f"{n} {k}" for n, k in rn["updates_per_robot"].items())
    picked = results["fig9"]["picked"]
    few = f" (**fewer than the paper's {PAPER['poses']:g}**)" if picked < PAPER["poses"] else ""
    threads = f"OMP_NUM_THREADS={st['omp_num_threads'] or 'unset'}, torch threads {st['torch_threads']}"
    names = [f.name for f in figures]
    lines = [
        f"# `mapd bench paper`: {results['source']}",
        "",
        'The evaluation of Zhang & Deng, "Deep Compressed Communication and Application in Multi-Robot',
        '2D-Lidar SLAM: An Intelligent Huffman Algorithm" (Sensors 2024), Figures 7, 8a, 8b and 9, redone',
        "with mapd's implementation of their codec (`paper`, model in `models/`) beside mapd's own codecs.",
        "",
        f"Made by `{results['command']}`",
        f"(mapd {results['mapd']}, {results['date']}, {results['wall_s']:.0f} s wall on {os.cpu_count()} CPUs, {threads}).",
        "",
        f"Run: {st['robots']} robots, {rn['scans']} scans over {rn['log_seconds']:.0f} s of {rn['clock']}; one map update",
        f"per robot every {st['period_s']:g} s of {rn['clock']} ({ups} updates); global map {rn['global_map'][0]} x",
        f"{rn['global_map'][1]} cells at {st['resolution']:g} m ({rn['global_known_cells']} known cells);",
        f"{picked} test poses{few}, starts perturbed by up to {st['start_offset'][0]:g} m and",
        f"{st['start_offset'][1]:g} degrees (seed {st['seed']}).",
        "",
        "## Summary: the paper's numbers beside ours",
        "",
        md_table(summary_rows(results), SUMMARY_COLS),
        "",
        "Means are over every robot's updates. `lossless` and `zstd-19` are exact, so their PSNR is",
        "infinite and their SSIM 1; localization in their recovered maps equals localization in the",
        "original map (computed, not assumed).",
        "",
        "## Figure 7: the global map with and without compressed communication",
        "",
        "![Figure 7](fig7_global.png)",
        "",
        f"As the paper measures it: at each of robot `{results['fig7']['receiver']}`'s snapshots, its own exact map",
        "and every other robot's latest map as each codec recovers it are fused with the run's known",
        "frames, and compared with the global map fused from every exact map (PSNR and SSIM as",
        "below). The receiver's own part and the cells it knows too are exact, which alone raises",
        "PSNR over the per-robot figures of Figure 8a; that is the part of the gap the measure explains.",
        "",
        md_table(
            [
                {
                    "row": r,
                    "psnr": _psnr(v["psnr"]),
                    "ssim": f"{v['ssim']:.4f}",
                    "exact": str(v["exact_steps"]),
                }
                for r, v in results["fig7"]["global"].items()
            ],
            [
                ("row", "codec", ""),
                ("psnr", "mean PSNR dB", ""),
                ("ssim", "mean SSIM", ""),
                ("exact", "exact steps", ""),
            ],
        ),
        f"over {len(results['fig7']['steps'])} steps.",
        "",
        "## Figure 8a: compression and map quality per update",
        "",
        f"![Figure 8a]({names[0]})",
        "",
        md_table(f8["summary"], FIG8A_COLS),
        "",
        "Ratio = raw cells (one byte each) / bytes; rate = 1 - bytes / raw bytes (the paper's",
        '"compression rate"). PSNR and SSIM on map_server grey levels (free 254, occupied 0, unknown',
        "205), data range 255, SSIM with a 7x7 window; mean PSNR over the lossy updates. `changed` is",
        "the share of the original's known cells whose class differs after decoding. mapd payloads",
        "include mapd's header (about 118 bytes); the zstd row compresses the cells alone.",
        "",
        "The global map (every robot's scans in one frame, the map Figure 9 localizes in), coded once:",
        "",
        md_table(f8["global"], GLOBAL_COLS),
        "",
        "## Figure 8b: bandwidth on the 12.5 kb/s link",
        "",
        f"![Figure 8b]({names[1]})",
        "",
        md_table(f8["summary"], FIG8B_COLS),
        "",
        f"bit/s = 8 x bytes / {st['period_s']:g} s (one update per period and robot); fleet bit/s adds",
        "the robots' means, as they share one channel; transfer = 8 x bytes / 12.5 kb/s; decode is the",
        "measured wall time on this machine. `fits`: the fleet's mean rate is under 12.5 kb/s and the",
        "largest update goes over the link within one period.",
        "",
        "## Figure 9: localization in the recovered maps",
        "",
        f"![Figure 9 poses]({names[2]})",
        "",
        f"![Figure 9 errors]({names[3]})",
        "",
        md_table(results["fig9"]["rows"], FIG9_COLS),
        "",
        "Errors are absolute, x and y in the global map's axes. \"vs original map\" is the paper's",
        "comparison: the same scan from the same start, localized in the recovered map and in the",
        'original one. "vs corrected pose" compares with the log\'s SLAM-corrected pose, "vs true',
        "pose\" with the simulator's.",
        "",
        "## Choices",
        "",
        "- **Maps on the link (Fig. 8):** each robot's own map, in its own frame, every period of log",
        "  time, as a `mapd run` daemon would send it. On a log, robot i of N replays an overlapping",
        "  slice (`mapd.mapping.replay.split_range`, 20 % overlap); on the sim, N robots share one building.",
        "  `lossless+delta` codes each update against the robot's previous one (the first goes whole);",
        "  `pooled+delta` likewise with mapd's lossy `pooled` codec (2 x 2 blocks, an occupied cell wins).",
        "- **Global map (Fig. 9):** every robot's scans mapped in one frame with the known (corrected or",
        "  simulated) poses, which is the fleet's global map when every update arrives exactly, without",
        "  a merge's resampling. Each codec codes it whole (the `+delta` rows against the global map one",
        "  period earlier) and the scans are localized in what comes back.",
        "- **Test poses:** farthest-point sampling over the positions of the run's own scans that",
        "  return at least half their beams; the scans were also used to build the map, as in the paper.",
        "- **Matcher:** `mapd.mapping.localize.ScanMatcher` (correlative, likelihood field, coarse to fine to",
        "  about 2 mm and 0.05 degrees), search window 0.4 m and 12 degrees around the start.",
        "- **Timing:** wall clock of one call on this (shared) machine; each codec is warmed up first.",
        "",
        "## Data",
        "",
        "`results.json` (everything above), `updates.csv` (one row per update and codec), `poses.csv`",
        "(one row per test pose: truth, start offset, the pose found in each map and its score).",
        "",
    ]
    return "\n".join(lines)


def write(
    out: Path,
    results: dict[str, Any],
    maps: dict[str, OccupancyGrid],
    fig9: dict[str, Any],
    global7: dict[str, Any],
) -> None:
    """Write results.json, updates.csv, poses.csv, the figures (Figure 7's from ``global7``, see
    :func:`mapd.bench.paper_global.fig7`) and report.md into ``out``."""
    from mapd.bench import paper_figures, paper_global

    try:
        # Each file whole or as it was: a run stopped mid-write left the last run's results cut short.
        atomic_write_bytes(out / "results.json", dump_json(results).encode())
        _write_csv(out / "updates.csv", results["fig8"]["updates"])
        _write_csv(out / "poses.csv", results["fig9"]["poses"])
        figures = paper_figures.write_all(out, results, maps, fig9, ROWS)
        # Inside the try, like every other file: a folder in its way is one error line.
        paper_global.figure(out / "fig7_global.png", global7, ROWS[0])
        atomic_write_bytes(out / "report.md", markdown(results, figures).encode())
    except OSError as exc:
        where = exc.filename or out  # the file in the way, where the error names one
        raise MapdError(f"{where}: cannot write the report: {exc.strerror or exc}") from None


def text_summary(results: dict[str, Any]) -> str:
    """What the terminal shows: the headline table and Figure 9's rows."""
    loc_cols = [
        c
        for c in FIG9_COLS
        if c[0]
        in ("map", "against", "poses", "mean_x_cm", "mean_y_cm", "mean_yaw_deg", "max_x_cm", "max_y_cm")
    ]
    return "\n".join(
        [
            f"{results['source']}: {results['command']}",
            "",
            table(
                summary_rows(results), [("what", "", ""), ("claim", "paper", "")] + [(r, r, "") for r in ROWS]
            ),
            "",
            table(results["fig9"]["rows"], loc_cols),
        ]
    )
