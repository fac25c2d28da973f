"""The plugin spine: entry-point groups for sources, codecs and transports, imported lazily.

A plugin is a class registered under one of four entry-point groups (see ``pyproject.toml``)::

    [project.entry-points."mapd.codecs"]
    lossless = "mapd.codec.lossless:LosslessCodec"

Listing plugins reads only package metadata; a plugin's module is imported the first time it is
used, so a missing optional dependency (say, ``eclipse-zenoh``) only matters to a config that asks
for that plugin, and then it is one clear :class:`~mapd.errors.PluginError`.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, overload

from mapd.errors import PluginError

if TYPE_CHECKING:  # the interfaces live above this module; only their types are needed here
    from mapd.codec.base import Codec
    from mapd.outputs.base import Output
    from mapd.sources.base import MapSource
    from transports.base import Transport

Kind = Literal["source", "codec", "transport", "output"]
GROUPS: dict[str, str] = {
    "source": "mapd.sources",
    "codec": "mapd.codecs",
    "transport": "mapd.transports",
    "output": "mapd.outputs",
}
#: The class every plugin of a group must subclass, imported only when a plugin is loaded.
INTERFACES: dict[str, str] = {
    "source": "mapd.sources.base:MapSource",
    "codec": "mapd.codec.base:Codec",
    "transport": "transports.base:Transport",
    "output": "mapd.outputs.base:Output",
}

# Import names that differ from the pip distribution a user must install.
_DIST_FOR_MODULE = {
    "zenoh": "eclipse-zenoh",
    "serial": "pyserial",
    "serial_asyncio": "pyserial-asyncio",
    "cv2": "opencv-python-headless",
    "rosbags": "rosbags (pip install 'mapd[ros2]')",
    "torch": "torch",
    "zstandard": "zstandard",
}

_cache: dict[tuple[str, str], type] = {}


@dataclass(frozen=True)
class PluginInfo:
    """What the registry knows about a plugin without importing it."""

    kind: str
    name: str
    target: str
    distribution: str


def _entry_points(kind: str) -> dict[str, importlib.metadata.EntryPoint]:
    if kind not in GROUPS:
        raise PluginError(f"unknown plugin kind '{kind}' (expected one of {', '.join(GROUPS)})")
    found: dict[str, importlib.metadata.EntryPoint] = {}
    for ep in importlib.metadata.entry_points(group=GROUPS[kind]):
        found.setdefault(ep.name, ep)
    return found


def available(kind: str) -> list[PluginInfo]:
    """Plugins registered for ``kind``, sorted by name, without importing them."""
    out = []
    for name, ep in sorted(_entry_points(kind).items()):
        dist = ep.dist.name if ep.dist is not None else "?"
        out.append(PluginInfo(kind=kind, name=name, target=ep.value, distribution=dist))
    return out


def names(kind: str) -> list[str]:
    """Names of the plugins registered for ``kind``."""
    return sorted(_entry_points(kind))


def name_type(kind: str, extra: tuple[str, ...] = ()) -> Callable[[str], str]:
    """An argparse ``type``: a name registered for ``kind`` (or one of ``extra``), else a usage error
    (exit 2) listing them, when the arguments are parsed rather than after work began. Reads the
    package metadata only: no plugin is imported."""

    def check(text: str) -> str:
        known = [*names(kind), *extra]
        if text not in known:
            raise argparse.ArgumentTypeError(
                f"no {kind} named {text!r} (installed: {', '.join(known) or 'none'})"
            )
        return text

    return check


def interface(kind: str) -> type:
    """The class every plugin of ``kind`` subclasses (:class:`~mapd.sources.base.MapSource`, ...)."""
    if kind not in INTERFACES:
        raise PluginError(f"unknown plugin kind '{kind}' (expected one of {', '.join(GROUPS)})")
    module, _, attr = INTERFACES[kind].partition(":")
    cls: type = getattr(importlib.import_module(module), attr)
    return cls


@overload
def load(kind: Literal["source"], name: str) -> type[MapSource]: ...
@overload
def load(kind: Literal["codec"], name: str) -> type[Codec]: ...
@overload
def load(kind: Literal["transport"], name: str) -> type[Transport]: ...
@overload
def load(kind: Literal["output"], name: str) -> type[Output]: ...
@overload
def load(kind: str, name: str) -> type: ...


def load(kind: str, name: str) -> type:
    """Import and return the class registered as ``name`` for ``kind``, typed as the group's interface.

    Raises :class:`PluginError` when no such plugin is registered, its import fails (naming the
    distribution to install when the cause is a missing dependency), or what it names is not a
    subclass of the group's interface.
    """
    key = (kind, name)
    if key in _cache:
        return _cache[key]
    eps = _entry_points(kind)
    if name not in eps:
        known = ", ".join(sorted(eps)) or "none"
        raise PluginError(f"no {kind} plugin named '{name}' (installed: {known})")
    try:
        cls = eps[name].load()
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if missing and not missing.startswith(("mapd", "transports")):
            need = _DIST_FOR_MODULE.get(missing, missing)
            raise PluginError(f"{kind} plugin '{name}' needs {need}, which is not installed") from None
        raise PluginError(f"{kind} plugin '{name}' is registered but its module is missing: {exc}") from None
    except ImportError as exc:
        raise PluginError(f"{kind} plugin '{name}' failed to import: {exc}") from None
    except AttributeError:
        raise PluginError(
            f"{kind} plugin '{name}' points at '{eps[name].value}', which does not exist"
        ) from None
    base = interface(kind)
    if not (isinstance(cls, type) and issubclass(cls, base)):
        raise PluginError(
            f"{kind} plugin '{name}' points at '{eps[name].value}', which is not a {base.__name__}"
        )
    _cache[key] = cls
    return cls
