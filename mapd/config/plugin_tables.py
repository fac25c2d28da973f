"""Plugin sections: the chosen plugins exist, and each plugin's table validates with its own options.

``[source]``, ``[codec]``, ``[transports]`` and ``[output]`` name plugins in ``use`` and keep each
plugin's options in a sub-table named after it. :func:`check_plugins` validates every such table
(also those of plugins not chosen, so a complete example config stays correct) with the plugin's
``Options`` model, and :func:`check_plugin_files` runs the checks the chosen plugins' options
offer (their files, this robot, the other chosen plugins) as their start will.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel

from mapd import plugins
from mapd.config.loading import validate
from mapd.config.sections import MapdConfig
from mapd.errors import ConfigError, MapdError

#: Config section -> plugin kind (mapd.plugins).
_KINDS = {"source": "source", "codec": "codec", "transports": "transport", "output": "output"}


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


def check_plugin_files(cfg: MapdConfig, options: dict[str, dict[str, BaseModel]]) -> None:
    """Have each chosen plugin read the files its options name (``check_files``), check what its
    start would refuse on this robot (``check_for_robot``), beside the other chosen plugins
    (``check_with_plugins``) and given the rest of the config (``check_with_config``), as it will
    at start."""
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
            # refuses beside the other chosen plugins (a ros2 output on its ros2 source's topic);
            # check_with_config(cfg): what it refuses given the rest of the config (a source's
            # files, found in the data folder or beside the config, and limits.max_cells).
            # Found here, not only by mapd run.
            for hook, args in (
                ("check_files", ()),
                ("check_for_robot", (cfg.robot.name,)),
                ("check_with_plugins", (chosen,)),
                ("check_with_config", (cfg,)),
            ):
                check = getattr(opts, hook, None)
                if check is None:
                    continue
                try:
                    check(*args)
                except ValueError as exc:
                    raise ConfigError(f"{where}: {section}.{name}.{exc}") from None
