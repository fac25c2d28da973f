"""The TF frames mapd names, shared by the ``ros2`` output and the MCAP recording.

REP-105: the fleet frame (``frame``, m-explore's ``world_frame``) is the parent of each robot's map
frame on ``/tf_static`` (its placement), and each robot's pose moves its ``base_link`` (or the frame
``robot_pose_frame`` names) under its map frame on ``/tf``. A robot no longer placed moves under
``unplaced_frame``, off the fleet's tree: tf2 keeps a static transform for as long as it runs, so a
placement only left out of the next message would stay in force. Pure (names and tuples), but for
:func:`load_shown` and :func:`save_shown`, which keep the robots whose frames went out across a
restart in a small JSON file.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from pathlib import Path

from mapd.config import NAME_PATTERN
from mapd.errors import MapdError
from mapd.files import atomic_write_json
from mapd.files.reading import read_json_capped
from mapd.grid import Pose2D

log = logging.getLogger(__name__)

#: Robot names a shown-frames file keeps at the most (a fleet's roster is far smaller), and its size cap.
MAX_SHOWN = 4096
MAX_SHOWN_FILE_BYTES = 1 << 20

#: The ROS type of /tf and /tf_static messages.
TF_TYPE = "tf2_msgs/msg/TFMessage"
#: (parent, child, pose, stamp): one transform of a TFMessage.
Transform = tuple[str, str, Pose2D, float]


@dataclass(frozen=True)
class TfFrames:
    """The frame names of ``[output.ros2]`` (its defaults here), which the MCAP recording uses too:
    a bag played into the graph the output publishes on must agree with it."""

    frame: str = "map"
    robot_map_frame: str = "{robot}/map"
    robot_pose_frame: str = "{robot}/base_link"
    unplaced_frame: str = "mapd/unplaced"


@dataclass(frozen=True)
class Ros2Names:
    """The names of the ROS 2 graph an output publishes on (the ``ros2`` output's defaults here): the
    fully qualified topics of the global map and of each robot's map, and the TF frames. The MCAP
    recording uses them, so a bag played into that graph agrees with the output."""

    map_topic: str = "/map"
    frames: TfFrames = field(default_factory=TfFrames)
    #: Each robot's map's fully qualified topic; ``{robot}`` is its name.
    robot_map_topic: str = "/{robot}/map"


def check_robot_frame(template: str) -> str:
    """``template`` when it names one frame per robot (``{robot}`` in it) that tf2 takes as
    written; ValueError with one line otherwise."""
    from mapd.ros2 import rmw

    if "{robot}" not in template:
        raise ValueError(f"{template!r} must name the robot with {{robot}}: one frame each")
    rmw.check_frame_id(robot_frame(template, "robot0"), shown=template)
    return template


def robot_frame(template: str, robot: str) -> str:
    """``template`` with ``{robot}`` replaced (plain replacement: a config's braces never reach
    ``str.format``)."""
    return template.replace("{robot}", robot)


def static_transforms(
    frame: str, frames: dict[str, Pose2D], stamp: float, map_frame: str = "{robot}/map"
) -> list[Transform]:
    """``frame -> <robot>/map`` (``map_frame``) for each placed robot, by name."""
    return [(frame, robot_frame(map_frame, robot), pose, stamp) for robot, pose in sorted(frames.items())]


def unplaced_transforms(
    unplaced: str, robots: list[str], stamp: float, map_frame: str = "{robot}/map"
) -> list[Transform]:
    """``unplaced -> <robot>/map`` (``map_frame``) for each robot no longer placed, by name."""
    return [(unplaced, robot_frame(map_frame, r), Pose2D(), stamp) for r in sorted(robots)]


def tf_static(
    names: TfFrames, placed: dict[str, Pose2D], shown: set[str], stamp: float
) -> tuple[list[Transform], list[str], set[str]]:
    """One latched ``/tf_static`` message: the fleet frame -> each ``placed`` robot's map frame, and
    ``unplaced_frame`` -> the map frame of each robot of ``shown`` (whose frame went out under the
    fleet frame before) that is no longer placed (none with ``unplaced_frame = ""``).

    Returns the transforms, the robots moved off the tree, and ``shown`` with the placed robots
    added: what the next message (and, kept with :func:`save_shown`, the next run) starts from.
    """
    gone = sorted(shown - set(placed)) if names.unplaced_frame else []
    items = static_transforms(names.frame, placed, stamp, names.robot_map_frame)
    items += unplaced_transforms(names.unplaced_frame, gone, stamp, names.robot_map_frame)
    return items, gone, shown | set(placed)


def load_shown(path: Path, who: str) -> set[str]:
    """The robots whose frames an earlier run sent, from ``path`` (none when the file is missing;
    none and one warning naming ``who`` when it is unreadable or damaged)."""
    try:
        doc = read_json_capped(path, MAX_SHOWN_FILE_BYTES)
        robots = doc.get("robots") if isinstance(doc, dict) else None
        if not isinstance(robots, list) or not all(
            isinstance(r, str) and re.fullmatch(NAME_PATTERN, r) for r in robots
        ):
            raise ValueError("no list of robot names under 'robots'")
    except FileNotFoundError:
        return set()
    except (OSError, ValueError, RecursionError, MapdError) as exc:
        # A lost list costs only the moving off of frames an earlier run sent: said, not fatal.
        log.warning("%s: ignoring %s (%s); frames sent before it are not moved off", who, path, exc)
        return set()
    return set(robots[:MAX_SHOWN])


def save_shown(path: Path, robots: list[str], who: str) -> None:
    """Keep ``robots`` in ``path`` for :func:`load_shown` (atomically; a failure is one warning)."""
    try:
        atomic_write_json(path, {"robots": robots[:MAX_SHOWN]})
    except OSError as exc:
        log.warning("%s: cannot write %s: %s", who, path, exc.strerror or exc)
