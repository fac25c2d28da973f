"""``config.toml``: read with tomllib, validated with pydantic, errors that name file and key.

The file has one table per part of the daemon. Plugin sections name the plugin in ``use`` and keep
each plugin's own options in a sub-table named after it, which that plugin validates itself::

    [source]
    use = "sim"
    [source.sim]
    seed = 7

so a complete example config can hold every plugin's table while only the chosen ones run.

The package is split by idea: :mod:`~mapd.config.sections` holds the schema (one model per table,
and :class:`MapdConfig` for the whole file); :mod:`~mapd.config.loading` reads the file (size,
nesting and value limits, paths beside the config) and turns validation errors into one line each;
:mod:`~mapd.config.plugin_tables` checks the plugin sections with each plugin's own options;
:mod:`~mapd.config.checking` is the one check ``mapd run`` and ``mapd check-config`` share (plugin
tables and files, the key files and roster, the view token, paths and listeners), with
:mod:`~mapd.config.paths` and :mod:`~mapd.config.endpoints` to look at the paths and addresses a
config names without touching them. Every name is importable from ``mapd.config`` as it was before
the split.
"""

from mapd.config.checking import Checked, Keys, check, read_keys, read_view_token
from mapd.config.loading import (
    MAX_CONFIG_BYTES,
    MAX_CONFIG_DEPTH,
    control_socket_of,
    format_validation_error,
    load,
    validate,
)
from mapd.config.plugin_tables import _KINDS, check_plugins, plugin_options
from mapd.config.sections import (
    MIN_VIEW_TOKEN,
    NAME_PATTERN,
    CodecSection,
    ControlSection,
    FleetSection,
    FusionSection,
    LimitsSection,
    LogSection,
    MapdConfig,
    OutputSection,
    PluginSection,
    RecordSection,
    RobotSection,
    SourceSection,
    StateSection,
    Strict,
    TransportsSection,
    ViewSection,
    is_loopback,
    split_listen,
)

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_CONFIG_DEPTH",
    "MIN_VIEW_TOKEN",
    "NAME_PATTERN",
    "_KINDS",
    "Checked",
    "CodecSection",
    "ControlSection",
    "FleetSection",
    "FusionSection",
    "Keys",
    "LimitsSection",
    "LogSection",
    "MapdConfig",
    "OutputSection",
    "PluginSection",
    "RecordSection",
    "RobotSection",
    "SourceSection",
    "StateSection",
    "Strict",
    "TransportsSection",
    "ViewSection",
    "check",
    "check_plugins",
    "control_socket_of",
    "format_validation_error",
    "is_loopback",
    "load",
    "plugin_options",
    "read_keys",
    "read_view_token",
    "split_listen",
    "validate",
]
