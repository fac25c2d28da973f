"""The demo's outputs: global_map.png, bandwidth.png, quality.png, metrics.csv and a summary table."""

from __future__ import annotations

import argparse
import csv
import io
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from mapd.daemon.versions import label, split
from mapd.errors import MapdError
from mapd.files import atomic_write_bytes, atomic_write_via
from mapd.fusion.store import read_owner
from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map
from mapd.grid.save import save_map
from mapd.tables import table

UWB_RATE = 12500
COLOURS = np.array(
    [
        [31, 119, 180],
        [214, 39, 40],
        [44, 160, 44],
        [255, 127, 14],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [23, 190, 207],
    ],
    dtype=np.float64,
)


def _updates(state: Path) -> list[dict[str, Any]]:
    path = state / "updates.csv"
    if not path.exists():
        return []
    rows = []
    with open(path, newline="") as fh:
        for r in csv.DictReader(fh):
            row: dict[str, Any] = dict(r)
            for k in ("time", "ratio", "encode_ms", "psnr", "ssim"):
                row[k] = float(r[k]) if r.get(k) not in (None, "") else float("nan")
            for k in ("version", "cells", "bytes"):
                row[k] = int(r[k])
            rows.append(row)
    return rows


def coloured_global(global_map: OccupancyGrid, contributions: np.ndarray | None) -> np.ndarray:
    """RGB image of the global map: free white, unknown grey, occupied dark, tinted by robot."""
    d = np.flipud(global_map.data)
    img = np.full((*d.shape, 3), 205.0)
    img[(d >= 0) & (d < 65)] = 250.0
    img[d >= 65] = 30.0
    if contributions is not None and contributions.shape == global_map.data.shape:
        who = np.flipud(contributions)
        for r in range(int(who.max(initial=-1)) + 1):
            m = (who == r) & (d >= 0)
            tint = COLOURS[r % len(COLOURS)]
            img[m] = 0.55 * img[m] + 0.45 * tint
    return img.astype(np.uint8)


def mark_robots(
    img: np.ndarray, global_map: OccupancyGrid, positions: dict[str, list[float]], names: list[str]
) -> np.ndarray:
    """``img`` (from :func:`coloured_global`) with each robot drawn where it is: a disc in its colour
    with a dark rim and a line along its heading. ``positions`` are [x, y, yaw] in the fleet frame."""
    from PIL import Image, ImageDraw

    pic = Image.fromarray(img)
    draw = ImageDraw.Draw(pic)
    o, res, h = global_map.origin, global_map.resolution, img.shape[0]
    r = max(4, min(img.shape[:2]) // 60)
    for robot, (x, y, yaw) in positions.items():
        # the global map's origin has no rotation (fusion builds it axis-aligned); rows are flipped
        col, row = (x - o.x) / res, h - 1 - (y - o.y) / res
        tint = tuple(int(v) for v in COLOURS[(names.index(robot) if robot in names else 0) % len(COLOURS)])
        draw.ellipse((col - r, row - r, col + r, row + r), fill=tint, outline=(20, 20, 20), width=2)
        draw.line(
            (col, row, col + 2 * r * math.cos(yaw), row - 2 * r * math.sin(yaw)), fill=(20, 20, 20), width=2
        )
    return np.asarray(pic)


def with_legend(img: np.ndarray, names: list[str]) -> np.ndarray:
    """``img`` with a strip below it naming each robot's tint, so the picture reads without the docs."""
    from PIL import Image, ImageDraw, ImageFont

    font = ImageFont.load_default()
    row_h = 16
    strip = Image.new("RGB", (img.shape[1], row_h * ((len(names) + 3) // 4) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(strip)
    col_w = max(1, img.shape[1] // 4)
    for i, name in enumerate(names):
        x, y = (i % 4) * col_w + 4, (i // 4) * row_h + 3
        tint = 0.55 * 250.0 + 0.45 * COLOURS[i % len(COLOURS)]  # a free cell of this robot
        draw.rectangle((x, y, x + 10, y + 10), fill=tuple(int(v) for v in tint), outline=(30, 30, 30))
        draw.text((x + 14, y - 1), name, fill=(0, 0, 0), font=font)
    return np.concatenate([img, np.asarray(strip)], axis=0)


def _plots(out: Path, series: dict[str, list[dict[str, Any]]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = min((rows[0]["time"] for rows in series.values() if rows), default=0.0)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for i, (name, rows) in enumerate(series.items()):
        if len(rows) < 2:
            continue
        t = np.array([r["time"] - t0 for r in rows])
        dt = np.diff(t)
        dt[dt <= 0] = np.nan
        raw = np.array([r["cells"] * 8 for r in rows[1:]]) / dt
        comp = np.array([r["bytes"] * 8 for r in rows[1:]]) / dt
        c = COLOURS[i % len(COLOURS)] / 255
        ax.plot(t[1:], raw / 1000, "--", color=c, label=f"{name} raw cells")
        ax.plot(t[1:], comp / 1000, "-", color=c, label=f"{name} compressed")
    ax.axhline(UWB_RATE / 1000, color="k", lw=1.5, label="UWB budget 12.5 kb/s")
    ax.set_yscale("log")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("bandwidth needed (kb/s)")
    ax.set_title("Bandwidth per robot, with and without compression (cf. paper Fig. 8b)")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write_via(out / "bandwidth.png", lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    lossy = False
    for i, (name, rows) in enumerate(series.items()):
        if not rows:
            continue
        ts = [r["time"] - t0 for r in rows]
        c = COLOURS[i % len(COLOURS)] / 255
        a1.plot(ts, [r["ratio"] for r in rows], "o-", ms=3, color=c, label=name)
        ps = [r["psnr"] for r in rows]
        if any(np.isfinite(ps)):
            lossy = True
            a2.plot(ts, ps, "o-", ms=3, color=c, label=f"{name} PSNR")
    a1.set_ylabel("compression ratio (cells : bytes)")
    a1.set_yscale("log")
    a1.set_title("Compression and map quality per update (cf. paper Fig. 8a)")
    a1.legend(fontsize=7)
    a1.grid(alpha=0.3)
    if lossy:
        a2.set_ylabel("PSNR (dB)")
        a2.legend(fontsize=7)
    else:
        a2.text(
            0.5,
            0.5,
            "lossless codec: every map arrives exact (PSNR = inf, SSIM = 1)",
            ha="center",
            va="center",
            transform=a2.transAxes,
        )
        a2.set_yticks([])
    a2.set_xlabel("time (s)")
    a2.grid(alpha=0.3)
    fig.tight_layout()
    atomic_write_via(out / "quality.png", lambda fh: fig.savefig(fh, format="png", dpi=110))
    plt.close(fig)


def write_report(
    out: Path, run_dir: Path, names: list[str], snaps: dict[str, dict[str, Any]], args: argparse.Namespace
) -> str:
    """Write every demo output under ``out`` and return the summary table as text."""
    from PIL import Image

    out.mkdir(parents=True, exist_ok=True)
    series = {n: _updates(run_dir / n / "state") for n in names}
    text = io.StringIO(newline="")
    fields = ["robot", "time", "version", "kind", "cells", "bytes", "ratio", "encode_ms", "psnr", "ssim"]
    w = csv.DictWriter(text, fieldnames=fields, extrasaction="ignore")
    w.writeheader()
    for n, rows in series.items():
        for r in rows:
            w.writerow({"robot": n, **r})
    atomic_write_bytes(out / "metrics.csv", text.getvalue().encode())
    _plots(out, series)

    gdir = run_dir / names[0] / "state" / "global"
    global_note = "no global map yet"
    if (gdir / "global.yaml").exists():
        try:
            g = load_map(gdir / "global.yaml")
            contrib = None
            owner = read_owner(gdir)
            if owner is not None and owner[0].shape == g.data.shape:  # else from another merge
                idx, owners = owner
                # owner.npy indexes owner.json's names; colour by the robot's place in the fleet
                lut = np.array([names.index(r) if r in names else -1 for r in owners] + [-1], dtype=np.int16)
                contrib = np.where(idx >= 0, lut[np.clip(idx, 0, len(owners))], -1)
            pic = coloured_global(g, contrib)
            # where each robot was at the end, as robot0 last heard (own pose and peers' pose messages)
            seen = (snaps.get(names[0], {}).get("poses") or {}).get("robots") or {}
            where = {r: p["fleet"] for r, p in seen.items() if isinstance(p, dict) and p.get("fleet")}
            pic = mark_robots(pic, g, where, names)
            image = Image.fromarray(with_legend(pic, names))
            atomic_write_via(out / "global_map.png", lambda fh: image.save(fh, format="PNG"))
            # A plain map_server pair (global.yaml + global.pgm): the state directory's own names a
            # numbered image (crash safety), which a reader of the report need not know of.
            save_map(g, out / "global.yaml")
            for f in gdir.iterdir():
                if f.suffix == ".json":
                    shutil.copy(f, out / f"global_{f.name}")
            c = g.counts()
            global_note = (
                f"global map {g.width} x {g.height} cells at {g.resolution} m, "
                f"{c['free'] + c['occupied']} known cells -> {out / 'global_map.png'}"
            )
        except (MapdError, OSError, ValueError) as exc:
            global_note = f"global map unreadable: {exc}"

    rows = []
    for n in names:
        ups = series[n]
        s = snaps.get(n, {})
        duration = (ups[-1]["time"] - ups[0]["time"]) if len(ups) > 1 else float("nan")
        coded = sum(r["bytes"] for r in ups)
        raw = sum(r["cells"] for r in ups)
        peers = s.get("peers", {})
        transforms = s.get("fusion", {}).get("robots") or {}
        confs: list[float] = [
            float(t["confidence"]) for t in transforms.values() if isinstance(t, dict) and t.get("confidence")
        ]
        # What the links carried (every frame, resends and acks included) over the daemon's uptime;
        # the pacing keeps it under the link rate, while versions made meanwhile wait uncoded.
        tx_bytes = sum(int(st.get("bytes_tx", 0)) for st in s.get("links", {}).values())
        up = s.get("uptime_s")
        rows.append(
            {
                "robot": n,
                "versions": split(int(ups[-1]["version"]))[1] if ups else 0,
                "keyframes": sum(r["kind"] == "keyframe" for r in ups),
                "deltas": sum(r["kind"] == "delta" for r in ups),
                "raw_kb": raw / 1000,
                "coded_kb": coded / 1000,
                "ratio": raw / coded if coded else float("nan"),
                "bps": 8 * coded / duration if duration and duration > 0 else float("nan"),
                "budget": (8 * coded / duration) / UWB_RATE if duration and duration > 0 else float("nan"),
                "link_bps": 8 * tx_bytes / up if isinstance(up, int | float) and up > 0 else float("nan"),
                "peers": " ".join(f"{p}:{label(v.get('version'))}" for p, v in peers.items()) or "-",
                "conf": min(confs) if confs else float("nan"),
                # how late its event loop ran at worst (mapd.daemon.loop_lag): what the CPU work
                # kept off the loop leaves it, on this machine with every robot on it
                "loop_ms": (s.get("loop") or {}).get("lag_ms_max", float("nan")),
            }
        )
    cols = [
        ("robot", "robot", ""),
        ("versions", "versions", ""),
        ("keyframes", "keyframes", ""),
        ("deltas", "deltas", ""),
        ("raw_kb", "raw kB", ".1f"),
        ("coded_kb", "coded kB", ".1f"),
        ("ratio", "ratio", ".1f"),
        ("bps", "coded bit/s", ".0f"),
        ("budget", "needs of 12.5 kb/s", ".1%"),
        ("link_bps", "link bit/s", ".0f"),
        ("peers", "holds peers", ""),
        ("conf", "fusion conf", ".2f"),
        ("loop_ms", "loop lag max ms", ".0f"),
    ]
    atomic_write_bytes(
        out / "summary.json",
        json.dumps({"robots": rows, "global": global_note}, indent=2, default=str).encode(),
    )
    return "\n".join(
        [
            "",
            "summary",
            table(rows, cols),
            "",
            global_note,
            f"figures: {out / 'bandwidth.png'}, {out / 'quality.png'}; table: {out / 'metrics.csv'}",
            f"daemon logs and state: {run_dir}",
        ]
    )
