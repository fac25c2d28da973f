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
* **Bad settings** are refused before any work, one line naming the option
  (:mod:`mapd.train.settings`: :class:`~mapd.train.settings.TrainConfig` and its bounds).
* **Stops.** After each epoch the whole training state goes to ``<-o>.checkpoint``
  (:mod:`mapd.train.checkpoint`); ``resume`` goes on from it to the same weights as an unbroken run,
  and ``time_limit`` ends a run cleanly after the epoch that reaches it (:class:`TrainingPaused`).
* **Output.** The model folder is written and evaluated in a hidden folder beside ``-o`` and then
  renamed into place (:mod:`mapd.train.install`), so a failure (a full disk, a diverged run: non-finite
  weights are never saved) leaves a model already there whole.

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
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mapd.codec import paper_model as pm
from mapd.codec import paper_net as pn
from mapd.errors import ConfigError, MapdError
from mapd.grid.load import load_map
from mapd.train import checkpoint as ckpt
from mapd.train.card import evaluate_maps, model_card, summarize
from mapd.train.data import MARGIN, PreparedMap, TileBatch, prepare_map, sample_tiles, split_maps
from mapd.train.install import CARD_FILE, install, output_folder, staging
from mapd.train.settings import TrainConfig, check_settings, pick_device
from mapd.train.snapshots import snapshot_maps

#: Held-out tiles scored at a time.
VAL_CHUNK = 64

# --------------------------------------------------------------------------------------------
# The loop
# --------------------------------------------------------------------------------------------


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


def _batches(
    maps: list[PreparedMap], n: int, size: int, tile: int, rng: np.random.Generator, edge_weight: float = 1.0
) -> Iterator[TileBatch]:
    """``n`` tiles drawn by :func:`sample_tiles`, ``size`` at a time.

    The sampler draws tile after tile from ``rng``, so these are the very tiles (and weights) of
    one ``sample_tiles(maps, n, ...)`` call, without all ``n`` of them in memory at once.
    """
    for i in range(0, n, size):
        yield sample_tiles(maps, min(size, n - i), tile, rng, edge_weight)


def _freeze_bn(net: pn.PaperNet) -> None:
    for m in net.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.eval()


def _label(p: Path, root: Path) -> str:
    return str(p.relative_to(root).parent) if p.is_relative_to(root) else p.stem


def _load_maps(paths: list[Path], root: Path, tile: int) -> list[PreparedMap]:
    return [prepare_map(_label(p, root), load_map(p), tile) for p in paths]


def train(cfg: TrainConfig) -> dict[str, Any]:
    """Train, write ``cfg.out`` (weights.npz, model.json, MODEL_CARD.md) and return model.json's content.

    The folder appears whole or not at all; an existing model there stays whole until the new one
    replaces it, also when the run fails (a full disk, a diverged training).
    """
    check_settings(cfg)
    if cfg.snapshots:
        cfg.snapshots.check()
    out = output_folder(cfg.out)
    saved = ckpt.checkpoint_path(out)
    if not cfg.resume and saved.exists():
        # Starting over would write over the progress of the stopped run.
        raise ConfigError(
            f"{saved} holds a stopped run of -o {out}: add --resume to go on with it, or delete it"
        )
    was_deterministic = torch.are_deterministic_algorithms_enabled()
    was_threads = torch.get_num_threads()
    if cfg.threads:
        # CPU summation order can depend on the thread count, so it is part of the recipe.
        torch.set_num_threads(cfg.threads)
    try:
        return _train(cfg, out)
    finally:
        torch.use_deterministic_algorithms(was_deterministic)
        torch.set_num_threads(was_threads)


def _train(cfg: TrainConfig, out: Path) -> dict[str, Any]:
    from tqdm import tqdm

    from mapd.data import shared_maps

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
    saved = ckpt.checkpoint_path(out)

    train_maps = _load_maps(train_paths, root, cfg.tile)
    recipe: dict[str, Any] = {"finished": cfg.finished, "finished_maps": len(train_paths)}
    if cfg.snapshots:
        snaps, recipe["snapshots"] = snapshot_maps(cfg.snapshots)
        train_maps += [prepare_map(label, grid, cfg.tile) for label, grid in snaps]
    if not train_maps:
        raise ConfigError("nothing to train on: --no-finished needs --snapshots-log or --snapshots-sim")
    val_maps = _load_maps(val_paths, root, cfg.tile)

    net = pn.PaperNet(cfg.levels).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    steps_per_epoch = -(-cfg.tiles_per_epoch // cfg.batch)
    total_steps = cfg.epochs * steps_per_epoch
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * min(s, total_steps) / total_steps))
    )
    settings = ckpt.fingerprint(
        {
            "epochs": cfg.epochs, "tile": cfg.tile, "seed": cfg.seed, "levels": cfg.levels,
            "tiles_per_epoch": cfg.tiles_per_epoch, "batch": cfg.batch, "lr": cfg.lr,
            "edge_weight": cfg.edge_weight, "val_tiles": cfg.val_tiles, "device": device.type,
            "threads": torch.get_num_threads(), "recipe": recipe,
            "train maps": sorted(_label(p, root) for p in train_paths),
            "validation maps": sorted(_label(p, root) for p in val_paths),
        }
    )  # fmt: skip
    history: list[dict[str, Any]] = []
    first, spent, resumed = 0, 0.0, []
    if cfg.resume:
        state = ckpt.load(saved, settings)
        try:
            net.load_state_dict(state["net"])
            opt.load_state_dict(state["opt"])
            sched.load_state_dict(state["sched"])
            rng.bit_generator.state = state["rng"]
            torch.set_rng_state(state["torch_rng"])
            if device.type == "cuda" and "cuda_rng" in state:
                torch.cuda.set_rng_state(state["cuda_rng"], device)
            first, spent, history = int(state["epoch"]), float(state["seconds"]), list(state["history"])
            resumed = [*state["resumed"], first]
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise ConfigError(
                f"--resume: checkpoint {saved} does not fit this run ({type(exc).__name__})"
            ) from None
        if not 0 < first < cfg.epochs:
            raise ConfigError(f"--resume: checkpoint {saved} says {first} epochs of {cfg.epochs} are done")
    bar = tqdm(
        total=total_steps,
        initial=first * steps_per_epoch,
        desc="train",
        unit="step",
        disable=not cfg.progress,
        file=sys.stderr,
    )
    for epoch in range(first, cfg.epochs):
        net.train()
        if epoch == cfg.epochs - 1 and cfg.epochs > 1:
            _freeze_bn(net)
        losses = []
        for batch in _batches(
            train_maps, steps_per_epoch * cfg.batch, cfg.batch, cfg.tile, rng, cfg.edge_weight
        ):
            loss = _loss(net, batch, device)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            losses.append(loss.item())
            bar.update(1)
            bar.set_postfix(epoch=epoch + 1, loss=f"{np.mean(losses[-20:]):.5f}")
        entry = {"epoch": epoch + 1, "train_mse": float(np.mean(losses))}
        if not math.isfinite(entry["train_mse"]):
            bar.close()
            raise MapdError(
                f"training diverged in epoch {epoch + 1} (loss {entry['train_mse']}): try a lower --lr;"
                " no model written"
            )
        if val_maps and cfg.val_tiles > 0:
            net.eval()
            # The same held-out tiles every epoch: drawn again from the same seed, a chunk at a time.
            val_rng = np.random.default_rng(cfg.seed + 1)
            with torch.no_grad():
                vl = [
                    float(_loss(net, b, device)) * b.x.shape[0]
                    for b in _batches(val_maps, cfg.val_tiles, VAL_CHUNK, cfg.tile, val_rng)
                ]
            entry["val_mse"] = sum(vl) / cfg.val_tiles
            bar.set_postfix(epoch=epoch + 1, loss=f"{entry['train_mse']:.5f}", val=f"{entry['val_mse']:.5f}")
        history.append(entry)
        if epoch + 1 < cfg.epochs:
            _save_checkpoint(saved, settings, net, opt, sched, rng, device, epoch + 1, history, resumed,
                             spent + time.time() - started)  # fmt: skip
            if cfg.time_limit and time.time() - started >= cfg.time_limit:
                bar.close()
                raise ckpt.TrainingPaused(
                    f"-o {out}: stopped after epoch {epoch + 1} of {cfg.epochs} (--time-limit"
                    f" {cfg.time_limit:g} s); {saved} holds it: run the same command with --resume to go on"
                )
    bar.close()
    train_seconds = spent + time.time() - started

    net = net.cpu().eval()
    arrays = pm.state_arrays(net)
    bad = sorted(k for k, a in arrays.items() if not np.isfinite(a).all())
    if bad:
        raise MapdError(
            f"training diverged: {len(bad)} weight arrays ({bad[0]}, ...) hold NaN or infinity:"
            " try a lower --lr; no model written"
        )
    name = cfg.name or out.name
    n_params = sum(int(p.numel()) for p in net.parameters())
    meta: dict[str, Any] = {
        "name": name,
        "format": pm.MODEL_FORMAT,
        "levels": cfg.levels,
        "channels": pn.CHANNELS,
        "parameters": n_params,
        "parameters_feature": sum(int(p.numel()) for p in net.feature.parameters()),
        "parameters_recovery": sum(int(p.numel()) for p in net.recovery.parameters()),
        "weights_file": pm.WEIGHTS_FILE,
        "weights_sha256": "",  # set once the weights are written
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
            "resumed_after_epochs": resumed,
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
    try:
        with staging(out) as folder:
            sha = pm.write_weights(folder / pm.WEIGHTS_FILE, arrays)
            meta["weights_sha256"] = sha
            # model.json first without metrics: the evaluation loads the model from the folder.
            (folder / pm.META_FILE).write_text(json.dumps(meta, indent=2) + "\n", encoding="utf-8")
            if cfg.evaluate:
                val_rows = evaluate_maps(folder, val_paths, root)
                train_rows = evaluate_maps(folder, train_paths, root)
                meta["metrics"] = {
                    "validation": summarize(val_rows),
                    "train": summarize(train_rows),
                    "per_map": {"validation": val_rows, "train": train_rows},
                }
                (folder / pm.META_FILE).write_text(
                    json.dumps(meta, indent=2, default=str) + "\n", encoding="utf-8"
                )
            (folder / CARD_FILE).write_text(model_card(meta), encoding="utf-8")
            install(folder, out)
        saved.unlink(missing_ok=True)  # the model is whole: nothing left to resume
    except OSError as exc:
        raise MapdError(
            f"-o {out}: cannot write the model ({exc.strerror or exc}); any model there is unchanged"
        ) from None
    return meta


def _save_checkpoint(
    path: Path,
    settings: dict[str, str],
    net: pn.PaperNet,
    opt: torch.optim.Optimizer,
    sched: torch.optim.lr_scheduler.LRScheduler,
    rng: np.random.Generator,
    device: torch.device,
    epochs_done: int,
    history: list[dict[str, Any]],
    resumed: list[int],
    seconds: float,
) -> None:
    """Everything the epochs after ``epochs_done`` depend on (see :mod:`mapd.train.checkpoint`)."""
    state: dict[str, Any] = {
        "settings": settings,
        "epoch": epochs_done,
        "net": net.state_dict(),
        "opt": opt.state_dict(),
        "sched": sched.state_dict(),
        "rng": rng.bit_generator.state,
        "torch_rng": torch.get_rng_state(),
        "history": history,
        "resumed": resumed,
        "seconds": seconds,
    }
    if device.type == "cuda":
        state["cuda_rng"] = torch.cuda.get_rng_state(device)
    try:
        ckpt.save(path, state)
    except OSError as exc:
        raise MapdError(f"cannot write the checkpoint {path}: {exc.strerror or exc}") from None


def main_train(cfg: TrainConfig) -> dict[str, Any]:
    """:func:`train`, with torch/numpy failures turned into one-line :class:`MapdError`s."""
    try:
        return train(cfg)
    except MapdError:
        raise
    except MemoryError:
        raise MapdError(
            "training failed: out of memory (try a smaller --batch, --tile or --val-tiles, or fewer maps)"
        ) from None
    except (RuntimeError, ValueError, OSError) as exc:
        # torch's messages can run to many lines; the first says what went wrong.
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise MapdError(f"training failed: {first}") from None


__all__ = ["main_train", "train"]
