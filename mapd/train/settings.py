"""What decides a ``mapd train`` run, and the bounds every setting is checked against first.

* :class:`TrainConfig` holds everything that decides the weights (recorded in ``model.json``).
* **Bad settings** are refused before any work, one line naming the option (:func:`check_settings`;
  the model folder: :func:`~mapd.train.install.output_folder`): every size has an upper bound, so
  memory stays bounded; tiles are drawn a batch at a time.
* :func:`pick_device` turns ``--device`` into a torch device, refusing ``cuda`` where there is none.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from mapd.errors import ConfigError
from mapd.train.data import MARGIN
from mapd.train.snapshots import SnapshotSpec

#: Upper bounds of the settings, so that a typo costs one error line instead of the machine's memory
#: (or a crash inside torch's thread pool). Torch threads: as ``[codec.paper] threads``.
MAX_THREADS = 256
#: The codec infers on 96-cell tiles and the shipped model trained on 64-cell ones.
MAX_TILE = 256
MAX_BATCH = 1024
#: Input cells of one step, batch x (tile + 2 MARGIN)²: 28 times the shipped recipe's 16 x 96², so
#: the activations kept for the backward pass stay within a few GiB whatever --batch and --tile say.
MAX_STEP_CELLS = 1 << 22
#: Tiles are drawn a batch at a time, so these bound the time of an epoch, not its memory.
MAX_TILES_PER_EPOCH = 1 << 20
MAX_VAL_TILES = 1 << 16
MAX_EPOCHS = 100_000
#: Adam's step size; far above this every run diverges.
MAX_LR = 1.0


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
    #: Go on from ``<out>.checkpoint`` (same settings) instead of starting over.
    resume: bool = False
    #: Seconds after which the run stops at the end of an epoch, checkpoint kept (0: no limit).
    time_limit: float = 0.0
    extra: dict[str, Any] = field(default_factory=dict)


def pick_device(name: str) -> torch.device:
    """The torch device ``--device`` names (``auto``: CUDA where there is one), or one ConfigError."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise ConfigError(f"--device must be auto, cpu or cuda, got '{name}'")
    return torch.device(name)


def check_settings(cfg: TrainConfig) -> None:
    """Refuse a setting out of range with one line naming the option, before any work is done."""
    if not 0 <= cfg.threads <= MAX_THREADS:
        raise ConfigError(f"--threads must be 0 (torch's default) to {MAX_THREADS}, got {cfg.threads}")
    for option, value, most in (
        ("--epochs", cfg.epochs, MAX_EPOCHS),
        ("--tiles-per-epoch", cfg.tiles_per_epoch, MAX_TILES_PER_EPOCH),
        ("--batch", cfg.batch, MAX_BATCH),
    ):
        if not 1 <= value <= most:
            raise ConfigError(f"{option} must be 1 to {most}, got {value}")
    if not 0 <= cfg.val_tiles <= MAX_VAL_TILES:
        raise ConfigError(f"--val-tiles must be 0 to {MAX_VAL_TILES}, got {cfg.val_tiles}")
    if not (math.isfinite(cfg.lr) and 0.0 < cfg.lr <= MAX_LR):
        raise ConfigError(f"--lr must be a number in (0, {MAX_LR:g}], got {cfg.lr}")
    if not 0.0 < cfg.edge_weight <= 1000.0:
        raise ConfigError(f"--edge-weight must be in (0, 1000], got {cfg.edge_weight}")
    if not 8 <= cfg.tile <= MAX_TILE or cfg.tile % 4:
        raise ConfigError(f"--tile must be a multiple of 4 from 8 to {MAX_TILE}, got {cfg.tile}")
    step = cfg.batch * (cfg.tile + 2 * MARGIN) ** 2
    if step > MAX_STEP_CELLS:
        raise ConfigError(
            f"--batch {cfg.batch} of --tile {cfg.tile} tiles is {step} input cells a step, over the"
            f" {MAX_STEP_CELLS} allowed: use a smaller --batch or --tile"
        )
    if not 2 <= cfg.levels <= 256:
        raise ConfigError(f"--levels must be 2 to 256, got {cfg.levels}")
    if not 0 <= cfg.seed < 2**63:  # torch and numpy take seeds in this range
        raise ConfigError(f"--seed must be 0 to 2**63 - 1, got {cfg.seed}")
    if not (math.isfinite(cfg.time_limit) and cfg.time_limit >= 0):
        raise ConfigError(f"--time-limit must be a number of seconds >= 0, got {cfg.time_limit}")
