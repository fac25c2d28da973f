"""Map-quality metrics shared by the benches and the paper evaluation.

PSNR and SSIM are computed on the map image in map_server grey levels (free 254, occupied 0,
unknown 205) with data range 255 over the whole grid; SSIM uses the usual 7x7 uniform window
(scikit-image's ``structural_similarity`` defaults). This is how the paper's 50.6 dB / 0.975 are
read here; identical maps give PSNR = inf.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from mapd.grid import CLASS_OCCUPIED, CLASS_UNKNOWN, cell_classes, grey_levels


def psnr(reference: np.ndarray, test: np.ndarray) -> float:
    """PSNR in dB between two int8 grids' grey-level images (inf when identical)."""
    a = grey_levels(reference).astype(np.float64)
    b = grey_levels(test).astype(np.float64)
    mse = float(np.mean((a - b) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0**2 / mse)


def ssim(reference: np.ndarray, test: np.ndarray) -> float:
    """Mean SSIM (7x7 window, data range 255) between two int8 grids' grey-level images."""
    from skimage.metrics import structural_similarity

    a = grey_levels(reference)
    b = grey_levels(test)
    if min(a.shape) < 7:
        return 1.0 if np.array_equal(a, b) else float(np.mean(a == b))
    return float(structural_similarity(a, b, win_size=7, data_range=255))


def occupied_f1(reference: np.ndarray, test: np.ndarray, tolerance: int = 0) -> float:
    """F1 of occupied cells; with ``tolerance`` > 0 a cell within that many cells counts as a match."""
    ref = cell_classes(reference) == CLASS_OCCUPIED
    tst = cell_classes(test) == CLASS_OCCUPIED
    if not ref.any() and not tst.any():
        return 1.0
    if tolerance > 0:
        st = np.ones((2 * tolerance + 1, 2 * tolerance + 1), dtype=bool)
        ref_near = ndimage.binary_dilation(ref, structure=st)
        tst_near = ndimage.binary_dilation(tst, structure=st)
    else:
        ref_near, tst_near = ref, tst
    precision = float((tst & ref_near).sum()) / max(int(tst.sum()), 1)
    recall = float((ref & tst_near).sum()) / max(int(ref.sum()), 1)
    return 0.0 if precision + recall == 0 else 2 * precision * recall / (precision + recall)


def class_change(reference: np.ndarray, test: np.ndarray) -> float:
    """Share of the reference's known cells whose class (free/occupied/unknown) differs in ``test``."""
    a = cell_classes(reference)
    b = cell_classes(test)
    known = a != CLASS_UNKNOWN
    n = int(known.sum())
    return 0.0 if n == 0 else float((a[known] != b[known]).sum()) / n


def quality(reference: np.ndarray, test: np.ndarray) -> dict[str, float]:
    """All four metrics at once."""
    return {
        "psnr": psnr(reference, test),
        "ssim": ssim(reference, test),
        "f1": occupied_f1(reference, test),
        "changed": class_change(reference, test),
    }
