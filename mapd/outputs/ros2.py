"""``[output.ros2]``: the global map and the robots' frames on ROS 2, over zenoh, with no ROS install.

Each global map goes out as ``nav_msgs/msg/OccupancyGrid`` on ``topic`` (default ``/map``) in the
fleet frame ``frame`` (default ``map``; m-explore's ``world_frame``), exactly as an rmw_zenoh
publisher with reliable, transient-local, depth-1 QoS sends it: on rmw_zenoh's data key, with its
attachment, announced by node and publisher liveliness tokens, through an advanced publisher whose
cache gives a late subscriber (RViz, Nav2) the current map. The rules (keys, tokens, QoS strings,
GIDs, type hashes per ``distro``) are :mod:`mapd.ros2.rmw`'s; the zenoh side is
:mod:`mapd.ros2.node`. The table's options and their checks are
:mod:`mapd.outputs.ros2_options`.

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

With ``robot_map_topic`` set (``"/{robot}/map"``, say) each robot's map as this daemon holds it, its
own and every peer's it accepted, goes out too, on that robot's topic in its ``robot_map_frame``
(latched, as the global map), so RViz can show each robot's map beside the fleet's, placed by
``/tf_static``. A robot whose name is none rcl accepts (robot names may hold ``-`` or begin with a
digit) is said once and left out.

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
import logging
import threading
from pathlib import Path
from typing import Any

from mapd.errors import UnreachableError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, OutputOptions, PoseUpdate
from mapd.outputs.retry import SessionRetry
from mapd.outputs.ros2_options import Ros2OutputOptions
from mapd.outputs.ros2_options import robot_of_frame as robot_of_frame  # importable from here as before
from mapd.ros2 import rmw
from mapd.ros2.tf import TF_TYPE, Ros2Names, load_shown, robot_frame, save_shown, tf_static

log = logging.getLogger("mapd.outputs.ros2")

#: In the state directory: the robots whose map frames went out on /tf_static.
FRAMES_FILE = "ros2_frames.json"
#: Robots' maps kept for a session not open yet, and robot publishers at most (the roster bounds
#: the robots a daemon holds maps of; this bounds them even so).
MAX_ROBOT_MAPS = 1024


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
        #: robot_map_topic: each robot's publisher, its newest map while the session is not open,
        #: the robots whose names are no ROS names (said once), and the maps sent
        self._robot_pubs: dict[str, Any] = {}
        self._robot_waiting: dict[str, tuple[OccupancyGrid, float]] = {}
        self._unnamed: set[str] = set()
        self.robot_maps = 0
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
            robots, self._robot_waiting = self._robot_waiting, {}
            for grid, stamp in robots.values():
                self._publish_robot(grid, stamp)

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

    def publish_robot_map(self, grid: OccupancyGrid, stamp: float) -> None:
        if not self.opts.robot_map_topic:
            return
        with self._put_lock:
            if self._map is None:  # the newest of each robot, for when the session opens
                if grid.robot in self._robot_waiting or len(self._robot_waiting) < MAX_ROBOT_MAPS:
                    self._robot_waiting[grid.robot] = (grid, stamp)
                return
            self._publish_robot(grid, stamp)

    def _publish_robot(self, grid: OccupancyGrid, stamp: float) -> None:
        from mapd.ros2 import cdr

        robot, o = grid.robot, self.opts
        pub = self._robot_pubs.get(robot)
        if pub is None:
            if robot in self._unnamed or len(self._robot_pubs) >= MAX_ROBOT_MAPS:
                return
            try:
                o.robot_topic(robot)
            except ValueError as exc:
                self._unnamed.add(robot)
                log.warning("ros2 output: %s; its map is not published on ROS 2 (robot_map_topic)", exc)
                return
            pub = self._robot_pubs[robot] = self._node.publisher(
                robot_frame(o.robot_map_topic, robot), cdr.MSGTYPE, rmw.LATCHED
            )
            if self._own is not None and pub.gid:  # before its first sample, as the others
                from mapd.ros2.node import own_publishers

                self._own[0].append(pub.gid)
                own_publishers.add(gids=[pub.gid], zid=self._own[1])
        payload = cdr.encode(grid, frame_id=robot_frame(o.robot_map_frame, robot), stamp=stamp)
        pub.put(payload)
        self.robot_maps += 1
        self.bytes += len(payload)

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
        o = self.opts
        if not o.robot_map_topic:  # (the recording keeps its own robots' topics: /{robot}/map)
            return Ros2Names(o.ros_topic(), o.tf_frames())
        return Ros2Names(o.ros_topic(), o.tf_frames(), o.fq(o.robot_map_topic))

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
            self._robot_pubs = {}  # (declared on the node: closed with it)
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
            "robot_maps": self.robot_maps,
            "robot_topics": len(self._robot_pubs),
            "tf_static": self.static_msgs,
            "unplaced": self.unplaced,
            "tf": self.tf_msgs,
            "bytes": self.bytes,
            **self.retry.stats(),
        }
