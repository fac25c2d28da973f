"""Training the paper codec: the loop, and the model folder it writes.

The loss is the paper's equation 1, the mean squared error between the recovered map and the input
map, minimised with Adam, end to end through the quantizer (straight-through rounding; the Huffman
stage after it is lossless, so "through Cod(.)" is through the rounding).

* **Data.** Every map_server map under ``--maps``. Maps are split into training and validation *by
  place*, never by tile: maps of one place (``intel``, ``intel_part1``, ``intel_part2``; the two
  ``house_20xx`` runs) share a group, and whole groups go to one side (:func:`split_maps`). The
  split depends only on the map names, so every seed trains on the same maps.
  (:mod:`mapd.train.data` holds the split and the tile sampler.)
  Snapshots of maps in the making (:mod:`mapd.train.snapshots`) can join the training maps or
  replace them (``finished=False``); ``exclude_places`` drops whole places from both sides.
* **Tiles.** A tile is a ``tile x tile`` output region with its real surroundings (the networks'
  receptive field, padded with unknown outside the map), so training sees exactly what whole-map
  inference sees, including the unknown symbol the decoder assumes beyond the map's edge. Nine in
  ten tiles are drawn where the map has an edge (class change), one in ten anywhere; each gets one
  of the eight rotations/reflections. Everything is drawn from one seeded generator.
* **Determinism.** ``torch.manual_seed``, ``torch.use_deterministic_algorithms(True)`` and the
  seeded sampler make two CPU runs with one seed give identical weights.
* **Last epoch.** BatchNorm layers are frozen (running statistics) for the final epoch, so the
  quantizer and the decoder are tuned on the features they will see at inference.
* **Loss weights.** ``edge_weight`` (default 1, the paper's plain MSE) counts the squared error of
  cells on a class boundary that many times; the loss stays a per-cell MSE on the PSNR's scale.

The whole-map evaluation and the model card live in :mod:`mapd.train.card`.
"""

from __future__ import annotations

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
from mapd.grid import load_map
from mapd.train.card import evaluate_maps, model_card, summarize
from mapd.train.data import (
    MARGIN,
    PreparedMap,
    TileBatch,
    map_group,
    prepare_map,
    sample_tiles,
    split_maps,
)
from mapd.train.snapshots import SnapshotSpec, snapshot_maps

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
    edge_weight: float = 1.0
    threads: int = 0  # torch CPU threads; 0 leaves torch's default
    #: Maps in the making to train on beside (or, with ``finished=False``, instead of) the finished maps.
    snapshots: SnapshotSpec | None = None
    finished: bool = True
    #: Places (split groups) left out of training and validation, e.g. the place of a held-out log.
    exclude_places: tuple[str, ...] = ()
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


def _label(p: Path, root: Path) -> str:
    return str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem


def _load_maps(paths: list[Path], root: Path, tile: int) -> list[PreparedMap]:
    return [prepare_map(_label(p, root), load_map(p), tile) for p in paths]


def train(cfg: TrainConfig) -> dict[str, Any]:
    """Train, write ``cfg.out`` (weights.npz, model.json, MODEL_CARD.md) and return model.json's content."""
    if cfg.threads < 0:
        raise ConfigError(f"--threads must be 0 (torch's default) or more, got {cfg.threads}")
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    was_threads = torch.get_num_threads()
    if cfg.threads:
        # CPU summation order can depend on the thread count, so it is part of the recipe.
        torch.set_num_threads(cfg.threads)
    try:
        return _train(cfg)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)
        torch.set_num_threads(was_threads)


def _train(cfg: TrainConfig) -> dict[str, Any]:
    from tqdm import tqdm

    from mapd.data import shared_maps

    if cfg.epochs < 1 or cfg.tiles_per_epoch < 1 or cfg.batch < 1:
        raise ConfigError("--epochs, --tiles-per-epoch and --batch must be at least 1")
    if not 0.0 < cfg.edge_weight <= 1000.0:
        raise ConfigError(f"--edge-weight must be in (0, 1000], got {cfg.edge_weight}")
    if cfg.tile < 8 or cfg.tile % 4:
        raise ConfigError(f"--tile must be a multiple of 4 and at least 8, got {cfg.tile}")
    paths = shared_maps(cfg.maps)
    if not paths:
        raise ConfigError(f"--maps {cfg.maps}: no map_server YAML files found")
    root = cfg.maps / "maps" if (cfg.maps / "maps").is_dir() else cfg.maps
    train_paths, val_paths, groups = split_maps(paths, cfg.val_fraction)
    excluded = sorted(p for p in map(str, paths) if groups[p] in cfg.exclude_places)
    unknown = set(cfg.exclude_places) - set(groups.values())
    if unknown:
        raise ConfigError(f"--exclude-place {', '.join(sorted(unknown))}: no such place among the maps")
    train_paths = [p for p in train_paths if str(p) not in excluded]
    val_paths = [p for p in val_paths if str(p) not in excluded]
    if not cfg.finished:
        train_paths = []
    device = pick_device(cfg.device)
    if device.type == "cuda":
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.manual_seed(cfg.seed)
    torch.use_deterministic_algorithms(True)
    rng = np.random.default_rng(cfg.seed)
    started = time.time()

    train_maps = _load_maps(train_paths, root, cfg.tile)
    recipe: dict[str, Any] = {"finished": cfg.finished, "finished_maps": len(train_paths)}
    if cfg.snapshots:
        snaps, recipe["snapshots"] = snapshot_maps(cfg.snapshots)
        train_maps += [prepare_map(label, grid, cfg.tile) for label, grid in snaps]
    if not train_maps:
        raise ConfigError("nothing to train on: --no-finished needs --snapshots-log or --snapshots-sim")
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
        tiles = sample_tiles(train_maps, steps_per_epoch * cfg.batch, cfg.tile, rng, cfg.edge_weight)
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
            "edge_weight": cfg.edge_weight,
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
            "recipe": recipe,
        },
        "split": {
            "rule": "by place: folder name up to the first '_' (numeric folders take the parent's name); "
            "groups ordered by sha256 of the name, the first round(val_fraction * groups) validate",
            "train": sorted(_label(p, root) for p in train_paths),
            "excluded": sorted(_label(Path(p), root) for p in excluded),
            "excluded_places": sorted(cfg.exclude_places),
            "validation": sorted(_label(p, root) for p in val_paths),
            "groups": {_label(Path(k), root): v for k, v in sorted(groups.items())},
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
