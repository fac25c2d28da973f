"""The ros2 output, seen by an independent rmw_zenoh peer: /map, /tf_static, /tf, QoS and the graph."""

from __future__ import annotations

import asyncio
import math
import re
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest
import zenoh.ext as zext

from mapd import plugins
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import GlobalUpdate, OutputContext, PoseUpdate
from mapd.outputs.ros2 import Ros2Output, Ros2OutputOptions


def _output(endpoint: str, state_dir: Path | None = None, **kw: Any) -> Ros2Output:
    out = Ros2Output(
        Ros2OutputOptions(listen=[endpoint], connect=[], **kw),
        OutputContext(robot="base", fleet="f", state_dir=state_dir),
    )
    asyncio.run(out.start())
    return out


def _update(k: int, frames: dict[str, Pose2D] | None = None) -> GlobalUpdate:
    rng = np.random.default_rng(k)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(40 + k, 60))
    grid = OccupancyGrid(data, 0.05, Pose2D(-3.0, 2.5, 0.0), frame_id="ignored", robot="base", version=k)
    return GlobalUpdate(grid=grid, frames=frames or {"robot0": Pose2D()}, stamp=1700000000.5 + k)


def test_registered_under_mapd_outputs() -> None:
    assert plugins.load("output", "ros2") is Ros2Output


def test_late_subscriber_gets_the_current_map_and_frames(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    out = _output(endpoint, frame="world")
    try:
        frames = {"robot0": Pose2D(), "robot1": Pose2D(4.0, -1.0, math.pi / 2)}
        out.publish(_update(1, frames))
        out.publish(_update(2, frames))  # the current one; a depth-1 cache holds only it
        time.sleep(0.3)
        peer = rmw_peer.RmwPeer(endpoint)  # joins after both were published
        peers.append(peer)
        peer.subscribe("/map", rmw_peer.GRID)
        peer.subscribe("/tf_static", rmw_peer.TF)
        got = peer.wait("/map", lambda r: True)
        m = got.msg
        assert (m.info.width, m.info.height) == (60, 42)  # update 2, not 1
        assert m.header.frame_id == "world" and m.info.resolution == pytest.approx(0.05)
        assert (m.info.origin.position.x, m.info.origin.position.y) == (-3.0, 2.5)
        assert np.array_equal(np.asarray(m.data).reshape(42, 60), _update(2).grid.data)
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1700000002, 500000000)
        # the attachment: sequence 2 (the second map), a wall-clock stamp, the GID of the MP token
        assert got.seq == 2 and abs(got.stamp_ns / 1e9 - time.time()) < 60
        graph = peer.graph(
            rmw_peer.having("mapd", ("NN", ""), ("MP", "/map"), ("MP", "/tf_static"), ("MP", "/tf"))
        )
        mine = [t for t in graph if t.node == "mapd"]
        pub = next(t for t in mine if t.kind == "MP" and t.topic == "/map")
        assert got.gid == rmw_peer.gid(pub.key)
        assert pub.hash == rmw_peer.GRID_HASH and pub.qos == rmw_peer.qos(True, 1)
        assert got.key == f"0/map/nav_msgs::msg::dds_::OccupancyGrid_/{rmw_peer.GRID_HASH}"
        assert any(t.kind == "NN" and t.namespace == "/" and t.enclave == "/" for t in mine)
        assert {t.topic for t in mine if t.kind == "MP"} == {"/map", "/tf_static", "/tf"}
        assert len({t.zid for t in mine}) == 1 and {t.nid for t in mine} == {pub.nid}
        tf = peer.wait("/tf_static", lambda r: True).msg
        placed = {t.child_frame_id: t for t in tf.transforms}
        assert set(placed) == {"robot0/map", "robot1/map"}
        r1 = placed["robot1/map"]
        assert r1.header.frame_id == "world" and (r1.transform.translation.x, r1.transform.translation.y) == (
            4.0,
            -1.0,
        )
        assert 2 * math.atan2(r1.transform.rotation.z, r1.transform.rotation.w) == pytest.approx(math.pi / 2)
        # the same placements are not sent again; a changed one is, with every robot
        out.publish(_update(3, frames))
        moved = {**frames, "robot1": Pose2D(5.0, -1.0, 0.0)}
        out.publish(_update(4, moved))
        again = peer.wait(
            "/tf_static", lambda r: any(t.transform.translation.x == 5.0 for t in r.msg.transforms)
        )
        assert len(again.msg.transforms) == 2
        assert len(peer.received("/tf_static")) == 2 and out.stats()["tf_static"] == 2
    finally:
        asyncio.run(out.close())


def _tf2_static(messages: list[Any]) -> dict[str, str]:
    """child -> parent as tf2's buffer keeps static transforms: for ever, a newer one of a frame
    replacing the older (tf2's StaticCache holds one transform, with its parent, per frame)."""
    parents: dict[str, str] = {}
    for msg in messages:
        for t in msg.transforms:
            parents[t.child_frame_id] = t.header.frame_id
    return parents


def _under(parents: dict[str, str], frame: str, root: str) -> bool:
    """Whether tf2 could look ``frame`` up in ``root`` (a chain of parents leads there)."""
    seen = set()
    while frame != root and frame in parents and frame not in seen:
        seen.add(frame)
        frame = parents[frame]
    return frame == root


def test_a_robot_no_longer_placed_leaves_the_fleet_tree_also_after_a_restart(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any], tmp_path: Path
) -> None:
    """tf2 keeps static transforms for as long as it runs. A revoked robot's map frame used to stay
    in the fleet frame for every listener that had heard it once; now the next message moves it off
    the tree, under ``unplaced_frame``, and a restarted output still knows to."""
    both = {"robot0": Pose2D(), "robot1": Pose2D(4.0, -1.0, 0.5)}
    peer = rmw_peer.RmwPeer(endpoint)
    peers.append(peer)
    peer.subscribe("/tf_static", rmw_peer.TF, depth=10)
    out = _output(endpoint, tmp_path)
    try:
        out.publish(_update(1, both))
        peer.wait("/tf_static", lambda r: len(r.msg.transforms) == 2)
        assert _under(_tf2_static([r.msg for r in peer.received("/tf_static")]), "robot1/map", "map")
        out.publish(_update(2, {"robot0": Pose2D()}))  # robot1 revoked: the global map goes on without it
        got = peer.wait("/tf_static", lambda r: len(r.msg.transforms) == 2 and r.seq == 2).msg
        assert sorted((t.header.frame_id, t.child_frame_id) for t in got.transforms) == [
            ("map", "robot0/map"),
            ("mapd/unplaced", "robot1/map"),
        ]
        tf2 = _tf2_static([r.msg for r in peer.received("/tf_static")])
        assert _under(tf2, "robot0/map", "map") and not _under(tf2, "robot1/map", "map")
        assert out.stats()["unplaced"] == 1
    finally:
        asyncio.run(out.close())
    # A restart, with robot1 still off the roster: the first message moves it off again, for
    # listeners that heard its frame from the run before and nothing since.
    again = _output(endpoint, tmp_path)
    late = rmw_peer.RmwPeer(endpoint)
    peers.append(late)
    try:
        again.publish(_update(3, {"robot0": Pose2D(1.0, 0.0, 0.0)}))
        late.subscribe("/tf_static", rmw_peer.TF)
        got = late.wait("/tf_static", lambda r: True).msg
        assert {t.child_frame_id: t.header.frame_id for t in got.transforms} == {
            "robot0/map": "map",
            "robot1/map": "mapd/unplaced",
        }
        # placed again (readmitted): back under the fleet frame, and nothing left off the tree
        again.publish(_update(4, {"robot0": Pose2D(1.0, 0.0, 0.0), "robot1": Pose2D(2.0, 0.0, 0.0)}))
        got = late.wait("/tf_static", lambda r: all(t.header.frame_id == "map" for t in r.msg.transforms)).msg
        assert len(got.transforms) == 2 and again.stats()["unplaced"] == 0
    finally:
        asyncio.run(again.close())


@pytest.mark.parametrize(
    "content",
    [
        b"",
        b"{",
        b"[" * 100_000,
        b'{"robots": ["ok", "../../x"]}',
        b'{"robots": 7}',
        b"\xff" * 10,
        b" " * (2 << 20),
    ],
)
def test_a_damaged_frames_file_is_said_and_ignored(
    tmp_path: Path, content: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    from mapd.outputs.ros2 import FRAMES_FILE

    (tmp_path / FRAMES_FILE).write_bytes(content)
    out = Ros2Output(Ros2OutputOptions(), OutputContext(robot="base", fleet="f", state_dir=tmp_path))
    with caplog.at_level("WARNING"):
        assert out._load_shown() == set()
    assert len(caplog.records) == 1 and "frames sent before it are not moved off" in caplog.text


def test_unplaced_frame_is_checked() -> None:
    assert Ros2OutputOptions(unplaced_frame="").unplaced_frame == ""
    for bad in ("map", "{robot}/gone", "a//b"):
        with pytest.raises(ValueError):
            Ros2OutputOptions(unplaced_frame=bad)
    with pytest.raises(ValueError):
        Ros2OutputOptions(frame="world", unplaced_frame="world")


def test_poses_go_on_tf(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any], zenoh_linked: Callable[..., None]
) -> None:
    out = _output(endpoint)
    peer = rmw_peer.RmwPeer(endpoint)
    peers.append(peer)
    peer.subscribe("/tf", rmw_peer.TF, transient_local=False, depth=100)
    try:
        zenoh_linked(peer.session)  # the volatile subscription reaches the output's session
        poses = {"robot0": StampedPose(Pose2D(1.5, 2.0, -0.5), 1700000100.0)}
        out.publish_poses(PoseUpdate(poses=poses, frames={"robot0": Pose2D()}))
        got = peer.wait("/tf", lambda r: True).msg.transforms[0]
        assert (got.header.frame_id, got.child_frame_id) == ("robot0/map", "robot0/base_link")
        assert (got.transform.translation.x, got.transform.translation.y) == (1.5, 2.0)
        assert got.header.stamp.sec == 1700000100
        # the same stamped pose again (a global map carries the latest poses too): not repeated
        out.publish(GlobalUpdate(grid=_update(1).grid, frames={"robot0": Pose2D()}, stamp=1.0, poses=poses))
        newer = {"robot0": StampedPose(Pose2D(1.6, 2.0, -0.5), 1700000100.5)}
        out.publish_poses(PoseUpdate(poses=newer, frames={"robot0": Pose2D()}))
        peer.wait("/tf", lambda r: r.msg.transforms[0].transform.translation.x == 1.6)
        assert len(peer.received("/tf")) == 2 and out.stats()["tf"] == 2
        tf_token = next(
            t
            for t in peer.graph(rmw_peer.having("mapd", ("MP", "/tf")))
            if t.node == "mapd" and t.topic == "/tf"
        )
        assert tf_token.qos == rmw_peer.qos(False, 100)  # volatile, keep last 100 (tf2's broadcaster)
    finally:
        asyncio.run(out.close())


def test_humble_namespace_and_domain(endpoint: str, rmw_peer: ModuleType, peers: list[Any]) -> None:
    out = _output(endpoint, distro="humble", namespace="/fleet", topic="merged", domain_id=7, tf=False)
    try:
        out.publish(_update(1))
        peer = rmw_peer.RmwPeer(endpoint, domain=7, distro="humble")
        peers.append(peer)
        peer.subscribe("/fleet/merged", rmw_peer.GRID)
        got = peer.wait("/fleet/merged", lambda r: True)
        assert got.key == "7/fleet/merged/nav_msgs::msg::dds_::OccupancyGrid_/TypeHashNotSupported"
        mine = [
            t
            for t in peer.graph(rmw_peer.having("mapd", ("NN", ""), ("MP", "/fleet/merged")))
            if t.node == "mapd"
        ]
        assert {(t.kind, t.topic) for t in mine} == {("NN", ""), ("MP", "/fleet/merged")}
        assert all(t.namespace == "/fleet" for t in mine)
        assert "%fleet/mapd/%fleet%merged/" in next(t.key for t in mine if t.kind == "MP")
    finally:
        asyncio.run(out.close())


def test_ros2dds_format_plain_keys_no_attachment(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    out = _output(endpoint, format="ros2dds", namespace="site")
    try:
        out.publish(_update(1))
        peer = rmw_peer.RmwPeer(endpoint)
        peers.append(peer)
        time.sleep(0.3)
        replies = list(peer.session.get("site/map", timeout=3.0))  # late joiner: the queryable answers
        sample = next(r.ok for r in replies if r.ok is not None)
        msg = rmw_peer.TS.deserialize_cdr(sample.payload.to_bytes(), rmw_peer.GRID)
        assert (msg.info.width, msg.info.height) == (60, 41) and sample.attachment is None
        # A bridge (zenoh-bridge-ros2dds 1.5.1 and later) routes a transient-local DDS reader (RViz
        # started after the merge) through an advanced subscriber that detects late publishers and
        # asks for their cache (route_subscriber.rs); mapd's plain publisher had none, so such a
        # reader got no map and no frames until the next merge.
        got: dict[str, list[bytes]] = {"site/map": [], "site/tf_static": []}
        subs = [
            zext.declare_advanced_subscriber(
                peer.session,
                key,
                lambda sample, key=key: got[key].append(sample.payload.to_bytes()),
                history=zext.HistoryConfig(detect_late_publishers=True, max_samples=1),
            )
            for key in got
        ]
        try:
            deadline = time.monotonic() + 10
            while not all(got.values()) and time.monotonic() < deadline:
                time.sleep(0.1)
        finally:
            for sub in subs:
                sub.undeclare()
        assert [len(v) for v in got.values()] == [1, 1], {k: len(v) for k, v in got.items()}
        bridged = rmw_peer.TS.deserialize_cdr(got["site/map"][0], rmw_peer.GRID)
        assert (bridged.info.width, bridged.info.height) == (60, 41)
        assert rmw_peer.TS.deserialize_cdr(got["site/tf_static"][0], "tf2_msgs/msg/TFMessage").transforms
        assert not [t for t in peer.graph() if t.node == "mapd"]  # a bridge announces topics, not mapd
    finally:
        asyncio.run(out.close())


def test_a_client_whose_rmw_zenohd_is_not_up_waits_and_then_latches_the_newest_map(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any], monkeypatch: pytest.MonkeyPatch
) -> None:
    # It stopped the daemon at start (its links too) when rmw_zenohd came up after it.
    from mapd.ros2 import cdr, zenoh_config

    monkeypatch.setattr(zenoh_config, "RETRY_FIRST_S", 0.2)
    out = Ros2Output(
        Ros2OutputOptions(mode="client", connect=[endpoint], listen=[]),
        OutputContext(robot="base", fleet="f"),
    )

    async def main() -> Any:
        await out.start()
        try:
            out.publish(_update(2))
            out.publish(_update(3))  # the newest waits
            await asyncio.sleep(0.6)
            assert out.stats()["session_open"] is False and out.stats()["maps"] == 0
            router = await asyncio.to_thread(cdr.open_session, mode="router", listen=[endpoint])
            try:
                end = time.monotonic() + 20
                while out.stats()["maps"] < 1:
                    assert time.monotonic() < end, "the waiting map never went out"
                    await asyncio.sleep(0.1)
                assert out.stats()["session_open"] is True and out.stats()["maps"] == 1
                peer = await asyncio.to_thread(rmw_peer.RmwPeer, endpoint)
                peers.append(peer)
                peer.subscribe("/map", rmw_peer.GRID)
                return await asyncio.to_thread(peer.wait, "/map", lambda r: True)
            finally:
                await out.close()
                router.close()
        finally:
            await out.close()  # (again, if the wait failed before the router: closing twice is safe)

    got = asyncio.run(main())
    assert (got.msg.info.width, got.msg.info.height) == (60, 43)  # update 3, latched


def test_frame_and_topic_names_are_ones_tf2_and_rcl_read_as_written() -> None:
    """tf2 strips a leading '/' when a transform is set and refuses it in lookups, and drops a
    transform from a frame to itself: names it reads otherwise than mapd put the robots that
    unplaced_frame took off the tree back on it. Topics must be names rcl accepts."""
    for ok in (
        {},
        {"frame": "world", "robot_map_frame": "{robot}/map_fleet", "robot_pose_frame": "{robot}/mapd_pose"},
        {"frame": "fleet", "topic": "/fleet/map", "unplaced_frame": "fleet/unplaced"},
        {"topic": "merged", "namespace": "/fleet"},
        {"topic": "fleet_map", "namespace": "robot_1/"},
        {"robot_pose_frame": ""},
        {"unplaced_frame": ""},
    ):
        Ros2OutputOptions(**ok)
    assert Ros2OutputOptions(frame="earth-1").frame == "earth-1"  # robot names make such frames anyway
    bad: list[tuple[dict[str, Any], str]] = [
        ({"frame": "/map"}, "no leading '/'"),  # tf2: lookups throw; the header is '/map'
        ({"robot_map_frame": "/{robot}/map"}, "no leading '/'"),
        ({"robot_pose_frame": "/{robot}/base_link"}, "no leading '/'"),
        ({"unplaced_frame": "/map"}, "no leading '/'"),  # tf2 reads it as 'map': placed again
        ({"frame": "map/"}, "empty part"),
        ({"frame": "map\nfoo"}, "printable ASCII"),
        ({"frame": "ma\tp"}, "printable ASCII"),
        ({"frame": "mäp"}, "printable ASCII"),
        ({"frame": "my map"}, "printable ASCII"),
        ({"unplaced_frame": "robot0/map"}, "robot_map_frame of a robot named 'robot0'"),
        ({"unplaced_frame": "robot0/base_link"}, "robot_pose_frame of a robot named 'robot0'"),
        ({"frame": "robot0/map"}, "robot_map_frame of a robot named 'robot0'"),
        ({"robot_map_frame": "{robot}"}, "frame 'map' is the robot_map_frame of a robot named 'map'"),
        ({"robot_pose_frame": "{robot}/map"}, "is robot_map_frame"),  # TF_SELF_TRANSFORM
        ({"frame": "world", "unplaced_frame": "world"}, "is the fleet frame"),
        ({"topic": "my-map"}, "not a ROS 2 topic name"),
        ({"topic": "/map/"}, "not a ROS 2 topic name"),
        ({"topic": "/2d/map"}, "not a ROS 2 topic name"),
        ({"topic": "/map\n"}, "not a ROS 2 topic name"),
        ({"topic": "~/map"}, "does not expand '~'"),
        ({"namespace": "my-fleet"}, "not a ROS 2 namespace name"),
    ]
    for kw, why in bad:
        with pytest.raises(ValueError) as info:
            Ros2OutputOptions(**kw)
        assert why in str(info.value), (kw, str(info.value))
        assert len(info.value.errors()) == 1, kw  # type: ignore[attr-defined]  # one clear error each


def _robot_map(robot: str, k: int) -> OccupancyGrid:
    rng = np.random.default_rng(100 + k)
    data = rng.choice(np.array([-1, 0, 100], dtype=np.int8), size=(30, 20 + k))
    return OccupancyGrid(data, 0.05, Pose2D(1.0, -2.0, 0.0), robot=robot, version=k)


def test_each_robots_map_goes_out_latched_on_its_topic_in_its_frame(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any], caplog: pytest.LogCaptureFixture
) -> None:
    """robot_map_topic: the maps the daemon holds, one latched topic per robot, in the robot's map
    frame (so RViz places each with /tf_static); a robot whose name rcl refuses is said once."""
    from mapd.ros2.node import own_publishers

    out = _output(endpoint, robot_map_topic="/{robot}/map")
    try:
        out.publish_robot_map(_robot_map("robot1", 1), 1700000010.25)
        out.publish_robot_map(_robot_map("robot1", 2), 1700000011.25)  # the newest is the latched one
        out.publish_robot_map(_robot_map("base", 1), 1700000012.0)
        for _ in range(2):
            out.publish_robot_map(_robot_map("alpha-1", 1), 1700000013.0)  # no ROS name: said once
        time.sleep(0.3)
        peer = rmw_peer.RmwPeer(endpoint)  # a late subscriber, as RViz
        peers.append(peer)
        peer.subscribe("/robot1/map", rmw_peer.GRID)
        peer.subscribe("/base/map", rmw_peer.GRID)
        got = peer.wait("/robot1/map", lambda r: True)
        m = got.msg
        assert m.header.frame_id == "robot1/map" and (m.info.width, m.info.height) == (22, 30)
        assert np.array_equal(np.asarray(m.data).reshape(30, 22), _robot_map("robot1", 2).data)
        assert (m.header.stamp.sec, m.header.stamp.nanosec) == (1700000011, 250000000)
        assert peer.wait("/base/map", lambda r: True).msg.header.frame_id == "base/map"
        graph = peer.graph(rmw_peer.having("mapd", ("MP", "/robot1/map"), ("MP", "/base/map")))
        pub = next(t for t in graph if t.node == "mapd" and t.topic == "/robot1/map")
        assert pub.qos == rmw_peer.qos(True, 1) and got.gid == rmw_peer.gid(pub.key)
        assert own_publishers.is_own(gid=got.gid)  # a ros2 source in this daemon drops its samples
        assert not any("alpha" in t.topic for t in graph if t.kind == "MP")
        st = out.stats()
        assert (st["robot_maps"], st["robot_topics"], st["maps"]) == (3, 2, 0)
        said = [r.getMessage() for r in caplog.records if "alpha-1" in r.getMessage()]
        assert len(said) == 1 and "not a ROS 2 topic name: '/alpha-1/map'" in said[0], said
    finally:
        asyncio.run(out.close())
    assert not own_publishers.is_own(gid=got.gid)  # forgotten with the session


def test_robot_map_topic_names_each_robot_apart_from_the_global_map_and_the_source() -> None:
    from mapd.sources.ros2_options import Ros2Options

    o = Ros2OutputOptions(robot_map_topic="{robot}/map", namespace="/fleet")
    assert o.robot_topic("robot7") == "/fleet/robot7/map"
    assert o.robot_maps_key_expr() == "0/fleet/*/map/nav_msgs::msg::dds_::OccupancyGrid_/*"
    assert Ros2OutputOptions(robot_map_topic="/mapd/{robot}_map").robot_maps_key_expr() == (
        "0/mapd/$*_map/nav_msgs::msg::dds_::OccupancyGrid_/*"
    )
    assert Ros2OutputOptions().robot_maps_key_expr() is None
    for bad, says in (
        ("/robots/map", "must name the robot with {robot}"),
        ("/{robot}-map", "not a ROS 2 topic name"),
        ("/{robot}/map/", "not a ROS 2 topic name"),
    ):
        with pytest.raises(ValueError, match=re.escape(says)):
            Ros2OutputOptions(robot_map_topic=bad)
    with pytest.raises(ValueError, match="the robot_map_topic of a robot named 'robot1'"):
        Ros2OutputOptions(robot_map_topic="/{robot}", topic="/robot1")
    with pytest.raises(
        ValueError, match="the robot_map_topic of a robot named 'robot1'"
    ):  # under the namespace
        Ros2OutputOptions(robot_map_topic="{robot}", topic="/fleet/robot1", namespace="fleet")
    with pytest.raises(ValueError, match=r"robot alpha-1: not a ROS 2 topic name"):
        o.robot_topic("alpha-1")
    # a map_merge drop-in source takes /<robot>/map: the robots' maps must go out elsewhere
    source = {"source": {"ros2": Ros2Options(discover_robots=True)}}
    with pytest.raises(
        ValueError, match=r"robot_map_topic: '/\{robot\}/map' .* is where \[source.ros2\] takes"
    ):
        Ros2OutputOptions(robot_map_topic="/{robot}/map", topic="/fleet_map").check_with_plugins(source)
    Ros2OutputOptions(robot_map_topic="/mapd/{robot}/map", topic="/fleet_map").check_with_plugins(source)
