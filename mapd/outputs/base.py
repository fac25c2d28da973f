"""The output interface: a plugin that takes every new global map, off the event loop.

The daemon builds each configured output with its validated options and an
:class:`OutputContext`, awaits :meth:`Output.start`, then calls :meth:`Output.publish` with a
:class:`GlobalUpdate` each time the fusion worker makes a new global map. ``publish`` runs on the
daemon's output thread, one call at a time and in order, never on the event loop: it may block (a
file write, a zenoh put). An output that fails logs and is called again with the next update; it
never stops the daemon.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from pydantic import BaseModel, ConfigDict

from mapd.grid import OccupancyGrid, Pose2D, StampedPose
from mapd.identity import Identity
from mapd.ros2.tf import Ros2Names


class OutputOptions(BaseModel):
    """Options an output reads from its ``[output.<name>]`` table. Subclass to add fields."""

    model_config = ConfigDict(extra="forbid")


@dataclass(frozen=True)
class GlobalUpdate:
    """One new global map: the grid (in the fleet frame) and where each robot's map frame lies in it."""

    grid: OccupancyGrid
    #: Robot -> its map frame's pose in the fleet frame, for every accepted placement.
    frames: dict[str, Pose2D]
    #: Wall-clock seconds when the map was made.
    stamp: float
    #: Which version of each robot's map the global map holds.
    versions: dict[str, int] = field(default_factory=dict)
    #: The latest known pose of each robot's ``base_link`` in that robot's own map frame.
    poses: dict[str, StampedPose] = field(default_factory=dict)


@dataclass(frozen=True)
class PoseUpdate:
    """New robot poses (more often than maps): each robot's ``base_link`` in its own map frame.

    ``frames`` is the latest placement of each robot's map frame in the fleet frame, so an output can
    put a pose in the fleet frame as ``compose(frames[robot], poses[robot].pose)``.
    """

    poses: dict[str, StampedPose]
    frames: dict[str, Pose2D]


@dataclass(frozen=True)
class OutputContext:
    """What the daemon hands every output."""

    robot: str
    fleet: str
    state_dir: Path | None = None
    #: This robot's signing key (outputs that send the map to others sign with it), if any.
    identity: Identity | None = None


class Output(ABC):
    """A pluggable place the global map goes. Subclasses set ``name`` and ``Options``."""

    name: ClassVar[str]
    Options: ClassVar[type[OutputOptions]] = OutputOptions

    def __init__(self, options: OutputOptions | None, ctx: OutputContext) -> None:
        self.options = options if options is not None else self.Options()
        self.ctx = ctx

    async def start(self) -> None:  # noqa: B027 - optional hook
        """Open what the output needs (a session, a folder); one clear MapdError line on failure."""

    @abstractmethod
    def publish(self, update: GlobalUpdate) -> None:
        """Take a new global map (blocking is fine: called on the output thread)."""

    def publish_poses(self, update: PoseUpdate) -> None:  # noqa: B027 - optional hook
        """Take new robot poses (on the output thread, like :meth:`publish`); default: ignore them."""

    def publish_robot_map(self, grid: OccupancyGrid, stamp: float) -> None:  # noqa: B027 - optional hook
        """Take one robot's map as the daemon now holds it (its own, or a peer's it accepted;
        ``grid.robot`` names it; ``stamp``: wall-clock seconds when the daemon took it), on the
        output thread like :meth:`publish`, the newest per robot; default: ignore it."""

    async def close(self) -> None:  # noqa: B027 - optional hook
        """Release everything promptly."""

    def stats(self) -> dict[str, int | float | str]:
        """Counters for ``mapd status``."""
        return {}

    def ros2_names(self) -> Ros2Names | None:
        """The ROS 2 graph names this output publishes under (the global map's topic, the TF
        frames), which the MCAP recording then uses too; None (the default): it publishes on none."""
        return None
