"""How the daemon takes several robots' maps from one source (the map_merge drop-in), in one process."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import numpy as np
import pytest

from mapd import config as configmod
from mapd.daemon.server import Daemon
from mapd.grid import OccupancyGrid, Pose2D
from mapd.sources.base import MapSource, SourceContext

#: The ``base_config`` fixture (tests/ros2/conftest.py): writes a signed base-station config.
BaseConfig = Callable[[Path, dict[str, dict[str, object]]], Path]


class TwoRobots(MapSource):
    """Yields robot1's and robot2's maps (or those of ``robots``), and knows where their map frames lie."""

    name = "two"

    def __init__(self, robots: tuple[str, ...] = ("robot1", "robot2")) -> None:
        super().__init__(None, SourceContext(robot="base"))
        self.robots = robots

    def robot_poses(self) -> dict[str, Pose2D]:
        known = {"robot1": Pose2D(0.0, 0.0, 0.0), "robot2": Pose2D(3.0, 0.0, 0.0)}
        return {r: known[r] for r in self.robots}

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        for robot in self.robots:
            data = np.zeros((20, 30), np.int8)
            data[0, :] = 100
            yield OccupancyGrid(data, 0.1, robot=robot, version=1)
        await asyncio.Event().wait()


def _config(base_config: BaseConfig, root: Path, source: dict[str, object]) -> configmod.MapdConfig:
    return configmod.load(base_config(root, {"source.ros2": source, "fusion": {"debounce_s": 0.05}}))


def test_a_discovering_source_leaves_the_fleet_frame_to_the_robots(
    tmp_path: Path, base_config: BaseConfig
) -> None:
    own = Daemon(_config(base_config, tmp_path / "a", {"topic": "/map"}))
    merge = Daemon(_config(base_config, tmp_path / "b", {"discover_robots": True}))
    assert own.fusion.placer.anchor == "base"  # a robot's own map frame is the fleet frame
    assert merge.fusion.placer.anchor is None  # as with source none: the first robot by name


def test_other_robots_maps_are_fused_as_peers_and_never_sent(tmp_path: Path, base_config: BaseConfig) -> None:
    cfg = _config(base_config, tmp_path, {"discover_robots": True})
    daemon = Daemon(cfg, source=TwoRobots())

    async def go() -> dict[str, object]:
        task = asyncio.ensure_future(daemon.run())
        end = time.monotonic() + 20
        while daemon.fusion.status()["maps"] < 2 and time.monotonic() < end:
            await asyncio.sleep(0.05)
        status = daemon.snapshot()
        daemon.request_stop()
        await asyncio.wait_for(task, 20)
        return status

    status = asyncio.run(go())
    robots = status["fusion"]["robots"]  # type: ignore[index]
    # placed by the source's known poses, as a peer's map is placed by the pose it sends
    assert all(robots[r]["source"] == "pose" and robots[r]["accepted"] for r in ("robot1", "robot2"))
    assert (robots["robot2"]["x"], robots["robot2"]["y"]) == (3.0, 0.0)
    assert status["fusion"]["fleet_frame"] == "frame of the known poses (robot1, robot2)"  # type: ignore[index]
    assert status["source"]["version"] == 0  # type: ignore[index]  # no own map: nothing to send
    assert daemon.own is None and daemon.publisher.counters.keyframes_sent == 0
    g = daemon.fusion.global_map
    assert g is not None and g.width >= 60 and g.resolution == 0.1  # robot2's 3 m to the right of robot1


def test_a_source_robot_named_as_a_fleet_robot_is_left_to_the_fleet(
    tmp_path: Path, base_config: BaseConfig, caplog: pytest.LogCaptureFixture
) -> None:
    # robot2 runs mapd and is on the roster; its map on the ROS graph too was fused under the same
    # name, and the two took turns in the global map. Its own (signed) maps count.
    from mapd.identity import Identity

    path = base_config(tmp_path, {"source.ros2": {"discover_robots": True}, "fusion": {"debounce_s": 0.05}})
    other = Identity.generate("robot2").public_text
    path.write_text(path.read_text().replace("[fleet.roster]\n", f'[fleet.roster]\nrobot2 = "{other}"\n'))
    daemon = Daemon(configmod.load(path), source=TwoRobots())

    async def go() -> dict[str, object]:
        task = asyncio.ensure_future(daemon.run())
        end = time.monotonic() + 20
        while daemon.fusion.status()["maps"] < 1 and time.monotonic() < end:
            await asyncio.sleep(0.05)
        await asyncio.sleep(0.3)
        status = daemon.fusion.status()
        daemon.request_stop()
        await asyncio.wait_for(task, 20)
        return status

    with caplog.at_level(logging.WARNING, logger="mapd"):
        status = asyncio.run(go())
    assert list(status["robots"]) == ["robot1"]  # type: ignore[call-overload]
    said = [r.getMessage() for r in caplog.records if "fleet robot's name" in r.getMessage()]
    assert len(said) == 1 and said[0].startswith("map of robot2 from the source skipped")


def test_a_restarted_daemon_records_the_outputs_names_and_moves_robots_off_the_tree_as_it_does(
    tmp_path: Path, base_config: BaseConfig
) -> None:
    # The recording put the global map on /map whatever the output's topic, and a restarted
    # daemon's recording forgot the robots the run before had placed: played after the files of
    # that run, the bag left robot2 placed where the ros2 output had moved it off the tree.
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from mapd.demo.ports import free_endpoint

    record = tmp_path / "rec" / "fleet.mcap"
    listen = free_endpoint()
    path = base_config(
        tmp_path,
        {
            "source.ros2": {"discover_robots": True},
            "fusion": {"debounce_s": 0.05},
            "record": {"path": str(record), "min_free_bytes": 0},
            "output": {"use": ["ros2"]},
            "output.ros2": {
                "topic": "merged",
                "namespace": "fleet",
                "frame": "world",
                "connect": [],
                "listen": [listen],
            },
        },
    )

    def run(robots: tuple[str, ...], unplaced: int) -> None:
        """Run until the robots are merged and the output moved ``unplaced`` robots off the tree."""
        daemon = Daemon(configmod.load(path), source=TwoRobots(robots))

        def done() -> bool:
            out = daemon.sinks.status().get("ros2", {})  # (none until the output has started)
            # (a merge that placed them has gone to the sinks: placements and sinks go together)
            merged = daemon.fusion.status()["maps"] == len(robots)
            return merged and bool(out.get("tf_static")) and out.get("unplaced") == unplaced

        async def go() -> None:
            task = asyncio.ensure_future(daemon.run())
            end = time.monotonic() + 20
            while not done():
                assert time.monotonic() < end, (daemon.fusion.status(), daemon.snapshot()["outputs"])
                await asyncio.sleep(0.05)
            daemon.request_stop()
            await asyncio.wait_for(task, 20)

        asyncio.run(go())

    def tf_static_and_map_topics(file: Path) -> tuple[list[dict[str, str]], set[str]]:
        static, maps = [], set()
        with open(file, "rb") as fh:
            reader = make_reader(fh, decoder_factories=[DecoderFactory()])
            for schema, channel, _, msg in reader.iter_decoded_messages():
                if channel.topic == "/tf_static":
                    static.append({t.child_frame_id: t.header.frame_id for t in msg.transforms})
                elif schema is not None and schema.name == "nav_msgs/msg/OccupancyGrid":
                    maps.add(channel.topic)
        return static, maps

    run(("robot1", "robot2"), unplaced=0)
    static, maps = tf_static_and_map_topics(record)
    assert maps == {"/fleet/merged", "/robot1/map", "/robot2/map"}  # the output's topic, not /map
    assert static[-1] == {"robot1/map": "world", "robot2/map": "world"}
    # The restart: robot2 is no longer placed (its map is not restored; its source is gone).
    # (a fresh port; and the robots' maps now on ROS 2 too, under the node's namespace: the bag's
    # robot map channels follow them)
    text = path.read_text().replace(listen, free_endpoint())
    assert 'frame = "world"\n' in text
    path.write_text(
        text.replace('frame = "world"\n', 'frame = "world"\nrobot_map_topic = "mapd/{robot}_map"\n')
    )
    run(("robot1",), unplaced=1)  # the ros2 output moves robot2 off the tree (its ros2_frames.json)
    static, maps = tf_static_and_map_topics(record.with_name("fleet.1.mcap"))
    assert maps == {"/fleet/merged", "/fleet/mapd/robot1_map"}
    assert static[0] == {"robot1/map": "world", "robot2/map": "mapd/unplaced"}  # and so does the bag
