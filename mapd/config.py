"""``config.toml``: read with tomllib, validated with pydantic, errors that name file and key.

The file has one table per part of the daemon. Plugin sections name the plugin in ``use`` and keep
each plugin's own options in a sub-table named after it, which that plugin validates itself::

    [source]
    use = "sim"
    [source.sim]
    seed = 7

so a complete example config can hold every plugin's table while only the chosen ones run.
"""

from __future__ import annotations

import ipaddress
import math
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from mapd import plugins
from mapd.errors import ConfigError, MapdError
from mapd.files import read_capped
from mapd.grid import DEFAULT_MAX_CELLS, short_repr
from mapd.identity import Identity, Roster, read_identity
from mapd.keys import read_key_file

M = TypeVar("M", bound=BaseModel)
#: Config section -> plugin kind (mapd.plugins).
_KINDS = {"source": "source", "codec": "codec", "transports": "transport", "output": "output"}

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
        # pydantic reads true as 1.0: a pose written with booleans is a typo, not a place
        if isinstance(v, dict):
            for robot, pose in v.items():
                if isinstance(pose, list) and any(isinstance(p, bool) for p in pose):
                    raise ValueError(f"pose of '{robot}' must be [x, y, yaw] in meters and radians")
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
    stats_every_s: float = Field(default=5.0, gt=0.0, description="how often the link counters are recorded")

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
    host, sep, port = listen.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"listen must be HOST:PORT with a port 1-65535 (got {listen!r})")
    return host.removeprefix("[").removesuffix("]"), int(port)


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
            split_listen(v)
        return v


def read_view_token(cfg: MapdConfig) -> str | None:
    """The view's token (None: none configured), refusing a non-loopback ``listen`` without one.

    Raises :class:`ConfigError` with one line naming the file and the key.
    """
    where = str(cfg.path) if cfg.path else "config"
    view = cfg.view
    path = view.token_file
    if view.listen is not None and path is None and not is_loopback(split_listen(view.listen)[0]):
        raise ConfigError(
            f"{where}: view.token_file: listen = {view.listen!r} is not a loopback address, so the view "
            "needs a token file (or listen on 127.0.0.1)"
        )
    if path is None:
        return None
    try:
        raw = read_capped(path, 4096)
    except OSError as exc:
        raise ConfigError(f"{where}: view.token_file: cannot read {path}: {exc.strerror}") from None
    try:
        token = raw.decode("ascii").strip()
    except UnicodeDecodeError:
        token = ""
    # Only what a URL carries unchanged (RFC 3986 unreserved): the README has users paste the token
    # into ``?token=`` as is, where "+" arrives as a space, "&" and "#" end it and "%" escapes.
    if len(raw) > 4096 or len(token) < MIN_VIEW_TOKEN or not re.fullmatch(r"[A-Za-z0-9._~-]+", token):
        raise ConfigError(
            f"{where}: view.token_file: {path} must hold one token of {MIN_VIEW_TOKEN}+ characters, "
            "each one of A-Z a-z 0-9 . _ ~ - (it goes into the URL as it is); make one with: "
            "openssl rand -hex 24"
        )
    return token


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


def format_validation_error(exc: ValidationError, where: str, prefix: str = "") -> str:
    """One line per problem: ``file: key.path: message``."""
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"] if p != "__root__")
        if prefix:
            loc = f"{prefix}.{loc}" if loc else prefix
        msg = err["msg"]
        if err["type"] == "extra_forbidden":
            msg = "unknown key (typo?)"
        elif err["type"] == "missing":
            msg = "required key is missing"
        elif "input" in err and err["type"] not in ("value_error",):
            # A hostile value can be a megabyte long or an integer too long to print; the error
            # stays one readable line.
            msg = f"{msg} (got {short_repr(err['input'], 80)})"
        lines.append(f"{where}: {loc}: {msg}" if loc else f"{where}: {msg}")
    return "\n".join(lines)


def validate(model: type[M], data: Any, where: str, prefix: str = "") -> M:
    """Validate ``data`` against ``model``, raising :class:`ConfigError` naming ``where`` and the key."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(format_validation_error(exc, where, prefix)) from None


#: Longest config file read; a real one is a few KiB. Reading stops here (``/dev/zero`` is refused).
MAX_CONFIG_BYTES = 1 << 20
#: Deepest nesting of tables and arrays accepted; a real config nests three or four levels.
MAX_CONFIG_DEPTH = 16


#: TOML integers are 64-bit signed (the spec asks a parser to refuse others; tomllib does not).
_TOML_INT_MIN, _TOML_INT_MAX = -(1 << 63), (1 << 63) - 1


def _too_deep(data: Any, limit: int) -> bool:
    """True when ``data`` nests dicts and lists more than ``limit`` levels (checked without recursion)."""
    stack: list[tuple[Any, int]] = [(data, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > limit:
            return True
        if isinstance(node, dict):
            stack.extend((v, depth + 1) for v in node.values())
        elif isinstance(node, list):
            stack.extend((v, depth + 1) for v in node)
    return False


def _bad_value(data: Any) -> str | None:
    """Where and why a parsed config holds a value no config can mean, or None.

    An integer outside 64 bits (``0x`` and 20,000 digits) cannot even be printed in an error, and
    one accepted as a limit or a seed would break later, far from the config; a NUL character in a
    string makes every path or name that holds it fail with a ValueError when it is opened. Called
    after :func:`_too_deep`, so the walk is shallow; it keeps no recursion either.
    """
    stack: list[tuple[Any, str]] = [(data, "")]
    while stack:
        node, where = stack.pop()
        if isinstance(node, dict):
            for k, v in node.items():
                if "\x00" in k:
                    return f"{where or 'a table'}: a key holds a NUL character"
                stack.append((v, f"{where}.{k}" if where else k))
        elif isinstance(node, list):
            stack.extend((v, f"{where}[{i}]") for i, v in enumerate(node))
        elif isinstance(node, str) and "\x00" in node:
            return f"{where}: the string holds a NUL character"
        elif isinstance(node, int) and not _TOML_INT_MIN <= node <= _TOML_INT_MAX:
            return f"{where}: integer out of the 64-bit range TOML allows"
        elif isinstance(node, float) and not math.isfinite(node):
            # TOML has inf and nan; no setting means them, and a limit of inf overflowed where it
            # became a count (limits.max_growth = inf stopped the daemon at its first peer's map)
            return f"{where}: {node} is not a finite number"
    return None


def load(path: str | os.PathLike[str]) -> MapdConfig:
    """Read and validate a config file. Plugin tables are checked by :func:`check_plugins`.

    At most :data:`MAX_CONFIG_BYTES` are read and nesting deeper than :data:`MAX_CONFIG_DEPTH` is
    refused, so a hostile file is one :class:`ConfigError`, never a hang or a RecursionError.
    """
    p = Path(path)
    try:
        # A FIFO named as the config reads as empty, or is given up after a deadline, instead of
        # blocking for ever (in the daemon's reload thread, which the daemon's exit waits for).
        raw = read_capped(p, MAX_CONFIG_BYTES)
    except FileNotFoundError:
        raise ConfigError(f"{p}: no such config file") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read config: {exc.strerror}") from None
    if len(raw) > MAX_CONFIG_BYTES:
        raise ConfigError(f"{p}: config is over {MAX_CONFIG_BYTES} bytes; is this the right file?")
    try:
        data = tomllib.loads(raw.decode("utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except RecursionError:
        # tomllib parses nested arrays and inline tables recursively.
        raise ConfigError(f"{p}: not valid TOML: arrays or tables nested too deeply") from None
    if _too_deep(data, MAX_CONFIG_DEPTH):
        raise ConfigError(f"{p}: arrays or tables nested more than {MAX_CONFIG_DEPTH} levels deep")
    problem = _bad_value(data)
    if problem is not None:
        raise ConfigError(f"{p}: {problem}")
    cfg = validate(MapdConfig, data, str(p))
    cfg._path = p
    # Relative paths in a config are relative to the file, like systemd drop-ins expect: the
    # daemon runs with cwd "/" under systemd, and `mapd status` must find the socket from anywhere.
    folder = cfg.folder
    assert folder is not None  # (just set)
    for section, field in _PATHS_BESIDE_CONFIG:
        table = getattr(cfg, section)
        value = getattr(table, field)
        if value is not None and not value.is_absolute():
            setattr(table, field, folder / value)
    return cfg


#: (section, field) of every path in the main tables; plugin options name theirs in ``beside_config``.
_PATHS_BESIDE_CONFIG = (
    ("robot", "key_file"),
    ("fleet", "link_key_file"),
    ("state", "dir"),
    ("state", "runtime_dir"),
    ("control", "socket"),
    ("record", "path"),
    ("view", "token_file"),
)


def plugin_options(cfg: MapdConfig, section: str, name: str) -> BaseModel:
    """Validate the ``[section.name]`` table with that plugin's own ``Options`` model."""
    kind = _KINDS[section]
    cls = plugins.load(kind, name)
    where = str(cfg.path) if cfg.path else "config"
    table = getattr(cfg, section).table(name)
    options_model = getattr(cls, "Options", None)
    if options_model is None:
        if table:
            raise ConfigError(f"{where}: {section}.{name}: this plugin takes no options")
        return BaseModel()
    options = validate(options_model, table, where, prefix=f"{section}.{name}")
    # Files an option names beside the config (a zenoh config): relative to it, as key_file is.
    for field in getattr(options, "beside_config", ()):
        value = getattr(options, field)
        if cfg.folder is not None and isinstance(value, Path) and not value.is_absolute():
            setattr(options, field, cfg.folder / value)
    return options


def check_plugins(cfg: MapdConfig, *, all_tables: bool = True) -> dict[str, dict[str, BaseModel]]:
    """Check that chosen plugins exist and that every plugin table validates; return the options.

    With ``all_tables``, tables of plugins that are not chosen are validated too (so a complete
    example config stays correct), except for plugins whose optional dependency is missing.
    """
    where = str(cfg.path) if cfg.path else "config"
    chosen = {
        "source": [cfg.source.use],
        "codec": [cfg.codec.use],
        "transports": list(cfg.transports.use),
        "output": list(cfg.output.use),
    }
    out: dict[str, dict[str, BaseModel]] = {"source": {}, "codec": {}, "transports": {}, "output": {}}
    for section, picked in chosen.items():
        kind = _KINDS[section]
        known = plugins.names(kind)
        for name in picked:
            if name not in known:
                raise ConfigError(
                    f"{where}: {section}.use: no {kind} plugin '{name}' (known: {', '.join(known)})"
                )
        tables = getattr(cfg, section).plugin_tables()
        for name in tables:
            if name not in known:
                raise ConfigError(
                    f"{where}: [{section}.{name}]: no {kind} plugin '{name}' (known: {', '.join(known)})"
                )
        names = set(picked) | (set(tables) if all_tables else set())
        for name in sorted(names):
            try:
                out[section][name] = plugin_options(cfg, section, name)
            except ConfigError:
                raise
            except MapdError:
                if name in picked:
                    raise
    if len(set(cfg.transports.use)) != len(cfg.transports.use):
        raise ConfigError(f"{where}: transports.use: a transport is listed twice")
    return out


@dataclass(frozen=True)
class Keys:
    """What a robot signs and verifies with, as ``run`` and ``check-config`` read it."""

    identity: Identity | None
    roster: Roster
    link_key: bytes | None

    @property
    def signed(self) -> bool:
        return not self.roster.allow_unsigned


def read_keys(cfg: MapdConfig) -> Keys:
    """The robot's key, the roster and the uwb link key, checked together (one ConfigError line).

    A signed fleet (the default) needs the robot's own key, a roster that lists this robot with
    that key's public half, and, when the uwb transport is used, the link key. With
    ``fleet.allow_unsigned = true`` each of these is optional; whatever is set is still used.
    """
    where = str(cfg.path) if cfg.path else "config"
    roster = Roster.from_texts(cfg.fleet.roster, allow_unsigned=cfg.fleet.allow_unsigned)
    identity = None
    if cfg.robot.key_file is not None:
        identity = read_identity(cfg.robot.key_file, cfg.robot.name)
    link_key = read_key_file(cfg.fleet.link_key_file, "fleet.link_key_file")
    if not cfg.fleet.allow_unsigned:
        hint = "(make keys with 'mapd keygen', or set fleet.allow_unsigned = true)"
        if identity is None:
            raise ConfigError(f"{where}: robot.key_file: a signed fleet needs this robot's key {hint}")
        if "uwb" in cfg.transports.use and link_key is None:
            raise ConfigError(f"{where}: fleet.link_key_file: uwb frames need the fleet's link key {hint}")
    if (
        identity is not None
        and cfg.robot.name in roster
        and cfg.fleet.roster[cfg.robot.name] != identity.public_text
    ):
        raise ConfigError(
            f"{where}: fleet.roster.{cfg.robot.name} does not match robot.key_file "
            f"(its public key is {identity.public_text})"
        )
    if identity is not None and not cfg.fleet.allow_unsigned and cfg.robot.name not in roster:
        raise ConfigError(
            f"{where}: fleet.roster: this robot '{cfg.robot.name}' is missing; add: "
            f'{cfg.robot.name} = "{identity.public_text}"'
        )
    return Keys(identity, roster, link_key)


@dataclass(frozen=True)
class Checked:
    """A config as ``mapd run`` uses it: every plugin table validated, and the keys read."""

    options: dict[str, dict[str, BaseModel]]
    keys: Keys
    #: The live view's access token (``[view] token_file``), if any.
    view_token: str | None = None


def check(cfg: MapdConfig) -> Checked:
    """The one validation ``mapd run`` and ``mapd check-config`` both do (so they never disagree).

    Every plugin table is validated, also those of plugins not chosen (a typo in one is an error,
    not a table silently ignored), the files chosen plugins name are read (zenoh configs), and the
    key files are read and matched against the roster.
    """
    options = check_plugins(cfg)
    _check_plugin_files(cfg, options)
    return Checked(options, read_keys(cfg), read_view_token(cfg))


def _check_plugin_files(cfg: MapdConfig, options: dict[str, dict[str, BaseModel]]) -> None:
    """Have each chosen plugin read the files its options name (``check_files``), check what its
    start would refuse on this robot (``check_for_robot``) and beside the other chosen plugins
    (``check_with_plugins``), as it will at start."""
    where = str(cfg.path) if cfg.path else "config"
    picked = (
        ("source", [cfg.source.use]),
        ("codec", [cfg.codec.use]),
        ("transports", cfg.transports.use),
        ("output", cfg.output.use),
    )
    # What each check_with_plugins() sees: the options of every chosen plugin, by section and name.
    chosen = {s: {n: options[s][n] for n in names if n in options[s]} for s, names in picked}
    for section, names in picked:
        for name in names:
            opts = options[section].get(name)
            # check_files(): the files its options name; check_for_robot(robot): what its start
            # would refuse on this robot (the uwb link ids); check_with_plugins(chosen): what it
            # refuses beside the other chosen plugins (a ros2 output on its ros2 source's topic).
            # Found here, not only by mapd run.
            for hook, args in (
                ("check_files", ()),
                ("check_for_robot", (cfg.robot.name,)),
                ("check_with_plugins", (chosen,)),
            ):
                check = getattr(opts, hook, None)
                if check is None:
                    continue
                try:
                    check(*args)
                except ValueError as exc:
                    raise ConfigError(f"{where}: {section}.{name}.{exc}") from None
