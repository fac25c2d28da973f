"""MCAP recordings of a running fleet, readable by Foxglove and ``ros2 bag`` (ROS 2 CDR, schemas inside).

Channels, named as the ``ros2`` output names its topics and frames when the daemon runs one (its
``topic``, with its namespace; ``frame``, ``robot_map_frame``, ``robot_pose_frame`` and
``unplaced_frame``), so that a bag plays into the same graph; else (REP-105) ``/map``, ``map``,
``<robot>/map``, ``<robot>/base_link`` and ``mapd/unplaced``:

* ``/map`` (the output's topic): the global map, ``nav_msgs/msg/OccupancyGrid`` in the fleet
  frame, on every merge;
* ``/<robot>/map``: each robot's map as this daemon holds it (received, or its own); on the
  output's ``robot_map_topic`` when it sets one;
* ``/tf_static``: ``tf2_msgs/msg/TFMessage``, fleet frame -> ``<robot>/map`` for every placed
  robot, written again whenever a placement changes, and ``unplaced_frame`` -> ``<robot>/map`` for
  every robot the recording placed before that is no longer placed. Which robots it placed is kept
  beside the files (``NAME.placed.json``, :data:`PLACED_SUFFIX`), so a restarted daemon moves the
  ones the run before placed off the tree too, as the ``ros2`` output does with its own list;
* ``/tf``: ``<robot>/map`` -> ``<robot>/base_link`` whenever a robot's pose changes;
* ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray``, one status per link (its faults, and
  its counters as key/values: :mod:`mapd.ros2.diagnostics`), every ``stats_every_s``. Every channel
  is CDR: rosbag2's reader refuses a file with one channel in another encoding (the counters were
  JSON on ``/mapd/links`` before, and ``ros2 bag play`` refused every recording).

Every message is stamped with the wall clock (log time and publish time, nanoseconds). The file is
written in chunks (``chunk_bytes``), each handed to the OS as it is made, so a daemon killed
with ``kill -9`` leaves a file readable up to its last chunk; a clean stop writes the summary and
footer.

Files: past ``max_bytes`` the recording rotates: ``fleet.mcap``, ``fleet.1.mcap``, ... A file that
exists is never written over: a restarted daemon goes on after the highest number there, so the
numbers sort the files by time even after the oldest were removed. As each new file opens, the
oldest files of the recording are removed until the others and a new file of ``max_bytes`` fit in
``max_total_bytes``. While the filesystem has less than ``min_free_bytes`` free, messages are
refused (:class:`~mapd.errors.StateError`), so a recording never takes the last space the daemon's
own state needs; it records again by itself once there is room.

A write that fails (a full disk) takes the file back to its last whole chunk, closes it without a
summary and goes on in a new file, so a streaming reader reads every file to its end; the
messages of the chunk that failed are lost with it.

Blocking (file writes, CDR encoding): the daemon calls it from its file thread, never the loop.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any, cast

import yaml

from mapd.errors import ConfigError, StateError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.record.files import RawFile, RecordingFiles
from mapd.ros2.diagnostics import DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE, Diagnostic, encode_diagnostics
from mapd.ros2.tf import TF_TYPE, load_shown, save_shown

log = logging.getLogger("mapd.record")

GRID_TYPE = "nav_msgs/msg/OccupancyGrid"
#: Defaults of ``[record]`` (the config's RecordSection has the same).
DEFAULT_MAX_BYTES = 256 << 20
DEFAULT_MAX_TOTAL_BYTES = 2 << 30
DEFAULT_MIN_FREE_BYTES = 256 << 20
#: Beside ``NAME.mcap``: ``NAME.placed.json``, the robots the recording placed under the fleet frame.
PLACED_SUFFIX = ".placed.json"


def _ns(wall: float) -> int:
    # From the header stamp's own (sec, nanosec) split: ``round(wall * 1e9)`` rounds the float
    # product, which for today's epoch is off by up to ~128 ns from the stamp inside the message.
    from mapd.ros2.cdr import split_stamp

    sec, nanosec = split_stamp(wall)
    return sec * 1_000_000_000 + nanosec


# rosbag2's encoding of RMW_DURATION_INFINITE (``rosbag2_storage/qos.cpp``).
_INFINITE = {"sec": 9223372036, "nsec": 854775807}


def offered_qos_profiles(topic: str) -> str:
    """The ``offered_qos_profiles`` channel metadata the MCAP ``ros2`` profile requires, as rosbag2
    writes it (one profile, rmw/types.h enum values, which every rosbag2 since Humble reads), for the
    QoS ``topic`` is published with: maps and ``/tf_static`` reliable, transient local, keep last 1
    (so ``ros2 bag play`` latches them again), as the ``ros2`` output publishes them; ``/tf``
    reliable, volatile, keep last 100; ``/diagnostics`` reliable, volatile, keep last 1.
    """
    from mapd.ros2 import rmw
    from mapd.ros2.diagnostics import DIAGNOSTICS_TOPIC

    qos = {"/tf": rmw.TF_QOS, DIAGNOSTICS_TOPIC: rmw.DIAGNOSTICS_QOS}.get(topic, rmw.LATCHED)
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
    """Writes one fleet's maps, transforms and link counters to MCAP files, rotating by size and
    keeping the recording's files within ``max_total_bytes`` (see the module's docstring)."""

    def __init__(
        self,
        path: Path,
        *,
        max_bytes: int = DEFAULT_MAX_BYTES,
        chunk_bytes: int = 256 << 10,
        max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
        min_free_bytes: int = DEFAULT_MIN_FREE_BYTES,
    ) -> None:
        try:
            from mcap.writer import CompressionType, Writer  # noqa: F401 - checked here, used below
            from rosbags.typesys import Stores, get_typestore
        except ModuleNotFoundError as exc:
            raise ConfigError(f"record: needs {exc.name} (pip install 'mapd[record]')") from None
        self.path = path
        self.chunk_bytes = chunk_bytes
        #: Which files, and how much disk they may take (the limits: ``disk.max_bytes``, ...).
        self.disk = RecordingFiles(
            path, max_bytes=max_bytes, max_total_bytes=max_total_bytes, min_free_bytes=min_free_bytes
        )
        self._ts = get_typestore(Stores.ROS2_HUMBLE)
        self._lock = threading.Lock()
        self._file: RawFile | None = None
        self._writer: Any = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._index: int | None = None  # the number of the file to open next (found at the first open)
        self._data_start = 0  # where the open file's first chunk goes (after its header)
        self.messages = 0
        self._last_tf: tuple[bytes, float] | None = None
        self._tf_owed = False  # the open file lacks the latest /tf_static (new, or it was refused)
        #: The robots this recording placed under the fleet frame in the files of a run before this
        #: one (a small file, read once at start).
        self.placed_before: set[str] = load_shown(self.placed_path, "record")

    # ------------------------------------------------------------------ properties
    @property
    def files(self) -> list[Path]:
        """This recorder's files still on disk, oldest first."""
        return self.disk.files

    @property
    def removed(self) -> int:
        """Files of the recording removed to stay within ``max_total_bytes``."""
        return self.disk.removed

    @property
    def placed_path(self) -> Path:
        """Where the robots the recording placed are kept (``NAME.placed.json``, never a file of the
        recording's own: those end in ``.N.mcap``)."""
        return self.path.with_name(self.path.stem + PLACED_SUFFIX)

    # ------------------------------------------------------------------ files
    def _open(self) -> None:
        """Start the next file: make room for it, then create it with its header (and /tf_static)."""
        from mcap.writer import CompressionType, Writer

        self._index, path, fd = self.disk.open_next(self._index)
        file = RawFile(fd)
        # (cast: the Writer is typed for any IO but uses only write and tell, which RawFile has)
        writer = Writer(cast(IO[bytes], file), chunk_size=self.chunk_bytes, compression=CompressionType.ZSTD)
        try:
            writer.start(profile="ros2", library="mapd")
        except OSError as exc:
            # Not even the header fits (a full disk): no file is left behind, and the number is
            # used again at the next try, so a long outage does not leave a trail of empty files.
            file.close()
            path.unlink(missing_ok=True)
            self.disk.forget(path)
            raise StateError(f"record: cannot write {path}: {exc.strerror}") from None
        self._file, self._writer = file, writer
        self._data_start = file.tell()
        self._channels.clear()
        self._schemas.clear()
        # /tf_static is latched: every file starts with the transforms (written with its first
        # message, where a failure is handled as any write's)
        self._tf_owed = self._last_tf is not None

    def _put_tf(self) -> None:
        """The latest /tf_static, into the open file."""
        assert self._last_tf is not None and self._writer is not None
        data, wall = self._last_tf
        ch = self._ros2_channel("/tf_static", TF_TYPE)
        self._writer.add_message(channel_id=ch, log_time=_ns(wall), publish_time=_ns(wall), data=data)
        self._tf_owed = False

    def _abandon(self, mark: int) -> None:
        """After a failed write: cut the file back to ``mark`` (where its last whole chunk ends),
        close it without a summary, which would not fit either, and move on to the next file.

        Best effort: a file that cannot be cut (rare: shrinking needs no space) keeps the partial
        chunk, which a streaming reader stops at. A file that holds no chunk yet is removed instead.
        """
        assert self._file is not None and self._index is not None
        path = self.disk.path_of(self._index)
        empty = mark <= self._data_start
        try:
            if empty:
                path.unlink(missing_ok=True)
            else:
                self._file.truncate(mark)
        except OSError as exc:
            log.warning("record: cannot cut %s back to its last chunk: %s", path, exc.strerror)
        self._file.close()
        self._file = None
        self._writer = None
        if empty:
            self.disk.forget(path)
        else:
            self._index += 1

    def _guarded(self, step: Callable[[], None]) -> None:
        """``step`` on the open file; on an OSError the file is taken back to where it was."""
        assert self._file is not None
        mark = self._file.tell()
        path = self.disk.path_of(self._index or 0)
        try:
            step()
        except OSError as exc:
            self._abandon(mark)
            raise StateError(
                f"record: cannot write {path}: {exc.strerror or exc}; the file was cut back to its last "
                "whole chunk (the next message starts a new file)"
            ) from None

    def _finish(self) -> None:
        """Summary and footer, then close (the file stays as it was if they do not fit)."""
        if self._writer is not None:
            self._guarded(self._writer.finish)
        if self._file is not None:
            self._file.close()
        self._file = None
        self._writer = None

    def close(self) -> None:
        """Write the summary and footer (a clean stop). StateError when they cannot be written (the
        file then ends at its last whole chunk, without them)."""
        with self._lock:
            self._finish()

    def _channel(
        self,
        topic: str,
        schema: str,
        encoding: str,
        schema_data: bytes,
        schema_encoding: str,
        metadata: dict[str, str] | None = None,
    ) -> int:
        writer = self._writer
        assert writer is not None
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
        qos = {"offered_qos_profiles": offered_qos_profiles(topic)}
        return self._channel(topic, msgtype, "cdr", msgdef.encode(), "ros2msg", qos)

    def _write(self, topic: str, channel: Callable[[], int], data: bytes, wall: float) -> None:
        """One message on the channel ``channel()`` registers (called with the lock held)."""
        if self._writer is None:
            self._open()  # makes room first, then checks the free space
        else:
            try:
                self.disk.check_space()
            except StateError:
                if topic == "/tf_static":  # refused: written first once there is room
                    self._tf_owed = True
                raise
        t = _ns(wall)

        def step() -> None:
            # Registering a schema or a channel may write out a full chunk, as adding a message
            # may: all of it is guarded. A /tf_static message is the latest transforms itself.
            if self._tf_owed and topic != "/tf_static":
                self._put_tf()
            self._writer.add_message(channel_id=channel(), log_time=t, publish_time=t, data=data)

        self._guarded(step)
        if topic == "/tf_static":
            self._tf_owed = False
        self.messages += 1
        assert self._file is not None
        if self._file.tell() >= self.disk.max_bytes:
            self._finish()
            assert self._index is not None
            self._index += 1

    # ------------------------------------------------------------------ messages
    def grid(self, topic: str, grid: OccupancyGrid, frame_id: str, wall: float) -> None:
        """An OccupancyGrid on ``topic``, stamped ``wall`` (seconds)."""
        from mapd.ros2.cdr import encode

        data = encode(grid, frame_id=frame_id, stamp=wall)
        with self._lock:
            self._write(topic, lambda: self._ros2_channel(topic, GRID_TYPE), data, wall)

    def transforms(
        self, topic: str, parent: str, children: dict[str, Pose2D], wall: float, stamp: float | None = None
    ) -> None:
        """A TFMessage: ``parent`` -> each child frame at its pose (x, y in m, yaw in rad), logged at
        ``wall``; its header stamp is ``stamp`` (when the pose held, as the ``ros2`` output stamps
        it), or ``wall``."""
        self.transform_list(
            topic, [(parent, child, pose) for child, pose in sorted(children.items())], wall, stamp
        )

    def transform_list(
        self, topic: str, transforms: list[tuple[str, str, Pose2D]], wall: float, stamp: float | None = None
    ) -> None:
        """A TFMessage of (parent, child, pose) in the order given, as :meth:`transforms` writes it:
        one message with several parents (``/tf_static``: the placed robots under the fleet frame
        and the ones no longer placed under another, so that every file starts with both)."""
        from mapd.ros2.cdr import split_stamp

        t = self._ts.types
        sec, nanosec = split_stamp(wall if stamp is None else stamp)
        header_stamp = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
        items = []
        for parent, child, pose in transforms:
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
            self._write(topic, lambda: self._ros2_channel(topic, TF_TYPE), data, wall)

    def tf_static(
        self, transforms: list[tuple[str, str, Pose2D]], wall: float, placed: list[str] | None = None
    ) -> None:
        """The latest ``/tf_static`` (:meth:`transform_list`). ``placed``, when the robots the
        recording placed under the fleet frame grew: all of them, kept first (a crash after the
        message must not forget one) for the next run's :attr:`placed_before`."""
        if placed is not None:
            save_shown(self.placed_path, placed, "record")
        self.transform_list("/tf_static", transforms, wall)

    def diagnostics(self, statuses: list[Diagnostic], wall: float) -> None:
        """The links' health on ``/diagnostics`` (:mod:`mapd.ros2.diagnostics`), stamped ``wall``."""
        data = encode_diagnostics(statuses, wall)
        with self._lock:
            self._write(
                DIAGNOSTICS_TOPIC, lambda: self._ros2_channel(DIAGNOSTICS_TOPIC, DIAGNOSTICS_TYPE), data, wall
            )
