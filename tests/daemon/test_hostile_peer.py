"""A live daemon under a hostile peer on its zenoh bus: garbage, unsigned, forged, foreign and a flood.

The daemon is a real ``mapd run`` process with a fleet key; the attacker is a plain zenoh session
in this process that publishes on the daemon's fleet keys. Everything bad must be counted in
``mapd status``, the control socket must keep answering during the flood, and the last good update
of the flood must be the one the daemon holds.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.codec import encode
from mapd.daemon.status_socket import query
from mapd.demo.fleet import write_config
from mapd.demo.ports import free_port
from mapd.envelope import Envelope
from mapd.errors import DaemonError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.save import save_map
from mapd.identity import Identity

pytestmark = pytest.mark.slow

FLEET = "lab"
#: mallory is on the roster (it holds its own key) and sends as fast as it can: a noisy fleet member.
MALLORY = Identity.generate("mallory")


def envelope(version: int, *, fleet: str = FLEET, robot: str = "mallory") -> Envelope:
    grid = OccupancyGrid(np.full((20, 30), -1, np.int8), 0.05, version=version)
    grid.data[5:15, 5:25] = 0
    grid.data[5, 5:25] = 100
    return Envelope(
        fleet=fleet,
        robot=robot,
        version=version,
        base_version=0,
        codec="raw",
        width=grid.width,
        height=grid.height,
        resolution=grid.resolution,
        origin=Pose2D(0.0, 0.0, 0.0),
        seq=version,
        payload=encode(grid, "raw"),
    )


def status(sock: Path) -> dict[str, Any]:
    return query(sock, timeout=2.0)


def wait_status(sock: Path, pred: Any, timeout: float) -> dict[str, Any]:
    end = time.monotonic() + timeout
    last: dict[str, Any] = {}
    while time.monotonic() < end:
        try:
            last = status(sock)
        except DaemonError:
            last = {}
        if last and pred(last):
            return last
        time.sleep(0.3)
    raise AssertionError(f"status condition not met in {timeout} s: {last}")


def test_garbage_unsigned_forged_foreign_and_flood_are_counted_and_never_stall(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    import zenoh

    port = free_port()
    save_map(room_grid, tmp_path / "map.yaml")
    me = Identity.generate("robot0")
    me.write(tmp_path / "robot0.key")
    run = tmp_path / "run"
    write_config(
        tmp_path / "config.toml",
        {
            "robot": {"name": "robot0", "fleet": FLEET, "key_file": str(tmp_path / "robot0.key")},
            "fleet.roster": {"robot0": me.public_text, "mallory": MALLORY.public_text},
            "state": {"dir": str(tmp_path / "state"), "runtime_dir": str(run)},
            "source": {"use": "mapfile"},
            "source.mapfile": {"path": str(tmp_path / "map.yaml"), "poll_s": 0.5},
            "codec": {"use": "lossless"},
            "transports": {"use": ["zenoh"]},
            "transports.zenoh": {
                "mode": "peer",
                "listen": [f"tcp/127.0.0.1:{port}"],
                "multicast_scouting": False,
            },
        },
    )
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", "run", "--config", str(tmp_path / "config.toml")],
        stdout=open(tmp_path / "daemon.log", "wb"),  # noqa: SIM115 - lives as long as the process
        stderr=subprocess.STDOUT,
    )
    sock = run / "mapd.sock"
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    conf.insert_json5("scouting/multicast/enabled", "false")
    try:
        wait_status(sock, lambda s: s["source"]["version"] >= 1, 90)
        with zenoh.open(conf) as z:
            token = z.liveliness().declare_token(f"mapd/{FLEET}/mallory")
            key = f"mapd/{FLEET}/mallory/update"
            # the daemon sees the token once the two sessions are linked (its subscription with it)
            wait_status(sock, lambda s: s["peers"].get("mallory", {}).get("present") is True, 30)
            rng = np.random.default_rng(0)
            for _ in range(50):
                z.put(key, rng.bytes(int(rng.integers(1, 400))))
            for v in range(1, 11):
                z.put(key, envelope(v).pack())  # unsigned while the fleet has a key
                z.put(key, envelope(v).signed(Identity.generate("mallory")).pack())  # not mallory's key
                z.put(key, envelope(v, fleet="other").signed(MALLORY).pack())  # another fleet's update
            # A flood of valid updates, as fast as this process can publish them, while an operator
            # keeps asking for status: the socket must answer every time.
            latencies = []
            last = 0
            for v in range(100, 1100):
                z.put(key, envelope(v).signed(MALLORY).pack())
                last = v
                if v % 100 == 0:
                    t0 = time.monotonic()
                    status(sock)  # raises DaemonError (test fails) if the daemon stalls past 2 s
                    latencies.append(time.monotonic() - t0)
            s = wait_status(sock, lambda s: s["peers"].get("mallory", {}).get("version") == last, 60)
            token.undeclare()
        link = s["links"]["zenoh"]
        counters = s["counters"]
        # garbage and the foreign fleet's updates are dropped by the transport, forgeries as bad signatures
        assert link["dropped"] >= 50 + 10, link
        assert link["bad_signature"] + counters.get("bad_signature", 0) >= 20, (link, counters)
        # the flood was taken latest-wins: the newest version is held, and nothing older replaced it
        assert s["peers"]["mallory"]["version"] == last
        assert 1 <= counters["updates_received"] <= 1000
        assert counters["dropped_events"] == 0  # superseded, never dropped: memory is per peer
        assert max(latencies) < 2.0
        assert proc.poll() is None, "the daemon died under the hostile peer"
        assert s["source"]["version"] >= 1
    finally:
        proc.terminate()
        code = proc.wait(15)
        log = (tmp_path / "daemon.log").read_text(errors="replace")
    assert code == 0, log[-2000:]
    assert "Traceback" not in log, log[-4000:]
    os.sync()
