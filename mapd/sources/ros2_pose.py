"""The ``ros2`` source's robot pose: the latest ``geometry_msgs`` pose on a topic, such as AMCL's ``/amcl_pose``.

:class:`PoseSubscription` subscribes as an rmw_zenoh subscription does: on the data key with the
type's dds name and the distro's type hash (``<domain>/<topic>/geometry_msgs::msg::dds_::
PoseWithCovarianceStamped_/RIHS01_...``), through an advanced subscriber that asks for history, and
with a subscription liveliness token (``MS``; reliable, transient local, keep last 1: the QoS of
Nav2 AMCL's ``amcl_pose`` publisher), so a late mapd gets the last estimate at once and ``ros2 topic
info`` lists mapd. AMCL publishes only when its filter updates (the robot moved), so that cached
estimate is where a standing robot still is.

A pose is a few hundred bytes: it is decoded in zenoh's callback thread and the latest kept under a
lock; :meth:`PoseSubscription.latest` only reads it. Its stamp is the wall clock at reception, not
the message's header stamp (ROS time may be simulated or skewed), because the daemon compares
stamps across robots. A pose whose header ``frame_id`` is not ``pose_frame`` (the robot's map
frame, where mapd's map is) is counted and ignored, as is a payload that does not parse; neither
ever stops the source.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from typing import Any, Literal

from mapd.errors import CodecError, TransportError
from mapd.grid import MAX_ORIGIN_M, Pose2D, StampedPose
from mapd.ros2 import cdr as ros2cdr
from mapd.ros2 import rmw

log = logging.getLogger(__name__)

PoseType = Literal["PoseWithCovarianceStamped", "PoseStamped"]
#: The ROS message type of each ``pose_type``.
MSGTYPES: dict[str, str] = {
    "PoseWithCovarianceStamped": "geometry_msgs/msg/PoseWithCovarianceStamped",
    "PoseStamped": "geometry_msgs/msg/PoseStamped",
}
#: Nav2 AMCL's ``amcl_pose`` publisher: reliable, transient local, keep last 1.
POSE_QOS = rmw.LATCHED
#: Far more than any pose message (about 400 bytes plus the frame id): larger payloads are refused
#: before decoding, so a bogus one cannot make zenoh's thread parse megabytes.
MAX_POSE_BYTES = 16 * 1024


def decode_pose(payload: bytes, msgtype: str, *, distro: rmw.Distro = "jazzy") -> tuple[str, Pose2D]:
    """The header ``frame_id`` and the planar pose (x, y, yaw; REP-103) of a CDR pose message.

    Raises :class:`CodecError` for bytes that do not parse as ``msgtype`` or a pose that is not finite
    or has a zero quaternion.
    """
    if len(payload) > MAX_POSE_BYTES:
        raise CodecError(f"{len(payload)} bytes is over {MAX_POSE_BYTES} for a {msgtype}")
    if len(payload) < 4 or payload[:2] not in (b"\x00\x01", b"\x00\x00"):
        raise CodecError("not a CDR payload (bad encapsulation header)")
    try:
        msg = rmw.typestore(distro).deserialize_cdr(bytes(payload), msgtype)
    except CodecError:
        raise
    except Exception as exc:  # rosbags raises many kinds (struct.error, IndexError, ...) on bad bytes
        raise CodecError(f"CDR does not parse as {msgtype}: {type(exc).__name__}") from None
    # PoseWithCovarianceStamped nests the pose one level deeper (pose.pose) than PoseStamped (pose).
    pose = msg.pose.pose if msgtype == MSGTYPES["PoseWithCovarianceStamped"] else msg.pose
    p, q = pose.position, pose.orientation
    nums = (p.x, p.y, q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in nums):
        raise CodecError("pose is not finite")
    if q.x == q.y == q.z == q.w == 0:
        raise CodecError("pose has a zero quaternion")
    if abs(p.x) > MAX_ORIGIN_M or abs(p.y) > MAX_ORIGIN_M:
        # What every peer refuses in a pose message: sent on, each would have been dropped, unsaid.
        raise CodecError(f"pose ({p.x:.6g}, {p.y:.6g}) is over {MAX_ORIGIN_M:g} m from the origin")
    return str(msg.header.frame_id), Pose2D(
        float(p.x), float(p.y), ros2cdr.quaternion_yaw(q.x, q.y, q.z, q.w)
    )


def _same_frame(a: str, b: str) -> bool:
    # tf2 frame ids have no leading '/', but ROS 1 habits ("/map") are common in configs and nodes.
    return a.lstrip("/") == b.lstrip("/")


class PoseSubscription:
    """The robot's pose from ``topic`` (``pose_type`` messages in frame ``frame``), newest wins."""

    def __init__(
        self,
        topic: str,
        pose_type: PoseType,
        *,
        frame: str = "map",
        key_format: rmw.KeyFormat = "rmw_zenoh",
        domain: int = 0,
        distro: rmw.Distro = "jazzy",
        namespace: str = "",
    ) -> None:
        self.topic = rmw.fq_topic(topic)
        self.msgtype = MSGTYPES[pose_type]
        self.frame = frame
        self.distro = distro
        if key_format == "rmw_zenoh":
            # any type hash, as the map's key: Humble's rmw_zenoh publishes TypeHashNotSupported
            # where the distro's hash was asked for, and no pose ever arrived, without a word
            self.key = rmw.data_key(self.topic, self.msgtype, domain=domain, distro=distro, hash_="*")
        else:
            self.key = rmw.bridge_key(self.topic, namespace=namespace)
        self._lock = threading.Lock()
        self._latest: StampedPose | None = None
        self._sub: Any = None
        self.received = 0
        self.bad = 0
        self.wrong_frame = 0
        self._last_wrong = ""

    def declare(self, session: Any, node: Any | None) -> None:
        """Subscribe on ``session`` and, given an rmw_zenoh ``node``, declare the subscription token."""
        import zenoh.ext as zext

        try:
            self._sub = zext.declare_advanced_subscriber(
                session,
                self.key,
                self.on_sample,
                history=zext.HistoryConfig(detect_late_publishers=True, max_samples=1),
                recovery=zext.RecoveryConfig(
                    periodic_queries=None, heartbeat=True
                ),  # (see ros2.py: a lost sample asked again)
            )
            if node is not None:
                node.subscription(self.topic, self.msgtype, POSE_QOS)
        except TransportError:
            raise
        except Exception as exc:  # zenoh.ZError
            raise TransportError(f"ros2 source: cannot subscribe to '{self.key}': {exc}") from None
        log.info("ros2 source: robot pose from %s (%s, frame %s)", self.topic, self.msgtype, self.frame)

    def on_sample(self, sample: Any) -> None:
        """One sample (on a zenoh thread): decoded here, kept if it is in the map frame."""
        try:
            payload = sample.payload.to_bytes()
        except Exception:  # a sample we cannot read at all
            payload = b""
        self.offer(payload)

    def offer(self, payload: bytes, now: float | None = None) -> bool:
        """Take one CDR payload received at ``now`` (wall clock); True when it became the pose."""
        try:
            frame, pose = decode_pose(payload, self.msgtype, distro=self.distro)
        except CodecError as exc:
            with self._lock:
                self.received += 1
                self.bad += 1
            log.debug("ros2 source: dropped a payload on %s: %s", self.topic, exc)
            return False
        stamp = time.time() if now is None else now
        with self._lock:
            self.received += 1
            if _same_frame(frame, self.frame):
                # zenoh may run callbacks on several threads: never let an older pose replace a newer
                if self._latest is not None and stamp < self._latest.stamp:
                    return False
                self._latest = StampedPose(pose, stamp)
                return True
            self.wrong_frame += 1
            first = self.wrong_frame == 1
            self._last_wrong = frame[:64]
        if first:  # a misconfiguration (pose_frame, or a pose in odom): say it once
            log.warning(
                "ros2 source: ignoring poses on %s in frame %r; pose_frame is %r",
                self.topic,
                frame[:64],
                self.frame,
            )
        return False

    def latest(self) -> StampedPose | None:
        """The newest pose in the map frame, stamped at its reception; None before the first."""
        with self._lock:
            return self._latest

    def stats(self) -> dict[str, int | float | str]:
        """Counters for ``mapd status`` (each name starts with ``pose_``)."""
        with self._lock:
            return {
                "pose_key": self.key,
                "pose_received": self.received,
                "pose_bad_payloads": self.bad,
                "pose_wrong_frame": self.wrong_frame,
                "pose_last_wrong_frame": self._last_wrong or "-",
            }

    def close(self) -> None:
        """Undeclare the subscriber (the token goes with the node; the session is the caller's)."""
        sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()
            except Exception as exc:  # already gone when the session closed first
                log.debug("closing the pose subscriber: %s", exc)
