"""The ros2 source's robot pose from /amcl_pose (or a PoseStamped topic), fed by an independent rmw_zenoh peer."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import pytest

from mapd.errors import CodecError
from mapd.grid import StampedPose
from mapd.sources.base import SourceContext
from mapd.sources.ros2 import Ros2Options, Ros2Source
from mapd.sources.ros2_pose import decode_pose


def _pose_msg(
    peer_mod: ModuleType, msgtype: str, x: float, y: float, yaw: float, frame: str = "map", scale: float = 1.0
) -> bytes:
    """A CDR pose message built with the peer's own type store (``scale``: a quaternion off unit length)."""
    t = peer_mod.TS.types
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=scale * math.sin(yaw / 2), w=scale * math.cos(yaw / 2)
        ),
    )
    header = t["std_msgs/msg/Header"](
        stamp=t["builtin_interfaces/msg/Time"](sec=12, nanosec=0), frame_id=frame
    )
    if msgtype == peer_mod.POSE_COV:
        cov = np.arange(36, dtype=np.float64)
        msg = t[msgtype](
            header=header, pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov)
        )
    else:
        msg = t[msgtype](header=header, pose=pose)
    return bytes(peer_mod.TS.serialize_cdr(msg, msgtype))


def _run_source(src: Ros2Source, body: Callable[[], Any]) -> Any:
    """Run the source's stream (its subscriptions live while it runs) and ``body`` in a thread beside it."""

    async def go() -> Any:
        it = src.maps().__aiter__()
        task = asyncio.ensure_future(it.__anext__())  # waits for a map that never comes; the pose does
        try:
            return await asyncio.to_thread(body)
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    return asyncio.run(go())


def _wait(pred: Callable[[], Any], what: str, timeout: float = 15.0) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"{what} within {timeout} s")


# -- options and decoding ------------------------------------------------------------------------------


def test_options() -> None:
    o = Ros2Options()
    assert o.pose_topic is None and o.pose_type == "PoseWithCovarianceStamped" and o.pose_frame == "map"
    src = Ros2Source(o, SourceContext(robot="r1"))
    assert src.pose() is None and not any(k.startswith("pose_") for k in src.stats())
    assert Ros2Options(pose_topic="amcl_pose").pose_topic == "/amcl_pose"
    with pytest.raises(ValueError, match="discover_robots"):
        Ros2Options(pose_topic="/amcl_pose", discover_robots=True)
    for bad in ("a//b", "/amcl*", ""):
        with pytest.raises(ValueError):
            Ros2Options(pose_topic=bad)
    with pytest.raises(ValueError):
        Ros2Options(pose_topic="/p", pose_type="Odometry")  # type: ignore[arg-type]


@pytest.mark.parametrize("msgtype", ["POSE_COV", "POSE"])
def test_decode_pose_yaw_from_the_quaternion(rmw_peer: ModuleType, msgtype: str) -> None:
    mt = getattr(rmw_peer, msgtype)
    for yaw in (0.0, 0.7, -2.9, math.pi / 2):
        for scale in (1.0, 0.5):  # a quaternion off unit length still gives the yaw
            frame, pose = decode_pose(_pose_msg(rmw_peer, mt, 1.5, -2.25, yaw, "map", scale), mt)
            assert frame == "map" and (pose.x, pose.y) == (1.5, -2.25)
            assert pose.yaw == pytest.approx(yaw, abs=1e-9)
    # roll and pitch do not leak into the yaw: a quaternion with x, y set (a robot on a slope)
    t = rmw_peer.TS.types
    q = (0.05, -0.03, math.sin(0.4), math.cos(0.4))
    n = math.sqrt(sum(v * v for v in q))
    msg = t[rmw_peer.POSE](
        header=t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="map"
        ),
        pose=t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](*(v / n for v in q)),
        ),
    )
    _, tilted = decode_pose(bytes(rmw_peer.TS.serialize_cdr(msg, rmw_peer.POSE)), rmw_peer.POSE)
    assert tilted.yaw == pytest.approx(0.8, abs=0.01)


def test_decode_pose_refuses_bad_payloads(rmw_peer: ModuleType) -> None:
    good = _pose_msg(rmw_peer, rmw_peer.POSE_COV, 1.0, 2.0, 0.3)
    for bad in (
        b"",
        b"\x00\x01\x00\x00",
        b"garbage!" * 4,
        good[: len(good) // 2],
        b"\x00\x01\x00\x00" + b"\xff" * 40000,
    ):
        with pytest.raises(CodecError):
            decode_pose(bad, rmw_peer.POSE_COV)
    with pytest.raises(CodecError, match="finite"):
        decode_pose(_pose_msg(rmw_peer, rmw_peer.POSE, math.nan, 0.0, 0.0), rmw_peer.POSE)
    with pytest.raises(CodecError, match="zero quaternion"):
        decode_pose(_pose_msg(rmw_peer, rmw_peer.POSE, 0.0, 0.0, 0.0, scale=0.0), rmw_peer.POSE)
    # what every peer's unpack_pose refuses: it was sent on, and dropped by each of them, unsaid
    with pytest.raises(CodecError, match="from the origin"):
        decode_pose(_pose_msg(rmw_peer, rmw_peer.POSE, 2e7, 0.0, 0.0), rmw_peer.POSE)
    # components that overflow when multiplied: a yaw all the same, not NaN
    _, pose = decode_pose(_pose_msg(rmw_peer, rmw_peer.POSE, 0.0, 0.0, 0.3, scale=1e200), rmw_peer.POSE)
    assert pose.yaw == pytest.approx(0.3, abs=1e-9)


# -- over zenoh, with the independent peer --------------------------------------------------------------


def test_amcl_pose_cached_before_start_then_updates_wrong_frames_and_garbage(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)
    peers.append(peer)
    pub = peer.publisher("/amcl_pose", rmw_peer.POSE_COV)  # transient local, depth 1: AMCL's QoS
    peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE_COV, 3.0, -1.0, 2.5), seq=1)  # before mapd starts
    opts = Ros2Options(mode="peer", connect=[endpoint], pose_topic="/amcl_pose")
    src = Ros2Source(opts, SourceContext(robot="r1"))

    def body() -> tuple[StampedPose, StampedPose | None, StampedPose, dict[str, Any], list[Any]]:
        t0 = time.time()
        first = _wait(src.pose, "the cached pose (history)")
        assert t0 - 1.0 <= first.stamp <= time.time()  # stamped at reception, not the header's 12 s
        peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE_COV, 9.0, 9.0, 0.0, frame="odom"), seq=2)
        _wait(lambda: src.stats()["pose_wrong_frame"] == 1, "the odom pose counted")
        after_odom = src.pose()
        peer.put(pub, b"\x00\x01\x00\x00not a pose at all", seq=3)
        _wait(lambda: src.stats()["pose_bad_payloads"] == 1, "the garbage counted")
        peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE_COV, 3.5, -0.5, -1.0, frame="/map"), seq=4)
        last = _wait(lambda: (p := src.pose()) is not None and p.pose.x == 3.5 and p, "the next pose")
        graph = peer.graph(rmw_peer.having("mapd_source", ("NN", ""), ("MS", "/map"), ("MS", "/amcl_pose")))
        return first, after_odom, last, src.stats(), graph

    first, after_odom, last, stats, graph = _run_source(src, body)
    assert (first.pose.x, first.pose.y) == (3.0, -1.0) and first.pose.yaw == pytest.approx(2.5)
    assert after_odom == first  # the odom pose was ignored
    assert (last.pose.x, last.pose.y) == (3.5, -0.5) and last.pose.yaw == pytest.approx(-1.0)
    assert last.stamp >= first.stamp
    assert stats["pose_received"] == 4 and stats["pose_last_wrong_frame"] == "odom"
    # any type hash, as the map's key: one for the distro's (jazzy's) never matched Humble's
    # TypeHashNotSupported, and on Humble no pose arrived, without a word
    assert stats["pose_key"] == f"0/amcl_pose/{rmw_peer.DDS[rmw_peer.POSE_COV]}/*"
    import zenoh

    humble = f"0/amcl_pose/{rmw_peer.DDS[rmw_peer.POSE_COV]}/TypeHashNotSupported"
    assert zenoh.KeyExpr(stats["pose_key"]).intersects(zenoh.KeyExpr(humble))
    mine = {(t.kind, t.topic): t for t in graph if t.node == "mapd_source"}
    assert set(mine) == {("NN", ""), ("MS", "/map"), ("MS", "/amcl_pose")}
    sub = mine[("MS", "/amcl_pose")]
    assert sub.type == rmw_peer.DDS[rmw_peer.POSE_COV] and sub.hash == rmw_peer.POSE_HASHES[rmw_peer.POSE_COV]
    assert sub.qos == rmw_peer.qos(True, 1)
    assert src._session is None  # closed with the stream


def test_pose_stamped_from_a_late_publisher_in_a_custom_frame(
    endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True, domain=3)
    peers.append(peer)
    opts = Ros2Options(
        mode="peer", connect=[endpoint], domain=3, pose_topic="/robot/pose", pose_type="PoseStamped",
        pose_frame="robot/map",
    )  # fmt: skip
    src = Ros2Source(opts, SourceContext(robot="r1"))

    def body() -> StampedPose:
        time.sleep(1.0)  # the source is up first: the publisher appears later
        pub = peer.publisher("/robot/pose", rmw_peer.POSE)
        time.sleep(0.3)
        peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE, 9.0, 9.0, 0.0, frame="map"), seq=1)  # not robot/map
        peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE, -4.0, 0.25, -3.0, frame="robot/map"), seq=2)
        return _wait(src.pose, "the PoseStamped pose")

    got = _run_source(src, body)
    assert (got.pose.x, got.pose.y) == (-4.0, 0.25) and got.pose.yaw == pytest.approx(-3.0)
    assert src.stats()["pose_wrong_frame"] == 1


# -- a mapd process ---------------------------------------------------------------------------------------


@pytest.mark.slow
def test_mapd_status_shows_the_robot_pose_from_amcl(
    tmp_path: Path, endpoint: str, rmw_peer: ModuleType, peers: list[Any]
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)
    peers.append(peer)
    room = np.zeros((30, 40), dtype=np.int8)
    room[0, :] = room[-1, :] = 100
    peer.publish_map(peer.publisher("/map"), room, 0.05, (0.0, 0.0), "map", seq=1)
    pub = peer.publisher("/amcl_pose", rmw_peer.POSE_COV)
    peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE_COV, 1.25, 0.5, 0.75), seq=1)
    run = tmp_path / "run"
    cfg = tmp_path / "config.toml"
    cfg.write_text(
        f'[robot]\nname = "r7"\n[fleet]\nallow_unsigned = true\n'
        f'[source]\nuse = "ros2"\n[source.ros2]\nmode = "peer"\nconnect = ["{endpoint}"]\n'
        f'pose_topic = "/amcl_pose"\n'
        f'[state]\ndir = "{tmp_path / "state"}"\nruntime_dir = "{run}"\n'
    )
    log = open(tmp_path / "daemon.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", "run", "--config", str(cfg)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )

    def status() -> dict[str, Any] | None:
        assert proc.poll() is None, (tmp_path / "daemon.log").read_text(errors="replace")[-2000:]
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--json", "--socket", str(run / "mapd.sock")],
            capture_output=True,
            text=True,
            timeout=30,
        )
        return json.loads(out.stdout) if out.returncode == 0 else None

    def has_pose(s: dict[str, Any] | None) -> bool:
        return s is not None and "r7" in s.get("poses", {}).get("robots", {})

    try:
        first = _wait(lambda: (s := status()) is not None and has_pose(s) and s, "r7's pose in status", 60)
        peer.put(pub, _pose_msg(rmw_peer, rmw_peer.POSE_COV, -2.0, 3.0, -0.5), seq=2)
        moved = _wait(
            lambda: (s := status()) is not None and s["poses"]["robots"]["r7"]["map"][0] == -2.0 and s,
            "the moved pose in status",
            30,
        )
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(20)
        log.close()
    assert code == 0, (tmp_path / "daemon.log").read_text(errors="replace")[-2000:]
    assert first["poses"]["robots"]["r7"]["map"] == [1.25, 0.5, 0.75]
    assert moved["poses"]["robots"]["r7"]["map"] == [-2.0, 3.0, -0.5]
    assert (
        moved["source"]["stats"]["pose_received"] >= 2 and moved["source"]["stats"]["pose_bad_payloads"] == 0
    )
