"""The schema of ``config.toml``: one pydantic model per table, and :class:`MapdConfig` for the file.

Main tables are :class:`Strict` (an unknown key is an error). Sections that pick plugins
(:class:`PluginSection`) allow extra keys: the sub-tables named after plugins, which each plugin
validates with its own options (:mod:`mapd.config.plugin_tables`). Reading the file and resolving
its relative paths is :mod:`mapd.config.loading`'s.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from mapd.config.endpoints import host_problem, split_host_port
from mapd.grid import DEFAULT_MAX_CELLS, MAX_RESOLUTION, MIN_RESOLUTION
from mapd.grid.reprs import short_repr

#: A fleet or robot id: also a zenoh key chunk and a ROS 2 namespace part, so no separators.
NAME_PATTERN = r"^[A-Za-z0-9_\-]{1,32}$"


class Strict(BaseModel):
    """Base for config tables: unknown keys are errors."""

    model_config = ConfigDict(extra="forbid")


class RobotSection(Strict):
    name: str = Field(pattern=NAME_PATTERN, description="this robot's id in the fleet")
    fleet: str = Field(
        default="default", pattern=NAME_PATTERN, description="fleet id; updates from other fleets are dropped"
    )
    key_file: Path | None = Field(
        default=None,
        description="this robot's Ed25519 private key (PEM, from 'mapd keygen'); required unless fleet.allow_unsigned",
    )


class FleetSection(Strict):
    """Who may speak for whom: the roster of robots' public keys, and the link key of the radio."""

    allow_unsigned: bool = Field(
        default=False,
        description="accept and send unsigned messages (no roster needed); must be said in so many words",
    )
    roster: dict[str, str] = Field(
        default_factory=dict,
        description="robot -> 'ed25519:<base64>' public key, as 'mapd keygen' prints it",
    )
    link_key_file: Path | None = Field(
        default=None,
        description="shared secret (16+ bytes, raw or hex) authenticating uwb frames; required on uwb when signed",
    )

    @field_validator("roster")
    @classmethod
    def _check_roster(cls, v: dict[str, str]) -> dict[str, str]:
        for robot in v:
            if not re.fullmatch(NAME_PATTERN, robot):
                raise ValueError(f"roster: '{robot}' is not a valid robot name")
        return v


class LimitsSection(Strict):
    max_cells: int = Field(
        default=DEFAULT_MAX_CELLS, ge=1, description="largest grid accepted from any input"
    )
    max_message_bytes: int = Field(default=8 << 20, ge=1024, description="largest envelope accepted or sent")
    max_peers: int = Field(default=64, ge=1, description="peers tracked at once")
    max_version_jump: int = Field(
        default=1000, ge=1, description="a peer's version may jump this far, plus max_version_rate per second"
    )
    max_version_rate: float = Field(
        default=10.0, ge=0.0, description="map versions per second a peer may make"
    )
    max_growth: float = Field(
        default=4.0,
        ge=1.0,
        le=1e6,
        description="a peer's map may grow to this many times its last one's cells (+1 M)",
    )


class StateSection(Strict):
    dir: Path = Field(default=Path("/var/lib/mapd"), description="state directory (systemd StateDirectory)")
    runtime_dir: Path = Field(default=Path("/run/mapd"), description="control socket dir (RuntimeDirectory)")
    clock_wait_s: float = Field(
        default=0.0,
        ge=0.0,
        le=3600.0,
        description="with a new (or lost) state directory, wait up to this long for the kernel to say "
        "the clock is synchronized before the first own map: the robot's versions start from its "
        "clock, and a clock behind makes them older than those its peers hold (0: do not wait)",
    )


class PluginSection(BaseModel):
    """A section that picks plugins; sub-tables named after plugins hold their options."""

    model_config = ConfigDict(extra="allow")

    def plugin_tables(self) -> dict[str, Any]:
        return dict(self.model_extra or {})

    def table(self, name: str) -> dict[str, Any]:
        value = (self.model_extra or {}).get(name, {})
        return value if isinstance(value, dict) else {}


class SourceSection(PluginSection):
    use: str = Field(default="sim", description="map-source plugin (mapd.sources)")


class CodecSection(PluginSection):
    use: str = Field(default="lossless", description="codec plugin (mapd.codecs)")
    keyframe_every: int = Field(
        default=100,
        ge=1,
        description="send a whole map at least every K coded updates (a backstop: a peer lacking a base "
        "asks for a whole map, and a new or restarted one gets it unasked)",
    )
    measure_quality: bool = Field(
        default=False, description="lossy codecs: decode each update locally and log its PSNR/SSIM"
    )


class OutputSection(PluginSection):
    use: list[str] = Field(
        default_factory=list, description="output plugins fed each new global map (mapd.outputs)"
    )


class TransportsSection(PluginSection):
    use: list[str] = Field(default_factory=list, description="transport plugins to run (mapd.transports)")


class FusionSection(Strict):
    mode: Literal["logodds", "occupied_wins"] = "logodds"
    debounce_s: float = Field(
        default=1.0, ge=0.0, description="wait this long after an update before re-merging"
    )
    min_confidence: float = Field(
        default=0.5, ge=0.0, le=1.0, description="accept estimates at or above this"
    )
    min_agreement: float = Field(
        default=0.8, ge=0.0, le=1.0, description="overlap agreement needed to accept"
    )
    poses: dict[str, list[float] | Literal["estimate"]] = Field(
        default_factory=dict,
        description="robot -> [x m, y m, yaw rad] of its map frame in the fleet frame, or 'estimate'",
    )
    anchor: str | None = Field(
        default=None,
        pattern=NAME_PATTERN,
        description="robot whose map frame is the fleet frame when no pose is configured; default: "
        "this robot, or on a base station (source none) the first robot heard, by name",
    )
    max_extent_m: float = Field(
        default=10_000.0,
        gt=0.0,
        le=1e7,
        description="a map placed with any corner farther than this from the fleet frame's origin (m) "
        "is left out of the global map (the others keep merging)",
    )
    resolution: float | None = Field(
        default=None,
        ge=MIN_RESOLUTION,
        le=MAX_RESOLUTION,
        description="m a cell of the global map; unset: this robot's own map's, or on a base station "
        "(source none) the median of the first maps placed, kept from then on",
    )
    search_budget_s: float = Field(
        default=10.0,
        gt=0.0,
        le=3600.0,
        description="seconds of placement searches one merge spends at most; robots not searched "
        "by then keep their placements and go first at the next merge",
    )

    @field_validator("poses")
    @classmethod
    def _check_poses(cls, v: dict[str, Any]) -> dict[str, Any]:
        for robot, pose in v.items():
            if not re.fullmatch(NAME_PATTERN, robot):
                raise ValueError(f"{short_repr(robot, 40)} is not a valid robot name")
            if isinstance(pose, list) and (len(pose) != 3 or not all(math.isfinite(p) for p in pose)):
                raise ValueError(f"pose of '{robot}' must be [x, y, yaw] in meters and radians")
        return v

    @field_validator("poses", mode="before")
    @classmethod
    def _no_boolean_poses(cls, v: Any) -> Any:
        # pydantic reads true as 1.0: a pose written with booleans is a typo, not a place. And a
        # value of neither kind is said here once: the union said it twice, a line per member.
        if isinstance(v, dict):
            for robot, pose in v.items():
                if isinstance(pose, list) and any(isinstance(p, bool) for p in pose):
                    raise ValueError(f"pose of '{robot}' must be [x, y, yaw] in meters and radians")
                if not isinstance(pose, list) and pose != "estimate":
                    raise ValueError(
                        f"pose of {short_repr(robot, 40)} must be [x, y, yaw] in meters and radians, "
                        f'or "estimate" (got {short_repr(pose, 40)})'
                    )
        return v


class ControlSection(Strict):
    socket: Path | None = Field(
        default=None, description="control socket path; default <runtime_dir>/mapd.sock"
    )


class RecordSection(Strict):
    """``[record]``: an MCAP recording of the fleet as this daemon sees it (off unless ``path`` is set)."""

    path: Path | None = Field(default=None, description="the MCAP file to write; rotates to NAME.1.mcap, ...")
    max_bytes: int = Field(default=256 << 20, ge=1 << 20, description="start the next file past this size")
    max_total_bytes: int = Field(
        default=2 << 30,
        ge=1 << 20,
        description="the recording's files together: as each new file opens, the oldest are removed until "
        "the rest and max_bytes fit (the newest finished file always stays); at least twice max_bytes "
        "(there is no 'no cap': 0 is refused)",
    )
    min_free_bytes: int = Field(
        default=256 << 20,
        ge=0,
        description="below this much free space on its disk nothing is recorded (the daemon's own state "
        "needs it); recording resumes once there is room; 0: no check",
    )
    stats_every_s: float = Field(
        default=5.0,
        gt=0.0,
        description="how often the links' health and counters are recorded (/diagnostics)",
    )

    @model_validator(mode="after")
    def _check_total(self) -> RecordSection:
        # Room for the file being written and the one just finished (each ends a little past
        # max_bytes): under that, every rotation would leave the recording with almost nothing.
        if self.max_total_bytes < 2 * self.max_bytes:
            raise ValueError(
                f"max_total_bytes ({self.max_total_bytes}) must be at least twice max_bytes ({self.max_bytes})"
            )
        return self


class LogSection(Strict):
    level: Literal["debug", "info", "warning", "error"] = "info"


#: Shortest view token accepted: a guessable token on a non-loopback port is no protection.
MIN_VIEW_TOKEN = 16


def split_listen(listen: str) -> tuple[str, int]:
    """``"HOST:PORT"`` (``"[::1]:8080"`` for IPv6) -> ``(host, port)``; ValueError when malformed."""
    try:
        return split_host_port(listen, lowest_port=1)
    except ValueError as exc:
        raise ValueError(f"{listen!r} {exc}") from None


def is_loopback(host: str) -> bool:
    """True for ``localhost`` and loopback addresses (127.0.0.0/8, ::1); names are not resolved."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ViewSection(Strict):
    """``[view]``: the live web view of the fleet, read-only (off unless ``listen`` is set)."""

    listen: str | None = Field(
        default=None, description='HOST:PORT to serve the view on, e.g. "127.0.0.1:8080"; unset: no view'
    )
    token_file: Path | None = Field(
        default=None,
        description=f"file holding the access token ({MIN_VIEW_TOKEN}+ characters of A-Z a-z 0-9 . _ ~ -, "
        "as a URL carries them); required unless listen is a loopback address",
    )
    max_viewers: int = Field(default=256, ge=1, le=4096, description="concurrent viewers; more get 503")

    @field_validator("listen")
    @classmethod
    def _check_listen(cls, v: str | None) -> str | None:
        if v is not None:
            # a host no address can be made of stopped the view at start ("Name or service not
            # known"); a well-formed name is resolved there
            problem = host_problem(split_listen(v)[0].partition("%")[0])
            if problem:
                raise ValueError(problem)
        return v


class MapdConfig(Strict):
    """The whole ``config.toml``."""

    robot: RobotSection
    fleet: FleetSection = Field(default_factory=FleetSection)
    limits: LimitsSection = Field(default_factory=LimitsSection)
    state: StateSection = Field(default_factory=StateSection)
    source: SourceSection = Field(default_factory=SourceSection)
    codec: CodecSection = Field(default_factory=CodecSection)
    transports: TransportsSection = Field(default_factory=TransportsSection)
    output: OutputSection = Field(default_factory=OutputSection)
    fusion: FusionSection = Field(default_factory=FusionSection)
    control: ControlSection = Field(default_factory=ControlSection)
    log: LogSection = Field(default_factory=LogSection)
    record: RecordSection = Field(default_factory=RecordSection)
    view: ViewSection = Field(default_factory=ViewSection)

    @model_validator(mode="after")
    def _check_plugin_tables(self) -> MapdConfig:
        for section in ("source", "codec", "transports", "output"):
            for key, value in getattr(self, section).plugin_tables().items():
                if not isinstance(value, dict):
                    raise ValueError(f"{section}.{key}: expected a table of plugin options")
        return self

    # Resolved after validation by load(); not part of the file.
    _path: Path | None = None

    @property
    def path(self) -> Path | None:
        return self._path

    @property
    def folder(self) -> Path | None:
        """The config file's folder, absolute: relative paths in the config are taken from it."""
        return Path(os.path.abspath(self._path)).parent if self._path is not None else None

    def control_socket(self) -> Path:
        return self.control.socket or (self.state.runtime_dir / "mapd.sock")
