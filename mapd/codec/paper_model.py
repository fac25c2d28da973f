"""A paper model folder on disk: ``weights.npz`` and ``model.json``, written and loaded checked.

The weights are written as an ``.npz`` whose bytes depend only on the arrays (fixed zip timestamps),
so one training gives one sha256, and ``model.json`` records that sha256. :func:`load_model` refuses
a folder whose weights do not match it (a tampered or half-copied model), whose format this mapd does
not read, or whose arrays do not fit the network, each as one :class:`~mapd.errors.CodecError`; the
weights are read with ``allow_pickle=False``, so no code runs from the file. Models are found by
name (the folder's) and named in payloads by that name and the sha256's first 12 hex digits.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np
import torch

from mapd.codec.paper_infer import PaperModel
from mapd.codec.paper_net import CHANNELS, PaperNet
from mapd.errors import CodecError
from mapd.files import atomic_write_bytes

WEIGHTS_FILE = "weights.npz"
META_FILE = "model.json"
MODEL_FORMAT = 1


def state_arrays(net: PaperNet) -> dict[str, np.ndarray]:
    """The state dict as float32 numpy arrays (BatchNorm's batch counter dropped)."""
    out = {}
    for k, v in net.state_dict().items():
        if k.endswith("num_batches_tracked"):
            continue
        out[k] = v.detach().cpu().numpy().astype(np.float32)
    return out


def write_weights(path: Path, arrays: dict[str, np.ndarray]) -> str:
    """Write an ``.npz`` whose bytes depend only on the arrays (fixed zip timestamps); return sha256."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            arr_buf = io.BytesIO()
            np.lib.format.write_array(arr_buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            zf.writestr(info, arr_buf.getvalue())
    data = buf.getvalue()
    atomic_write_bytes(path, data)  # a full disk leaves the weights there before whole
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_model(model_dir: Path) -> PaperModel:
    """Load ``model.json`` + ``weights.npz`` from ``model_dir``, checking the recorded sha256.

    Raises :class:`CodecError` when the folder, the files or the arrays are missing or do not
    match; the weights are read with ``allow_pickle=False`` (no code runs from the file).
    """
    meta_path = model_dir / META_FILE
    weights_path = model_dir / WEIGHTS_FILE
    if not meta_path.is_file() or not weights_path.is_file():
        # Name what is there: after an upgrade renames the shipped model (paper-v1 -> paper-v3), a
        # config that still names the old one should say which names would work.
        parent = model_dir.parent
        have = sorted(m.parent.name for m in parent.glob(f"*/{META_FILE}")) if parent.is_dir() else []
        raise CodecError(
            f"paper model not found: {model_dir} needs {META_FILE} and {WEIGHTS_FILE}"
            f" (models in {parent}: {', '.join(have) or 'none'})"
        )
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
        levels = int(meta["levels"])
        channels = int(meta.get("channels", CHANNELS))
        expect = str(meta["weights_sha256"])
        fmt = int(meta.get("format", MODEL_FORMAT))
    except (OSError, ValueError, KeyError, TypeError, OverflowError, RecursionError) as exc:
        raise CodecError(f"{meta_path}: unreadable model metadata ({exc})") from None
    if fmt != MODEL_FORMAT:
        raise CodecError(f"{meta_path}: model format {fmt}, this mapd reads {MODEL_FORMAT}")
    actual = sha256_file(weights_path)
    if actual != expect:
        raise CodecError(f"{weights_path}: sha256 {actual[:12]} does not match model.json ({expect[:12]})")
    try:
        net = PaperNet(levels, channels)
    except ValueError as exc:
        raise CodecError(f"{meta_path}: {exc}") from None
    state = net.state_dict()
    try:
        with np.load(weights_path, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, zipfile.BadZipFile) as exc:
        raise CodecError(f"{weights_path}: unreadable weights ({exc})") from None
    want = {k for k in state if not k.endswith("num_batches_tracked")}
    if set(arrays) != want:
        raise CodecError(f"{weights_path}: weights do not fit the {levels}-level paper network")
    for k, arr in arrays.items():
        if tuple(arr.shape) != tuple(state[k].shape):
            raise CodecError(f"{weights_path}: '{k}' has shape {arr.shape}, expected {tuple(state[k].shape)}")
        state[k] = torch.from_numpy(np.ascontiguousarray(arr, dtype=np.float32))
    net.load_state_dict(state)
    return PaperModel(name=str(meta.get("name", model_dir.name)), sha256=actual, meta=meta, net=net)
