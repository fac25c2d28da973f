"""ROS conventions checked on what mapd's outputs actually write, against independent references.

Each check is written from the convention, not from mapd's code: a known asymmetric grid (one
occupied cell at the origin corner, one unknown cell at the far corner) goes through an output, and
the result is read back with a reader that knows only the convention (Pillow for the PGM, rosbags'
deserializer for the CDR bytes, the official ``mcap`` / ``mcap_ros2`` readers for recordings),
then the cell must be where the convention puts it (the live view's is checked in a real browser,
``tests/view/test_browser.py``). The MCAP profile rules are the MCAP format registry's (``ros2`` profile); the QoS YAML is
rosbag2's (``rosbag2_storage/qos.cpp``).
"""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from mapd.daemon.sinks import link_diagnostics
from mapd.grid import OccupancyGrid, Pose2D
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.files import FilesOptions, FilesOutput

ORIGIN = Pose2D(1.0, 2.0, 0.3)


def corner_grid() -> OccupancyGrid:
    """3 x 4 cells: occupied at cell (row 0, col 0), the origin corner; unknown at the far corner."""
    d = np.zeros((3, 4), dtype=np.int8)
    d[0, 0] = 100
    d[2, 3] = -1
    return OccupancyGrid(d, 0.05, ORIGIN, robot="r1")


def test_files_output_writes_map_server_layout(tmp_path: Path) -> None:
    from PIL import Image

    out = FilesOutput(FilesOptions(dir=tmp_path), OutputContext("base", "lab"))
    asyncio.run(out.start())
    out.publish(GlobalUpdate(corner_grid(), {"r1": Pose2D(1.0, 2.0, 0.5)}, 1.7e9))
    meta = yaml.safe_load((tmp_path / "map.yaml").read_text())
    assert meta["origin"] == [1.0, 2.0, 0.3] and meta["resolution"] == 0.05
    assert meta["negate"] == 0 and meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196
    img = np.asarray(Image.open(tmp_path / meta["image"]))
    # map_saver: image row 0 is the top (highest y), so the origin cell is the bottom-left pixel
    assert img.shape == (3, 4)
    assert img[2, 0] == 0 and img[0, 3] == 205
    assert int((img == 254).sum()) == 10
    doc = json.loads((tmp_path / "transforms.json").read_text())
    assert doc["frame_id"] == "map" and doc["robots"]["r1"]["child_frame_id"] == "r1/map"


def test_files_output_names_robot_frames_as_the_ros2_output_is_told_to(tmp_path: Path) -> None:
    # transforms.json said "<robot>/map" whatever frames the fleet uses on its TF tree.
    opts = FilesOptions(dir=tmp_path, frame_id="fleet", robot_map_frame="{robot}/map_fleet")
    out = FilesOutput(opts, OutputContext("base", "lab"))
    asyncio.run(out.start())
    out.publish(GlobalUpdate(corner_grid(), {"r1": Pose2D(1.0, 2.0, 0.5)}, 1.7e9))
    doc = json.loads((tmp_path / "transforms.json").read_text())
    assert doc["frame_id"] == "fleet" and doc["robots"]["r1"]["child_frame_id"] == "r1/map_fleet"
    for bad in ("map", "/{robot}/map"):  # one frame for every robot; a leading '/' tf2 refuses
        with pytest.raises(ValueError):
            FilesOptions(dir=tmp_path, robot_map_frame=bad)


def test_ros2_cdr_is_an_occupancy_grid_with_data0_at_the_origin() -> None:
    pytest.importorskip("rosbags")
    from rosbags.typesys import Stores, get_typestore

    from mapd.ros2 import cdr

    payload = cdr.encode(corner_grid(), frame_id="map", stamp=1_700_000_000.25)
    for store in (Stores.ROS2_HUMBLE, Stores.ROS2_JAZZY):
        msg: Any = get_typestore(store).deserialize_cdr(payload, "nav_msgs/msg/OccupancyGrid")
        assert msg.header.frame_id == "map"
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1_700_000_000, 250_000_000)
        assert (msg.info.width, msg.info.height) == (4, 3)
        assert msg.data[0] == 100 and msg.data[11] == -1  # row-major from the origin cell
        o = msg.info.origin
        assert (o.position.x, o.position.y) == (1.0, 2.0)
        # counter-clockwise yaw about +z: q = (0, 0, sin(yaw/2), cos(yaw/2))
        assert o.orientation.z == pytest.approx(math.sin(0.15)) and o.orientation.w > 0


# ------------------------------------------------------------------------------- recordings


def _record(path: Path) -> None:
    from mapd.record.writer import Recorder

    r = Recorder(path)
    r.grid("/map", corner_grid(), "map", 1_700_000_000.25)
    r.grid("/r1/map", corner_grid(), "r1/map", 1_700_000_000.3)
    r.transforms("/tf_static", "map", {"r1/map": Pose2D(1.0, 2.0, 0.5)}, 1_700_000_000.5)
    r.transforms("/tf", "r1/map", {"r1/base_link": Pose2D(3.0, 4.0, -0.5)}, 1_700_000_001.1)
    r.diagnostics(link_diagnostics({"uwb": {"port_open": True, "frames_tx": 3}}, "r1"), 1_700_000_001.2)
    r.close()


def test_recording_log_time_is_the_header_stamp_in_nanoseconds(tmp_path: Path) -> None:
    """The same wall-clock instant, written as the message's header stamp and as its log time,
    must be the same nanosecond (a float product ``wall * 1e9`` is off by up to ~128 ns)."""
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "r.mcap"
    _record(path)
    with open(path, "rb") as f:
        seen = 0
        for _, channel, message, msg in make_reader(
            f, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages():
            header = msg.transforms[0].header if channel.topic.startswith("/tf") else msg.header
            stamp_ns = header.stamp.sec * 1_000_000_000 + header.stamp.nanosec
            assert message.log_time == message.publish_time == stamp_ns, channel.topic
            seen += 1
    assert seen == 5


def test_recording_follows_the_mcap_ros2_profile(tmp_path: Path) -> None:
    """MCAP registry, profile ``ros2``: message_encoding ``cdr``, schema ``ros2msg``/``ros2idl``, and
    channel metadata ``offered_qos_profiles`` (required) in rosbag2's YAML, which ``ros2 bag play``
    uses to offer the recorded QoS again (a latched /map or /tf_static replayed as volatile would
    never reach an RViz that joins after the message was played)."""
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    path = tmp_path / "r.mcap"
    _record(path)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: c for c in summary.channels.values()}
        grids = {}
        for _, channel, _, msg in reader.iter_decoded_messages(topics=["/map", "/r1/map"]):
            grids[channel.topic] = msg
    assert set(channels) == {"/map", "/r1/map", "/tf_static", "/tf", "/diagnostics"}
    # rosbag2's reader (SequentialReader::check_topics_serialization_formats) refuses a file whose
    # topics differ in serialization format: the link counters were JSON, and no recording played
    assert {ch.message_encoding for ch in channels.values()} == {"cdr"}
    for topic, ch in channels.items():
        assert ch.message_encoding == "cdr"
        assert summary.schemas[ch.schema_id].encoding == "ros2msg"
        assert "offered_qos_profiles" in ch.metadata, topic
        profiles = yaml.safe_load(ch.metadata["offered_qos_profiles"])
        assert isinstance(profiles, list) and len(profiles) == 1, topic
        p = profiles[0]
        # rmw/types.h: reliability RELIABLE = 1; durability TRANSIENT_LOCAL = 1, VOLATILE = 2;
        # history KEEP_LAST = 1; liveliness AUTOMATIC = 1; infinite durations as RMW_DURATION_INFINITE
        latched = topic not in ("/tf", "/diagnostics")  # (diagnostic_updater: volatile, keep last 1)
        assert p["reliability"] == 1 and p["history"] == 1 and p["liveliness"] == 1, topic
        assert p["durability"] == (1 if latched else 2), topic
        assert p["depth"] == (100 if topic == "/tf" else 1), topic
        for key in ("deadline", "lifespan", "liveliness_lease_duration"):
            assert p[key] == {"sec": 9223372036, "nsec": 854775807}, (topic, key)
        assert p["avoid_ros_namespace_conventions"] is False
    assert grids["/map"].header.frame_id == "map" and grids["/r1/map"].header.frame_id == "r1/map"
    cells = [int(v) for v in grids["/map"].data]
    assert cells[0] == 100 and cells[11] == -1  # data[0] is the origin cell
