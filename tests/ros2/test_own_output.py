"""A daemon's ros2 source never takes its own ros2 output's global map back (audit ROS finding 1).

On a robot both default to ``/map``: the source read the output's global map as the robot's own
map, signed it and sent it to the fleet. The source drops samples whose rmw_zenoh attachment GID
(``ros2dds``: whose zenoh timestamp's session id) is one this process's ros2 output published with,
and the output refuses to share a topic with ``[source.ros2]`` (``check_with_plugins``, the hook
``config.check`` is to call for ``mapd check-config`` and ``mapd run``).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncGenerator
from types import ModuleType
from typing import Any, cast

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.ros2 import Ros2Output, Ros2OutputOptions
from mapd.ros2 import cdr
from mapd.sources.base import SourceContext
from mapd.sources.ros2 import Ros2Options, Ros2Source


def _room(k: int, shape: tuple[int, int] = (20, 30)) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(shape[0] + k, shape[1]))


def _global(k: int) -> GlobalUpdate:
    grid = OccupancyGrid(_room(k, (40, 60)), 0.05, Pose2D(-7.0, -3.0, 0.0), robot="robot0", version=k)
    return GlobalUpdate(grid=grid, frames={"robot0": Pose2D()}, stamp=1700000000.0 + k)


def _output(endpoint: str, **kw: Any) -> Ros2Output:
    out = Ros2Output(
        Ros2OutputOptions(mode="peer", connect=[endpoint], **kw), OutputContext(robot="robot0", fleet="f")
    )
    asyncio.run(out.start())
    return out


def test_the_source_drops_its_own_outputs_maps_and_takes_the_robots(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)  # the robot's rmw_zenohd, and its SLAM node
    peers.append(peer)
    slam = peer.publisher("/map")
    out = _output(endpoint)  # the defaults: /map, as the source's
    src = Ros2Source(Ros2Options(mode="peer", connect=[endpoint]), SourceContext(robot="robot0"))
    try:
        out.publish(_global(1))  # cached before the source starts: it comes by history

        async def go() -> list[OccupancyGrid]:
            it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
            first = asyncio.ensure_future(it.__anext__())
            await asyncio.sleep(1.5)
            await asyncio.to_thread(out.publish, _global(2))  # and live
            await asyncio.sleep(0.5)
            peer.publish_map(slam, _room(3), 0.05, (-2.0, -3.0), "map", seq=1)
            got = [await asyncio.wait_for(first, 15)]
            await asyncio.to_thread(out.publish, _global(4))
            await asyncio.sleep(0.5)
            peer.publish_map(slam, _room(5), 0.05, (-2.0, -3.0), "map", seq=2)
            got.append(await asyncio.wait_for(it.__anext__(), 15))
            await it.aclose()
            return got

        got = asyncio.run(go())
    finally:
        asyncio.run(out.close())
    assert [(g.robot, g.version) for g in got] == [("robot0", 1), ("robot0", 2)]
    assert np.array_equal(got[0].data, _room(3)) and np.array_equal(got[1].data, _room(5))
    assert src.stats()["own_output_dropped"] >= 3


def test_ros2dds_the_source_drops_samples_from_its_own_outputs_session(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)  # stands in for a zenoh-bridge-ros2dds
    peers.append(peer)
    bridge = peer.session.declare_publisher("map")
    peers.append(SimpleCloser(bridge))
    out = _output(endpoint, format="ros2dds")
    opts = Ros2Options(mode="peer", connect=[endpoint], key_format="ros2dds", history=False)
    src = Ros2Source(opts, SourceContext(robot="robot0"))
    try:

        async def go() -> OccupancyGrid:
            it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
            first = asyncio.ensure_future(it.__anext__())
            await asyncio.sleep(1.5)
            await asyncio.to_thread(out.publish, _global(2))
            await asyncio.sleep(0.5)
            bridge.put(cdr.encode(OccupancyGrid(_room(6), 0.05, Pose2D(-2.0, -3.0, 0.0)), frame_id="map"))
            grid = await asyncio.wait_for(first, 15)
            await it.aclose()
            return grid

        grid = asyncio.run(go())
    finally:
        asyncio.run(out.close())
    assert np.array_equal(grid.data, _room(6)) and grid.version == 1
    assert src.stats()["own_output_dropped"] >= 1


class SimpleCloser:
    """Lets the ``peers`` fixture undeclare a zenoh publisher (it calls ``close``)."""

    def __init__(self, thing: Any) -> None:
        self.thing = thing

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.thing.undeclare()


def test_a_discovering_source_takes_no_robot_from_its_own_outputs_topic(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    # /fleet/map has the shape of robot "fleet"'s /<robot>/map: neither its samples nor its
    # publisher's token may make "fleet" a robot of this base station.
    peer = rmw_peer.RmwPeer(endpoint, listen=True)
    peers.append(peer)
    out = _output(endpoint, topic="/fleet/map")
    out.publish(_global(1))
    opts = Ros2Options(discover_robots=True, known_init_poses=False, mode="peer", connect=[endpoint])
    src = Ros2Source(opts, SourceContext(robot="base"))
    try:

        async def go() -> OccupancyGrid:
            it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
            first = asyncio.ensure_future(it.__anext__())
            await asyncio.sleep(1.5)
            await asyncio.to_thread(out.publish, _global(2))
            await asyncio.sleep(0.5)
            pub = await asyncio.to_thread(peer.publisher, "/robot1/map")
            peer.publish_map(pub, _room(7), 0.05, (0.0, 0.0), "robot1/map", seq=1)
            grid = await asyncio.wait_for(first, 15)
            await asyncio.sleep(0.5)
            await it.aclose()
            return grid

        grid = asyncio.run(go())
    finally:
        asyncio.run(out.close())
    assert grid.robot == "robot1" and np.array_equal(grid.data, _room(7))
    assert src._taken == {"robot1"} and src._announced == {"robot1"}


# -- the config check ------------------------------------------------------------------------------


def _chosen(source: Any) -> dict[str, dict[str, Any]]:
    return {"source": {"ros2": source}, "output": {"ros2": Ros2OutputOptions()}}


def test_an_output_on_the_sources_topic_is_refused_in_one_line() -> None:
    out = Ros2OutputOptions()
    with pytest.raises(ValueError) as info:
        out.check_with_plugins(_chosen(Ros2Options()))  # both default to /map on domain 0
    msg = str(info.value)
    assert msg.startswith("topic: ") and "\n" not in msg
    assert "[source.ros2]" in msg and 'topic = "/fleet/map" and frame = "fleet"' in msg
    # the same topic spelled otherwise is the same topic
    for src, kw in (
        (Ros2Options(topic="map"), {}),
        (Ros2Options(topic="/fleet/map"), {"topic": "map", "namespace": "/fleet"}),
        (Ros2Options(key="0/**"), {}),
        (Ros2Options(key_format="ros2dds", namespace="site"), {"format": "ros2dds", "namespace": "site"}),
        (Ros2Options(discover_robots=True), {"topic": "/fleet/map"}),  # robot "fleet"
        (Ros2Options(domain=3), {"topic": "/map", "domain_id": 3}),
    ):
        with pytest.raises(ValueError, match=r"^topic: "):
            Ros2OutputOptions(**kw).check_with_plugins(_chosen(src))


def test_a_robot_side_layout_and_other_graphs_pass() -> None:
    for src, kw in (
        (Ros2Options(pose_topic="/amcl_pose"), {"topic": "/fleet/map", "frame": "fleet"}),
        (Ros2Options(), {"domain_id": 1}),  # another ROS graph
        (Ros2Options(), {"format": "ros2dds"}),  # rmw_zenoh keys against a bridge's: no overlap
        (Ros2Options(key_format="ros2dds", namespace="a"), {"format": "ros2dds", "namespace": "b"}),
        (Ros2Options(discover_robots=True), {}),  # a base station: /map is no /<robot>/map
        (Ros2Options(key="0/robot1/**"), {}),
    ):
        Ros2OutputOptions(**kw).check_with_plugins(_chosen(src))
    Ros2OutputOptions().check_with_plugins({"source": {}, "output": {}})  # another source


def test_key_expressions_meet_as_zenoh_matches_them() -> None:
    from mapd.ros2.rmw import key_exprs_intersect as meet

    dds = "nav_msgs::msg::dds_::OccupancyGrid_"
    for a, b, want in (
        (f"0/map/{dds}/*", f"0/map/{dds}/RIHS01_8d34", True),
        (f"0/map/{dds}/*", f"0/fleet/map/{dds}/*", False),
        (f"0/*/map/{dds}/*", f"0/fleet/map/{dds}/*", True),
        (f"0/*/map/{dds}/*", f"0/map/{dds}/*", False),
        ("0/**", f"0/map/{dds}/*", True),
        ("**", "a", True),
        ("0/**/map", "0/map", True),  # '**' takes no chunk
        ("0/**/x", "0/map", False),
        ("a/**", "**/b", True),
        ("m$*p", "map", True),
        ("m$*p", "mop/x", False),
        ("map", "maps", False),
        ("1/map", "0/map", False),
    ):
        assert meet(a, b) is want and meet(b, a) is want, (a, b)
