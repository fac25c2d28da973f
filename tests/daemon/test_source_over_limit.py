"""A robot whose own map outgrows ``limits.max_cells`` stops sharing it: said once, and shown.

Before, each skipped map was a warning of its own (a line per map, all day) that named no fix, and
``mapd status`` still said "map v12" and no fault: the robot looked healthy while no peer got its
map again, nor did its own global map.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from mapd import config as configmod
from mapd.commands.status_text import render_status
from mapd.daemon.headline import status_line
from mapd.daemon.server import Daemon
from mapd.grid import OccupancyGrid


def _map(side: int) -> OccupancyGrid:
    data = np.zeros((side, side), np.int8)
    data[::7, :] = 100
    return OccupancyGrid(data, 0.05, robot="robot0")


def test_a_source_map_over_max_cells_is_said_once_with_the_fix_and_shown_until_one_fits(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    path = dk.write_config(
        tmp_path,
        "robot0",
        extra='[limits]\nmax_cells = 30000\n[transports]\nuse = ["virtual"]\n',
        # (the sim's own building must fit the limit too: check-config refuses it otherwise)
        **{"transports.virtual": f'channel = "{dk.channel()}"', "source.sim": "width_m = 6\nheight_m = 6"},
    )
    source = dk.QueueSource("robot0")
    d = Daemon(configmod.load(path), source=source)
    caplog.set_level(logging.INFO, logger="mapd.daemon")

    async def main() -> None:
        task = asyncio.create_task(d.run())
        try:
            source.queue.put_nowait(_map(100))  # 10,000 cells: taken
            await dk.wait_for(lambda: d.own is not None, what="the first map")
            assert d.snapshot()["source"]["skipped"] is None
            for _ in range(3):  # 40,000 cells each: over the limit
                source.queue.put_nowait(_map(200))
            await dk.wait_for(lambda: source.queue.empty(), what="the big maps taken off")
            await dk.wait_for(
                lambda: (d.snapshot()["source"]["skipped"] or {}).get("maps") == 3, what="3 skipped"
            )
            snap = d.snapshot()
            skipped = snap["source"]["skipped"]
            assert "40000 cells" in skipped["why"] and "30000" in skipped["why"]
            assert "own map not shared" in status_line(snap)
            assert "own map not shared: its last 3 maps skipped" in render_status(snap)
            said = [r.getMessage() for r in caplog.records if "max_cells" in r.getMessage()]
            assert len(said) == 1, said
            assert "limits.max_cells" in said[0] and "every robot" in said[0]
            assert d.own is not None and d.own.width == 100  # the last map that fit stays the newest

            source.queue.put_nowait(_map(120))  # fits again
            await dk.wait_for(lambda: d.own is not None and d.own.width == 120, what="a map that fits")
            assert d.snapshot()["source"]["skipped"] is None
            assert "own map not shared" not in status_line(d.snapshot())
            assert any("fit" in r.getMessage() and "again" in r.getMessage() for r in caplog.records)
        finally:
            d.request_stop()
            await task

    asyncio.run(main())
