"""MCAP recordings of a running fleet, readable by Foxglove and ``ros2 bag`` (ROS 2 CDR, schemas inside).

Channels (REP-105 frame names: the fleet frame is ``map``, each robot's map frame ``<robot>/map``):

* ``/map``: the global map, ``nav_msgs/msg/OccupancyGrid`` in the fleet frame, on every merge;
* ``/<robot>/map``: each robot's map as this daemon holds it (received, or its own);
* ``/tf_static``: ``tf2_msgs/msg/TFMessage``, fleet frame -> ``<robot>/map`` for every placed
  robot, written again whenever a placement changes;
* ``/mapd/links``: the transports' counters (JSON with a JSON schema), every ``stats_every_s``.

Every message is stamped with the wall clock (log time and publish time, nanoseconds). The file is
written in chunks (``chunk_bytes``) and flushed to the OS after each one, so a daemon killed with
``kill -9`` leaves a file readable up to its last chunk; a clean stop writes the summary and
footer. Past ``max_bytes`` the recording rotates: ``fleet.mcap``, ``fleet.1.mcap``, ... A file that
exists is never written over: a restarted daemon records into the next free number.

Blocking (file writes, CDR encoding): the daemon calls it from its file thread, never the loop.
"""

from __future__ import annotations

import json
import math
import threading
from pathlib import Path
from typing import IO, Any

import yaml

from mapd.errors import ConfigError
from mapd.grid import OccupancyGrid, Pose2D

GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
TF_TYPE = "tf2_msgs/msg/TFMessage"
LINKS_SCHEMA = {
    "type": "object",
    "description": "mapd link counters by transport (see mapd status --json, links)",
    "additionalProperties": {"type": "object"},
}


def _ns(wall: float) -> int:
    # From the header stamp's own (sec, nanosec) split: ``round(wall * 1e9)`` rounds the float
    # product, which for today's epoch is off by up to ~128 ns from the stamp inside the message.
    from mapd.ros2.cdr import split_stamp

    sec, nanosec = split_stamp(wall)
    return sec * 1_000_000_000 + nanosec


# rosbag2's encoding of RMW_DURATION_INFINITE (``rosbag2_storage/qos.cpp``).
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def offered_qos_profiles(latched: bool) -> str:
    """The ``offered_qos_profiles`` channel metadata the MCAP ``ros2`` profile requires, as rosbag2
    writes it (one profile, rmw/types.h enum values, which every rosbag2 since Humble reads), for the
    QoS the ``ros2`` output publishes with: maps and ``/tf_static`` reliable, transient local, keep
    last 1 (so ``ros2 bag play`` latches them again); ``/tf`` reliable, volatile, keep last 100.
    """
    from mapd.ros2 import rmw

    qos = rmw.LATCHED if latched else rmw.TF_QOS
    profile = {
        "history": qos.history,
        "depth": qos.depth,
        "reliability": qos.reliability,
        "durability": qos.durability,
        # copies: one shared dict would be dumped as a YAML anchor and aliases
        "deadline": dict(_INFINITE),
        "lifespan": dict(_INFINITE),
        "liveliness": 1,  # RMW_QOS_POLICY_LIVELINESS_AUTOMATIC
        "liveliness_lease_duration": dict(_INFINITE),
        "avoid_ros_namespace_conventions": False,
    }
    return yaml.safe_dump([profile], sort_keys=False)


class Recorder:
    """Writes one fleet's maps, transforms and link counters to MCAP files, rotating by size."""

    def __init__(self, path: Path, *, max_bytes: int = 256 << 20, chunk_bytes: int = 256 << 10) -> None:
        try:
            from mcap.writer import CompressionType, Writer  # noqa: F401 - checked here, used below
            from rosbags.typesys import Stores, get_typestore
        except ModuleNotFoundError as exc:
            raise ConfigError(f"record: needs {exc.name} (pip install 'mapd[record]')") from None
        self.path = path
        self.max_bytes = max_bytes
        self.chunk_bytes = chunk_bytes
        self._ts = get_typestore(Stores.ROS2_HUMBLE)
        self._lock = threading.Lock()
        self._file: IO[bytes] | None = None
        self._writer: Any = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._index = 0
        self.files: list[Path] = []
        self.messages = 0
        self._last_tf: tuple[bytes, float] | None = None

    # ------------------------------------------------------------------ files
    def _current_path(self) -> Path:
        if self._index == 0:
            return self.path
        return self.path.with_name(f"{self.path.stem}.{self._index}{self.path.suffix}")

    def _open(self) -> Any:
        from mcap.writer import CompressionType, Writer

        path = self._current_path()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            while True:
                # "xb", never "wb": a daemon restarted after a crash (systemd, 2 s later) must not
                # truncate the recording of that crash; it goes on with the next free number.
                try:
                    self._file = open(path, "xb")  # noqa: SIM115 - closed in _close
                    break
                except FileExistsError:
                    self._index += 1
                    path = self._current_path()
        except OSError as exc:
            raise ConfigError(f"record: cannot write {path}: {exc.strerror}") from None
        self._writer = Writer(self._file, chunk_size=self.chunk_bytes, compression=CompressionType.ZSTD)
        self._writer.start(profile="ros2", library="mapd")
        self._channels.clear()
        self._schemas.clear()
        self.files.append(path)
        if self._last_tf is not None:  # /tf_static is latched: every file starts with the transforms
            data, wall = self._last_tf
            ch = self._ros2_channel("/tf_static", TF_TYPE)
            self._writer.add_message(channel_id=ch, log_time=_ns(wall), publish_time=_ns(wall), data=data)
        return self._writer

    def _close(self) -> None:
        if self._writer is not None:
            self._writer.finish()
            self._writer = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def close(self) -> None:
        """Write the summary and footer (a clean stop)."""
        with self._lock:
            self._close()

    def _channel(
        self,
        topic: str,
        schema: str,
        encoding: str,
        schema_data: bytes,
        schema_encoding: str,
        metadata: dict[str, str] | None = None,
    ) -> int:
        writer = self._writer if self._writer is not None else self._open()
        if schema not in self._schemas:
            self._schemas[schema] = writer.register_schema(
                name=schema, encoding=schema_encoding, data=schema_data
            )
        if topic not in self._channels:
            self._channels[topic] = writer.register_channel(
                topic=topic,
                message_encoding=encoding,
                schema_id=self._schemas[schema],
                metadata=metadata or {},
            )
        return self._channels[topic]

    def _ros2_channel(self, topic: str, msgtype: str) -> int:
        msgdef, _ = self._ts.generate_msgdef(msgtype, ros_version=2)
        qos = {"offered_qos_profiles": offered_qos_profiles(latched=topic != "/tf")}
        return self._channel(topic, msgtype, "cdr", msgdef.encode(), "ros2msg", qos)

    def _write(self, channel: int, data: bytes, wall: float) -> None:
        assert self._writer is not None and self._file is not None
        t = _ns(wall)
        self._writer.add_message(channel_id=channel, log_time=t, publish_time=t, data=data)
        self._file.flush()  # what the writer has put out survives kill -9 (the OS holds it)
        self.messages += 1
        if self._file.tell() >= self.max_bytes:
            self._close()
            self._index += 1

    # ------------------------------------------------------------------ messages
    def grid(self, topic: str, grid: OccupancyGrid, frame_id: str, wall: float) -> None:
        """An OccupancyGrid on ``topic``, stamped ``wall`` (seconds)."""
        from mapd.ros2.cdr import encode

        data = encode(grid, frame_id=frame_id, stamp=wall)
        with self._lock:
            self._write(self._ros2_channel(topic, GRID_TYPE), data, wall)

    def transforms(
        self, topic: str, parent: str, children: dict[str, Pose2D], wall: float, stamp: float | None = None
    ) -> None:
        """A TFMessage: ``parent`` -> each child frame at its pose (x, y in m, yaw in rad), logged at
        ``wall``; its header stamp is ``stamp`` (when the pose held, as the ``ros2`` output stamps
        it), or ``wall``."""
        from mapd.ros2.cdr import split_stamp

        t = self._ts.types
        sec, nanosec = split_stamp(wall if stamp is None else stamp)
        header_stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        items = []
        for child, pose in sorted(children.items()):
            items.append(
                t["geometry_msgs/msg/TransformStamped"](
                    header=t["std_msgs/msg/Header"](stamp=header_stamp, frame_id=parent),
                    child_frame_id=child,
                    transform=t["geometry_msgs/msg/Transform"](
                        translation=t["geometry_msgs/msg/Vector3"](x=pose.x, y=pose.y, z=0.0),
                        rotation=t["geometry_msgs/msg/Quaternion"](
                            x=0.0, y=0.0, z=math.sin(pose.yaw / 2), w=math.cos(pose.yaw / 2)
                        ),
                    ),
                )
            )
        data = bytes(self._ts.serialize_cdr(t[TF_TYPE](transforms=items), TF_TYPE))
        with self._lock:
            if topic == "/tf_static":
                self._last_tf = (data, wall)
            self._write(self._ros2_channel(topic, TF_TYPE), data, wall)

    def json(self, topic: str, doc: dict[str, Any], wall: float) -> None:
        """A JSON document (the link counters) on ``topic``."""
        data = json.dumps(doc, default=str, sort_keys=True).encode()
        with self._lock:
            ch = self._channel(topic, "mapd.links", "json", json.dumps(LINKS_SCHEMA).encode(), "jsonschema")
            self._write(ch, data, wall)
