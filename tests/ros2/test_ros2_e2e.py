"""Real ``mapd run`` processes and an independent rmw_zenoh peer: a demo fleet's base station on ROS 2,
and mapd replacing multirobot_map_merge (robots' /<robot>/map in, the merged /map and TF out)."""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.demo.fleet import Fleet
from mapd.grid.load import load_map

pytestmark = pytest.mark.slow


def test_demo_fleet_base_station_publishes_map_and_frames(
    tmp_path: Path, endpoint: str, rmw_peer: ModuleType, peers: list[Any], fk: SimpleNamespace
) -> None:
    args = argparse.Namespace(
        robots=2, transport="zenoh", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0,
        ros2_listen=endpoint,
    )  # fmt: skip
    f = Fleet(args)
    f.prepare()
    assert f.members == ["robot0", "robot1", "base"]
    known = tomllib.loads((f.run_dir / "base" / "config.toml").read_text())["fusion"]["poses"]
    assert set(known) == {"robot0", "robot1"}
    f.start()
    try:
        snaps = fk.wait_for(lambda s: s.get("base", {}).get("fusion", {}).get("maps", 0) >= 2, 150, f)
        assert snaps["base"]["source"]["name"] == "none"
        poses = {r: p for r, p in snaps["base"]["fusion"]["robots"].items()}
        peer = rmw_peer.RmwPeer(endpoint)  # a ROS 2 machine joining late, as RViz does
        peers.append(peer)
        peer.subscribe("/map", rmw_peer.GRID)
        peer.subscribe("/tf_static", rmw_peer.TF)
        first = peer.wait("/map", lambda r: True, timeout=20)
        assert first.msg.header.frame_id == "map" and first.msg.info.resolution == pytest.approx(0.05)
        tf = peer.wait("/tf_static", lambda r: len(r.msg.transforms) == 2, timeout=30).msg
        placed = {t.child_frame_id: t for t in tf.transforms}
        assert set(placed) == {"robot0/map", "robot1/map"} and all(
            t.header.frame_id == "map" for t in tf.transforms
        )
        for robot in ("robot0", "robot1"):
            t = placed[f"{robot}/map"].transform
            want = poses[robot]  # the fusion's placement, as mapd status reports it: the robot's start pose
            assert want["source"] == "pose" and [want["x"], want["y"], want["yaw"]] == pytest.approx(
                known[robot]
            )
            assert (t.translation.x, t.translation.y) == pytest.approx((want["x"], want["y"]), abs=1e-6)
            assert 2 * math.atan2(t.rotation.z, t.rotation.w) == pytest.approx(want["yaw"], abs=1e-6)
        # the robots' poses reach the base station (signed, over zenoh) and leave it as /tf
        peer.subscribe("/tf", rmw_peer.TF, transient_local=False, depth=100)
        for robot in ("robot0", "robot1"):
            child = f"{robot}/base_link"
            got = peer.wait(
                "/tf", lambda r, c=child: any(t.child_frame_id == c for t in r.msg.transforms), 30
            )
            moved = next(t for t in got.msg.transforms if t.child_frame_id == child)
            assert moved.header.frame_id == f"{robot}/map"
        want = (("NN", ""), ("MP", "/map"), ("MP", "/tf_static"), ("MP", "/tf"))
        graph = peer.graph(rmw_peer.having("mapd", *want))
        mine = {(t.kind, t.topic) for t in graph if t.node == "mapd"}
        assert set(want) <= mine
        # The status read before /map arrived may predate the output's first publish (it runs on a
        # worker thread after the merge): read it again, now that the peer has a map.
        fk.wait_for(lambda s: s.get("base", {}).get("outputs", {}).get("ros2", {}).get("maps", 0) >= 1, 10, f)
        peer.wait("/map", lambda r: r.seq >= 3, timeout=60)  # updates keep coming
        # stop the robots; once the base station is idle, its last /map is the global map it keeps
        for robot in ("robot0", "robot1"):
            f.procs[robot].send_signal(signal.SIGTERM)
            assert f.procs[robot].wait(20) == 0
        merges, still, deadline = -1, 0, time.monotonic() + 60
        while still < 3:
            assert time.monotonic() < deadline, "the base station did not settle"
            time.sleep(1.0)
            fusion = f.status()["base"]["fusion"]
            still = still + 1 if fusion["merges"] == merges and not fusion["pending"] else 0
            merges = fusion["merges"]
        glob = load_map(f.run_dir / "base" / "state" / "global" / "global.yaml")
        time.sleep(0.5)
        last = peer.received("/map")[-1]
        # and each robot's map as the base station holds it, latched, in that robot's map frame
        robots = {}
        for robot in ("robot0", "robot1"):
            peer.subscribe(f"/{robot}/map", rmw_peer.GRID)
            robots[robot] = peer.wait(f"/{robot}/map", lambda r: True, timeout=20).msg
        held = {r: v["version"] for r, v in f.status()["base"]["peers"].items()}
        # restarted with the robots gone, the base station publishes the robots' maps it restored
        # at once (they waited for each robot's next map, which never came)
        f.procs["base"].send_signal(signal.SIGTERM)
        assert f.procs["base"].wait(20) == 0
        fk.restart(f, "base")
        deadline = time.monotonic() + 60
        while "base" not in f.status():  # (the robots are stopped: not fk.wait_for, which wants all)
            assert time.monotonic() < deadline and f.procs["base"].poll() is None, (
                "the base did not come back"
            )
            time.sleep(0.5)
        again = rmw_peer.RmwPeer(endpoint)
        peers.append(again)
        again.subscribe("/robot1/map", rmw_peer.GRID)
        restored = again.wait("/robot1/map", lambda r: True, timeout=20).msg
    finally:
        codes = f.stop()
    assert codes["base"] == 0
    seqs = [r.seq for r in peer.received("/map")]
    assert seqs == sorted(set(seqs))  # in order, none twice
    m = last.msg
    assert (m.info.width, m.info.height) == (glob.width, glob.height)
    assert (m.info.origin.position.x, m.info.origin.position.y) == pytest.approx(
        (glob.origin.x, glob.origin.y)
    )
    assert np.array_equal(np.asarray(m.data).reshape(glob.height, glob.width), glob.data)
    assert int((glob.data >= 0).sum()) > 1000
    from mapd.daemon.state import StateStore

    store = StateStore(f.run_dir / "base" / "state")
    store.open()
    for robot, rm in robots.items():
        saved = store.peer_map(robot)  # the map the base station holds of it, as it saved it
        assert saved is not None and saved.version == held[robot]
        assert rm.header.frame_id == f"{robot}/map" and (rm.info.width, rm.info.height) == (
            saved.width,
            saved.height,
        )
        assert np.array_equal(np.asarray(rm.data).reshape(saved.height, saved.width), saved.data)
    assert restored.header.frame_id == "robot1/map" and np.array_equal(restored.data, robots["robot1"].data)


def _room(h: int, w: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    data = np.zeros((h, w), dtype=np.int8)
    data[0, :] = data[-1, :] = data[:, 0] = data[:, -1] = 100
    data[rng.integers(2, h - 2, 30), rng.integers(2, w - 2, 30)] = 100
    return data


def test_mapd_run_replaces_multirobot_map_merge(
    tmp_path: Path, endpoint: str, rmw_peer: ModuleType, peers: list[Any], base_config: Any
) -> None:
    peer = rmw_peer.RmwPeer(endpoint, listen=True)  # the ROS 2 side (robots, RViz) behind one endpoint
    peers.append(peer)
    cfg = base_config(
        tmp_path,
        {
            "source.ros2": {
                "discover_robots": True,
                "robot_map_topic": "map",
                "robot_namespace": "robot",
                "known_init_poses": True,
                "mode": "peer",
                "connect": [endpoint],
                "init_poses": {"robot1": [0.0, 0.0, 0.0], "robot2": [4.0, 0.0, 0.0]},
            },
            "fusion": {"debounce_s": 0.2},
            "output": {"use": ["ros2"]},
            "output.ros2": {"connect": [endpoint], "frame": "world", "distro": "jazzy"},
        },
    )
    rooms = {"robot1": _room(40, 60, 1), "robot2": _room(40, 60, 2)}
    for robot, data in rooms.items():  # published before mapd starts: it takes them from the cache
        peer.publish_map(peer.publisher(f"/{robot}/map"), data, 0.05, (0.0, 0.0), f"{robot}/map", seq=1)
    peer.subscribe("/map", rmw_peer.GRID)
    peer.subscribe("/tf_static", rmw_peer.TF)
    log = open(tmp_path / "daemon.log", "wb")  # noqa: SIM115 - closed below
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", "run", "--config", str(cfg)],
        stdout=log,
        stderr=subprocess.STDOUT,
        env=dict(os.environ, PYTHONUNBUFFERED="1"),
    )
    try:
        # both robots merged (the known cells of two 40 x 60 maps)
        got = peer.wait("/map", lambda r: (np.asarray(r.msg.data) >= 0).sum() >= 2 * 40 * 60, timeout=60).msg
        tf = peer.wait("/tf_static", lambda r: len(r.msg.transforms) == 2, timeout=20).msg
        subs = ("MS", "/robot1/map"), ("MS", "/robot2/map")
        graph = peer.graph(
            lambda g: rmw_peer.having("mapd_source", *subs)(g) and rmw_peer.having("mapd", ("NN", ""))(g)
        )
    finally:
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(20)
        log.close()
    text = (tmp_path / "daemon.log").read_text(errors="replace")
    assert code == 0, text[-2000:]
    w, h = got.info.width, got.info.height
    assert got.header.frame_id == "world" and got.info.resolution == pytest.approx(0.05)
    merged = np.asarray(got.data).reshape(h, w)
    # where the fleet frame's origin (robot1's map origin) falls in the global grid
    ox = round(-got.info.origin.position.x / 0.05)
    oy = round(-got.info.origin.position.y / 0.05)
    rows, cols = np.nonzero(merged >= 0)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (oy, oy + 39, ox, ox + 139)  # 7 m x 2 m known
    # robot1's map at the origin, robot2's 80 cells (4 m) to the right, nothing seen in between
    area = merged[oy : oy + 40, ox : ox + 140]
    assert np.array_equal(area[:, :60] >= 65, rooms["robot1"] >= 65)
    assert np.array_equal(area[:, 80:] >= 65, rooms["robot2"] >= 65)
    assert (area[:, 60:80] == -1).all() and (area[:, :60] >= 0).all()
    placed = {t.child_frame_id: (t.transform.translation.x, t.transform.translation.y) for t in tf.transforms}
    assert placed == {"robot1/map": (0.0, 0.0), "robot2/map": (4.0, 0.0)}
    nodes = {t.node for t in graph}
    assert {"mapd", "mapd_source", "tester"} <= nodes
    subs = {t.topic for t in graph if t.node == "mapd_source" and t.kind == "MS"}
    assert subs == {"/robot1/map", "/robot2/map"}
