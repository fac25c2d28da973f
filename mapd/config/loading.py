"""Reading ``config.toml``: bounded, parsed with tomllib, validated, relative paths resolved.

A hostile file is one :class:`~mapd.errors.ConfigError`, never a hang or a RecursionError: at most
:data:`MAX_CONFIG_BYTES` are read, nesting deeper than :data:`MAX_CONFIG_DEPTH` is refused, and so
are values no config can mean (integers past 64 bits, NUL characters, inf and nan). Validation
errors become one line per problem naming the file and the key (:func:`validate`), here and for
each plugin's own options.
"""

from __future__ import annotations

import math
import os
import tomllib
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from mapd.config.sections import MapdConfig
from mapd.errors import ConfigError
from mapd.files.reading import read_capped
from mapd.grid.reprs import short_repr

M = TypeVar("M", bound=BaseModel)


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
    if not raw.strip():  # (/dev/null, a FIFO closed unwritten: "robot: required key is missing" misled)
        raise ConfigError(
            f"{p}: the config is empty; is this the right file? (the least one holds: [robot] name)"
        )
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


def control_socket_of(path: str | os.PathLike[str]) -> Path | None:
    """The control socket a config names (``control.socket``, else ``state.runtime_dir``'s
    ``mapd.sock``), read from its TOML alone: for ``mapd status`` when :func:`load` refuses the
    file (edited with a mistake while the daemon runs on the config it loaded before: ``mapd
    status`` must still show it, the reload it refused included). None when even that cannot be
    read (not TOML, no such file)."""
    p = Path(path)
    try:
        raw = read_capped(p, MAX_CONFIG_BYTES)
        data = tomllib.loads(raw.decode("utf-8")) if len(raw) <= MAX_CONFIG_BYTES else None
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError, RecursionError):
        return None
    if not isinstance(data, dict):
        return None
    control, state = data.get("control"), data.get("state")
    socket = control.get("socket") if isinstance(control, dict) else None
    runtime = state.get("runtime_dir") if isinstance(state, dict) else None
    if isinstance(socket, str) and socket:
        chosen = Path(socket)
    elif isinstance(runtime, str) and runtime:
        chosen = Path(runtime) / "mapd.sock"
    else:
        chosen = Path("/run/mapd/mapd.sock")  # the defaults' (StateSection.runtime_dir)
    return chosen if chosen.is_absolute() else p.parent / chosen


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
