"""A ROS 2 node on a zenoh session, as rmw_zenoh shows one: tokens, publishers and subscription tokens.

The thin zenoh adapter around :mod:`mapd.ros2.rmw` (which holds every rule). A :class:`Ros2Node`
declares the node's liveliness token; :meth:`Ros2Node.publisher` declares a publisher entity: its
token, and a zenoh advanced publisher on rmw_zenoh's data key whose samples carry rmw_zenoh's
attachment (sequence number from 1, source timestamp, the GID derived from the token). As in
rmw_zenoh's ``rmw_publisher_data.cpp``, a transient-local publisher's cache holds ``depth`` samples
and it announces itself (publisher detection), so a late subscriber asking for history (RViz, Nav2
with map QoS) gets the current message; a reliable one also sends sporadic heartbeats (500 ms) for
sample-miss detection; congestion control blocks only for reliable keep-all. :meth:`Ros2Node.subscription` declares only a subscription's
token, so ``ros2 topic info`` counts mapd as a subscriber; the caller subscribes to the data itself.

With ``key_format="ros2dds"`` there are no tokens and no attachment: samples go on the topic's
zenoh-bridge-ros2dds key from an advanced publisher (a cache for a transient-local topic, publisher
detection), as the bridge's own routes publish: since 1.5.1 the bridge routes a transient-local DDS
reader (RViz started after the last merge) through an advanced subscriber that detects publishers
and asks for their cache. A queryable on the key answers a plain ``get`` with the newest too.

The session stays the caller's; :meth:`Ros2Node.close` undeclares only what the node declared.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from typing import Any

from mapd.errors import TransportError
from mapd.ros2 import rmw

#: rmw_zenoh numbers a context's nodes and entities from one counter; here one counter per session.
_counters: dict[str, itertools.count[int]] = {}
_counters_lock = threading.Lock()


def _next_id(zid: str) -> int:
    with _counters_lock:
        return next(_counters.setdefault(zid, itertools.count(0)))


class OwnPublishers:
    """What this process's ``ros2`` output publishes from: its publishers' rmw GIDs and its zenoh
    session ids, so that a ``ros2`` source in the same process can tell its samples apart.

    On a robot the source and the output may meet on one topic (both default to ``/map``): the
    source then took the fleet's global map back in as the robot's own map. rmw_zenoh samples
    carry their publisher's GID in the attachment; ``ros2dds`` samples carry none, but their zenoh
    timestamp names the session that stamped them (timestamping is on in every session mapd opens).
    Thread-safe: zenoh's callback threads ask while the output's thread adds and removes.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._gids: set[bytes] = set()
        self._zids: set[str] = set()

    def add(self, *, gids: list[bytes], zid: str) -> None:
        """Note a session and its publishers' GIDs (each unique: a GID hashes the session's id)."""
        with self._lock:
            self._gids.update(gids)
            self._zids.add(zid)

    def remove(self, *, gids: list[bytes], zid: str) -> None:
        with self._lock:
            self._gids.difference_update(gids)
            self._zids.discard(zid)

    def is_own(self, *, gid: bytes | None = None, zid: str | None = None) -> bool:
        """True when ``gid`` is one of the output's publishers' or ``zid`` one of its sessions'."""
        with self._lock:
            return (gid is not None and gid in self._gids) or (zid is not None and zid in self._zids)


#: The one registry of this process (the ros2 output adds to it, the ros2 source asks it).
own_publishers = OwnPublishers()


#: rmw_zenoh's SAMPLE_MISS_DETECTION_HEARTBEAT_PERIOD (500 ms) for reliable, transient-local publishers.
HEARTBEAT_S = 0.5


def _advanced_options(qos: rmw.Qos) -> dict[str, Any]:
    """The advanced publisher's options rmw_zenoh uses for ``qos`` (``rmw_publisher_data.cpp``)."""
    import zenoh
    import zenoh.ext as zext

    reliable = qos.reliability == rmw.RELIABLE
    opts: dict[str, Any] = {
        "reliability": zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
        "congestion_control": zenoh.CongestionControl.BLOCK
        if reliable and qos.history == rmw.KEEP_ALL
        else zenoh.CongestionControl.DROP,
    }
    if qos.durability == rmw.TRANSIENT_LOCAL:
        # Late subscribers that ask for history get the cached samples; they find the publisher by
        # its liveliness (publisher detection); a reliable one heartbeats so misses are recovered.
        opts["publisher_detection"] = True
        opts["cache"] = zext.CacheConfig(max_samples=qos.depth)
        if reliable:
            opts["sample_miss_detection"] = zext.MissDetectionConfig(
                heartbeat=None, sporadic_heartbeat=HEARTBEAT_S
            )
    return opts


class Ros2Publisher:
    """One topic's publisher (see the module docstring). ``put`` is thread-safe."""

    def __init__(
        self, node: Ros2Node, topic: str, msgtype: str, qos: rmw.Qos, entity: rmw.Entity | None
    ) -> None:
        import zenoh.ext as zext

        self.node = node
        self.topic = topic
        self.msgtype = msgtype
        self.qos = qos
        self.entity = entity
        self.gid = entity.gid() if entity is not None else b""
        if node.key_format == "rmw_zenoh":
            self.key = rmw.data_key(topic, msgtype, domain=node.domain, distro=node.distro)
        else:
            self.key = rmw.bridge_key(topic, namespace=node.bridge_namespace)
        self._lock = threading.Lock()
        self._seq = 0
        self._latest: bytes | None = None
        self._token: Any = None
        self._queryables: list[Any] = []
        self.published = 0
        session = node.session
        try:
            # An advanced publisher in both formats: zenoh-bridge-ros2dds (1.5.1 and later) routes a
            # transient-local DDS reader (RViz, Nav2's map QoS) through an advanced subscriber that
            # asks the publishers it detects for their cache, as rmw_zenoh's subscribers do.
            self._pub = zext.declare_advanced_publisher(session, self.key, **_advanced_options(qos))
            if qos.durability == rmw.TRANSIENT_LOCAL and node.key_format == "ros2dds":
                # (and a plain get on the key, for zenoh clients that are no bridge)
                self._queryables = [session.declare_queryable(self.key, self._on_query)]
            if entity is not None:
                self._token = session.liveliness().declare_token(entity.token())
        except Exception as exc:  # zenoh.ZError
            raise TransportError(f"cannot publish {topic} on zenoh key '{self.key}': {exc}") from None

    def _on_query(self, query: Any) -> None:
        with self._lock:
            data = self._latest
        if data is not None:
            with contextlib.suppress(Exception):  # the querier gone, or the session closing
                query.reply(self.key, data)

    def put(self, payload: bytes) -> None:
        """Publish one CDR payload (with rmw_zenoh's attachment when the format is rmw_zenoh)."""
        with self._lock:
            self._seq += 1
            seq = self._seq
            self._latest = payload
        att = rmw.attachment(seq, time.time_ns(), self.gid) if self.entity is not None else None
        try:
            self._pub.put(payload, attachment=att)
        except Exception as exc:  # zenoh.ZError: the session closed
            raise TransportError(f"cannot publish {self.topic}: {exc}") from None
        self.published += 1

    def close(self) -> None:
        for thing in (self._token, *self._queryables, self._pub):
            if thing is not None:
                with contextlib.suppress(Exception):  # already gone when the session closed first
                    thing.undeclare()
        self._token, self._queryables = None, []


class Ros2Node:
    """A ROS 2 node named ``name`` in ``namespace`` on domain ``domain``, as rmw_zenoh announces one."""

    def __init__(
        self,
        session: Any,
        name: str = "mapd",
        *,
        namespace: str = "",
        domain: int = 0,
        distro: rmw.Distro = "jazzy",
        key_format: rmw.KeyFormat = "rmw_zenoh",
        enclave: str = "/",
        bridge_namespace: str = "",
    ) -> None:
        self.session = session
        self.name = rmw.check_name(name, "node")
        self.namespace = rmw.fq_namespace(namespace)
        self.domain = domain
        self.distro = distro
        self.key_format = key_format
        self.enclave = enclave
        self.bridge_namespace = bridge_namespace
        self.zid = str(session.zid())
        self.nid = _next_id(self.zid)
        self.entity = rmw.Entity(
            domain, self.zid, self.nid, self.nid, "NN", self.namespace, self.name, enclave
        )
        self._things: list[Any] = []
        self._token: Any = None
        if key_format == "rmw_zenoh":
            try:
                self._token = session.liveliness().declare_token(self.entity.token())
            except Exception as exc:  # zenoh.ZError
                raise TransportError(f"cannot declare ROS 2 node {self.name}: {exc}") from None

    def topic_entity(self, kind: rmw.EntityKind, topic: str, msgtype: str, qos: rmw.Qos) -> rmw.Entity:
        """The publisher (``MP``) or subscription (``MS``) entity of this node on ``topic``."""
        return rmw.Entity(
            self.domain,
            self.zid,
            self.nid,
            _next_id(self.zid),
            kind,
            self.namespace,
            self.name,
            self.enclave,
            topic=rmw.fq_topic(topic, self.namespace),
            type=rmw.dds_type(msgtype),
            type_hash=rmw.type_hash(msgtype, self.distro),
            qos=qos,
        )

    def publisher(self, topic: str, msgtype: str, qos: rmw.Qos) -> Ros2Publisher:
        """Declare a publisher on ``topic`` (relative names are taken under the node's namespace)."""
        fq = rmw.fq_topic(topic, self.namespace)
        entity = self.topic_entity("MP", fq, msgtype, qos) if self.key_format == "rmw_zenoh" else None
        pub = Ros2Publisher(self, fq, msgtype, qos, entity)
        self._things.append(pub)
        return pub

    def subscription(self, topic: str, msgtype: str, qos: rmw.Qos) -> Any:
        """Declare a subscription's liveliness token (``MS``); returns it (``undeclare()`` drops it)."""
        if self.key_format != "rmw_zenoh":
            return None
        entity = self.topic_entity("MS", topic, msgtype, qos)
        try:
            token = self.session.liveliness().declare_token(entity.token())
        except Exception as exc:  # zenoh.ZError
            raise TransportError(f"cannot declare a subscription to {topic}: {exc}") from None
        self._things.append(token)
        return token

    def close(self) -> None:
        """Undeclare the node's publishers, tokens and the node (the session is left open)."""
        for thing in reversed(self._things):
            with contextlib.suppress(Exception):
                if isinstance(thing, Ros2Publisher):
                    thing.close()
                else:
                    thing.undeclare()
        self._things = []
        if self._token is not None:
            with contextlib.suppress(Exception):
                self._token.undeclare()
            self._token = None


class Ros2Sink:
    """Publishes grids as ``nav_msgs/msg/OccupancyGrid`` on one topic, as a one-publisher ROS 2 node.

    Reliable, transient local, depth 1 (``rmw.LATCHED``): late subscribers that ask for history get
    the current map.
    """

    def __init__(
        self,
        session: Any,
        topic: str = "/map",
        *,
        key_format: rmw.KeyFormat = "rmw_zenoh",
        domain: int = 0,
        namespace: str = "",
        node: str = "mapd",
        frame_id: str = "map",
        distro: rmw.Distro = "jazzy",
    ) -> None:
        from mapd.ros2 import cdr

        self._encode = cdr.encode
        self.frame_id = frame_id
        ns_node = "" if key_format == "ros2dds" else namespace
        self.node = Ros2Node(
            session,
            node,
            namespace=ns_node,
            domain=domain,
            distro=distro,
            key_format=key_format,
            bridge_namespace=namespace if key_format == "ros2dds" else "",
        )
        self.pub = self.node.publisher(topic, cdr.MSGTYPE, rmw.LATCHED)
        self.topic = self.pub.topic
        self.key = self.pub.key
        self.gid = self.pub.gid

    def publish(self, grid: Any, *, stamp: float | None = None) -> int:
        """Publish one grid; returns the payload size in bytes."""
        payload = self._encode(grid, frame_id=self.frame_id, stamp=stamp)
        self.pub.put(payload)
        return len(payload)

    def close(self) -> None:
        self.node.close()
