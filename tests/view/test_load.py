"""A measurement: 200 viewers on the live view do not slow the daemon's map updates.

A real two-robot fleet; the test rewrites robot0's map file and measures how long until the new
global map reaches a viewer over SSE (file poll, load, fusion debounce and merge, tile diff, SSE),
first with one viewer, then with 200 more connected and reading. The bound is generous (a shared
2-core machine); the numbers are printed (run with -s) and quoted in the README.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import time
from pathlib import Path
from typing import Any

import aiohttp
import pytest

from mapd.grid import OCCUPIED

VIEWERS = 200
UPDATES = 6


async def read_maps(resp: aiohttp.ClientResponse, seen: dict[int, float]) -> None:
    """Read an SSE stream, noting when each map message (by seq) arrived."""
    kind = None
    async for raw in resp.content:
        line = raw.decode().rstrip("\n")
        if line.startswith("event: "):
            kind = line[7:]
        elif line.startswith("data: ") and kind == "map":
            seen.setdefault(json.loads(line[6:])["seq"], time.monotonic())


@pytest.mark.slow
def test_200_viewers_do_not_slow_map_updates(map_fleet: Any, vk: Any, tmp_path: Path) -> None:
    map_fleet.wait_merged()
    url = f"http://127.0.0.1:{map_fleet.view_port}/events"
    step = [0]

    async def measure(seen: dict[int, float]) -> list[float]:
        """Latencies (s) from a map file write to the new global map at the measuring viewer."""
        out = []
        for _ in range(UPDATES):
            await asyncio.sleep(1.0)  # quiet: nothing else in flight
            last = max(seen, default=0)
            step[0] += 1
            x = 1.0 + 0.5 * (step[0] % 12)  # a new block each time, so the map really changes
            blocks = [*vk.BLOCKS["robot0"], (x, 1.0, x + 0.4, 1.4, OCCUPIED)]
            t0 = time.monotonic()
            await asyncio.to_thread(map_fleet.write_map, "robot0", vk.box_map("robot0", blocks))
            while max(seen, default=0) <= last:
                assert time.monotonic() - t0 < 30, "no map update within 30 s"
                await asyncio.sleep(0.005)
            out.append(seen[max(seen)] - t0)
        return out

    async def main() -> tuple[list[float], list[float], list[float]]:
        async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(limit=0)) as s:
            seen: dict[int, float] = {}
            probe = await s.get(url)
            probe_task = asyncio.create_task(read_maps(probe, seen))
            base = await measure(seen)

            crowd: list[dict[int, float]] = [{} for _ in range(VIEWERS)]
            responses = await asyncio.gather(*(s.get(url) for _ in range(VIEWERS)))
            assert all(r.status == 200 for r in responses)
            tasks = [asyncio.create_task(read_maps(r, c)) for r, c in zip(responses, crowd, strict=True)]
            deadline = time.monotonic() + 30
            while not all(crowd) and time.monotonic() < deadline:
                await asyncio.sleep(0.1)
            assert all(crowd), "every viewer gets the current map on connecting"
            view = map_fleet.status("robot0")["outputs"]["view"]
            assert view["viewers"] == VIEWERS + 1
            loaded = await measure(seen)
            await asyncio.sleep(2.0)
            newest = max(seen)
            # every viewer got the newest map too: how far apart the first and the last got it
            got = [c[newest] for c in crowd if newest in c]
            assert len(got) == VIEWERS, f"{VIEWERS - len(got)} viewers never got the newest map"
            lags = [t - min(*got, seen[newest]) for t in (*got, seen[newest])]
            for t in (*tasks, probe_task):
                t.cancel()
            for r in (*responses, probe):
                r.close()
            return base, loaded, lags

    base, loaded, lags = asyncio.run(main())
    b, m = statistics.median(base), statistics.median(loaded)
    print(
        f"\nmap file -> viewer latency, {UPDATES} updates each: 1 viewer median {b:.3f} s "
        f"(max {max(base):.3f}); {VIEWERS + 1} viewers median {m:.3f} s (max {max(loaded):.3f}); "
        f"all {VIEWERS + 1} got the newest map within {1000 * max(lags):.1f} ms of each other"
    )
    assert m <= 2 * b + 1.0, (base, loaded)
    assert max(lags) < 5.0
