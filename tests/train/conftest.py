"""What the training tests share: small walled rooms saved as map_server maps, one folder a place."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mapd.grid import OccupancyGrid
from mapd.grid.save import save_map


def write_rooms(root: Path, places: list[str], height: int, width: int) -> Path:
    """A walled room per place under ``root/<place>/map.yaml``, each two rows taller than the one before."""
    for i, place in enumerate(places):
        d = np.full((height + 2 * i, width), -1, dtype=np.int8)
        d[3:-3, 4:-4] = 0
        d[3, 4:-4] = d[-4, 4:-4] = d[3:-3, 4] = d[3:-3, -5] = 100
        save_map(OccupancyGrid(d, 0.05), root / place / "map.yaml")
    return root
