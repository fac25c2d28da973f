"""ROS 2 ``nav_msgs/msg/OccupancyGrid`` over zenoh, with no ROS install: CDR, keys, sessions, a sink.

* :func:`encode` / :func:`decode` turn an :class:`~mapd.grid.OccupancyGrid` into a CDR payload and
  back with the ``rosbags`` type store (pure Python). :func:`decode` checks sizes against limits and
  raises one :class:`~mapd.errors.CodecError` for anything that does not parse.
* Key expressions for the two ways ROS 2 meets zenoh: ``rmw_zenoh``
  (``<domain>/<topic>/nav_msgs::msg::dds_::OccupancyGrid_/<type hash>``; subscribe with ``*`` for
  the hash) and ``zenoh-bridge-ros2dds`` (the topic without its leading slash, under an optional
  namespace).
* :func:`open_session` builds a zenoh session from plain options (timestamping on, which the
  advanced publisher's cache needs).
* :class:`Ros2Sink` publishes a grid as CDR the way an ``rmw_zenoh`` transient-local publisher does
  (an advanced publisher with a one-sample cache and publisher detection, the rmw attachment, and
  liveliness tokens so ``ros2 topic list`` sees it), so RViz or Nav2 can take mapd's global map.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import os
import struct
import time
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mapd.errors import CodecError, LimitError, TransportError
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D

MSGTYPE = "nav_msgs/msg/OccupancyGrid"
DDS_TYPE = "nav_msgs::msg::dds_::OccupancyGrid_"
KeyFormat = Literal["rmw_zenoh", "ros2dds"]
#: CDR bytes beyond the cells: header, frame id, metadata (a generous bound for the size check).
_OVERHEAD = 64 * 1024


@lru_cache(maxsize=1)
def _typestore() -> Any:
    try:
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError:
        raise CodecError("ROS 2 CDR needs rosbags (pip install 'mapd[ros2]')") from None
    return get_typestore(Stores.ROS2_JAZZY)


@lru_cache(maxsize=1)
def type_hash() -> str:
    """The RIHS01 type hash of ``nav_msgs/msg/OccupancyGrid``, as rmw_zenoh puts it in keys."""
    return str(_typestore().hash_rihs01(MSGTYPE))


# ------------------------------------------------------------------------------------------------
# CDR
# ------------------------------------------------------------------------------------------------


def split_stamp(wall: float) -> tuple[int, int]:
    """``builtin_interfaces/Time``'s (sec, nanosec) of wall-clock seconds."""
    sec = math.floor(wall)
    return int(sec), min(round((wall - sec) * 1e9), 999_999_999)


def encode(grid: OccupancyGrid, *, frame_id: str | None = None, stamp: float | None = None) -> bytes:
    """A CDR-serialised (little-endian, with encapsulation header) ``nav_msgs/msg/OccupancyGrid``."""
    ts = _typestore()
    t = ts.types
    sec, nanosec = split_stamp(grid.stamp if stamp is None else stamp)
    stamp_msg = t["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    yaw = grid.origin.yaw
    pose = t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=grid.origin.x, y=grid.origin.y, z=0.0),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2)),
    )
    info = t["nav_msgs/msg/MapMetaData"](
        map_load_time=stamp_msg,
        resolution=float(grid.resolution),
        width=grid.width,
        height=grid.height,
        origin=pose,
    )
    header = t["std_msgs/msg/Header"](
        stamp=stamp_msg, frame_id=frame_id if frame_id is not None else grid.frame_id
    )
    msg = t[MSGTYPE](header=header, info=info, data=np.ascontiguousarray(grid.data, dtype=np.int8).ravel())
    return bytes(ts.serialize_cdr(msg, MSGTYPE))


def decode(
    payload: bytes, *, max_cells: int = DEFAULT_MAX_CELLS, where: str = "CDR payload"
) -> OccupancyGrid:
    """An :class:`OccupancyGrid` from CDR bytes; ``where`` (say, the topic) starts every error line.

    Raises :class:`CodecError` for bytes that do not parse or describe no valid grid, and
    :class:`LimitError` for a grid over ``max_cells`` (checked before anything is allocated for it).
    """
    if len(payload) > max_cells + _OVERHEAD:
        raise LimitError(f"{where}: {len(payload)} bytes is more than a grid of {max_cells} cells needs")
    if len(payload) < 4 or payload[:2] not in (b"\x00\x01", b"\x00\x00"):
        raise CodecError(f"{where}: not a CDR payload (bad encapsulation header)")
    try:
        msg = _typestore().deserialize_cdr(bytes(payload), MSGTYPE)
    except CodecError:
        raise
    except Exception as exc:  # rosbags raises many kinds (struct.error, IndexError, ...) on bad bytes
        raise CodecError(f"{where}: CDR does not parse as {MSGTYPE}: {type(exc).__name__}") from None
    info = msg.info
    w, h = int(info.width), int(info.height)
    if w * h > max_cells:
        raise LimitError(f"{where}: {w} x {h} grid is over the limit of {max_cells} cells")
    if w < 1 or h < 1:
        raise CodecError(f"{where}: empty grid ({w} x {h})")
    data = np.asarray(msg.data)
    if data.size != w * h:
        raise CodecError(f"{where}: {data.size} cells for a {w} x {h} grid")
    # ROS keeps the resolution as float32: take the shortest decimal that float32 maps to it (0.05).
    res = float(str(np.float32(info.resolution)))
    p, q = info.origin.position, info.origin.orientation
    nums = (res, p.x, p.y, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in nums) or res <= 0:
        raise CodecError(f"{where}: resolution or origin is not a finite number (resolution {res})")
    norm = math.sqrt(q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w)
    yaw = 0.0 if norm == 0 else math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    stamp = float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) * 1e-9
    return OccupancyGrid(
        data=np.ascontiguousarray(data.astype(np.int8, copy=False).reshape(h, w)),
        resolution=res,
        origin=Pose2D(float(p.x), float(p.y), yaw),
        frame_id=str(msg.header.frame_id) or "map",
        stamp=stamp,
    )


# ------------------------------------------------------------------------------------------------
# Keys
# ------------------------------------------------------------------------------------------------


def _check_topic(topic: str) -> str:
    name = topic.strip("/")
    if not name or any(not part for part in name.split("/")) or any(c in name for c in "*$?#"):
        raise ValueError(f"not a ROS 2 topic name: {topic!r}")
    return name


def rmw_zenoh_key(topic: str, *, domain: int = 0, hash_: str | None = None) -> str:
    """rmw_zenoh's key for an OccupancyGrid topic; ``hash_='*'`` gives the subscription wildcard."""
    return f"{domain}/{_check_topic(topic)}/{DDS_TYPE}/{hash_ if hash_ is not None else type_hash()}"


def ros2dds_key(topic: str, *, namespace: str = "") -> str:
    """zenoh-bridge-ros2dds's key: the topic without its leading slash, under ``namespace`` if given."""
    ns = namespace.strip("/")
    name = _check_topic(topic)
    return f"{_check_topic(ns)}/{name}" if ns else name


def key_for(
    topic: str, key_format: KeyFormat, *, domain: int = 0, namespace: str = "", subscribe: bool = False
) -> str:
    """The key to publish on (or, with ``subscribe``, to subscribe to) for a topic in either format."""
    if key_format == "rmw_zenoh":
        return rmw_zenoh_key(topic, domain=domain, hash_="*" if subscribe else None)
    return ros2dds_key(topic, namespace=namespace)


def _mangle(name: str) -> str:
    # rmw_zenoh replaces '/' by '%' in liveliness keys, and writes an empty name as '%'.
    return name.replace("/", "%") or "%"


def rmw_attachment(sequence: int, gid: bytes, now_ns: int | None = None) -> bytes:
    """The attachment rmw_zenoh puts on each sample: sequence, source time (ns), 16-byte publisher GID,
    in zenoh's serialization format (little-endian int64s, then a LEB128 length and the bytes)."""
    if len(gid) != 16:
        raise ValueError("an rmw GID has 16 bytes")
    stamp = time.time_ns() if now_ns is None else now_ns
    return struct.pack("<qq", sequence, stamp) + b"\x10" + gid


# ------------------------------------------------------------------------------------------------
# Sessions
# ------------------------------------------------------------------------------------------------


def session_config(
    *,
    mode: Literal["peer", "client"] = "peer",
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    multicast_scouting: bool = False,
    config_file: Path | None = None,
) -> Any:
    """A ``zenoh.Config``: the file's (if any), with mode, endpoints and scouting set over it."""
    try:
        import zenoh
    except ModuleNotFoundError:
        raise TransportError("ros2 over zenoh needs eclipse-zenoh, which is not installed") from None
    try:
        cfg = zenoh.Config.from_file(str(config_file)) if config_file is not None else zenoh.Config()
    except Exception as exc:  # zenoh.ZError for a missing or malformed file
        raise TransportError(f"{config_file}: cannot use zenoh config: {exc}") from None
    settings: dict[str, Any] = {
        "mode": mode,
        "scouting/multicast/enabled": multicast_scouting,
        # The advanced publisher's cache orders samples by timestamp, so sessions must stamp them.
        "timestamping/enabled": {"router": True, "peer": True, "client": True},
    }
    if connect:
        settings["connect/endpoints"] = list(connect)
    if listen:
        settings["listen/endpoints"] = list(listen)
    for key, value in settings.items():
        try:
            cfg.insert_json5(key, json.dumps(value))
        except Exception as exc:  # zenoh.ZError: a malformed endpoint
            raise TransportError(f"zenoh config {key} = {value!r}: {exc}") from None
    return cfg


def open_session(**options: Any) -> Any:
    """Open a zenoh session from :func:`session_config` options; TransportError when it cannot."""
    import zenoh

    cfg = session_config(**options)
    try:
        return zenoh.open(cfg)
    except Exception as exc:  # zenoh.ZError: refused endpoint, address in use
        raise TransportError(f"cannot open zenoh session: {exc}") from None


# ------------------------------------------------------------------------------------------------
# The sink
# ------------------------------------------------------------------------------------------------

_entity_ids = itertools.count(1)


class Ros2Sink:
    """Publishes grids as ``nav_msgs/msg/OccupancyGrid`` CDR on a zenoh session, like a ROS 2 /map.

    With ``key_format="rmw_zenoh"`` it behaves as a transient-local, reliable, depth-1 rmw_zenoh
    publisher: late subscribers that ask for history (RViz, Nav2 with map QoS) get the current
    map; liveliness tokens announce a node ``node`` and its publisher to the ROS graph. With
    ``"ros2dds"`` it publishes where ``zenoh-bridge-ros2dds`` routes the topic into DDS.
    The session stays the caller's: :meth:`close` undeclares only what the sink declared.
    """

    def __init__(
        self,
        session: Any,
        topic: str = "/map",
        *,
        key_format: KeyFormat = "rmw_zenoh",
        domain: int = 0,
        namespace: str = "",
        node: str = "mapd",
        frame_id: str = "map",
    ) -> None:
        import zenoh.ext as zext

        self.session = session
        self.topic = "/" + _check_topic(topic)
        self.key_format = key_format
        self.frame_id = frame_id
        self.key = key_for(topic, key_format, domain=domain, namespace=namespace)
        self._seq = 0
        self._tokens: list[Any] = []
        self.gid = os.urandom(16)
        try:
            self._pub = zext.declare_advanced_publisher(
                session, self.key, cache=zext.CacheConfig(max_samples=1), publisher_detection=True
            )
            if key_format == "rmw_zenoh":
                zid = str(session.zid())
                nid, eid = next(_entity_ids), next(_entity_ids)
                node_ke = f"@ros2_lv/{domain}/{zid}/{nid}/{nid}/NN/%/{_mangle(namespace)}/{_mangle(node)}"
                # QoS: reliable (1), transient local (1), keep last (1) with depth 1; rest default.
                pub_ke = (
                    f"@ros2_lv/{domain}/{zid}/{nid}/{eid}/MP/%/{_mangle(namespace)}/{_mangle(node)}/"
                    f"{_mangle(self.topic)}/{DDS_TYPE}/{type_hash()}/1:1:1,1:,:,:,,"
                )
                liveliness = session.liveliness()
                self._tokens = [liveliness.declare_token(node_ke), liveliness.declare_token(pub_ke)]
        except Exception as exc:  # zenoh.ZError
            raise TransportError(f"cannot publish {self.topic} on zenoh key '{self.key}': {exc}") from None

    def publish(self, grid: OccupancyGrid, *, stamp: float | None = None) -> int:
        """Publish one grid; returns the payload size in bytes."""
        payload = encode(grid, frame_id=self.frame_id, stamp=stamp)
        self._seq += 1
        attachment = rmw_attachment(self._seq, self.gid) if self.key_format == "rmw_zenoh" else None
        try:
            self._pub.put(payload, attachment=attachment)
        except Exception as exc:  # zenoh.ZError: session closed
            raise TransportError(f"cannot publish {self.topic}: {exc}") from None
        return len(payload)

    def close(self) -> None:
        """Undeclare the publisher and tokens (the session is left open)."""
        for tok in self._tokens:
            # Already gone when the session was closed first.
            with contextlib.suppress(Exception):
                tok.undeclare()
        self._tokens = []
        with contextlib.suppress(Exception):
            self._pub.undeclare()
