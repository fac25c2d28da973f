"""The paper's two networks, the quantizer between them, and fast whole-map inference.

Zhang & Deng (2024) give the layers; what they leave open is our choice and says so (see
``models/paper-v3/MODEL_CARD.md`` for the full list):

* **Input.** A cell becomes its map_server grey level minus the unknown grey, over 255:
  ``x = (grey - 205) / 255``, so unknown is 0.0, free (254) is +0.192 and occupied (0) is -0.804.
  The paper's MSE on this scale is exactly the MSE the PSNR measures, and "outside the map" (the
  padding) is 0.0, unknown, which is what it is. Graded cells 0..100 go linearly from free to
  occupied grey (``254 - 2.54 v``).
* **Padding.** Every convolution is *valid* (unpadded); the map is padded once, with unknown, by
  the receptive field. The output of any crop is then exactly the output of the whole map there,
  which lets inference skip tiles whose input is constant (most of a map is uniform unknown or
  free) and lets training use crops with their real surroundings.
* **Quantizer.** ``m_feature`` (the third layer's output) goes through ``(L-1) * sigmoid(.)`` and
  is rounded to one of ``L`` integer levels, the symbols the Huffman stage codes. Training rounds
  too, with a straight-through gradient, so the decoder only ever sees quantized features.
  Level ``q`` means the value ``lo + q (hi - lo) / (L - 1)`` on the input scale (occupied..free).
* **Back to full size.** CNN_recovery's layers 1-5 run at half resolution; the 16-channel
  activation is upsampled 2x (nearest) and layer 6 (3x3x16, one filter) makes the full-resolution
  map (resize-convolution); the residual skip adds the bilinearly upsampled dequantized
  ``m_feature``. See :class:`CNNRecovery` for why.
"""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mapd.errors import CodecError
from mapd.files import atomic_write_bytes
from mapd.grid import GREY_FREE, GREY_OCCUPIED, GREY_UNKNOWN

CHANNELS = 16
#: Full-resolution padding CNN_feature needs around the (even-sized) map: 3 valid layers, one of stride 2.
FEATURE_PAD = 4
#: Half-resolution padding CNN_recovery needs around m_feature: 5 valid layers + layer 6 + bilinear skip.
RECOVERY_PAD = 6
LO = (GREY_OCCUPIED - GREY_UNKNOWN) / 255.0
HI = (GREY_FREE - GREY_UNKNOWN) / 255.0
WEIGHTS_FILE = "weights.npz"
META_FILE = "model.json"
MODEL_FORMAT = 1
#: Full-resolution cells recovered at a time by :meth:`PaperModel.decode_values` (at least one row
#: of tiles): bounds the float32 temporaries of a decode whatever the map's size.
BAND_CELLS = 1 << 20


# --------------------------------------------------------------------------------------------
# Map values <-> network values
# --------------------------------------------------------------------------------------------


def map_to_input(data: np.ndarray) -> np.ndarray:
    """int8 cells to network input (float32): unknown 0.0, free +0.192, occupied -0.804.

    Values 0..100 map linearly between the free and the occupied grey; any negative value is
    unknown (as map_server and :func:`mapd.grid.cell_classes` read it); values above 100 are 100.
    """
    d = np.asarray(data)
    v = np.clip(d, 0, 100).astype(np.float32)
    grey = GREY_FREE - v * ((GREY_FREE - GREY_OCCUPIED) / 100.0)
    grey = np.where(d < 0, np.float32(GREY_UNKNOWN), grey)
    return ((grey - GREY_UNKNOWN) / 255.0).astype(np.float32)


def input_levels(data: np.ndarray) -> np.ndarray:
    """The distinct network input values a map holds (for the constant-tile tables)."""
    return np.unique(map_to_input(np.unique(np.asarray(data))))


# --------------------------------------------------------------------------------------------
# The networks
# --------------------------------------------------------------------------------------------


class CNNFeature(nn.Module):
    """CNN_feature as the paper gives it: three weight layers, the second of stride 2.

    1. conv 3x3, 16 filters, ReLU; 2. conv 3x3x16, 16 filters, stride 2, BatchNorm, ReLU;
    3. conv 3x3x16, 1 filter: ``m_feature`` at half resolution each side. All convolutions are
    valid; the caller pads the map by :data:`FEATURE_PAD` with unknown (0.0).
    """

    def __init__(self, channels: int = CHANNELS) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(1, channels, 3)
        self.c2 = nn.Conv2d(channels, channels, 3, stride=2, bias=False)
        self.bn2 = nn.BatchNorm2d(channels)
        self.c3 = nn.Conv2d(channels, 1, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = F.relu(self.c1(x))
        x = F.relu(self.bn2(self.c2(x)))
        return self.c3(x)


class CNNRecovery(nn.Module):
    """CNN_recovery as the paper gives it: six weight layers and a skip from input to output.

    1. conv 3x3, 16 filters, ReLU; 2.-5. conv 3x3x16 + BatchNorm + ReLU; 6. conv 3x3x16, one
    filter, the full-resolution map; plus the (upsampled) input.

    How m_feature gets back to full size is our choice, because the paper does not say: layers 1-5
    run at half resolution, the 16 channels are upsampled 2x by nearest neighbour, and layer 6 runs
    at full resolution (a resize-convolution, Odena et al. 2016). Why: running the five 16-channel
    layers at half resolution costs about 2.5k multiply-adds per cell instead of 9.5k for the
    pre-upsampling design (VDSR-style) - upsampling first measured 8-11 s for a 2000x2000 map on
    this project's shared 2-core CPU, far past the 2 s budget - while doubling the receptive field in full-resolution cells (ESPCN, Shi et al. 2016, found
    low-resolution processing as good or better); and a full-resolution last layer keeps the
    paper's single filter producing the map itself. The skip adds m_feature's dequantized value,
    upsampled bilinearly, so the layers learn only the residual detail.

    Input: dequantized m_feature padded by :data:`RECOVERY_PAD` (valid convolutions). Output: the
    map on the input scale, ``2 * (h - 2 * RECOVERY_PAD)`` cells each side.
    """

    def __init__(self, channels: int = CHANNELS) -> None:
        super().__init__()
        self.c1 = nn.Conv2d(1, channels, 3)
        self.mid = nn.ModuleList([nn.Conv2d(channels, channels, 3, bias=False) for _ in range(4)])
        self.bns = nn.ModuleList([nn.BatchNorm2d(channels) for _ in range(4)])
        self.c6 = nn.Conv2d(channels, 1, 3)

    def residual(self, f: torch.Tensor) -> torch.Tensor:
        """The learned part alone, without the skip (full resolution, cropped to the interior)."""
        x = F.relu(self.c1(f))
        for conv, bn in zip(self.mid, self.bns, strict=True):
            x = F.relu(bn(conv(x)))
        x = F.interpolate(x, scale_factor=2.0, mode="nearest")
        x = self.c6(x)
        return x[:, :, 1:-1, 1:-1]

    @staticmethod
    def skip(f: torch.Tensor) -> torch.Tensor:
        """The bilinearly upsampled input, cropped to the same interior as :meth:`residual`."""
        up = (
            bilinear2x(f)
            if f.is_cuda
            else F.interpolate(f, scale_factor=2.0, mode="bilinear", align_corners=False)
        )
        m = 2 * RECOVERY_PAD
        return up[:, :, m:-m, m:-m]

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.residual(f) + self.skip(f)


def bilinear2x(f: torch.Tensor) -> torch.Tensor:
    """``F.interpolate(f, scale_factor=2, mode="bilinear", align_corners=False)``, from operations
    whose gradient CUDA computes deterministically.

    ``torch.use_deterministic_algorithms(True)``, which ``mapd train`` sets so that a run can be
    repeated, refuses the backward pass of bilinear interpolation on CUDA (torch lists it among
    the operations it refuses: that pass sums with atomics), so training on a GPU would stop at its
    first step. The same upsampling is a transposed
    convolution: output cell ``2m`` is ``0.75 f[m] + 0.25 f[m-1]`` and ``2m+1`` is
    ``0.75 f[m] + 0.25 f[m+1]`` along each axis, and the edge rows repeat (interpolate clamps its
    source index there), hence the replicate padding. On the CPU the two agree to float rounding;
    the CPU keeps ``F.interpolate``, so the shipped weights' payloads stay bit for bit.
    """
    c = f.shape[1]
    k = torch.tensor([0.25, 0.75, 0.75, 0.25], dtype=f.dtype, device=f.device)
    w = (k[:, None] * k[None, :]).expand(c, 1, 4, 4).contiguous()
    up = F.conv_transpose2d(F.pad(f, (1, 1, 1, 1), mode="replicate"), w, stride=2, groups=c)
    return up[:, :, 3:-3, 3:-3]


class Quantizer(nn.Module):
    """m_feature to one of ``levels`` integer symbols, and symbols back to input-scale values.

    ``(L-1) * sigmoid(z)`` rounded; during training the rounding passes the gradient straight
    through, so the forward pass is the same quantized value the decoder will see.
    """

    def __init__(self, levels: int) -> None:
        super().__init__()
        if not 2 <= levels <= 256:
            raise ValueError(f"levels must be 2..256, got {levels}")
        self.levels = levels

    def soft(self, z: torch.Tensor) -> torch.Tensor:
        return (self.levels - 1) * torch.sigmoid(z)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        """Straight-through rounding: quantized symbols forward, identity gradient backward."""
        u = self.soft(z)
        return u + (torch.round(u) - u).detach()

    def symbols(self, z: torch.Tensor) -> torch.Tensor:
        return torch.round(self.soft(z)).to(torch.uint8)

    def value(self, q: torch.Tensor) -> torch.Tensor:
        """Symbol (or straight-through symbol) to its value on the input scale."""
        return LO + q * ((HI - LO) / (self.levels - 1))


class PaperNet(nn.Module):
    """CNN_feature, quantizer and CNN_recovery, trained end to end."""

    def __init__(self, levels: int, channels: int = CHANNELS) -> None:
        super().__init__()
        self.levels = levels
        self.channels = channels
        self.feature = CNNFeature(channels)
        self.quant = Quantizer(levels)
        self.recovery = CNNRecovery(channels)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A padded input crop to (recovered interior, straight-through symbols).

        ``x`` is ``2 * (t + 2 * RECOVERY_PAD) + 2 * FEATURE_PAD`` cells each side for a ``2t`` output.
        """
        q = self.quant(self.feature(x))
        return self.recovery(self.quant.value(q)), q


def crop_margin() -> int:
    """Full-resolution context a training crop needs on each side of its output tile."""
    return 2 * RECOVERY_PAD + FEATURE_PAD


# --------------------------------------------------------------------------------------------
# Weights on disk: deterministic npz + model.json with the sha256
# --------------------------------------------------------------------------------------------


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


# --------------------------------------------------------------------------------------------
# Inference: whole maps, tile by tile, skipping constant tiles
# --------------------------------------------------------------------------------------------


def _fold_bn(conv: nn.Module, bn: nn.Module | None) -> nn.Conv2d:
    """An eval-time conv with BatchNorm folded in (same function, one layer fewer)."""
    assert isinstance(conv, nn.Conv2d)
    stride = conv.stride[0]
    out = nn.Conv2d(conv.in_channels, conv.out_channels, 3, stride=stride)
    w = conv.weight.detach().clone()
    b = conv.bias.detach().clone() if conv.bias is not None else torch.zeros(conv.out_channels)
    if bn is not None:
        assert isinstance(bn, nn.BatchNorm2d)
        assert bn.running_var is not None and bn.running_mean is not None
        scale = bn.weight.detach() / torch.sqrt(bn.running_var + bn.eps)
        w = w * scale[:, None, None, None]
        b = (b - bn.running_mean) * scale + bn.bias.detach()
    with torch.no_grad():
        out.weight.copy_(w)
        assert out.bias is not None
        out.bias.copy_(b)
    return out.eval()


class _Chain:
    """Folded convolutions with ReLU between them (eval only)."""

    def __init__(self, convs: list[nn.Conv2d], relu_last: bool) -> None:
        self.convs = convs
        self.relu_last = relu_last

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        for i, conv in enumerate(self.convs):
            x = conv(x)
            if i < len(self.convs) - 1 or self.relu_last:
                x = torch.relu_(x)
        return x


class _FeatureInfer(nn.Module):
    def __init__(self, net: CNNFeature) -> None:
        super().__init__()
        self.chain = _Chain(
            [_fold_bn(net.c1, None), _fold_bn(net.c2, net.bn2), _fold_bn(net.c3, None)], False
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.chain(x)


def _phase_conv(conv: nn.Conv2d) -> nn.Conv2d:
    """A 3x3 conv after 2x nearest upsampling, rewritten as a half-resolution conv with 4 outputs.

    Output cell (2i + a, 2j + b) of ``conv(upsample(x))`` reads upsampled rows 2i + a - 1 .. 2i + a + 1,
    which are half-resolution rows ``i + (a + dy) // 2``. Summing the taps that land on the same
    half-resolution cell gives one 3x3 kernel per phase (a, b); ``pixel_shuffle`` then interleaves
    the phases. Same arithmetic, without the 16-channel full-resolution tensor.
    """
    w = conv.weight.detach()
    assert conv.bias is not None
    out_c, in_c = w.shape[:2]
    k = torch.zeros(out_c * 4, in_c, 3, 3)
    for o in range(out_c):
        for a in range(2):
            for b in range(2):
                for dy in range(3):
                    for dx in range(3):
                        r = 1 + (a + dy - 1) // 2
                        c = 1 + (b + dx - 1) // 2
                        k[o * 4 + a * 2 + b, :, r, c] += w[o, :, dy, dx]
    out = nn.Conv2d(in_c, out_c * 4, 3)
    with torch.no_grad():
        out.weight.copy_(k)
        assert out.bias is not None
        out.bias.copy_(conv.bias.detach().repeat_interleave(4))
    return out.eval()


class _RecoveryInfer(nn.Module):
    def __init__(self, net: CNNRecovery) -> None:
        super().__init__()
        mid = [_fold_bn(c, b) for c, b in zip(net.mid, net.bns, strict=True)]
        self.low = _Chain([_fold_bn(net.c1, None), *mid], True)
        self.c6 = _phase_conv(_fold_bn(net.c6, None))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return F.pixel_shuffle(self.c6(self.low(f)), 2)


def _tiles(arr: np.ndarray, tile: int, halo: int, step: int) -> np.ndarray:
    """Overlapping (rows, cols, size, size) view: tile (i, j) starts at (i*step, j*step)."""
    size = tile + halo
    rows = (arr.shape[0] - halo) // step
    cols = (arr.shape[1] - halo) // step
    s0, s1 = arr.strides
    return np.lib.stride_tricks.as_strided(
        arr, shape=(rows, cols, size, size), strides=(s0 * step, s1 * step, s0, s1), writeable=False
    )


@dataclass
class PaperModel:
    """A loaded, eval-mode model with its metadata and the cached constant-tile responses."""

    name: str
    sha256: str
    meta: dict[str, Any]
    net: PaperNet
    tile: int = 48  # half-resolution cells per inference tile side
    batch: int = 32
    _feat: _FeatureInfer = field(init=False)
    _rec: _RecoveryInfer = field(init=False)
    _const_res: np.ndarray = field(init=False)
    _const_sym: dict[float, int] = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.net.eval()
        self._feat = _FeatureInfer(self.net.feature).eval()
        self._rec = _RecoveryInfer(self.net.recovery).eval()
        levels = torch.arange(self.levels, dtype=torch.float32)
        vals = self.net.quant.value(levels).reshape(-1, 1, 1, 1)
        side = 2 * RECOVERY_PAD + 1
        with torch.inference_mode():
            out = self._rec(vals.expand(-1, 1, side, side).contiguous())
        self._const_res = out[:, 0, 0, 0].numpy().astype(np.float32)
        self.unknown_symbol = self.symbols_for_constants(np.array([0.0], dtype=np.float32))[0]

    @property
    def levels(self) -> int:
        return self.net.levels

    @property
    def variant(self) -> str:
        return f"{self.name}:{self.sha256[:12]}"

    def symbols_for_constants(self, values: np.ndarray) -> np.ndarray:
        """m_feature symbols of maps that are one constant input value everywhere."""
        missing = [float(v) for v in values if float(v) not in self._const_sym]
        if missing:
            side = 2 + 2 * FEATURE_PAD
            x = torch.tensor(missing, dtype=torch.float32).reshape(-1, 1, 1, 1).expand(-1, 1, side, side)
            with torch.inference_mode():
                z = self._feat(x.contiguous())
            syms = self.net.quant.symbols(z)[:, 0, 0, 0].numpy()
            for v, s in zip(missing, syms, strict=True):
                self._const_sym[v] = int(s)
        return np.array([self._const_sym[float(v)] for v in values], dtype=np.uint8)

    def _run_tiles(
        self, padded: np.ndarray, tile_in: int, halo: int, step: int, fn: Any, out_tile: int, fill: Any
    ) -> np.ndarray:
        """Apply ``fn`` to every non-constant tile of ``padded``; constant tiles get ``fill(value)``."""
        view = _tiles(padded, tile_in, halo, step)
        rows, cols = view.shape[:2]
        lo = view.min(axis=(2, 3))
        hi = view.max(axis=(2, 3))
        out = np.empty((rows, cols, out_tile, out_tile), dtype=np.float32)
        const = lo == hi
        if const.any():
            out[const] = fill(lo[const])[:, None, None]
        active = np.argwhere(~const)
        with torch.inference_mode():
            for start in range(0, len(active), self.batch):
                idx = active[start : start + self.batch]
                crops = np.stack([view[i, j] for i, j in idx])[:, None]
                res = fn(torch.from_numpy(crops)).numpy()
                out[idx[:, 0], idx[:, 1]] = res[:, 0]
        return out.transpose(0, 2, 1, 3).reshape(rows * out_tile, cols * out_tile)

    def encode_symbols(self, x: np.ndarray) -> np.ndarray:
        """Network input (H, W) to m_feature symbols (ceil(H/2), ceil(W/2)) as uint8."""
        h_out, w_out = (x.shape[0] + 1) // 2, (x.shape[1] + 1) // 2
        t = self.tile
        rows, cols = -(-h_out // t), -(-w_out // t)
        padded = np.zeros((2 * rows * t + 2 * FEATURE_PAD, 2 * cols * t + 2 * FEATURE_PAD), dtype=np.float32)
        padded[FEATURE_PAD : FEATURE_PAD + x.shape[0], FEATURE_PAD : FEATURE_PAD + x.shape[1]] = x

        def fn(crops: torch.Tensor) -> torch.Tensor:
            return self.net.quant.soft(self._feat(crops)).round()

        def fill(values: np.ndarray) -> np.ndarray:
            return self.symbols_for_constants(values).astype(np.float32)

        sym = self._run_tiles(padded, 2 * t, 2 * FEATURE_PAD, 2 * t, fn, t, fill)
        return sym[:h_out, :w_out].astype(np.uint8)

    def decode_values(
        self,
        sym: np.ndarray,
        height: int,
        width: int,
        finish: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> np.ndarray:
        """m_feature symbols (h, w) to the recovered map (height, width) on the input scale.

        The map is recovered a band of tile rows at a time (about :data:`BAND_CELLS` cells), and
        ``finish``, when given, turns each band of float32 values into what is kept (the codec snaps
        it to int8 cells): then the float32 map, its skip path and the tiles' outputs never exist for
        the whole map, and a decode's memory is the output and the symbols plus a few tens of MiB.
        Tiles are independent and the bilinear skip of a band reads one half-resolution row beyond
        it on each side, so the result is the same, bit for bit, as recovering the whole map at once.
        """
        h, w = sym.shape
        t = self.tile
        rows, cols = -(-h // t), -(-w // t)
        p = RECOVERY_PAD
        values = self.net.quant.value(torch.arange(self.levels, dtype=torch.float32)).numpy()
        padded_h, padded_w = rows * t + 2 * p, cols * t + 2 * p
        outside = values[self.unknown_symbol]

        def padded(r0: int, r1: int) -> np.ndarray:
            # Rows r0..r1 of the dequantized m_feature padded with unknown, made when a band needs
            # them: the whole padded array would be one more float32 per four cells of the map.
            rows_ = np.full((r1 - r0, padded_w), outside, dtype=np.float32)
            s0, s1 = max(r0, p), min(r1, p + h)
            if s1 > s0:
                rows_[s0 - r0 : s1 - r0, p : p + w] = values[sym[s0 - p : s1 - p]]
            return rows_

        by_value = {float(v): float(r) for v, r in zip(values, self._const_res, strict=True)}

        def fn(crops: torch.Tensor) -> torch.Tensor:
            return self._rec(crops)

        def fill(vals: np.ndarray) -> np.ndarray:
            return np.array([by_value[float(v)] for v in vals], dtype=np.float32)

        out: np.ndarray | None = None
        step = max(1, BAND_CELLS // (4 * t * t * cols))  # tile rows per band
        for i0 in range(0, rows, step):
            y0 = 2 * t * i0
            if y0 >= height:
                break
            i1 = min(rows, i0 + step)
            y1 = min(height, 2 * t * i1)
            res = self._run_tiles(padded(i0 * t, i1 * t + 2 * p), t, 2 * p, t, fn, 2 * t, fill)
            # CNNRecovery.skip on the whole map is the 2x bilinear upsampling of the padded features
            # cropped by 2p cells. Full-resolution row y reads half-resolution rows (y + 2p) / 2 +- 1,
            # so the band's rows come from padded rows a..b with one row to spare on each side.
            a = max(0, i0 * t + p - 1)
            b = min(padded_h, i1 * t + p + 1)
            with torch.inference_mode():
                up = F.interpolate(
                    torch.from_numpy(padded(a, b))[None, None],
                    scale_factor=2.0,
                    mode="bilinear",
                    align_corners=False,
                )[0, 0].numpy()
            m = 2 * p
            skip = up[y0 + m - 2 * a : y1 + m - 2 * a, m : m + width]
            band = (res[: y1 - y0, :width] + skip).astype(np.float32)
            kept = finish(band) if finish is not None else band
            if out is None:
                out = np.empty((height, width), dtype=kept.dtype)
            out[y0:y1] = kept
        assert out is not None
        return out


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
