"""ROS 2 messages over zenoh with no ROS install: CDR, key helpers, sessions.

* :func:`encode` / :func:`decode` turn an :class:`~mapd.grid.OccupancyGrid` into a CDR
  ``nav_msgs/msg/OccupancyGrid`` payload and back with the ``rosbags`` type store (pure Python).
  :func:`decode` checks sizes against limits and raises one :class:`~mapd.errors.CodecError` for
  anything that does not parse. :func:`encode_tf` makes a ``tf2_msgs/msg/TFMessage``.
* Key helpers for the two ways ROS 2 meets zenoh (the rules themselves, tokens and GIDs included,
  are in :mod:`mapd.ros2.rmw`).
* :func:`open_session` builds a zenoh session from plain options (timestamping on, which the
  advanced publisher's cache needs). Publishing as an rmw_zenoh node is :mod:`mapd.ros2.node`.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mapd.envelope import MAX_STR
from mapd.errors import CodecError, LimitError, TransportError
from mapd.grid import DEFAULT_MAX_CELLS, MAX_GRID_SIDE, OccupancyGrid, Pose2D, geometry_problem
from mapd.grid.reprs import short_repr
from mapd.ros2 import rmw
from mapd.ros2.tf import TF_TYPE
from mapd.ros2.zenoh_config import open_zenoh, zenoh_config_text

MSGTYPE = "nav_msgs/msg/OccupancyGrid"
DDS_TYPE = "nav_msgs::msg::dds_::OccupancyGrid_"
KeyFormat = rmw.KeyFormat
#: CDR bytes beyond the cells: header, frame id, metadata (a generous bound for the size check).
_OVERHEAD = 64 * 1024


def typestore(distro: str = "jazzy") -> Any:
    """rosbags' type store of a ROS 2 distro (see :func:`mapd.ros2.rmw.typestore`)."""
    return rmw.typestore(distro)


def _typestore() -> Any:
    return typestore("jazzy")


def type_hash() -> str:
    """The RIHS01 type hash of ``nav_msgs/msg/OccupancyGrid`` (Jazzy), as rmw_zenoh puts it in keys."""
    return rmw.type_hash(MSGTYPE, "jazzy")


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


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """The rotation about z (REP-103) of a finite quaternion, of any length; 0 for a zero one.

    Normalized first (hypot does not overflow): components of 1e200 made the products inf and the
    yaw NaN.
    """
    norm = math.hypot(x, y, z, w)
    if norm == 0:
        return 0.0
    x, y, z, w = x / norm, y / norm, z / norm, w / norm
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def check_size(size: int, max_cells: int, where: str) -> None:
    """LimitError for a CDR payload of ``size`` bytes, more than an OccupancyGrid of at most
    ``max_cells`` cells takes: checked before the payload is copied or parsed."""
    if size > max_cells + _OVERHEAD:
        raise LimitError(f"{where}: {size} bytes is more than a grid of {max_cells} cells needs")


def decode(
    payload: bytes, *, max_cells: int = DEFAULT_MAX_CELLS, where: str = "CDR payload"
) -> OccupancyGrid:
    """An :class:`OccupancyGrid` from CDR bytes; ``where`` (say, the topic) starts every error line.

    Raises :class:`CodecError` for bytes that do not parse or describe no valid grid, and
    :class:`LimitError` for a grid over ``max_cells`` (checked before anything is allocated for it).
    """
    check_size(len(payload), max_cells, where)
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
    if max(w, h) > MAX_GRID_SIDE:
        raise CodecError(f"{where}: {w} x {h} grid is over {MAX_GRID_SIDE} cells a side")
    data = np.asarray(msg.data)
    if data.size != w * h:
        raise CodecError(f"{where}: {data.size} cells for a {w} x {h} grid")
    # ROS keeps the resolution as float32: take the shortest decimal that float32 maps to it (0.05).
    res = float(str(np.float32(info.resolution)))
    p, q = info.origin.position, info.origin.orientation
    nums = (res, p.x, p.y, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in nums) or res <= 0:
        raise CodecError(f"{where}: resolution or origin is not a finite number (resolution {res})")
    origin = Pose2D(float(p.x), float(p.y), quaternion_yaw(q.x, q.y, q.z, q.w))
    # The bounds every map file and payload keeps: a resolution of 1e-30 was taken, and froze the
    # global map at it until a restart.
    problem = geometry_problem(res, origin)
    if problem is not None:
        raise CodecError(f"{where}: {problem}")
    frame_id = str(msg.header.frame_id) or "map"
    if len(frame_id) > MAX_STR or not frame_id.isprintable():
        # An envelope's fields hold 64 characters: every peer refused the robot's maps, unsaid.
        raise CodecError(
            f"{where}: frame_id {short_repr(frame_id)} ({len(frame_id)} characters) is not a frame"
            f" name of at most {MAX_STR} printable characters"
        )
    stamp = float(msg.header.stamp.sec) + float(msg.header.stamp.nanosec) * 1e-9
    return OccupancyGrid(
        # A copy the grid owns: the message's array is a read-only view of the payload's bytes,
        # which numba's kernels refuse (the lossless codec's failure stopped the daemon).
        data=np.array(data, dtype=np.int8).reshape(h, w),
        resolution=res,
        origin=origin,
        frame_id=frame_id,
        stamp=stamp,
    )


def encode_tf(transforms: list[tuple[str, str, Pose2D, float]]) -> bytes:
    """A CDR ``tf2_msgs/msg/TFMessage``: one ``TransformStamped`` per (parent, child, pose, stamp).

    A pose is x, y (m) and yaw (rad, counter-clockwise) of the child frame in the parent frame (REP-103);
    z is 0 and the rotation is about z only.
    """
    ts = _typestore()
    t = ts.types
    items = [
        t["geometry_msgs/msg/TransformStamped"](
            header=t["std_msgs/msg/Header"](
                stamp=t["builtin_interfaces/msg/Time"](*split_stamp(stamp)), frame_id=parent
            ),
            child_frame_id=child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=float(pose.x), y=float(pose.y), z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](
                    x=0.0, y=0.0, z=math.sin(pose.yaw / 2), w=math.cos(pose.yaw / 2)
                ),
            ),
        )
        for parent, child, pose, stamp in transforms
    ]
    return bytes(ts.serialize_cdr(t[TF_TYPE](transforms=items), TF_TYPE))


# ------------------------------------------------------------------------------------------------
# Keys (the rules are in mapd.ros2.rmw)
# ------------------------------------------------------------------------------------------------


def _check_topic(topic: str) -> str:
    return rmw.check_name(topic)


def rmw_zenoh_key(topic: str, *, domain: int = 0, hash_: str | None = None) -> str:
    """rmw_zenoh's key for an OccupancyGrid topic; ``hash_='*'`` gives the subscription wildcard."""
    return rmw.data_key(topic, MSGTYPE, domain=domain, hash_=hash_)


def ros2dds_key(topic: str, *, namespace: str = "") -> str:
    """zenoh-bridge-ros2dds's key: the topic without its leading slash, under ``namespace`` if given."""
    return rmw.bridge_key(topic, namespace=namespace)


def key_for(
    topic: str, key_format: KeyFormat, *, domain: int = 0, namespace: str = "", subscribe: bool = False
) -> str:
    """The key to publish on (or, with ``subscribe``, to subscribe to) for a topic in either format."""
    if key_format == "rmw_zenoh":
        return rmw_zenoh_key(topic, domain=domain, hash_="*" if subscribe else None)
    return ros2dds_key(topic, namespace=namespace)


# ------------------------------------------------------------------------------------------------
# Sessions
# ------------------------------------------------------------------------------------------------


def session_config(
    *,
    mode: Literal["peer", "client"] | None = None,
    connect: list[str] | None = None,
    listen: list[str] | None = None,
    multicast_scouting: bool | None = None,
    config_file: Path | None = None,
) -> Any:
    """A ``zenoh.Config``: the file's (if any), with mode, endpoints and scouting set over it
    where given; without a file, a peer without multicast scouting where not given."""
    try:
        import zenoh
    except ModuleNotFoundError:
        raise TransportError("ros2 over zenoh needs eclipse-zenoh, which is not installed") from None
    try:
        # Read by mapd, not zenoh.Config.from_file: a FIFO or /dev/zero named here hung the daemon.
        cfg = (
            zenoh.Config.from_json5(zenoh_config_text(config_file))
            if config_file is not None
            else zenoh.Config()
        )
    except Exception as exc:  # ValueError from the read, zenoh.ZError for a malformed config
        raise TransportError(f"{config_file}: cannot use zenoh config: {exc}") from None
    if config_file is None:
        mode = mode or "peer"
        multicast_scouting = bool(multicast_scouting)
    settings: dict[str, Any] = {
        # The advanced publisher's cache orders samples by timestamp, so sessions must stamp them.
        "timestamping/enabled": {"router": True, "peer": True, "client": True},
    }
    if mode is not None:
        settings["mode"] = mode
    if multicast_scouting is not None:
        settings["scouting/multicast/enabled"] = multicast_scouting
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


def session_options_for(o: Any) -> dict[str, Any]:
    """:func:`session_config`'s options for an ``[output.ros2]`` or ``[source.ros2]`` table (both
    have mode, connect, listen, multicast_scouting and zenoh_config). With a config file, the keys
    the file sets stand unless the table sets them too (check_files refuses a conflict): the
    table's defaults (a peer, no scouting) made a file's TLS client a peer. The keys the file leaves
    out take the table's values, its defaults included (a client of rmw_zenohd on localhost that
    does not scout: a file of TLS or timeouts alone gave zenoh's peer that scouts the LAN)."""
    from mapd.ros2.zenoh_config import TABLE_KEYS, file_values, table_keys_set

    keys = set(TABLE_KEYS)
    if o.zenoh_config is not None:
        keys -= set(file_values(o.zenoh_config)) - table_keys_set(o)
    return {"config_file": o.zenoh_config, **{k: getattr(o, k) for k in sorted(keys)}}


def open_session_for(o: Any) -> Any:
    """Open the session an ``[output.ros2]`` or ``[source.ros2]`` table describes."""
    return open_session(**session_options_for(o))


def open_session(**options: Any) -> Any:
    """Open a zenoh session from :func:`session_config` options; TransportError when it cannot
    (UnreachableError when no router it must connect to answers: see ``open_zenoh``)."""
    return open_zenoh(session_config(**options), "cannot open zenoh session")
