"""``[output.ros2]``: the options of the ``ros2`` output (:mod:`mapd.outputs.ros2`), checked.

Which topic, frames, ROS 2 identity and key format, and how to reach the zenoh network; the checks
that keep the fleet frame, the robots' frames and ``unplaced_frame`` apart; and the check, against
the chosen ``[source.ros2]``, that the global map does not go out where the source takes maps in.
Apart from the publisher so that what the table accepts can be read (and tested) without the
sessions, locks and messages that publish.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar, Literal

from pydantic import BaseModel, Field, ValidationInfo, field_validator, model_validator

from mapd.config import NAME_PATTERN
from mapd.config.endpoints import ZenohEndpoints
from mapd.outputs.base import OutputOptions
from mapd.ros2 import rmw
from mapd.ros2.tf import TfFrames, check_robot_frame, robot_frame
from mapd.ros2.zenoh_config import ZenohConfigFiles


class Ros2OutputOptions(ZenohEndpoints, ZenohConfigFiles, OutputOptions):
    """``[output.ros2]``: topic, frames, ROS 2 identity, key format and how to reach zenoh."""

    beside_config: ClassVar[tuple[str, ...]] = ("zenoh_config",)

    topic: str = Field(default="/map", description="topic of the global nav_msgs/msg/OccupancyGrid")
    robot_map_topic: str = Field(
        default="",
        description="each robot's map as this daemon holds it (its own and its peers'), as "
        "nav_msgs/msg/OccupancyGrid in its robot_map_frame; {robot} is its name (e.g. '/{robot}/map'; "
        "the MCAP recording's channels follow it); empty: none",
    )
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

    @field_validator("robot_map_topic")
    @classmethod
    def _check_robot_map_topic(cls, v: str) -> str:
        if v == "":
            return v
        if "{robot}" not in v:
            raise ValueError(f"{v!r} must name the robot with {{robot}}: one topic each")
        try:
            rmw.check_topic_name(robot_frame(v, "robot0"))
        except ValueError as exc:
            raise ValueError(f"{v!r} with robot0 for {{robot}}: {exc}") from None
        return v

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
        return check_robot_frame(v)

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
        if self.robot_map_topic:  # compared fully qualified: a relative one is under the namespace
            robot = robot_of_frame(self.fq(self.robot_map_topic), self.ros_topic())
            if robot is not None:
                raise ValueError(
                    f"topic {self.topic!r} is the robot_map_topic of a robot named {robot!r} "
                    f"({self.robot_map_topic!r}): the global map and the robots' maps need topics of their own"
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

    def robot_topic(self, robot: str) -> str:
        """Robot ``robot``'s map topic, fully qualified (as :meth:`ros_topic`); ValueError when its
        name is none rcl accepts (robot names may hold ``-`` or begin with a digit; ROS names not).
        Only with ``robot_map_topic`` set."""
        topic = robot_frame(self.robot_map_topic, robot)
        try:
            rmw.check_topic_name(topic)
        except ValueError as exc:
            raise ValueError(f"robot {robot}: {exc}") from None
        return self.fq(topic)

    def ros_topic(self) -> str:
        """The global map's fully qualified topic in the ROS graph."""
        return self.fq(self.topic)

    def fq(self, topic: str) -> str:
        """``topic`` (a ``{robot}`` template too) fully qualified in the ROS graph: under
        ``namespace`` with rmw_zenoh; with ``ros2dds`` the namespace is the bridge's, on the zenoh
        side only."""
        return rmw.fq_topic(topic, self.namespace if self.format == "rmw_zenoh" else "")

    def map_key_expr(self, topic: str | None = None) -> str:
        """The zenoh key the global map (or ``topic``) is published on (any type hash: ``*``)."""
        from mapd.ros2.cdr import MSGTYPE

        topic = self.topic if topic is None else topic
        if self.format == "rmw_zenoh":
            return rmw.data_key(
                rmw.fq_topic(topic, self.namespace), MSGTYPE, domain=self.domain_id, hash_="*"
            )
        return rmw.bridge_key(rmw.fq_topic(topic), namespace=self.namespace)

    def robot_maps_key_expr(self) -> str | None:
        """The zenoh key expression every robot's map is published under (``{robot}`` as a
        wildcard), or None without ``robot_map_topic``."""
        if not self.robot_map_topic:
            return None
        import zenoh  # (only where a config is checked, as rmw.key_exprs_intersect)

        # A name no config spells stands in while the key is built (and its names checked), then
        # zenoh's wildcard for any part of a chunk ("$*"; alone in a chunk it becomes "*").
        stand_in = "mapd_robot_stand_in_"
        key = self.map_key_expr(robot_frame(self.robot_map_topic, stand_in))
        return str(zenoh.KeyExpr.autocanonize(key.replace(stand_in, "$*")))

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
        robots = self.robot_maps_key_expr()
        if robots is not None and rmw.key_exprs_intersect(source.map_key_expr(), robots):
            raise ValueError(
                f"robot_map_topic: {self.robot_map_topic!r} ({robots!r}) is where [source.ros2] takes "
                "maps from: mapd would read the robots' maps it publishes back in as maps; publish "
                'them elsewhere, e.g. robot_map_topic = "/mapd/{robot}/map"'
            )
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
