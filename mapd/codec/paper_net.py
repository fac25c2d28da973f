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

Running the trained networks on whole maps fast is :mod:`mapd.codec.paper_infer`'s; the model folder
on disk (weights, ``model.json``, the sha256 check) is :mod:`mapd.codec.paper_model`'s.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from mapd.grid import GREY_FREE, GREY_OCCUPIED, GREY_UNKNOWN

CHANNELS = 16
#: Full-resolution padding CNN_feature needs around the (even-sized) map: 3 valid layers, one of stride 2.
FEATURE_PAD = 4
#: Half-resolution padding CNN_recovery needs around m_feature: 5 valid layers + layer 6 + bilinear skip.
RECOVERY_PAD = 6
LO = (GREY_OCCUPIED - GREY_UNKNOWN) / 255.0
HI = (GREY_FREE - GREY_UNKNOWN) / 255.0


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
