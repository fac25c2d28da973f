"""``[source.ros2]``: the options of the ``ros2`` map source (:mod:`mapd.sources.ros2`), checked.

Which topic and key format, how to reach the zenoh network, the robot's pose topic, and, for a base
station merging several robots' maps, which robots to take and where each one started.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import ClassVar, Literal

from pydantic import Field, field_validator, model_validator

from mapd.config import NAME_PATTERN
from mapd.config.endpoints import ZenohEndpoints
from mapd.ros2 import cdr as ros2cdr
from mapd.ros2 import rmw
from mapd.ros2.zenoh_config import ZenohConfigFiles
from mapd.sources.base import SourceOptions, check_start_pose, is_pose
from mapd.sources.ros2_pose import PoseType

#: A robot name mapd takes from a discovered topic (as ``[robot] name`` in config.py).
ROBOT_NAME = re.compile(NAME_PATTERN)


class Ros2Options(ZenohEndpoints, ZenohConfigFiles, SourceOptions):
    """``[source.ros2]``: which topic, which key format, and how to reach the zenoh network."""

    beside_config: ClassVar[tuple[str, ...]] = ("zenoh_config",)

    topic: str = Field(default="/map", description="ROS 2 topic of the nav_msgs/msg/OccupancyGrid")
    key_format: Literal["rmw_zenoh", "ros2dds"] = Field(
        default="rmw_zenoh", description="rmw_zenoh keys, or zenoh-bridge-ros2dds keys"
    )
    domain: int = Field(default=0, ge=0, le=232, description="ROS_DOMAIN_ID (rmw_zenoh keys)")
    namespace: str = Field(default="", description="bridge namespace (ros2dds keys)")
    key: str | None = Field(default=None, description="subscribe to this key expression instead")
    history: bool = Field(default=True, description="ask publishers for their cached map on start")
    snap_origin: bool = Field(
        default=False,
        description="move each map's origin, by at most half a cell, onto the first map's cell lattice: "
        "a SLAM whose origin moves by a fraction of a cell as the map grows (slam_toolbox) then sends "
        "deltas, not whole maps",
    )
    mode: Literal["peer", "client"] = Field(default="client", description="zenoh session mode")
    connect: list[str] = Field(
        default_factory=lambda: ["tcp/127.0.0.1:7447"], description="zenoh endpoints to connect to"
    )
    listen: list[str] = Field(default_factory=list, description="zenoh endpoints to listen on")
    multicast_scouting: bool = Field(default=False, description="find peers by multicast")
    zenoh_config: Path | None = Field(default=None, description="a zenoh JSON5 config to start from")
    start_pose: list[float] | None = Field(
        default=None, description="[x, y, yaw] of the ROS map frame in the fleet frame, when known"
    )
    node: str = Field(default="mapd_source", description="the ROS 2 node name mapd's tokens announce")
    distro: rmw.Distro = Field(default="jazzy", description="ROS 2 distro (type hash in tokens)")
    discover_robots: bool = Field(
        default=False, description="take /<robot>/<robot_map_topic> of every robot (map_merge)"
    )
    robot_map_topic: str = Field(default="map", description="each robot's map topic, under its namespace")
    robot_namespace: str = Field(default="", description="only robots whose namespace starts with this")
    known_init_poses: bool = Field(
        default=True, description="merge a robot only with its init_poses entry (false: estimate)"
    )
    init_poses: dict[str, list[float]] = Field(
        default_factory=dict, description="robot -> [x, y, yaw] of its map frame in the fleet frame"
    )
    max_robots: int = Field(default=32, ge=1, le=256, description="robots taken at most")
    pose_topic: str | None = Field(default=None, description="the robot's pose topic, e.g. /amcl_pose")
    pose_type: PoseType = Field(default="PoseWithCovarianceStamped", description="its geometry_msgs type")
    pose_frame: str = Field(default="map", min_length=1, description="poses in other frames are ignored")

    @property
    def yields_own_map(self) -> bool:
        return not self.discover_robots

    def map_key_expr(self) -> str:
        """The zenoh key expression the source takes maps from: ``key``, the topic's key, or (with
        ``discover_robots``) every robot's ``/<robot>/<robot_map_topic>``."""
        if self.discover_robots:
            topic = rmw.check_name(self.robot_map_topic)
            if self.key_format == "rmw_zenoh":
                return f"{self.domain}/*/{topic}/{rmw.dds_type(ros2cdr.MSGTYPE)}/*"
            ns = self.namespace.strip("/")
            return (f"{ns}/" if ns else "") + f"*/{topic}"
        return self.key or ros2cdr.key_for(
            self.topic, self.key_format, domain=self.domain, namespace=self.namespace, subscribe=True
        )

    @field_validator("topic", "robot_map_topic")
    @classmethod
    def _check_topic(cls, v: str) -> str:
        # rcl's grammar, as [output.ros2] has it: a name no ROS node can spell is never published
        return rmw.check_topic_name(v)

    @field_validator("robot_map_topic")
    @classmethod
    def _one_name(cls, v: str) -> str:
        # Discovery takes /<robot>/<robot_map_topic> with the robot as the first part: a deeper
        # name ('slam/map') is a topic rcl allows, on which no robot would ever be taken.
        if "/" in v.strip("/"):
            raise ValueError(f"'{v}' must be one name under each robot's namespace (as 'map')")
        return v

    @field_validator("namespace")
    @classmethod
    def _check_namespace(cls, v: str) -> str:
        return rmw.check_namespace(v)

    @field_validator("init_poses")
    @classmethod
    def _check_init_poses(cls, v: dict[str, list[float]]) -> dict[str, list[float]]:
        for robot, pose in v.items():
            if not is_pose(pose):
                raise ValueError(f"init pose of '{robot}' must be [x, y, yaw] (m, m, rad)")
        return v

    @field_validator("pose_topic")
    @classmethod
    def _check_pose_topic(cls, v: str | None) -> str | None:
        return v if v is None else rmw.fq_topic(rmw.check_topic_name(v))

    @model_validator(mode="after")
    def _one_robot_pose(self) -> Ros2Options:
        if self.pose_topic is not None and self.discover_robots:
            raise ValueError(
                "pose_topic is for one robot's source; with discover_robots = true the robots' poses "
                "are not this daemon's to send (each robot's mapd sends its own)"
            )
        return self

    @field_validator("start_pose")
    @classmethod
    def _check_pose(cls, v: list[float] | None) -> list[float] | None:
        return check_start_pose(v)
