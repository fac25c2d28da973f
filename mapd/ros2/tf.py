"""The TF frames mapd names, shared by the ``ros2`` output and the MCAP recording.

REP-105: the fleet frame (``frame``, m-explore's ``world_frame``) is the parent of each robot's map
frame on ``/tf_static`` (its placement), and each robot's pose moves its ``base_link`` (or the frame
``robot_pose_frame`` names) under its map frame on ``/tf``. A robot no longer placed moves under
``unplaced_frame``, off the fleet's tree: tf2 keeps a static transform for as long as it runs, so a
placement only left out of the next message would stay in force. Pure: names and tuples only.
"""

from __future__ import annotations

from dataclasses import dataclass

from mapd.grid import Pose2D


@dataclass(frozen=True)
class TfFrames:
    """The frame names of ``[output.ros2]`` (its defaults here), which the MCAP recording uses too:
    a bag played into the graph the output publishes on must agree with it."""

    frame: str = "map"
    robot_map_frame: str = "{robot}/map"
    robot_pose_frame: str = "{robot}/base_link"
    unplaced_frame: str = "mapd/unplaced"


def robot_frame(template: str, robot: str) -> str:
    """``template`` with ``{robot}`` replaced (plain replacement: a config's braces never reach
    ``str.format``)."""
    return template.replace("{robot}", robot)


def static_transforms(
    frame: str, frames: dict[str, Pose2D], stamp: float, map_frame: str = "{robot}/map"
) -> list[tuple[str, str, Pose2D, float]]:
    """``frame -> <robot>/map`` (``map_frame``) for each placed robot, by name."""
    return [(frame, robot_frame(map_frame, robot), pose, stamp) for robot, pose in sorted(frames.items())]


def unplaced_transforms(
    unplaced: str, robots: list[str], stamp: float, map_frame: str = "{robot}/map"
) -> list[tuple[str, str, Pose2D, float]]:
    """``unplaced -> <robot>/map`` (``map_frame``) for each robot no longer placed, by name."""
    return [(unplaced, robot_frame(map_frame, r), Pose2D(), stamp) for r in sorted(robots)]
