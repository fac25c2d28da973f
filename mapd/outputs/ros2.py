"""``[output.ros2]``: the global map and the robots' frames on ROS 2, over zenoh, with no ROS install.

Each global map goes out as ``nav_msgs/msg/OccupancyGrid`` on ``topic`` (default ``/map``) in the
fleet frame ``frame`` (default ``map``; m-explore's ``world_frame``), exactly as an rmw_zenoh
publisher with reliable, transient-local, depth-1 QoS sends it: on rmw_zenoh's data key, with its
attachment, announced by node and publisher liveliness tokens, through an advanced publisher whose
cache gives a late subscriber (RViz, Nav2) the current map. The rules (keys, tokens, QoS strings,
GIDs, type hashes per ``distro``) are :mod:`mapd.ros2.rmw`'s; the zenoh side is
:mod:`mapd.ros2.node`.

With ``tf = true`` (the default) it also publishes, following REP-105 frame names:

* ``/tf_static`` (transient local): ``<frame> -> <robot>/map`` for every placed robot, sent again
  (all of them, as one latched message) whenever a placement changes. A robot that is no longer
  placed (revoked, or its placement dropped) is moved under ``unplaced_frame`` in that message,
  off the fleet's tree: tf2 keeps a static transform for as long as it runs and no message removes
  one, but a frame has one parent, and a newer static transform of the frame replaces the old one,
  so lookups of the robot's frame in ``frame`` fail from then on instead of using a transform
  mapd has taken back. The robots whose frames went out are kept in the state directory, so this
  holds across a restart too;
* ``/tf``: ``<robot>/map -> <robot>/base_link`` for every robot whose pose is known
  (:meth:`publish_poses`, and the poses a :class:`GlobalUpdate` carries).

``format = "ros2dds"`` publishes plain CDR on zenoh-bridge-ros2dds keys instead (no tokens, no
attachment, a queryable answers late joiners). Example::

    [output]
    use = ["ros2"]
    [output.ros2]
    topic = "/map"
    frame = "map"
    distro = "jazzy"                  # humble | jazzy | kilted | rolling
    listen = ["tcp/0.0.0.0:7448"]     # or connect = ["tcp/127.0.0.1:7447"] (rmw_zenohd)
"""

from __future__ import annotations

import asyncio
import contextlib
import re
import threading
from pathlib import Path
from typing import Any, ClassVar, Literal

from pydantic import BaseModel, Field, ValidationInfo, field_validator, model_validator

from mapd.config import NAME_PATTERN
from mapd.config.endpoints import ZenohEndpoints
from mapd.errors import UnreachableError
from mapd.grid import Pose2D
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, OutputOptions, PoseUpdate
from mapd.outputs.retry import SessionRetry
from mapd.ros2 import rmw
from mapd.ros2.tf import Ros2Names, TfFrames, load_shown, robot_frame, save_shown, tf_static
from mapd.ros2.zenoh_config import ZenohConfigFiles

TF_TYPE = "tf2_msgs/msg/TFMessage"
#: In the state directory: the robots whose map frames went out on /tf_static.
FRAMES_FILE = "ros2_frames.json"


class Ros2OutputOptions(ZenohEndpoints, ZenohConfigFiles, OutputOptions):
    """``[output.ros2]``: topic, frames, ROS 2 identity, key format and how to reach zenoh."""

    beside_config: ClassVar[tuple[str, ...]] = ("zenoh_config",)

    topic: str = Field(default="/map", description="topic of the global nav_msgs/msg/OccupancyGrid")
    frame: str = Field(default=TfFrames.frame, description="the fleet frame's name (m-explore's world_frame)")
    distro: rmw.Distro = Field(default="jazzy", description="ROS 2 distro: sets the type hash in keys")
    namespace: str = Field(default="", description="the node's namespace (ros2dds: the bridge namespace)")
    node: str = Field(default="mapd", description="the ROS 2 node name")
    domain_id: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID")
    format: rmw.KeyFormat = Field(default="rmw_zenoh", description="rmw_zenoh, or zenoh-bridge-ros2dds keys")
    tf: bool = Field(default=True, description="publish /tf_static (robot map frames) and /tf (poses)")
    robot_map_frame: str = Field(
        default=TfFrames.robot_map_frame,
        description="each robot's map frame, a child of `frame` on /tf_static; {robot} is its name",
    )
    unplaced_frame: str = Field(
        default=TfFrames.unplaced_frame,
        description="where a robot's map frame moves on /tf_static once it is no longer placed "
        "(revoked, or its placement dropped), off the fleet's tree; empty: left where it was",
    )
    robot_pose_frame: str = Field(
        default=TfFrames.robot_pose_frame,
        description="the frame a robot's pose moves on /tf, a child of its map frame. A frame has one "
        "parent: where the robots' own TF reaches this ROS graph ({robot}/odom -> {robot}/base_link), "
        "name another, e.g. {robot}/mapd_pose; empty: no poses on /tf",
    )
    mode: Literal["peer", "client"] = Field(default="peer", description="zenoh session mode")
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"],
        description="zenoh endpoints to connect to (default: rmw_zenohd on this machine, as rmw_zenoh nodes do)",
    )
    listen: list[str] = Field(default_factory=list, description="zenoh endpoints to listen on")
    multicast_scouting: bool = Field(default=False, description="find peers by UDP multicast")
    zenoh_config: Path | None = Field(default=None, description="a zenoh JSON5 config to start from")

    @field_validator("topic")
    @classmethod
    def _check_topic(cls, v: str) -> str:
        return rmw.check_topic_name(v)

    @field_validator("node")
    @classmethod
    def _check_node(cls, v: str) -> str:
        rmw.check_name(v, "node")
        return v

    @field_validator("frame")
    @classmethod
    def _check_frame(cls, v: str) -> str:
        return rmw.check_frame_id(v)

    @field_validator("robot_map_frame", "robot_pose_frame")
    @classmethod
    def _check_robot_frame(cls, v: str, info: ValidationInfo) -> str:
        if v == "" and info.field_name == "robot_pose_frame":
            return v
        if "{robot}" not in v:
            raise ValueError(f"{v!r} must name the robot with {{robot}}: one frame each")
        rmw.check_frame_id(robot_frame(v, "robot0"), shown=v)
        return v

    @field_validator("unplaced_frame")
    @classmethod
    def _check_unplaced(cls, v: str) -> str:
        if v == "":
            return v
        rmw.check_frame_id(v)
        if "{robot}" in v:
            raise ValueError(f"{v!r} must be one frame of its own, not the fleet frame or a robot's")
        return v

    @field_validator("namespace")
    @classmethod
    def _check_ns(cls, v: str) -> str:
        return rmw.check_namespace(v)

    @model_validator(mode="after")
    def _frames_apart(self) -> Ros2OutputOptions:
        """The fleet frame, the robots' frames and ``unplaced_frame`` must never be one frame: tf2
        drops a transform from a frame to itself (``TF_SELF_TRANSFORM``), and a robot moved under
        another robot's frame, or under the fleet frame, is placed again instead of off the tree."""
        if self.robot_pose_frame == self.robot_map_frame:
            raise ValueError(
                f"robot_pose_frame {self.robot_pose_frame!r} is robot_map_frame: a robot's pose would "
                "move its map frame against itself, which tf2 drops; name another, e.g. '{robot}/base_link'"
            )
        robots = [("robot_map_frame", self.robot_map_frame), ("robot_pose_frame", self.robot_pose_frame)]
        for key, name in (("frame", self.frame), ("unplaced_frame", self.unplaced_frame)):
            for field, template in robots:
                robot = robot_of_frame(template, name) if template and name else None
                if robot is not None:
                    raise ValueError(
                        f"{key} {name!r} is the {field} of a robot named {robot!r} ({template!r}); "
                        f"{key} must be a frame of its own, apart from every robot's"
                    )
        if self.unplaced_frame and self.unplaced_frame == self.frame:
            raise ValueError(
                f"unplaced_frame {self.unplaced_frame!r} is the fleet frame: a robot no longer placed "
                "must leave the fleet's tree, not stay under it at the origin"
            )
        return self

    def tf_frames(self) -> TfFrames:
        """The frame names set here."""
        return TfFrames(self.frame, self.robot_map_frame, self.robot_pose_frame, self.unplaced_frame)

    def ros_topic(self) -> str:
        """The global map's fully qualified topic in the ROS graph: under ``namespace`` with
        rmw_zenoh; with ``ros2dds`` the namespace is the bridge's, on the zenoh side only."""
        return rmw.fq_topic(self.topic, self.namespace if self.format == "rmw_zenoh" else "")

    def map_key_expr(self) -> str:
        """The zenoh key the global map is published on (any type hash: ``*``)."""
        from mapd.ros2.cdr import MSGTYPE

        if self.format == "rmw_zenoh":
            return rmw.data_key(
                rmw.fq_topic(self.topic, self.namespace), MSGTYPE, domain=self.domain_id, hash_="*"
            )
        return rmw.bridge_key(rmw.fq_topic(self.topic), namespace=self.namespace)

    def check_with_plugins(self, chosen: dict[str, dict[str, BaseModel]]) -> None:
        """ValueError (one line, naming ``topic``) when the chosen ``ros2`` source takes maps from
        where this output publishes the global map.

        On a robot both default to ``/map``: mapd read its own global map back in as the robot's
        own map (and sent it to the fleet as such), and the robot's Nav2 saw two ``/map``
        publishers in two frames. ``chosen``: the options of every chosen plugin, by section and
        name; a hook for ``config.check`` beside ``check_files`` and ``check_for_robot``, so that
        ``mapd check-config`` and ``mapd run`` refuse the layout in one line.
        """
        from mapd.sources.ros2_options import Ros2Options

        source = chosen.get("source", {}).get("ros2")
        if not isinstance(source, Ros2Options):
            return
        if not rmw.key_exprs_intersect(source.map_key_expr(), self.map_key_expr()):
            return
        topic = self.ros_topic()
        where = (
            f"ROS domain {self.domain_id}" if self.format == "rmw_zenoh" else f"key {self.map_key_expr()!r}"
        )
        if source.discover_robots:
            whose, instead = "robots' maps", 'a topic that is no robot\'s map topic, e.g. topic = "/map"'
        else:
            whose, instead = "this robot's own map", 'e.g. topic = "/fleet/map" and frame = "fleet"'
        raise ValueError(
            f"topic: {topic!r} ({where}) is where [source.ros2] takes {whose} from: mapd would read "
            "its own global map back in as a robot's map, and the robot's nodes would get two maps "
            f"on one topic; publish the fleet's map elsewhere, {instead}"
        )


def robot_of_frame(template: str, frame: str) -> str | None:
    """The robot name whose ``template`` frame is ``frame`` (robot names as ``[robot] name``), or None."""
    name = NAME_PATTERN.removeprefix("^").removesuffix("$")
    parts = template.split("{robot}")
    regex = re.escape(parts[0])
    for k, part in enumerate(parts[1:]):
        regex += (f"(?P<robot>{name})" if k == 0 else "(?P=robot)") + re.escape(part)
    m = re.fullmatch(regex, frame)
    return m["robot"] if m and len(parts) > 1 else None


def pose_transforms(
    update: PoseUpdate | GlobalUpdate,
    sent: dict[str, float] | None = None,
    map_frame: str = "{robot}/map",
    pose_frame: str = "{robot}/base_link",
) -> list[tuple[str, str, Pose2D, float]]:
    """``<robot>/map -> <robot>/base_link`` (``map_frame -> pose_frame``) for each robot with a
    known pose, at the pose's stamp.

    With ``sent`` (robot -> stamp already published), only newer poses: tf2 warns about, and drops,
    a transform repeated with the same stamp (``TF_REPEATED_DATA``).
    """
    last = sent or {}
    return [
        (robot_frame(map_frame, r), robot_frame(pose_frame, r), sp.pose, sp.stamp)
        for r, sp in sorted(update.poses.items())
        if sp.stamp > last.get(r, float("-inf"))
    ]


class Ros2Output(Output):
    """Publishes every global map, the robots' map frames and their poses as a ROS 2 node would."""

    name = "ros2"
    Options = Ros2OutputOptions

    def __init__(self, options: OutputOptions | None, ctx: OutputContext) -> None:
        super().__init__(options, ctx)
        if not isinstance(self.options, Ros2OutputOptions):
            raise TypeError("ros2 output needs Ros2OutputOptions")
        self.opts: Ros2OutputOptions = self.options
        self._session: Any = None
        self._node: Any = None
        self._map: Any = None
        self._tf_static: Any = None
        self._tf: Any = None
        #: The GIDs and session id noted in :data:`~mapd.ros2.node.own_publishers` while open.
        self._own: tuple[list[bytes], str] | None = None
        self._lock = threading.Lock()
        #: Tries again while no router answers (a client whose rmw_zenohd is not up yet), and the
        #: newest global map meanwhile
        self.retry = SessionRetry("ros2 output")
        self._waiting: GlobalUpdate | None = None
        # Held while the session opens or closes and while anything is put: a map published as the
        # session opens goes out once, after any older one; a session opened after close() closes.
        self._put_lock = threading.RLock()
        self._closing = False
        self._static_sent: dict[str, Pose2D] | None = None
        #: Robots whose map frame went out under ``frame`` (kept in FRAMES_FILE across restarts).
        self._shown: set[str] = set()
        self.unplaced = 0
        self._pose_sent: dict[str, float] = {}
        self.maps = 0
        self.static_msgs = 0
        self.tf_msgs = 0
        self.bytes = 0

    async def start(self) -> None:
        try:
            await asyncio.to_thread(self._open)
        except UnreachableError as exc:
            # A client whose rmw_zenohd is not up yet: the daemon runs, and the newest global map
            # goes out (latched) once the session opens.
            self.retry.begin(exc, self._open_and_flush)

    def _open_and_flush(self) -> None:
        """On a worker thread: open, then publish the map that waited (a cancelled wait does not
        stop this thread: ``_open`` closes what it opened if the output closed meanwhile)."""
        with self._put_lock:
            self._open()
            if self._map is None:
                return  # closed meanwhile
            self.retry.opened()
            waiting, self._waiting = self._waiting, None
            if waiting is not None:
                self.publish(waiting)

    def _open(self) -> None:
        """Open the session and declare the node and its publishers (nothing once closing)."""
        with self._put_lock:
            if not self._closing:
                self._open_session()

    def _open_session(self) -> None:
        from mapd.ros2 import cdr
        from mapd.ros2.node import Ros2Node, own_publishers

        o = self.opts
        self._shown = self._load_shown()
        self._session = cdr.open_session_for(o)
        try:
            rmw_format = o.format == "rmw_zenoh"
            self._node = Ros2Node(
                self._session,
                o.node,
                namespace=o.namespace if rmw_format else "",
                domain=o.domain_id,
                distro=o.distro,
                key_format=o.format,
                bridge_namespace="" if rmw_format else o.namespace,
            )
            self._map = self._node.publisher(o.topic, cdr.MSGTYPE, rmw.LATCHED)
            if o.tf:
                self._tf_static = self._node.publisher("/tf_static", TF_TYPE, rmw.LATCHED)
                self._tf = self._node.publisher("/tf", TF_TYPE, rmw.TF_QOS)
            # Before the first sample: a ros2 source in this daemon tells them by these and drops
            # them (a robot's source on the same topic took the global map as its own map).
            pubs = (self._map, self._tf_static, self._tf)
            self._own = ([p.gid for p in pubs if p is not None and p.gid], self._node.zid)
            own_publishers.add(gids=self._own[0], zid=self._own[1])
        except BaseException:
            self._close()
            raise

    def publish(self, update: GlobalUpdate) -> None:
        with self._put_lock:
            if self._map is None:
                self._waiting = update  # the newest, for when the session opens
                return
            self._waiting = None  # (an older one that waited is superseded)
            self._publish(update)

    def _publish(self, update: GlobalUpdate) -> None:
        from mapd.ros2 import cdr

        payload = cdr.encode(update.grid, frame_id=self.opts.frame, stamp=update.stamp)
        self._map.put(payload)
        self.maps += 1
        self.bytes += len(payload)
        if self._tf_static is not None:
            self._send_static(update.frames, update.stamp)
        if update.poses:
            self._send_poses(update)

    def publish_poses(self, update: PoseUpdate) -> None:
        with self._put_lock:
            if self._tf_static is not None and update.frames:
                self._send_static(update.frames, max((p.stamp for p in update.poses.values()), default=0.0))
            self._send_poses(update)

    def _send_static(self, frames: dict[str, Pose2D], stamp: float) -> None:
        with self._lock:
            items, gone, shown = tf_static(self.opts.tf_frames(), frames, self._shown, stamp)
            if frames == self._static_sent or not (frames or gone):
                return
            self._static_sent = dict(frames)
            grown, self._shown = shown != self._shown, shown
        from mapd.ros2 import cdr

        path = self._frames_file()
        if grown and path is not None:  # before the message: a crash after it must not forget one
            save_shown(path, sorted(shown), "ros2 output")
        self._tf_static.put(cdr.encode_tf(items))
        self.static_msgs += 1
        self.unplaced = len(gone)

    def _frames_file(self) -> Path | None:
        d = self.ctx.state_dir
        return None if d is None or not self.opts.unplaced_frame else d / FRAMES_FILE

    def _load_shown(self) -> set[str]:
        """The robots whose frames an earlier run sent (none when the file is missing or unreadable)."""
        path = self._frames_file()
        return set() if path is None else load_shown(path, "ros2 output")

    def ros2_names(self) -> Ros2Names:
        """The global map's topic and the frames set in ``[output.ros2]``."""
        return Ros2Names(self.opts.ros_topic(), self.opts.tf_frames())

    def _send_poses(self, update: PoseUpdate | GlobalUpdate) -> None:
        from mapd.ros2 import cdr

        o = self.opts
        if self._tf is None or not o.robot_pose_frame:
            return
        with self._lock:
            items = pose_transforms(update, self._pose_sent, o.robot_map_frame, o.robot_pose_frame)
            self._pose_sent.update(
                {
                    r: sp.stamp
                    for r, sp in update.poses.items()
                    if sp.stamp > self._pose_sent.get(r, float("-inf"))
                }
            )
        if not items:
            return
        self._tf.put(cdr.encode_tf(items))
        self.tf_msgs += 1

    async def close(self) -> None:
        await self.retry.stop()
        await asyncio.to_thread(self._close, True)

    def _close(self, closing: bool = False) -> None:
        from mapd.ros2.node import own_publishers

        with self._put_lock:  # after an open under way on a retry's thread, which then sees this
            self._closing = self._closing or closing
            node, session, own = self._node, self._session, self._own
            self._node = self._session = self._map = self._tf = self._tf_static = self._own = None
        if node is not None:
            node.close()
        if session is not None:
            with contextlib.suppress(Exception):  # already closed; closing is best effort
                session.close()
        if own is not None:  # (after the session: nothing of it is on its way any more)
            own_publishers.remove(gids=own[0], zid=own[1])

    def stats(self) -> dict[str, int | float | str]:
        return {
            "key": self._map.key if self._map is not None else "",
            "maps": self.maps,
            "tf_static": self.static_msgs,
            "unplaced": self.unplaced,
            "tf": self.tf_msgs,
            "bytes": self.bytes,
            **self.retry.stats(),
        }
