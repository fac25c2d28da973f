"""The map-source interface: an async iterator of the robot's own map versions."""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from mapd.data import data_dir
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid, Pose2D, StampedPose

if TYPE_CHECKING:
    from mapd.config import MapdConfig


def is_pose(v: list[float]) -> bool:
    """Whether an option's ``v`` is a pose: ``[x, y, yaw]`` (m, m, rad), all finite."""
    return len(v) == 3 and all(math.isfinite(x) for x in v)


def check_start_pose(v: list[float] | None) -> list[float] | None:
    """A ``start_pose`` option: None, or a pose (:func:`is_pose`)."""
    if v is not None and not is_pose(v):
        raise ValueError("start_pose must be [x, y, yaw] (m, m, rad)")
    return v


class SourceOptions(BaseModel):
    """Options a source reads from its ``[source.<name>]`` table. Subclass to add fields."""

    model_config = ConfigDict(extra="forbid")

    @property
    def yields_own_map(self) -> bool:
        """False for a source that yields only other robots' maps (a base station's, say ros2 with
        ``discover_robots``): the daemon then has no map frame of its own (as with source ``none``)."""
        return True


class FleetSliceOptions(SourceOptions):
    """Options of a source that drives robot ``index`` of ``robots`` (a shared log or simulated building)."""

    robots: int = Field(default=1, ge=1, le=64, description="robots sharing the log or the building")
    index: int = Field(default=0, ge=0, description="which of them this daemon is (0-based)")

    @model_validator(mode="after")
    def _check_index(self) -> FleetSliceOptions:
        if self.index >= self.robots:
            raise ValueError(f"index {self.index} must be below robots ({self.robots})")
        return self


@dataclass
class SourceContext:
    """What the daemon hands every source."""

    robot: str
    max_cells: int = DEFAULT_MAX_CELLS
    #: Folder of shared data (MAPD_DATA), for sources that read logs or maps by relative path.
    data_dir: Path | None = None
    #: Folder of the config file: a relative path not found in ``data_dir`` is taken from here.
    config_dir: Path | None = None

    @classmethod
    def of(cls, cfg: MapdConfig) -> SourceContext:
        """The context the daemon hands the source ``cfg`` names (its robot, ``limits.max_cells``,
        the shared data folder, the config's folder): the source's ``check_with_config`` looks up
        its files with it, as the source will at start."""
        return cls(
            robot=cfg.robot.name, max_cells=cfg.limits.max_cells, data_dir=data_dir(), config_dir=cfg.folder
        )

    def resolve(self, p: Path) -> Path:
        """A path an option names: as is when absolute, else in the data folder when it is there,
        else beside the config (the daemon's cwd is "/" under systemd), else from the cwd."""
        if p.is_absolute():
            return p
        if self.data_dir is not None and (self.data_dir / p).exists():
            return self.data_dir / p
        if self.config_dir is not None:
            return self.config_dir / p
        return p


class MapSource(ABC):
    """Yields :class:`OccupancyGrid` versions of one robot's map, in that robot's map frame.

    Versions strictly increase (per robot). ``robot`` is set to the context's robot id, or, for a
    source that carries several robots' maps, to the robot each map belongs to. A source that meets bad
    input (a bad log line, a half-written file) logs it, counts it in :meth:`stats` and goes on.
    """

    name: ClassVar[str]
    Options: ClassVar[type[SourceOptions]] = SourceOptions

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        self.options = options if options is not None else self.Options()
        self.ctx = ctx

    @abstractmethod
    def maps(self) -> AsyncIterator[OccupancyGrid]:
        """The stream of map versions; ends when the source is exhausted (a log replay)."""

    def start_pose(self) -> Pose2D | None:
        """Where this robot's map frame sits in the fleet/world frame, when the source knows it
        (a simulator or a log with corrected poses); ``None`` otherwise."""
        return None

    def pose(self) -> StampedPose | None:
        """Where the robot's ``base_link`` is now, in its own map frame, and when that was (wall
        clock); ``None`` when the source does not know (a map file). Polled by the daemon at its
        pose rate, so it must be cheap and never block."""
        return None

    def robot_poses(self) -> dict[str, Pose2D]:
        """Known map-frame poses (in the fleet frame) of other robots whose maps this source yields.

        A source may yield maps whose ``robot`` is not the daemon's own (several robots' maps on one
        machine); the daemon fuses those as maps received from peers, placed by these poses."""
        return {}

    def stats(self) -> dict[str, int | float | str]:
        """Counters for ``mapd status`` (scans, skipped lines, last error ...)."""
        return {}

    async def close(self) -> None:  # noqa: B027 - optional hook
        """Release files, sessions or threads."""
