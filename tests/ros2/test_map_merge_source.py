"""The ros2 source taking several robots' /<robot>/map (a map_merge drop-in), fed by an independent peer."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncGenerator
from types import ModuleType
from typing import Any, cast

import numpy as np
import pytest

from mapd.grid import OccupancyGrid, Pose2D
from mapd.sources.base import SourceContext
from mapd.sources.ros2 import Ros2Options, Ros2Source


def _room(k: int) -> np.ndarray:
    rng = np.random.default_rng(k)
    return rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(20 + k, 30))


def test_options() -> None:
    o = Ros2Options(discover_robots=True)
    assert not o.yields_own_map and Ros2Options().yields_own_map
    with pytest.raises(ValueError):
        Ros2Options(init_poses={"robot1": [0.0, 1.0]})
    with pytest.raises(ValueError):
        Ros2Options(robot_map_topic="a//b")


def test_discovers_robots_by_namespace_and_waits_for_known_poses(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)  # as the ROS 2 side's router would
    peers.append(peer)
    pubs = {r: peer.publisher(f"/{r}/map") for r in ("robot1", "robot2", "robot3", "visitor")}
    for i, (robot, pub) in enumerate(pubs.items()):
        peer.publish_map(pub, _room(i), 0.05, (float(i), 0.0), f"{robot}/map", seq=1)
    peer.publisher("/robot1/scan")  # another topic of a robot: not a map
    opts = Ros2Options(
        discover_robots=True,
        robot_namespace="robot",
        init_poses={"robot1": [0.0, 0.0, 0.0], "robot2": [4.0, -1.0, 1.5]},
        mode="peer",
        connect=[endpoint],
    )
    src = Ros2Source(opts, SourceContext(robot="base"))
    assert src.robot_poses() == {"robot1": Pose2D(0.0, 0.0, 0.0), "robot2": Pose2D(4.0, -1.0, 1.5)}

    async def go() -> tuple[list[OccupancyGrid], list[Any], dict[str, Any]]:
        it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
        got = [await asyncio.wait_for(it.__anext__(), 15) for _ in range(2)]  # the cached maps: history
        peer.publish_map(pubs["robot1"], _room(9), 0.05, (0.0, 0.0), "robot1/map", seq=2)
        got.append(await asyncio.wait_for(it.__anext__(), 15))
        want = rmw_peer.having("mapd_source", ("NN", ""), ("MS", "/robot1/map"), ("MS", "/robot2/map"))
        graph = await asyncio.to_thread(peer.graph, want)
        # robot3's cached map may come after the others: the source sees it when it is next asked
        # for a map (there is none to give, so the ask is cancelled once robot3 is held back).
        more = asyncio.ensure_future(it.__anext__())
        end = asyncio.get_running_loop().time() + 15
        while src.stats()["waiting_for_init_pose"] == "-" and asyncio.get_running_loop().time() < end:
            await asyncio.sleep(0.05)
        stats = src.stats()
        more.cancel()
        with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
            got.append(await more)  # a map here would fail the count below
        await it.aclose()
        return got, graph, stats

    got, graph, stats = asyncio.run(go())
    assert sorted((g.robot, g.version) for g in got) == [("robot1", 1), ("robot1", 2), ("robot2", 1)]
    latest = {g.robot: g for g in got}
    assert np.array_equal(latest["robot1"].data, _room(9)) and np.array_equal(latest["robot2"].data, _room(1))
    assert latest["robot2"].origin.x == 1.0 and latest["robot2"].frame_id == "robot2/map"
    # robot3 has no init pose (known_init_poses = true): held back, as m-explore does; visitor is filtered
    assert stats["robots"] == "robot1:2,robot2:1" and stats["waiting_for_init_pose"] == "robot3"
    mine = [t for t in graph if t.node == "mapd_source"]
    assert any(t.kind == "NN" for t in mine)
    subs = {t.topic: t for t in mine if t.kind == "MS"}
    assert {"/robot1/map", "/robot2/map"} <= set(subs) and "/visitor/map" not in subs
    assert subs["/robot1/map"].qos == rmw_peer.qos(True, 1) and subs["/robot1/map"].hash == rmw_peer.GRID_HASH
    assert src._session is None  # closed with the stream


def test_estimation_mode_takes_every_robot(endpoint: str, rmw_peer: ModuleType, peers: list[Any]) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)
    peers.append(peer)
    opts = Ros2Options(discover_robots=True, known_init_poses=False, mode="peer", connect=[endpoint])
    src = Ros2Source(opts, SourceContext(robot="base"))
    assert src.robot_poses() == {}

    async def go() -> list[OccupancyGrid]:
        it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
        task = asyncio.ensure_future(it.__anext__())
        await asyncio.sleep(1.0)  # the source is up before the robots appear: late publishers
        for i, robot in enumerate(("a1", "b2")):
            pub = await asyncio.to_thread(peer.publisher, f"/{robot}/map")
            await asyncio.sleep(0.2)
            peer.publish_map(pub, _room(i), 0.1, (0.0, 0.0), "map", seq=1)
        got = [await asyncio.wait_for(task, 15), await asyncio.wait_for(it.__anext__(), 15)]
        await it.aclose()
        return got

    got = asyncio.run(go())
    assert sorted(g.robot for g in got) == ["a1", "b2"] and all(g.resolution == 0.1 for g in got)


def test_one_robot_mode_announces_its_node_and_subscription(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True, distro="humble")
    peers.append(peer)
    pub = peer.publisher("/map")
    peer.publish_map(pub, _room(3), 0.05, (-1.0, 2.0), "map", seq=1)
    opts = Ros2Options(mode="peer", connect=[endpoint], distro="humble", node="merger")
    src = Ros2Source(opts, SourceContext(robot="r1"))

    async def go() -> tuple[OccupancyGrid, list[Any]]:
        it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
        grid = await asyncio.wait_for(it.__anext__(), 15)
        want = rmw_peer.having("merger", ("NN", ""), ("MS", "/map"))
        graph = await asyncio.to_thread(peer.graph, want)
        await it.aclose()
        return grid, graph

    grid, graph = asyncio.run(go())
    assert grid.robot == "r1" and grid.origin.x == -1.0 and np.array_equal(grid.data, _room(3))
    mine = [t for t in graph if t.node == "merger"]
    assert {(t.kind, t.topic) for t in mine} == {("NN", ""), ("MS", "/map")}
    sub = next(t for t in mine if t.kind == "MS")
    assert sub.hash == "TypeHashNotSupported" and sub.qos == rmw_peer.qos(True, 1)
    assert sub.type == "nav_msgs::msg::dds_::OccupancyGrid_" and sub.namespace == "/"


def test_names_past_max_robots_take_no_subscription(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    # A robot counts from its first token, not its first map that decodes: before, every made-up
    # name on the ROS graph (a publisher that never sends a map that parses) held a subscription.
    peer = rmw_peer.RmwPeer(endpoint, listen=True)
    peers.append(peer)
    opts = Ros2Options(
        discover_robots=True, known_init_poses=False, mode="peer", connect=[endpoint], max_robots=3
    )
    src = Ros2Source(opts, SourceContext(robot="base"))

    async def go() -> None:
        it = cast(AsyncGenerator[OccupancyGrid, None], src.maps().__aiter__())
        task = asyncio.ensure_future(it.__anext__())
        await asyncio.sleep(1.0)
        for i in range(12):
            await asyncio.to_thread(peer.publisher, f"/ghost{i}/map")
        end = asyncio.get_running_loop().time() + 10
        while len(src._ignored) < 9 and asyncio.get_running_loop().time() < end:
            await asyncio.sleep(0.05)
        assert len(src._announced) == 3 and len(src._ignored) == 9
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, StopAsyncIteration):
            await task
        await it.aclose()

    asyncio.run(go())
