"""The plugins a config names, made: the source, the transports and the outputs.

Each is loaded by its entry point (:mod:`mapd.plugins`) and given the options ``check_plugins``
validated (what ``mapd check-config`` checks, so ``mapd run`` makes just what it passed) and its
context: who this robot is, its keys, where its files go. Making one only constructs it; the daemon
starts them (:mod:`~mapd.daemon.server`), after the source's start pose is read.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

from pydantic import BaseModel

from mapd import config as configmod
from mapd import plugins
from mapd.envelope import Envelope
from mapd.errors import StateError
from mapd.outputs.base import Output, OutputContext
from mapd.sources.base import MapSource, SourceContext
from transports.base import Transport, TransportContext, TransportEvent

M = TypeVar("M", bound=BaseModel)
#: Every plugin's validated options, by section then name (``configmod.check(cfg).options``).
Options = dict[str, dict[str, BaseModel]]


def plugin_options(options: Options, section: str, name: str, model: type[M]) -> M | None:
    """A plugin's validated options (``check_plugins`` built them with ``model``)."""
    opts = options[section].get(name)
    return opts if isinstance(opts, model) else None


def make_source(cfg: configmod.MapdConfig, options: Options) -> MapSource:
    """The source ``[source] use`` names."""
    source_cls = plugins.load("source", cfg.source.use)
    return source_cls(
        plugin_options(options, "source", cfg.source.use, source_cls.Options),
        SourceContext.of(cfg),  # as check-config's check_with_config finds its files
    )


def make_transport(
    cfg: configmod.MapdConfig,
    name: str,
    options: Options,
    keys: configmod.Keys,
    *,
    emit: Callable[[TransportEvent], None],
    latest_keyframe: Callable[[], Envelope | None],
) -> Transport:
    """The transport ``name`` (of ``[transports] use``), with its folder in the state directory;
    ``emit`` takes its events, ``latest_keyframe`` is this robot's newest keyframe sent."""
    cls = plugins.load("transport", name)
    state_dir = cfg.state.dir / "links" / name
    try:  # (check-config refuses a file in the way; this is for one put there since)
        state_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StateError(f"state directory {cfg.state.dir} is not writable: {exc.strerror or exc}") from None
    ctx = TransportContext(
        robot=cfg.robot.name,
        fleet=cfg.robot.fleet,
        identity=keys.identity,
        roster=keys.roster,
        link_key=keys.link_key,
        max_message_bytes=cfg.limits.max_message_bytes,
        emit=emit,
        state_dir=state_dir,
        latest_keyframe=latest_keyframe,
    )
    return cls(plugin_options(options, "transports", name, cls.Options), ctx)


def output_context(cfg: configmod.MapdConfig, keys: configmod.Keys) -> OutputContext:
    """What every output of ``[output] use`` is handed."""
    return OutputContext(
        robot=cfg.robot.name,
        fleet=cfg.robot.fleet,
        state_dir=cfg.state.dir,
        identity=keys.identity,
    )


def make_output(name: str, options: Options, ctx: OutputContext) -> Output:
    """The output ``name`` (of ``[output] use``)."""
    cls = plugins.load("output", name)
    return cls(plugin_options(options, "output", name, cls.Options), ctx)
