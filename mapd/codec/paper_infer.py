"""Whole-map inference with a trained paper model: fast, tile by tile, skipping constant tiles.

Every convolution of the networks is valid (:mod:`mapd.codec.paper_net`), so the output of a crop is
exactly the output of the whole map there. :class:`PaperModel` uses that: the map is cut into
overlapping tiles, a tile whose input is one constant value everywhere (most of a map is uniform
unknown or free) takes its answer from a table computed once per model, and the others run in
batches. For speed at inference BatchNorm is folded into the convolutions before it, and the
recovery's last layer (3x3 after 2x nearest upsampling) is rewritten as a half-resolution
convolution with four outputs per cell. A decode is recovered a band of tile rows at a time, so its
memory stays bounded whatever the map's size, with the same result, bit for bit.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mapd.codec.paper_net import FEATURE_PAD, RECOVERY_PAD, CNNFeature, CNNRecovery, PaperNet

#: Full-resolution cells recovered at a time by :meth:`PaperModel.decode_values` (at least one row
#: of tiles): bounds the float32 temporaries of a decode whatever the map's size.
BAND_CELLS = 1 << 20


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
