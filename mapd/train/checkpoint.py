"""Training that survives a stop: the state after each epoch, kept beside the model folder.

A 200-epoch run takes most of an hour on two cores, and a GPU machine may be lent for ten minutes a
command. So after every epoch but the last, ``mapd train`` writes everything that decides the rest
of the run to ``<-o>.checkpoint`` (weights, BatchNorm statistics, Adam's moments, the learning-rate
schedule's step, the tile sampler's and torch's generators, the history so far, the seconds spent):
a power cut, a kill or ``--time-limit`` loses at most one epoch. ``--resume`` goes on from it, and
gives **the same weights, bit for bit, as a run that never stopped** (same device kind and thread
count, as for any two runs).

The file is written to a temporary name, fsynced and renamed, so it is always the last whole epoch.
It records the settings that decide the weights (:func:`fingerprint`); resuming with others is
refused by name, since it would silently train a model that no command line describes. A run that
finishes removes it. It is read with ``torch.load(weights_only=True)`` (tensors, numbers, strings
and containers only: no code runs from the file), and a damaged or foreign file is one
:class:`~mapd.errors.ConfigError`, never a traceback.
"""

from __future__ import annotations

import os
import pickle
import tempfile
import zipfile
from pathlib import Path
from typing import Any

import torch

from mapd.errors import ConfigError

#: Bump when what a checkpoint holds changes; older ones are then refused by name.
FORMAT = 1
#: Read at most this much: a checkpoint of the largest network mapd trains is under 1 MiB.
MAX_BYTES = 64 << 20


class TrainingPaused(Exception):
    """``--time-limit`` ended the run after a whole epoch; the checkpoint holds it. Not an error."""


def checkpoint_path(out: Path) -> Path:
    """Where the run writing model folder ``out`` keeps its checkpoint: ``<out>.checkpoint``."""
    return out.with_name(out.name + ".checkpoint")


def fingerprint(settings: dict[str, Any]) -> dict[str, str]:
    """The settings that decide the weights, as strings (so floats compare as they were given)."""
    return {k: repr(v) for k, v in sorted(settings.items())}


def save(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` to ``path`` atomically: the old checkpoint stays whole until the new one is."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save({"format": FORMAT, **state}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(path: Path, expected: dict[str, str]) -> dict[str, Any]:
    """The checkpoint at ``path``, checked against the settings ``expected`` of this run."""
    what = f"checkpoint {path}"
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise ConfigError(f"--resume: no {what} (it is written after each epoch of a run)") from None
    except OSError as exc:
        raise ConfigError(f"--resume: cannot read {what}: {exc.strerror or exc}") from None
    if size > MAX_BYTES:
        raise ConfigError(f"--resume: {what} is {size} bytes, more than a checkpoint can be")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError, ValueError, pickle.UnpicklingError, zipfile.BadZipFile) as exc:
        raise ConfigError(f"--resume: {what} is damaged or not a checkpoint ({type(exc).__name__})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        raise ConfigError(f"--resume: {what} is not a checkpoint of this mapd (format {FORMAT})")
    got = state.get("settings")
    if not isinstance(got, dict):
        raise ConfigError(f"--resume: {what} names no settings")
    for key in sorted(set(expected) | set(got)):
        if got.get(key) != expected.get(key):
            raise ConfigError(
                f"--resume: {what} was made with {key} {got.get(key, 'unset')}, this run has"
                f" {expected.get(key, 'unset')}: give the same settings, or delete it to start over"
            )
    return state
