"""A minimal ROS 2 node speaking rmw_zenoh's protocol, written for the tests from rmw_zenoh's sources.

It shares no code with mapd: zenoh and rosbags directly, its own message definitions (the few it
needs, registered in an empty rosbags type store), its own key, token, QoS, GID and attachment rules
(from ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``, ``qos.cpp``, ``attachment_helpers.cpp``).
It subscribes the way an rmw_zenoh subscription does (an advanced subscriber asking for history
when transient local) and publishes the way an rmw_zenoh publisher does.
"""

from __future__ import annotations

import contextlib
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import xxhash
import zenoh
import zenoh.ext as zext
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.msg import get_types_from_msg

MSGS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "nav_msgs/msg/MapMetaData": (
        "builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\nuint32 height\n"
        "geometry_msgs/Pose origin"
    ),
    "nav_msgs/msg/OccupancyGrid": "std_msgs/Header header\nMapMetaData info\nint8[] data",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "std_msgs/Header header\nPoseWithCovariance pose",
}
#: From ``ros2 topic info -v /map`` on Jazzy.
GRID_HASH = "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7"
GRID = "nav_msgs/msg/OccupancyGrid"
TF = "tf2_msgs/msg/TFMessage"
DDS = {GRID: "nav_msgs::msg::dds_::OccupancyGrid_", TF: "tf2_msgs::msg::dds_::TFMessage_"}
POSE_COV = "geometry_msgs/msg/PoseWithCovarianceStamped"
POSE = "geometry_msgs/msg/PoseStamped"
DDS[POSE_COV] = "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_"
DDS[POSE] = "geometry_msgs::msg::dds_::PoseStamped_"
#: Published Jazzy RIHS01 hashes of the two pose types (as other rmw_zenoh implementations list them).
POSE_HASHES = {
    POSE_COV: "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    POSE: "RIHS01_10f3786d7d40fd2b54367835614bff85d4ad3b5dab62bf8bca0cc232d73b4cd8",
}


def store() -> Any:
    ts = get_typestore(Stores.EMPTY)
    types: dict[str, Any] = {}
    for name, text in MSGS.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


TS = store()


def type_hash(msgtype: str, distro: str) -> str:
    return "TypeHashNotSupported" if distro == "humble" else str(TS.hash_rihs01(msgtype))


def gid(token: str) -> bytes:
    # XXH3-128 canonical form is big-endian (high, low); rmw_zenoh stores low then high, little-endian.
    return xxhash.xxh3_128_digest(token.encode())[::-1]


def qos(durability_transient: bool, depth: int) -> str:
    # Defaults (reliable, volatile, keep last, 42) are left empty.
    return f":{'1' if durability_transient else ''}:,{'' if depth == 42 else depth}:,:,:,,"


@dataclass
class Token:
    key: str
    zid: str
    nid: str
    eid: str
    kind: str
    enclave: str
    namespace: str
    node: str
    topic: str = ""
    type: str = ""
    hash: str = ""
    qos: str = ""


def having(node: str, *entities: tuple[str, str]) -> Callable[[list[Token]], bool]:
    """A ``graph(until=...)`` test: ``node`` shows each (kind, topic), e.g. ("MS", "/map")."""
    return lambda tokens: set(entities) <= {(t.kind, t.topic) for t in tokens if t.node == node}


def parse(key: str) -> Token:
    p = key.split("/")
    assert p[0] == "@ros2_lv" and len(p) in (9, 13), key
    t = Token(key, p[2], p[3], p[4], p[5], p[6].replace("%", "/"), p[7].replace("%", "/"), p[8])
    if len(p) == 13:
        t.topic, t.type, t.hash, t.qos = p[9].replace("%", "/"), p[10], p[11], p[12]
    return t


@dataclass
class Received:
    key: str
    msg: Any
    seq: int
    stamp_ns: int
    gid: bytes
    at: float = field(default_factory=time.time)


class RmwPeer:
    """A ROS 2 node ``/tester`` (domain ``domain``) on its own zenoh session."""

    def __init__(
        self, endpoint: str, *, domain: int = 0, distro: str = "jazzy", listen: bool = False
    ) -> None:
        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("listen/endpoints" if listen else "connect/endpoints", f'["{endpoint}"]')
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("timestamping/enabled", '{"router": true, "peer": true, "client": true}')
        self.session = zenoh.open(cfg)
        self.domain = domain
        self.distro = distro
        self.zid = str(self.session.zid())
        self._ids = iter(range(1000))
        self.nid = next(self._ids)
        self.things: list[Any] = [self._token("NN", "")]
        self.got: dict[str, list[Received]] = {}
        self.lock = threading.Lock()

    def _token(self, kind: str, rest: str) -> Any:
        eid = self.nid if kind == "NN" else next(self._ids)
        key = f"@ros2_lv/{self.domain}/{self.zid}/{self.nid}/{eid}/{kind}/%/%/tester{rest}"
        self.last_token = key
        return self.session.liveliness().declare_token(key)

    def data_key(self, topic: str, msgtype: str) -> str:
        return f"{self.domain}/{topic.strip('/')}/{DDS[msgtype]}/{type_hash(msgtype, self.distro)}"

    def subscribe(self, topic: str, msgtype: str, *, transient_local: bool = True, depth: int = 1) -> None:
        """Subscribe as rmw_zenoh does (any type hash in the key), and declare the MS token."""
        key = f"{self.domain}/{topic.strip('/')}/{DDS[msgtype]}/*"
        self.got.setdefault(topic, [])

        def on(sample: Any) -> None:
            att = sample.attachment.to_bytes() if sample.attachment is not None else b""
            seq, stamp = struct.unpack_from("<qq", att) if len(att) == 33 else (-1, -1)
            msg = TS.deserialize_cdr(sample.payload.to_bytes(), msgtype)
            with self.lock:
                self.got[topic].append(Received(str(sample.key_expr), msg, seq, stamp, att[17:]))

        history = (
            zext.HistoryConfig(detect_late_publishers=True, max_samples=depth) if transient_local else None
        )
        self.things.append(zext.declare_advanced_subscriber(self.session, key, on, history=history))
        rest = f"/{topic.replace('/', '%')}/{DDS[msgtype]}/{type_hash(msgtype, self.distro)}/{qos(transient_local, depth)}"
        self.things.append(self._token("MS", rest))

    def publisher(self, topic: str, msgtype: str = GRID) -> tuple[Any, bytes]:
        """A transient-local depth-1 publisher (advanced, cached) with its MP token; returns it and its GID."""
        pub = zext.declare_advanced_publisher(
            self.session,
            self.data_key(topic, msgtype),
            cache=zext.CacheConfig(max_samples=1),
            publisher_detection=True,
        )
        rest = f"/{topic.replace('/', '%')}/{DDS[msgtype]}/{type_hash(msgtype, self.distro)}/{qos(True, 1)}"
        self.things += [pub, self._token("MP", rest)]
        return pub, gid(self.last_token)

    def publish_map(
        self,
        pub: tuple[Any, bytes],
        data: Any,
        resolution: float,
        origin: tuple[float, float],
        frame: str,
        seq: int,
    ) -> None:
        t = TS.types
        stamp = t["builtin_interfaces/msg/Time"](sec=int(time.time()), nanosec=0)
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=origin[0], y=origin[1], z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
        )
        h, w = data.shape
        msg = t[GRID](
            header=t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame),
            info=t["nav_msgs/msg/MapMetaData"](
                map_load_time=stamp, resolution=resolution, width=w, height=h, origin=pose
            ),
            data=data.ravel().astype("int8"),
        )
        att = struct.pack("<qq", seq, time.time_ns()) + b"\x10" + pub[1]
        pub[0].put(bytes(TS.serialize_cdr(msg, GRID)), attachment=att)

    def put(self, pub: tuple[Any, bytes], payload: bytes, seq: int) -> None:
        """Publish raw CDR bytes (any message, or garbage) with rmw_zenoh's attachment."""
        pub[0].put(payload, attachment=struct.pack("<qq", seq, time.time_ns()) + b"\x10" + pub[1])

    def graph(self, until: Callable[[list[Token]], bool] | None = None, timeout: float = 10.0) -> list[Token]:
        """The ROS graph's tokens; with ``until``, asked again until it holds or ``timeout`` passes.

        A token declared by another session reaches this one a moment later, as in ``ros2 node
        list``; a test that waits for one passes ``until`` and asserts on what is returned.
        """
        end = time.monotonic() + timeout
        while True:
            replies = self.session.liveliness().get(f"@ros2_lv/{self.domain}/**", timeout=3.0)
            tokens = [parse(str(r.ok.key_expr)) for r in replies if r.ok is not None]
            if until is None or until(tokens) or time.monotonic() > end:
                return tokens
            time.sleep(0.1)

    def received(self, topic: str) -> list[Received]:
        with self.lock:
            return list(self.got.get(topic, []))

    def wait(self, topic: str, pred: Any, timeout: float = 20.0) -> Received:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for r in reversed(self.received(topic)):
                if pred(r):
                    return r
            time.sleep(0.05)
        raise AssertionError(
            f"nothing on {topic} matched within {timeout} s; got {len(self.received(topic))}"
        )

    def close(self) -> None:
        for thing in reversed(self.things):
            with contextlib.suppress(Exception):
                thing.undeclare()
        self.session.close()
