"""MCAP recordings read back with the mcap library and its independent ROS 2 decoder (mcap-ros2-support)."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from mapd.daemon.coding import CsvLog
from mapd.daemon.sinks import Sinks, link_diagnostics
from mapd.demo.fleet import Fleet, write_config
from mapd.fusion.placement import Placement
from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.outputs.base import OutputContext
from mapd.outputs.ros2 import Ros2Output, Ros2OutputOptions
from mapd.record.info import summarize
from mapd.record.writer import Recorder


def grid(w: int, h: int, robot: str = "robot0", seed: int = 0) -> OccupancyGrid:
    rng = np.random.default_rng(seed)
    d = rng.choice(np.array([-1, 0, 100], np.int8), size=(h, w))
    return OccupancyGrid(d, 0.05, Pose2D(1.5, -2.0, 0.3), robot=robot)


def read_all(path: Path) -> list[tuple[str, str, int, Any]]:
    """(topic, schema, log time, decoded) for every message, decoded with the schemas in the file."""
    out = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out.append((channel.topic, schema.name if schema else "", message.log_time, decoded))
    return out


def test_recorder_writes_grids_tf_and_links_that_an_independent_decoder_reads(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "r.mcap")
    g = grid(40, 30)
    rec.grid("/map", g, "map", 100.0)
    rec.grid("/robot1/map", grid(20, 10, "robot1", 1), "robot1/map", 100.5)
    rec.transforms(
        "/tf_static", "map", {"robot0/map": Pose2D(0, 0, 0), "robot1/map": Pose2D(3.0, 4.0, 1.0)}, 101.0
    )
    links = {
        "uwb": {"port_open": False, "frames_tx": 12, "radio_clock": {"role": "leads"}, "peers": ["robot1"]},
        "zenoh": {"session_open": True, "latency_ms": 2.5},
    }
    rec.diagnostics(link_diagnostics(links, "robot0"), 102.0)
    rec.close()
    msgs = read_all(tmp_path / "r.mcap")
    assert [(t, s) for t, s, _, _ in msgs] == [
        ("/map", "nav_msgs/msg/OccupancyGrid"),
        ("/robot1/map", "nav_msgs/msg/OccupancyGrid"),
        ("/tf_static", "tf2_msgs/msg/TFMessage"),
        ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray"),
    ]
    # the links' health as diagnostic_updater gives a driver's: a fault sets WARN, counters are pairs
    diag = msgs[3][3]
    assert (diag.header.stamp.sec, msgs[3][2]) == (102, 102_000_000_000)
    uwb, zen = diag.status
    assert (uwb.name, uwb.level, uwb.hardware_id) == ("mapd: uwb link", 1, "robot0")
    assert uwb.message == "serial port closed (reopening)"
    assert [(v.key, v.value) for v in uwb.values] == [
        ("frames_tx", "12"),
        ("peers", '["robot1"]'),
        ("port_open", "false"),
        ("radio_clock.role", "leads"),
    ]
    assert (zen.name, zen.level, zen.message) == ("mapd: zenoh link", 0, "ok")
    assert [(v.key, v.value) for v in zen.values] == [("latency_ms", "2.5"), ("session_open", "true")]
    msgs = msgs[:3]
    m = msgs[0][3]
    assert (m.header.frame_id, m.info.width, m.info.height) == ("map", 40, 30)
    assert m.info.resolution == pytest.approx(0.05) and m.info.origin.position.x == pytest.approx(1.5)
    assert np.array_equal(np.asarray(m.data, np.int8).reshape(30, 40), g.data)
    assert msgs[0][2] == 100_000_000_000 and (m.header.stamp.sec, m.header.stamp.nanosec) == (100, 0)
    tf = msgs[2][3].transforms
    assert [(t.header.frame_id, t.child_frame_id) for t in tf] == [
        ("map", "robot0/map"),
        ("map", "robot1/map"),
    ]
    assert tf[1].transform.translation.x == pytest.approx(3.0)
    assert tf[1].transform.rotation.z == pytest.approx(np.sin(0.5))
    assert summarize(tmp_path / "r.mcap").complete


def test_recordings_rotate_by_size_and_each_file_starts_with_the_transforms(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "fleet.mcap", max_bytes=256 << 10, chunk_bytes=64 << 10)
    rec.transforms("/tf_static", "map", {"robot0/map": Pose2D(0, 0, 0)}, 1.0)
    for i in range(12):
        rec.grid("/map", grid(400, 400, seed=i), "map", 2.0 + i)  # random cells: ~35 kB each, zstd or not
    rec.close()
    assert len(rec.files) >= 2 and rec.files[1].name == "fleet.1.mcap"
    for f in rec.files:
        assert f.stat().st_size < 512 << 10
        topics = [t for t, _, _, _ in read_all(f)]
        assert topics[0] == "/tf_static", f
    assert sum(summarize(f).topics["/map"].messages for f in rec.files) == 12


def test_a_cut_file_reads_up_to_its_last_chunk_and_garbage_is_one_line(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "c.mcap", chunk_bytes=32 << 10)
    for i in range(10):
        rec.grid("/map", grid(200, 200, seed=i), "map", 10.0 + i)
    # no close(): as after kill -9, the footer is missing; what the writer put out is on disk
    data = (tmp_path / "c.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) - 100])
    s = summarize(tmp_path / "cut.mcap")
    assert not s.complete and 1 <= s.topics["/map"].messages < 10
    (tmp_path / "junk.mcap").write_bytes(os.urandom(5000))
    out = subprocess.run([sys.executable, "-m", "mapd", "record", "info", str(tmp_path / "junk.mcap")],
                         capture_output=True, text=True, timeout=60)  # fmt: skip
    assert out.returncode != 0 and out.stderr.startswith("mapd: error:") and "Traceback" not in out.stderr


@pytest.mark.slow
def test_a_daemon_records_the_fleet_and_kill_9_leaves_a_readable_file(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    args = argparse.Namespace(
        robots=2, transport="zenoh", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0,
        record=tmp_path / "fleet.mcap",
    )  # fmt: skip
    f = Fleet(args)
    f.prepare()
    path = f.run_dir / "robot0" / "config.toml"
    cfg = tomllib.loads(path.read_text())
    cfg["record"]["stats_every_s"] = 1.0
    cfg["record"]["max_bytes"] = 1 << 20
    write_config(path, cfg)
    f.start()
    try:
        fk.wait_for(
            lambda s: (
                s.get("robot0", {}).get("fusion", {}).get("maps", 0) >= 2
                and s.get("robot0", {}).get("fusion", {}).get("merges", 0) >= 4
            ),
            120,
            f,
        )
        time.sleep(3.0)
        os.kill(f.procs["robot0"].pid, signal.SIGKILL)
        f.procs["robot0"].wait(10)
    finally:
        f.stop()

    def index(p: Path) -> int:  # fleet.mcap, fleet.1.mcap, fleet.2.mcap, ...: the killed one is last
        parts = p.name.split(".")
        return int(parts[1]) if len(parts) == 3 else 0

    files = sorted(tmp_path.glob("fleet*.mcap"), key=index)
    assert files
    topics: dict[str, list[int]] = {}
    decoded: dict[str, Any] = {}
    tf_msgs: list[Any] = []
    tf_children: set[str] = set()
    for fp in files:
        with open(fp, "rb") as fh:
            schemas, channels = {}, {}
            try:
                for record in StreamReader(fh).records:  # reads in order, so a file without a footer works
                    name = type(record).__name__
                    if name == "Schema":
                        schemas[record.id] = record
                    elif name == "Channel":
                        channels[record.id] = record
                    elif name == "Message":
                        ch = channels[record.channel_id]
                        topics.setdefault(ch.topic, []).append(record.log_time)
                        sch = schemas[ch.schema_id]
                        if sch.encoding == "ros2msg":
                            decoded[ch.topic] = DecoderFactory().decoder_for("cdr", sch)(record.data)
                            if ch.topic == "/tf":
                                tf_msgs.append((record.log_time, decoded[ch.topic]))
                        else:  # every channel is CDR: rosbag2 refuses a file with one that is not
                            raise AssertionError(
                                f"{ch.topic} is {ch.message_encoding}, schema {sch.encoding}"
                            )
            except EndOfFile:  # the killed file ends mid-chunk: everything before it was read
                assert fp == files[-1], f"{fp} was closed whole, yet ends early"
    assert {"/map", "/robot0/map", "/robot1/map", "/tf_static", "/tf", "/diagnostics"} <= set(topics), (
        topics.keys()
    )
    for topic, times in topics.items():
        assert times == sorted(times), topic  # timestamps never go back
    assert decoded["/map"].header.frame_id == "map" and decoded["/map"].info.width > 0
    assert decoded["/robot1/map"].header.frame_id == "robot1/map"
    assert {t.child_frame_id for t in decoded["/tf_static"].transforms} == {"robot0/map", "robot1/map"}
    # robot poses: <robot>/map -> <robot>/base_link, one robot a message, both robots seen
    lags = []
    for log_time, msg in tf_msgs:
        for t in msg.transforms:
            assert t.header.frame_id == t.child_frame_id.replace("/base_link", "/map")
            tf_children.add(t.child_frame_id)
            lags.append(log_time - (t.header.stamp.sec * 1_000_000_000 + t.header.stamp.nanosec))
    assert {"robot0/base_link", "robot1/base_link"} <= tf_children
    # stamped when the robot was there (as the ros2 output stamps /tf), logged when it was recorded
    assert min(lags) >= 0 and max(lags) > 0, lags[:10]
    (status,) = decoded["/diagnostics"].status
    assert (status.name, status.hardware_id) == ("mapd: zenoh link", "robot0")
    assert "peers" in {v.key for v in status.values}
    info = subprocess.run([sys.executable, "-m", "mapd", "record", "info", str(files[-1])],
                          capture_output=True, text=True, timeout=60)  # fmt: skip
    assert info.returncode == 0 and "messages" in info.stdout, info.stderr


def _tf_static_and_tf(path: Path) -> tuple[list[list[tuple[str, str, float]]], list[tuple[str, str]]]:
    """Each /tf_static message as (parent, child, x) in order, and every /tf transform as (parent, child)."""
    static, tf = [], []
    for topic, _, _, msg in read_all(path):
        if topic == "/tf_static":
            static.append(
                [(t.header.frame_id, t.child_frame_id, t.transform.translation.x) for t in msg.transforms]
            )
        elif topic == "/tf":
            tf += [(t.header.frame_id, t.child_frame_id) for t in msg.transforms]
    return static, tf


def _tf2_after_playback(static: list[list[tuple[str, str, float]]]) -> dict[str, str]:
    """What tf2's static buffer holds once a bag is played: the last static parent of each child."""
    return {child: parent for msg in static for parent, child, _ in msg}


def test_the_recording_moves_a_dropped_placement_off_the_tree_as_the_ros2_output_does(tmp_path: Path) -> None:
    # tf2 keeps a static transform for as long as it runs: a robot left out of the next /tf_static
    # stayed placed on playback. It must move under unplaced_frame, as on the ros2 output.
    rec = Recorder(tmp_path / "fleet.mcap", min_free_bytes=0)
    sinks = Sinks([], rec, CsvLog(tmp_path / "fused.csv"))
    g = grid(64, 64)
    both = {
        "robot0": Placement("robot0", Pose2D(), "anchor", True),
        "robot1": Placement("robot1", Pose2D(4.0, -1.0, 1.5), "pose", True),
    }
    sinks.global_map(g, both, {})
    sinks.global_map(g, {"robot0": both["robot0"]}, {})  # robot1 revoked: its placement is gone
    sinks.global_map(g, {"robot0": both["robot0"]}, {})  # nothing changed: not written again
    sinks.global_map(g, both, {})  # placed again
    sinks.close()
    static, _ = _tf_static_and_tf(tmp_path / "fleet.mcap")
    assert static == [
        [("map", "robot0/map", 0.0), ("map", "robot1/map", 4.0)],
        [("map", "robot0/map", 0.0), ("mapd/unplaced", "robot1/map", 0.0)],
        [("map", "robot0/map", 0.0), ("map", "robot1/map", 4.0)],
    ]
    assert _tf2_after_playback(static[:2]) == {"robot0/map": "map", "robot1/map": "mapd/unplaced"}


def test_the_recording_names_frames_as_the_ros2_output_does(tmp_path: Path) -> None:
    # A fleet that renamed robot_pose_frame so base_link keeps one parent got base_link back as a
    # second parent when the bag was played into the same graph.
    opts = Ros2OutputOptions(
        frame="fleet",
        robot_map_frame="{robot}/map_fleet",
        robot_pose_frame="{robot}/mapd_pose",
        unplaced_frame="fleet/gone",
    )
    out = Ros2Output(opts, OutputContext(robot="base", fleet="f"))  # never started: no session
    rec = Recorder(tmp_path / "fleet.mcap", min_free_bytes=0)
    sinks = Sinks([out], rec, CsvLog(tmp_path / "fused.csv"))
    g = grid(64, 64)
    both = {
        "robot0": Placement("robot0", Pose2D(), "anchor", True),
        "robot1": Placement("robot1", Pose2D(4.0, -1.0, 1.5), "pose", True),
    }
    sinks.robot_map(grid(20, 10, "robot1", 1))
    sinks.global_map(g, both, {})
    sinks.poses({"robot1": StampedPose(Pose2D(1.0, 2.0, 0.0), 100.0)}, {"robot1": Pose2D(4.0, -1.0, 1.5)})
    sinks.global_map(g, {"robot0": both["robot0"]}, {})
    sinks.close()
    frames = {t: m.header.frame_id for t, _, _, m in read_all(tmp_path / "fleet.mcap") if t.endswith("/map")}
    assert frames == {"/robot1/map": "robot1/map_fleet", "/map": "fleet"}
    static, tf = _tf_static_and_tf(tmp_path / "fleet.mcap")
    assert static == [
        [("fleet", "robot0/map_fleet", 0.0), ("fleet", "robot1/map_fleet", 4.0)],
        [("fleet", "robot0/map_fleet", 0.0), ("fleet/gone", "robot1/map_fleet", 0.0)],
    ]
    assert tf == [("robot1/map_fleet", "robot1/mapd_pose")]

    # robot_pose_frame = "": the output sends no poses on /tf, and neither does the recording
    quiet = Ros2Output(Ros2OutputOptions(robot_pose_frame=""), OutputContext(robot="base", fleet="f"))
    rec = Recorder(tmp_path / "quiet.mcap", min_free_bytes=0)
    sinks = Sinks([quiet], rec, CsvLog(tmp_path / "fused2.csv"))
    sinks.global_map(g, both, {})
    sinks.poses({"robot1": StampedPose(Pose2D(1.0, 2.0, 0.0), 100.0)}, {"robot1": Pose2D(4.0, -1.0, 1.5)})
    sinks.close()
    static, tf = _tf_static_and_tf(tmp_path / "quiet.mcap")
    assert static == [[("map", "robot0/map", 0.0), ("map", "robot1/map", 4.0)]] and tf == []


def test_the_recording_puts_the_global_map_on_the_ros2_outputs_topic(tmp_path: Path) -> None:
    # A robot-side layout publishes the fleet's map on fleet/map (its own SLAM map is /map): a bag
    # that recorded the global map on /map played a second map onto the robot's /map.
    for k, (opts, topic) in enumerate(
        [
            (Ros2OutputOptions(topic="fleet/map", frame="fleet"), "/fleet/map"),
            (Ros2OutputOptions(topic="fleet_map", namespace="/robot1", frame="fleet"), "/robot1/fleet_map"),
            # ros2dds: the namespace is the bridge's, on the zenoh side; in the ROS graph it is the topic
            (Ros2OutputOptions(topic="/fleet/map", namespace="robot1", format="ros2dds"), "/fleet/map"),
        ]
    ):
        out = Ros2Output(opts, OutputContext(robot="base", fleet="f"))  # never started: no session
        path = tmp_path / f"fleet{k}.mcap"
        sinks = Sinks([out], Recorder(path, min_free_bytes=0), CsvLog(tmp_path / "fused.csv"))
        sinks.robot_map(grid(20, 10, "robot1", 1))
        sinks.global_map(grid(64, 64), {"robot0": Placement("robot0", Pose2D(), "anchor", True)}, {})
        sinks.close()
        got = {t: m.header.frame_id for t, s, _, m in read_all(path) if s == "nav_msgs/msg/OccupancyGrid"}
        assert got == {topic: opts.frame, "/robot1/map": "robot1/map"}, opts
    # without a ros2 output: /map, as before
    sinks = Sinks([], Recorder(tmp_path / "plain.mcap", min_free_bytes=0), CsvLog(tmp_path / "fused.csv"))
    sinks.global_map(grid(64, 64), {"robot0": Placement("robot0", Pose2D(), "anchor", True)}, {})
    sinks.close()
    assert [t for t, s, _, _ in read_all(tmp_path / "plain.mcap") if s == "nav_msgs/msg/OccupancyGrid"] == [
        "/map"
    ]


def test_a_restarted_recording_moves_the_robots_the_run_before_placed_off_the_tree(tmp_path: Path) -> None:
    # tf2 keeps every static transform of a bag it played: robot1, placed in the files of the run
    # before, stayed placed after a restart that no longer placed it, unless the restarted
    # recording moves it under unplaced_frame as the restarted ros2 output does.
    g = grid(64, 64)
    both = {
        "robot0": Placement("robot0", Pose2D(), "anchor", True),
        "robot1": Placement("robot1", Pose2D(4.0, -1.0, 1.5), "pose", True),
    }
    sinks = Sinks([], Recorder(tmp_path / "fleet.mcap", min_free_bytes=0), CsvLog(tmp_path / "fused.csv"))
    sinks.global_map(g, both, {})
    sinks.close()
    # the restart: a new recorder on the same files (it goes on in fleet.1.mcap)
    sinks = Sinks([], Recorder(tmp_path / "fleet.mcap", min_free_bytes=0), CsvLog(tmp_path / "fused.csv"))
    sinks.global_map(g, {"robot0": both["robot0"]}, {})  # robot1 no longer placed
    sinks.close()
    static, _ = _tf_static_and_tf(tmp_path / "fleet.1.mcap")
    assert static == [[("map", "robot0/map", 0.0), ("mapd/unplaced", "robot1/map", 0.0)]]
    assert _tf2_after_playback(_tf_static_and_tf(tmp_path / "fleet.mcap")[0] + static) == {
        "robot0/map": "map",
        "robot1/map": "mapd/unplaced",
    }


def test_a_robot_whose_name_makes_no_ros_topic_is_said_once_and_its_map_left_out(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Robot names may hold '-' or begin with a digit, ROS 2 topic names not: a channel /2-bot/map
    # made ros2 bag play fail creating its publisher. Left out, as the live ros2 output leaves it.
    rec = Recorder(tmp_path / "fleet.mcap", min_free_bytes=0)
    sinks = Sinks([], rec, CsvLog(tmp_path / "fused.csv"))
    caplog.set_level(logging.WARNING, logger="mapd.daemon")
    for k in range(3):
        sinks.robot_map(grid(20, 10, "2-bot", k + 1))
        sinks.robot_map(grid(20, 10, "robot1", k + 1))
    sinks.close()
    topics = [t for t, _, _, _ in read_all(tmp_path / "fleet.mcap")]
    assert topics == ["/robot1/map"] * 3
    said = [r.getMessage() for r in caplog.records if "2-bot" in r.getMessage()]
    assert len(said) == 1 and "not a ROS 2 topic name" in said[0] and "not recorded" in said[0], said
