"""Fusing the fleet's maps into one global map.

Pure functions (no asyncio):

* :func:`estimate_transform` (``mapd.fusion.estimate``): b's map frame in a's map frame, with a
  confidence, the overlap agreement and the inlier count, or "not accepted" with the reason;
* :func:`merge` (``mapd.fusion.merge``): the global map of maps placed in the fleet frame, log-odds or
  occupied-wins, honouring each map's origin and resolution;
* :class:`Placer` (``mapd.fusion.placer``): known poses and estimates together, held stable
  across updates (never flips).

and the asyncio owner of the global map, :class:`FusionWorker` (``mapd.fusion.worker``).
Names are imported lazily, so ``import mapd.fusion.transforms`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "Estimate": "mapd.fusion.estimate",
    "EstimateOptions": "mapd.fusion.options",
    "estimate_transform": "mapd.fusion.estimate",
    "check_transform": "mapd.fusion.estimate",
    "Bounds": "mapd.fusion.merge",
    "MergeResult": "mapd.fusion.merge",
    "MODES": "mapd.fusion.merge",
    "merge": "mapd.fusion.merge",
    "merge_with_owner": "mapd.fusion.merge",
    "Placement": "mapd.fusion.placement",
    "Placer": "mapd.fusion.placer",
    "FusionWorker": "mapd.fusion.worker",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'mapd.fusion' has no attribute '{name}'")
    return getattr(importlib.import_module(module), name)
