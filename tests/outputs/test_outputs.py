"""Output plugins: map_server files, and the global map on zenoh (a real session subscribes and queries)."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from mapd import plugins
from mapd.codec import decode
from mapd.envelope import unpack
from mapd.grid import OccupancyGrid, Pose2D, load_map
from mapd.identity import Identity, Roster
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.files import FilesOptions, FilesOutput
from mapd.outputs.zenoh import ZenohOutput, ZenohOutputOptions
from transports.zenoh.keys import global_key


def update(room_grid: OccupancyGrid, version: int = 3) -> GlobalUpdate:
    return GlobalUpdate(
        grid=room_grid.replace(version=version, robot="base"),
        frames={"robot0": Pose2D(0.0, 0.0, 0.0), "robot1": Pose2D(4.0, -1.0, 0.5)},
        stamp=1234.5,
        versions={"robot0": 7, "robot1": 9},
    )


def test_outputs_are_plugins() -> None:
    assert plugins.load("output", "files") is FilesOutput and plugins.load("output", "zenoh") is ZenohOutput


def test_files_output_writes_map_server_files_and_transforms(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    out = FilesOutput(FilesOptions(dir=tmp_path / "maps", name="fleet"), OutputContext("base", "f"))
    (tmp_path / "maps").mkdir()
    stale = tmp_path / "maps" / ".fleet.pgm.tmp999999.1"  # a write killed mid-way, by another pid
    stale.write_bytes(b"half a map")
    (tmp_path / "maps" / "notes.tmp").write_text("not ours")
    asyncio.run(out.start())
    assert not stale.exists() and (tmp_path / "maps" / "notes.tmp").exists()  # only our temps go
    out.publish(update(room_grid))
    back = load_map(tmp_path / "maps" / "fleet.yaml")
    assert back.same_map(room_grid)
    doc = json.loads((tmp_path / "maps" / "transforms.json").read_text())
    assert doc["frame_id"] == "map" and doc["robots"]["robot1"] == {
        "child_frame_id": "robot1/map", "x": 4.0, "y": -1.0, "yaw": 0.5, "version": 9
    }  # fmt: skip
    assert out.stats()["written"] == 1


def test_zenoh_output_puts_a_signed_lossless_map_and_answers_late_joiners(
    room_grid: OccupancyGrid, zenoh_linked: Callable[..., None]
) -> None:
    zenoh = pytest.importorskip("zenoh")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    me = Identity.generate("base")
    out = ZenohOutput(
        ZenohOutputOptions(listen=[f"tcp/127.0.0.1:{port}"], multicast_scouting=False),
        OutputContext("base", "f", identity=me),
    )
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")

    async def main() -> None:
        await out.start()
        try:
            got: list[bytes] = []
            with zenoh.open(conf) as z:
                sub = z.declare_subscriber(
                    global_key("f", "base"), lambda s: got.append(s.payload.to_bytes())
                )
                zenoh_linked(z)  # the subscription reaches the output's session
                out.publish(update(room_grid, 3))
                end = time.monotonic() + 5
                while not got and time.monotonic() < end:
                    await asyncio.sleep(0.05)
                sub.undeclare()
                assert got, "no global map arrived"
                env = unpack(got[0], roster=Roster({"base": me.public_key}))  # signed by the base
                assert (env.robot, env.version, env.codec, env.frame_id) == ("base", 3, "lossless", "map")
                assert decode(env.payload, None).same_map(room_grid)  # exact
                out.publish(update(room_grid, 4))
                replies = [
                    r.ok.payload.to_bytes() for r in z.get(global_key("f", "base"), timeout=5.0) if r.ok
                ]
                assert [unpack(r).version for r in replies] == [4]  # a late joiner gets the newest
        finally:
            await out.close()
        assert out.stats()["published"] == 2 and out.stats()["queries"] == 1

    asyncio.run(main())
