"""Training the paper codec: map tiles, a split by map, the loop, and the model folder it writes.

The loss is the paper's equation 1, the mean squared error between the recovered map and the input
map, minimised with Adam, end to end through the quantizer (straight-through rounding; the Huffman
stage after it is lossless, so "through Cod(.)" is through the rounding).

* **Data.** Every map_server map under ``--maps``. Maps are split into training and validation *by
  place*, never by tile: maps of one place (``intel``, ``intel_part1``, ``intel_part2``; the two
  ``house_20xx`` runs) share a group, and whole groups go to one side (:func:`split_maps`). The
  split depends only on the map names, so every seed trains on the same maps.
* **Tiles.** A tile is a ``tile x tile`` output region with its real surroundings (the networks'
  receptive field, padded with unknown outside the map), so training sees exactly what whole-map
  inference sees, including the unknown symbol the decoder assumes beyond the map's edge. Nine in
  ten tiles are drawn where the map has an edge (class change), one in ten anywhere; each gets one
  of the eight rotations/reflections. Everything is drawn from one seeded generator.
* **Determinism.** ``torch.manual_seed``, ``torch.use_deterministic_algorithms(True)`` and the
  seeded sampler make two CPU runs with one seed give identical weights.
* **Last epoch.** BatchNorm layers are frozen (running statistics) for the final epoch, so the
  quantizer and the decoder are tuned on the features they will see at inference.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapd.codec import paper_net as pn
from mapd.errors import ConfigError, MapdError
from mapd.grid import OccupancyGrid, cell_classes, load_map

MARGIN = pn.crop_margin()


# --------------------------------------------------------------------------------------------
# Split by place
# --------------------------------------------------------------------------------------------


def map_group(path: Path, shares_folder: bool = False) -> str:
    """The place a map shows: its folder name up to the first underscore.

    ``intel_part1`` -> ``intel``; ``ipa-office_2017`` -> ``ipa-office``; a purely numeric folder
    (``aws_small_warehouse/002``) takes its parent's name. When several maps share one folder the
    file name stands in for the folder name.
    """
    name = path.stem if shares_folder else path.parent.name
    if name.isdigit():
        name = path.parent.parent.name if not shares_folder else path.parent.name
    return name.split("_")[0] or name


def split_maps(paths: list[Path], val_fraction: float) -> tuple[list[Path], list[Path], dict[str, str]]:
    """Split maps into (train, validation) by group; also return each map's group.

    Groups are ordered by the sha256 of their name and the first ``round(val_fraction * groups)``
    (at least one, when there are two or more groups) go to validation.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ConfigError(f"--val-fraction must be in [0, 1), got {val_fraction}")
    per_folder: dict[Path, int] = {}
    for p in paths:
        per_folder[p.parent] = per_folder.get(p.parent, 0) + 1
    groups = {str(p): map_group(p, per_folder[p.parent] > 1) for p in paths}
    names = sorted(set(groups.values()), key=lambda g: hashlib.sha256(g.encode()).hexdigest())
    n_val = 0
    if len(names) >= 2 and val_fraction > 0:
        n_val = min(len(names) - 1, max(1, round(val_fraction * len(names))))
    val_groups = set(names[:n_val])
    train = [p for p in paths if groups[str(p)] not in val_groups]
    val = [p for p in paths if groups[str(p)] in val_groups]
    return train, val, groups


# --------------------------------------------------------------------------------------------
# Tiles
# --------------------------------------------------------------------------------------------


@dataclass
class PreparedMap:
    """One map padded for crop sampling, with its edge-tile candidates."""

    label: str
    x: np.ndarray  # network input, padded by MARGIN (and up to whole tiles) with unknown
    height: int
    width: int
    origins: np.ndarray  # (n, 2) even full-resolution tile origins
    content: np.ndarray  # (n,) True where the tile holds an edge


def prepare_map(label: str, grid: OccupancyGrid, tile: int) -> PreparedMap:
    h, w = grid.height, grid.width
    he = max(h + (h % 2), tile)
    we = max(w + (w % 2), tile)
    x = np.zeros((he + 2 * MARGIN, we + 2 * MARGIN), dtype=np.float32)
    x[MARGIN : MARGIN + h, MARGIN : MARGIN + w] = pn.map_to_input(grid.data)
    cls = cell_classes(grid.data).astype(np.int16)
    edge = np.zeros((he + 1, we + 1), dtype=np.int64)
    e = np.zeros((h, w), dtype=bool)
    e[:, 1:] |= cls[:, 1:] != cls[:, :-1]
    e[1:, :] |= cls[1:, :] != cls[:-1, :]
    edge[1 : h + 1, 1 : w + 1] = e
    integral = edge.cumsum(0).cumsum(1)
    step = max(2, (tile // 2) & ~1)
    rows = sorted({*range(0, he - tile + 1, step), he - tile})
    cols = sorted({*range(0, we - tile + 1, step), we - tile})
    origins = np.array([(r, c) for r in rows for c in cols], dtype=np.int64)
    r, c = origins[:, 0], origins[:, 1]
    count = integral[r + tile, c + tile] - integral[r, c + tile] - integral[r + tile, c] + integral[r, c]
    return PreparedMap(label, x, h, w, origins, count > 0)


@dataclass
class TileBatch:
    """A batch of training tiles.

    ``x``: crops (B, 1, tile + 2 MARGIN, ...); ``fmask``: where m_feature lies inside the map
    (B, 1, tile/2 + 12, ...); ``lmask``: output cells inside the map (B, 1, tile, tile).
    """

    x: torch.Tensor
    fmask: torch.Tensor
    lmask: torch.Tensor


def _crop(pm: PreparedMap, r0: int, c0: int, tile: int, k: int, flip: bool) -> tuple[np.ndarray, ...]:
    size = tile + 2 * MARGIN
    x = pm.x[r0 : r0 + size, c0 : c0 + size]
    half = tile // 2
    p = pn.RECOVERY_PAD
    fr = np.arange(r0 // 2 - p, r0 // 2 + half + p)
    fc = np.arange(c0 // 2 - p, c0 // 2 + half + p)
    fmask = ((fr >= 0) & (fr < (pm.height + 1) // 2))[:, None] & ((fc >= 0) & (fc < (pm.width + 1) // 2))[
        None, :
    ]
    lr = np.arange(r0, r0 + tile)
    lc = np.arange(c0, c0 + tile)
    lmask = ((lr < pm.height)[:, None] & (lc < pm.width)[None, :]).astype(np.float32)
    out = []
    for a in (x, fmask, lmask):
        a = np.rot90(a, k)
        out.append(np.ascontiguousarray(a[:, ::-1] if flip else a))
    return tuple(out)


def sample_tiles(maps: list[PreparedMap], n: int, tile: int, rng: np.random.Generator) -> TileBatch:
    """``n`` tiles drawn from ``maps`` with ``rng`` (nine in ten on an edge), randomly rotated."""
    weights = np.array([math.sqrt(max(1, int(m.content.sum()))) for m in maps])
    weights /= weights.sum()
    xs, fms, lms = [], [], []
    for _ in range(n):
        pm = maps[int(rng.choice(len(maps), p=weights))]
        he, we = pm.x.shape[0] - 2 * MARGIN, pm.x.shape[1] - 2 * MARGIN
        pool = np.flatnonzero(pm.content)
        if rng.random() < 0.9 and pool.size:
            r0, c0 = (int(v) for v in pm.origins[int(rng.choice(pool))])
            jitter = tile // 4
            r0 = int(np.clip(r0 + 2 * int(rng.integers(-jitter // 2, jitter // 2 + 1)), 0, he - tile))
            c0 = int(np.clip(c0 + 2 * int(rng.integers(-jitter // 2, jitter // 2 + 1)), 0, we - tile))
        else:
            r0 = 2 * int(rng.integers(0, (he - tile) // 2 + 1))
            c0 = 2 * int(rng.integers(0, (we - tile) // 2 + 1))
        x, fm, lm = _crop(pm, r0, c0, tile, int(rng.integers(0, 4)), bool(rng.integers(0, 2)))
        xs.append(x)
        fms.append(fm)
        lms.append(lm)
    return TileBatch(
        torch.from_numpy(np.stack(xs))[:, None],
        torch.from_numpy(np.stack(fms))[:, None],
        torch.from_numpy(np.stack(lms))[:, None],
    )


# --------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------


@dataclass
class TrainConfig:
    """Everything that decides the weights (recorded in model.json)."""

    maps: Path
    out: Path
    epochs: int = 12
    tile: int = 64
    seed: int = 0
    levels: int = 16
    tiles_per_epoch: int = 2048
    batch: int = 16
    lr: float = 2e-3
    val_fraction: float = 0.2
    val_tiles: int = 256
    device: str = "auto"
    name: str = ""
    progress: bool = True
    evaluate: bool = True
    extra: dict[str, Any] = field(default_factory=dict)


def _unknown_symbol(net: pn.PaperNet) -> torch.Tensor:
    """The symbol the decoder assumes beyond the map (eval-mode feature of an all-unknown patch)."""
    was = net.feature.training
    net.feature.eval()
    with torch.no_grad():
        side = 2 + 2 * pn.FEATURE_PAD
        z = net.feature(torch.zeros(1, 1, side, side, device=next(net.parameters()).device))
        q = torch.round(net.quant.soft(z))[0, 0, 0, 0]
    net.feature.train(was)
    return q


def _loss(net: pn.PaperNet, batch: TileBatch, device: torch.device) -> torch.Tensor:
    x = batch.x.to(device)
    fmask = batch.fmask.to(device)
    lmask = batch.lmask.to(device)
    q = net.quant(net.feature(x))
    q = torch.where(fmask, q, _unknown_symbol(net))
    out = net.recovery(net.quant.value(q))
    target = x[:, :, MARGIN:-MARGIN, MARGIN:-MARGIN]
    return ((out - target) ** 2 * lmask).sum() / lmask.sum().clamp_min(1.0)


def _chunks(batch: TileBatch, size: int) -> Iterator[TileBatch]:
    for i in range(0, batch.x.shape[0], size):
        yield TileBatch(batch.x[i : i + size], batch.fmask[i : i + size], batch.lmask[i : i + size])


def _freeze_bn(net: pn.PaperNet) -> None:
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.eval()


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise ConfigError(f"--device must be auto, cpu or cuda, got '{name}'")
    return torch.device(name)


def _load_maps(paths: list[Path], root: Path, tile: int) -> list[PreparedMap]:
    out = []
    for p in paths:
        label = str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem
        out.append(prepare_map(label, load_map(p), tile))
    return out


def evaluate_maps(model_dir: Path, paths: list[Path], root: Path) -> list[dict[str, Any]]:
    """Every map through the real codec API with the model in ``model_dir``: size and quality."""
    from mapd import metrics
    from mapd.codec import api
    from mapd.codec.paper import PaperOptions

    opts = PaperOptions(model=model_dir.name, model_dir=model_dir.parent)
    rows = []
    for p in paths:
        grid = load_map(p)
        t0 = time.perf_counter()
        payload = api.encode(grid, "paper", options=opts)
        t1 = time.perf_counter()
        back = api.decode(payload, options=opts)
        t2 = time.perf_counter()
        q = metrics.quality(grid.data, back.data)
        rows.append(
            {
                "map": str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem,
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


def train(cfg: TrainConfig) -> dict[str, Any]:
    """Train, write ``cfg.out`` (weights.npz, model.json, MODEL_CARD.md) and return model.json's content."""
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    try:
        return _train(cfg)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)


def _train(cfg: TrainConfig) -> dict[str, Any]:
    from tqdm import tqdm

    from mapd.data import shared_maps

    if cfg.epochs < 1 or cfg.tiles_per_epoch < 1 or cfg.batch < 1:
        raise ConfigError("--epochs, --tiles-per-epoch and --batch must be at least 1")
    if cfg.tile < 8 or cfg.tile % 4:
        raise ConfigError(f"--tile must be a multiple of 4 and at least 8, got {cfg.tile}")
    paths = shared_maps(cfg.maps)
    if not paths:
        raise ConfigError(f"--maps {cfg.maps}: no map_server YAML files found")
    root = cfg.maps / "maps" if (cfg.maps / "maps").is_dir() else cfg.maps
    train_paths, val_paths, groups = split_maps(paths, cfg.val_fraction)
    device = pick_device(cfg.device)
    if device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.manual_seed(cfg.seed)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(cfg.seed)
    started = time.time()

    train_maps = _load_maps(train_paths, root, cfg.tile)
    val_maps = _load_maps(val_paths, root, cfg.tile)
    val_batch = (
        sample_tiles(val_maps, cfg.val_tiles, cfg.tile, np.random.default_rng(cfg.seed + 1))
        if val_maps and cfg.val_tiles > 0
        else None
    )

    net = pn.PaperNet(cfg.levels).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    steps_per_epoch = -(-cfg.tiles_per_epoch // cfg.batch)
    total_steps = cfg.epochs * steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * min(s, total_steps) / total_steps))
    )
    history = []
    bar = tqdm(total=total_steps, desc="train", unit="step", disable=not cfg.progress, file=sys.stderr)
    for epoch in range(cfg.epochs):
        net.train()
        if epoch == cfg.epochs - 1 and cfg.epochs > 1:
            _freeze_bn(net)
        tiles = sample_tiles(train_maps, steps_per_epoch * cfg.batch, cfg.tile, rng)
        losses = []
        for batch in _chunks(tiles, cfg.batch):
            loss = _loss(net, batch, device)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.5f}")
        entry = {"epoch": epoch + 1, "train_mse": float(np.mean(losses))}
        if val_batch is not None:
            net.eval()
            with torch.no_grad():
                vl = [float(_loss(net, b, device)) * b.x.shape[0] for b in _chunks(val_batch, 64)]
            entry["val_mse"] = sum(vl) / val_batch.x.shape[0]
            bar.set_postfix(epoch=epoch + 1, loss=f"{entry['train_mse']:.5f}", val=f"{entry['val_mse']:.5f}")
        history.append(entry)
    bar.close()
    train_seconds = time.time() - started

    net = net.cpu().eval()
    cfg.out.mkdir(parents=True, exist_ok=True)
    sha = pn.write_weights(cfg.out / pn.WEIGHTS_FILE, pn.state_arrays(net))
    name = cfg.name or cfg.out.name
    n_params = sum(int(p.numel()) for p in net.parameters())
    meta: dict[str, Any] = {
        "name": name,
        "format": pn.MODEL_FORMAT,
        "levels": cfg.levels,
        "channels": pn.CHANNELS,
        "parameters": n_params,
        "parameters_feature": sum(int(p.numel()) for p in net.feature.parameters()),
        "parameters_recovery": sum(int(p.numel()) for p in net.recovery.parameters()),
        "weights_file": pn.WEIGHTS_FILE,
        "weights_sha256": sha,
        "training": {
            "maps": str(cfg.maps),
            "epochs": cfg.epochs,
            "tile": cfg.tile,
            "seed": cfg.seed,
            "tiles_per_epoch": cfg.tiles_per_epoch,
            "batch": cfg.batch,
            "lr": cfg.lr,
            "schedule": "cosine from lr to lr/100 over all steps",
            "optimizer": "Adam (torch defaults betas=(0.9, 0.999))",
            "val_fraction": cfg.val_fraction,
            "val_tiles": cfg.val_tiles,
            "device": str(device),
            "device_name": torch.cuda.get_device_name(device)
            if device.type == "cuda"
            else platform.processor() or platform.machine(),
            "torch_threads": torch.get_num_threads(),
            "torch": torch.__version__,
            "python": platform.python_version(),
            "seconds": round(train_seconds, 1),
            "command": " ".join(cfg.extra.get("argv", [])),
            "history": history,
        },
        "split": {
            "rule": "by place: folder name up to the first '_' (numeric folders take the parent's name); "
            "groups ordered by sha256 of the name, the first round(val_fraction * groups) validate",
            "train": sorted(
                str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem for p in train_paths
            ),
            "validation": sorted(
                str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem for p in val_paths
            ),
            "groups": {
                (str(Path(k).relative_to(root).parent) if Path(k).is_relative_to(root) else Path(k).stem): v
                for k, v in sorted(groups.items())
            },
        },
    }
    (cfg.out / pn.META_FILE).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
    if cfg.evaluate:
        val_rows = evaluate_maps(cfg.out, val_paths, root)
        train_rows = evaluate_maps(cfg.out, train_paths, root)
        meta["metrics"] = {
            "validation": summarize(val_rows),
            "train": summarize(train_rows),
            "per_map": {"validation": val_rows, "train": train_rows},
        }
        (cfg.out / pn.META_FILE).write_text(json.dumps(meta, indent=2, default=str) + "\n", encoding="utf-8")
    (cfg.out / "MODEL_CARD.md").write_text(model_card(meta), encoding="utf-8")
    return meta


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
        "as the paper; masked to cells inside the map; cosine learning-rate decay; BatchNorm frozen in "
        "the last epoch",
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
        *(f"| {a} | {b} | {c.format(levels=meta['levels'])} |" for a, b, c in CHOICES),
        "",
        "## Data and split",
        "",
        f"- maps: every map_server map under `{tr['maps']}`; {len(sp['train'])} for training,"
        f" {len(sp['validation'])} for validation",
        f"- split rule: {sp['rule']}",
        f"- validation maps: {', '.join(sp['validation']) or 'none'}",
        f"- training maps: {', '.join(sp['train'])}",
        "",
        "## Training",
        "",
        f"- command: `{tr['command'] or 'mapd train (see settings)'}`",
        f"- epochs {tr['epochs']}, {tr['tiles_per_epoch']} tiles per epoch of {tr['tile']} x {tr['tile']}"
        f" cells (plus context), batch {tr['batch']}, {tr['optimizer']}, lr {tr['lr']}, {tr['schedule']},"
        f" seed {tr['seed']}",
        f"- trained on: {tr['device']} ({tr['device_name']}, {tr['torch_threads']} torch threads),"
        f" torch {tr['torch']}, Python {tr['python']}; {tr['seconds']:.0f} s wall time",
        "",
        "| epoch | train MSE | validation MSE (tiles) |",
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
            "PSNR and SSIM on map_server grey levels over the whole grid (`mapd.metrics`); ratio = cells /",
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


def main_train(cfg: TrainConfig) -> dict[str, Any]:
    """:func:`train`, with torch/numpy failures turned into one-line :class:`MapdError`s."""
    try:
        return train(cfg)
    except MapdError:
        raise
    except (RuntimeError, ValueError) as exc:
        raise MapdError(f"training failed: {exc}") from None


__all__ = [
    "PreparedMap",
    "TileBatch",
    "TrainConfig",
    "evaluate_maps",
    "map_group",
    "model_card",
    "prepare_map",
    "sample_tiles",
    "split_maps",
    "summarize",
    "train",
]
