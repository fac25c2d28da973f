"""What ``mapd train`` reports about a model folder: whole-map metrics and ``MODEL_CARD.md``.

:func:`evaluate_maps` runs maps through the real codec API with a trained model, :func:`summarize`
aggregates the rows, and :func:`model_card` writes the card from ``model.json``'s content: identity
(sha256, payload variant, parameters), what is the paper's and what is our choice, the data and its
split by place, the training settings and curve, and the measured metrics next to the paper's.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from mapd.grid import OccupancyGrid
from mapd.grid.load import load_map


def evaluate_maps(model_dir: Path, paths: list[Path], root: Path) -> list[dict[str, Any]]:
    """Every map through the real codec API with the model in ``model_dir``: size and quality."""
    labelled = (
        (str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem, load_map(p)) for p in paths
    )
    return evaluate_grids(model_dir, labelled)


def evaluate_grids(model_dir: Path, grids: Iterable[tuple[str, OccupancyGrid]]) -> list[dict[str, Any]]:
    """Every (label, grid) through the real codec API with the model in ``model_dir``: size and quality."""
    from mapd.codec import api, metrics
    from mapd.codec.paper import PaperOptions

    opts = PaperOptions(model=model_dir.name, model_dir=model_dir.parent)
    rows = []
    for label, grid in grids:
        t0 = time.perf_counter()
        payload = api.encode(grid, "paper", options=opts)
        t1 = time.perf_counter()
        back = api.decode(payload, options=opts)
        t2 = time.perf_counter()
        q = metrics.quality(grid.data, back.data)
        rows.append(
            {
                "map": label,
                "cells": grid.cells,
                "bytes": len(payload),
                "ratio": grid.cells / len(payload),
                "bits_per_cell": 8.0 * len(payload) / grid.cells,
                "enc_ms": 1000 * (t1 - t0),
                "dec_ms": 1000 * (t2 - t1),
                **q,
            }
        )
    return rows


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Aggregate metrics: total ratio, mean PSNR over maps (finite values), mean SSIM, F1, change."""
    if not rows:
        return {}
    cells = sum(r["cells"] for r in rows)
    nbytes = sum(r["bytes"] for r in rows)
    finite = [r["psnr"] for r in rows if math.isfinite(r["psnr"])]
    return {
        "maps": len(rows),
        "cells": cells,
        "bytes": nbytes,
        "ratio": cells / nbytes,
        "bits_per_cell": 8.0 * nbytes / cells,
        "psnr_mean": sum(finite) / len(finite) if finite else math.inf,
        "psnr_exact_maps": len(rows) - len(finite),
        "ssim_mean": sum(r["ssim"] for r in rows) / len(rows),
        "f1_mean": sum(r["f1"] for r in rows) / len(rows),
        "changed_mean": sum(r["changed"] for r in rows) / len(rows),
    }


PAPER = {"ratio": 173.0, "psnr": 50.649, "ssim": 0.975}

#: (topic, as the paper says, our choice and why) for the model card.
CHOICES: list[tuple[str, str, str]] = [
    (
        "CNN_feature",
        "conv 3x3 16 + ReLU; conv 3x3x16 16 filters stride 2 + BN + ReLU; conv 3x3x16 1 filter = m_feature",
        'as the paper; all convolutions unpadded ("valid") after padding the map once by 4 cells with '
        "unknown, so any crop computes exactly what the whole map computes (tiles that are constant are "
        "skipped at inference)",
    ),
    (
        "map values into the network",
        "not said",
        "grey level of map_server (free 254, occupied 0, unknown 205) as x = (grey - 205) / 255: unknown "
        "0, free +0.192, occupied -0.804; graded 0..100 linear from free to occupied grey. The MSE on "
        'this scale is the MSE the PSNR measures, and the padding value 0 means "unknown", which is what '
        "lies outside a map",
    ),
    (
        "quantizing m_feature for Huffman",
        "not said",
        "L = {levels} levels: symbol = round((L-1) sigmoid(m_feature)); value = occupied + symbol (free -"
        " occupied)/(L-1). Trained with straight-through rounding, so the decoder sees quantized features"
        " in training too",
    ),
    (
        "Huffman tree and table T",
        "merge the two least probable nodes into one until one node is left; T maps values to codes",
        "the same tree (heapq, deterministic ties); T sent as canonical code lengths (one nibble per "
        "symbol, DEFLATE style), lengths capped at 15 bits (counts halved and rebuilt if ever deeper); a "
        "single distinct symbol gets the code 0",
    ),
    (
        "bit string -> hex -> RLE",
        "bits to a hex string, runs of one hex character become (count, character)",
        "exactly that; the last hex digit is padded with zero bits; e stored column-wise: number of runs "
        "(LEB128), the characters (one nibble each), the counts - 1 as nibble varints (3 bits + "
        "continuation)",
    ),
    (
        "decoder",
        "expand e, hex to bits, bits to values with T",
        "exactly that, vectorised (windowed table lookup + pointer doubling); every malformed input is a "
        "CodecError",
    ),
    (
        "CNN_recovery",
        "conv 3x3 16 + ReLU; 4 x (conv 3x3x16 + BN + ReLU); conv 3x3x16 1 filter = full-resolution map; "
        "skip from input to output",
        "layers 1-5 at half resolution, 16 channels upsampled 2x (nearest), layer 6 (1 filter) at full "
        "resolution; skip = m_feature's value upsampled bilinearly. The paper does not say how the "
        "half-resolution feature returns to full size; this needs about 2.5k multiply-adds per cell "
        "instead of 9.5k for upsampling first (which took 8-11 s for a 2000 x 2000 map on our 2 CPU "
        "cores), with twice the receptive field (ESPCN-style low-resolution processing, "
        "resize-convolution for the last layer)",
    ),
    (
        "loss, optimiser",
        "MSE between recovered and input map (eq. 1), Adam",
        "{loss}; masked to cells inside the map; cosine learning-rate decay; BatchNorm frozen in the last"
        " epoch",
    ),
    (
        "output values",
        "not said",
        "each cell snapped to the nearest grey level among the classes the source map held (trinary: "
        "-1/0/100); graded maps to the nearest of 0..100 or unknown",
    ),
    (
        "wire form of (T, e)",
        "not said",
        "one flags byte (classes present, graded), then T, then e; the model id (name:sha256[:12]) is the"
        " payload header's variant and other weights refuse the payload",
    ),
]


def _fmt(v: Any, spec: str) -> str:
    if isinstance(v, float) and not math.isfinite(v):
        return "inf"
    return format(v, spec) if isinstance(v, int | float) else str(v)


def _loss_text(training: dict[str, Any]) -> str:
    """The loss as the card states it: the paper's plain MSE, or the boundary-weighted one."""
    w = float(training.get("edge_weight", 1.0))
    if w == 1.0:
        return "as the paper"
    return (
        f"weighted MSE (a deviation from eq. 1): squared error of a cell on a class boundary (a 4-neighbour"
        f" of another class, both sides) counts {w:g} times, others once; the sum is divided by the sum of"
        f" the weights. Still MSE per cell on the PSNR's grey scale, only the cells where the class can"
        f" change weigh more; Adam as the paper"
    )


def _recipe_lines(tr: dict[str, Any], sp: dict[str, Any]) -> list[str]:
    """What the model learned from besides the finished maps (snapshots), and which places were left out."""
    from mapd.train.snapshots import describe

    lines = []
    if sp.get("excluded_places"):
        lines.append(
            f"- left out of training and validation (`--exclude-place`): places"
            f" {', '.join(sp['excluded_places'])} (maps {', '.join(sp.get('excluded', []))})"
        )
    recipe = tr.get("recipe") or {}
    snaps = recipe.get("snapshots")
    if snaps:
        kind = "beside the finished maps" if recipe.get("finished", True) else "only (`--no-finished`)"
        lines.append(f"- maps in the making, {kind}: {describe(snaps)}; {snaps['cells']} cells in all")
    return lines


def model_card(meta: dict[str, Any]) -> str:
    """MODEL_CARD.md for a trained model folder, from its model.json content."""
    tr = meta["training"]
    sp = meta["split"]
    lines = [
        f"# Model card: {meta['name']}",
        "",
        "The `paper` codec of mapd: CNN_feature + Huffman/hex/run-length coding + CNN_recovery after",
        'Zhang and Deng, "Deep Compressed Communication and Application in Multi-Robot 2D-Lidar SLAM:',
        'An Intelligent Huffman Algorithm", Sensors 24(10):3154, 2024. This card is written by `mapd train`.',
        "",
        "## Identity",
        "",
        f"- weights: `{meta['weights_file']}` (float32 arrays in an npz, read with `allow_pickle=False`),"
        f" sha256 `{meta['weights_sha256']}`",
        f"- payload variant (model id in every payload header):"
        f" `{meta['name']}:{meta['weights_sha256'][:12]}`; a payload made with other weights is refused",
        f"- parameters: {meta['parameters']} in all; CNN_feature {meta['parameters_feature']},"
        f" CNN_recovery {meta['parameters_recovery']} (BatchNorm running statistics not counted)",
        f"- quantizer: {meta['levels']} levels; {meta['channels']} channels per hidden layer",
        "",
        "## Architecture: as the paper says, and our choices",
        "",
        "| topic | as the paper says | our choice (and why) |",
        "|---|---|---|",
        *(f"| {a} | {b} | {c.format(levels=meta['levels'], loss=_loss_text(tr))} |" for a, b, c in CHOICES),
        "",
        "## Data and split",
        "",
        f"- maps: every map_server map under `{tr['maps']}`; {len(sp['train'])} for training,"
        f" {len(sp['validation'])} for validation",
        f"- split rule: {sp['rule']}",
        f"- validation maps: {', '.join(sp['validation']) or 'none'}",
        f"- training maps: {', '.join(sp['train']) or 'none (`--no-finished`: maps in the making only)'}",
        *_recipe_lines(tr, sp),
        "",
        "## Training",
        "",
        f"- command: `{tr['command'] or 'mapd train (see settings)'}`",
        f"- epochs {tr['epochs']}, {tr['tiles_per_epoch']} tiles per epoch of {tr['tile']} x {tr['tile']}"
        f" cells (plus context), batch {tr['batch']}, {tr['optimizer']}, lr {tr['lr']}, {tr['schedule']},"
        f" seed {tr['seed']}",
        f"- trained on: {tr['device']} ({tr['device_name']}, torch threads: {tr['torch_threads']}),"
        f" torch {tr['torch']}, Python {tr['python']}; {tr['seconds']:.0f} s wall time",
        "",
        "| epoch | train MSE | validation MSE (tiles) |"
        if float(tr.get("edge_weight", 1.0)) == 1.0
        else "| epoch | train loss (boundary-weighted MSE) | validation MSE (tiles, unweighted) |",
        "|---:|---:|---:|",
    ]
    for h in tr["history"]:
        lines.append(f"| {h['epoch']} | {h['train_mse']:.6f} | {_fmt(h.get('val_mse', math.nan), '.6f')} |")
    metrics = meta.get("metrics")
    if metrics:
        lines += [
            "",
            "## Metrics (whole maps through the real codec API, header included)",
            "",
            "PSNR and SSIM on map_server grey levels over the whole grid (`mapd.codec.metrics`); ratio = cells /",
            "payload bytes (one byte per raw cell); F1 over occupied cells; changed = share of known cells",
            "whose class changes.",
            "",
            "| set | maps | ratio | bits/cell | mean PSNR dB | mean SSIM | mean occ. F1 | mean changed |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for key in ("validation", "train"):
            s = metrics.get(key) or {}
            if s:
                lines.append(
                    f"| {key} | {s['maps']} | {s['ratio']:.1f} | {s['bits_per_cell']:.4f}"
                    f" | {_fmt(s['psnr_mean'], '.2f')} | {s['ssim_mean']:.4f} | {s['f1_mean']:.4f}"
                    f" | {s['changed_mean']:.4f} |"
                )
        lines.append(
            f"| paper (reported) | - | about {PAPER['ratio']:.0f} | {8 / PAPER['ratio']:.4f}"
            f" | {PAPER['psnr']} | {PAPER['ssim']} | - | - |"
        )
        lines += [
            "",
            "Validation maps, one by one:",
            "",
            "| map | cells | bytes | ratio | PSNR dB | SSIM | occ. F1 | changed |",
            "|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for r in metrics["per_map"]["validation"]:
            lines.append(
                f"| {r['map']} | {r['cells']} | {r['bytes']} | {r['ratio']:.1f} | {_fmt(r['psnr'], '.2f')}"
                f" | {r['ssim']:.4f} | {r['f1']:.4f} | {r['changed']:.4f} |"
            )
    lines += [
        "",
        "## Limits",
        "",
        "- Lossy: walls can move by a cell, thin structures can break, and small unknown islands can vanish;"
        " use the `lossless` codec where exact maps matter.",
        "- Trained only on trinary maps; graded maps (0..100) are coded through the same grey line, and",
        "  a graded value near 19 can come back as unknown or the other way round.",
        "- The CNNs run in float32 on CPU; two machines may differ in the last bits of the recovered values,",
        "  which only matters for a cell exactly between two grey levels.",
        "",
    ]
    return "\n".join(lines)


__all__ = ["CHOICES", "PAPER", "evaluate_grids", "evaluate_maps", "model_card", "summarize"]
