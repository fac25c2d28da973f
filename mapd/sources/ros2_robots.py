"""The ``ros2`` source's robots: which discovered robots it takes, and where each one started.

With ``discover_robots = true`` (:mod:`mapd.sources.ros2`) any session on the zenoh network can
publish ``/<name>/<robot_map_topic>``, or a liveliness token, naming any robot. These rules, and the
bookkeeping they keep, decide which names become robots: a valid name (``ROBOT_NAME``, matched in
full) that starts with ``robot_namespace``; never this robot's own name (its maps would be signed and
sent to the fleet as this robot's); at most ``max_robots`` of them, counted from a robot's first
sample or publisher token, a place given back when a robot that never sent a map withdraws its
publisher. Names refused are warned about once each, for at most ``MAX_IGNORED_SAID`` names. With
``known_init_poses = true`` (m-explore's default) a robot's maps are merged only once ``init_poses``
has its ``[x, y, yaw]``, which :meth:`Ros2Robots.robot_poses` gives the daemon; with ``false`` the
daemon estimates placements.

They are apart from the zenoh plumbing (session, subscribers, tokens, the inbox zenoh's threads
fill) because they are policy over names and counters that does no I/O: :class:`Ros2Robots` is a
mixin of :class:`~mapd.sources.ros2.Ros2Source`, whose ``__init__`` sets up the state it reads.
"""

from __future__ import annotations

import logging

from mapd.grid import Pose2D
from mapd.ros2 import rmw
from mapd.sources.base import SourceContext
from mapd.sources.ros2_options import ROBOT_NAME, Ros2Options

__all__ = ["MAX_IGNORED_SAID", "Ros2Robots"]

# The source's logger: these warnings keep the name they were always logged under.
log = logging.getLogger("mapd.sources.ros2")

#: Robots past ``max_robots`` named in a warning, at most (then quietly ignored): each name is one
#: line and one entry kept, and anyone on the ROS graph can make up names.
MAX_IGNORED_SAID = 64


class Ros2Robots:
    """Which robots a ``ros2`` source takes, and which of their maps wait for an initial pose."""

    # The source's state these rules read and keep (set up by Ros2Source.__init__).
    opts: Ros2Options
    ctx: SourceContext
    _pending: dict[str, tuple[str, bytes]]
    _robots: dict[str, int]
    _taken: set[str]
    _waiting_pose: set[str]
    _ignored: set[str]

    def robot_poses(self) -> dict[str, Pose2D]:
        """Known initial poses of the robots whose maps this source yields (``init_poses``)."""
        if not (self.opts.discover_robots and self.opts.known_init_poses):
            return {}
        return {r: Pose2D(*p) for r, p in self.opts.init_poses.items()}

    def robot_of_key(self, key: str) -> str | None:
        """The robot a data key belongs to (discovery), or this robot; None for a robot not taken."""
        o = self.opts
        if not o.discover_robots:
            return self.ctx.robot
        parts = key.split("/")
        if o.key_format == "rmw_zenoh":
            robot = parts[1] if len(parts) > 1 else ""
        else:
            robot = parts[len([p for p in o.namespace.strip("/").split("/") if p])] if parts else ""
        return self._accept_robot(robot)

    def robot_of_topic(self, topic: str) -> str | None:
        """The robot of a fully qualified topic ``/<robot>/<robot_map_topic>``, if it is one taken."""
        parts = topic.strip("/").split("/")
        if len(parts) != 2 or parts[1] != rmw.check_name(self.opts.robot_map_topic):
            return None
        return self._accept_robot(parts[0])

    def _accept_robot(self, robot: str) -> str | None:
        o = self.opts
        # fullmatch: the pattern's $ let "robot1\n" through, a robot and a TF frame with a newline.
        if not ROBOT_NAME.fullmatch(robot) or not robot.startswith(o.robot_namespace):
            return None
        if robot == self.ctx.robot:
            # Its maps would be taken as this robot's own, signed and sent to the fleet as such.
            if robot not in self._ignored:
                self._ignored.add(robot)
                log.warning("ros2 source: ignoring a robot named %s, as this robot is", robot)
            return None
        # A robot counts from its first sample or token, not its first map that decodes (nor its
        # init pose): names whose payloads never decode, or that wait for a pose, were kept for
        # ever without bound, in every key format.
        if robot not in self._taken and len(self._taken) >= o.max_robots:
            if robot not in self._ignored and len(self._ignored) < MAX_IGNORED_SAID:
                self._ignored.add(robot)  # said once a name, for as many names as are worth saying
                log.warning("ros2 source: already %d robots; ignoring %s", o.max_robots, robot)
            return None
        self._taken.add(robot)
        return robot

    def _publisher_gone(self, topic: str) -> None:
        """A robot's map publisher left: a robot that never sent a map no longer holds a place
        (tokens made up and withdrawn held every place for ever, the real robots refused)."""
        parts = topic.strip("/").split("/")
        robot = parts[0] if len(parts) == 2 else ""
        if robot in self._taken and robot not in self._robots and robot not in self._pending:
            self._taken.discard(robot)
            self._waiting_pose.discard(robot)

    def _waiting_for_pose(self, robot: str) -> bool:
        o = self.opts
        if not (o.discover_robots and o.known_init_poses) or robot in o.init_poses:
            return False
        if robot not in self._waiting_pose:
            self._waiting_pose.add(robot)
            log.warning(
                "ros2 source: no init_poses entry for %s (known_init_poses = true); not merged", robot
            )
        return True
