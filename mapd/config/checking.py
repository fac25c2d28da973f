"""The one check ``mapd run`` and ``mapd check-config`` share: plugin tables and files, keys, view
token, the paths the start writes to and the ports it listens on.

:func:`check` validates every plugin table (:mod:`mapd.config.plugin_tables`), has the chosen
plugins read the files they name, reads the robot's key, the roster and the uwb link key
(:func:`read_keys`) and the live view's token (:func:`read_view_token`), looks at the state
directory, the control socket and the recording's path (:func:`check_paths`) and at what two parts
of the config would both listen on (:func:`check_listeners`), each refusal one
:class:`~mapd.errors.ConfigError` line naming the file and the key. None of it creates or changes
anything: what only the machine decides at start (a radio not plugged in yet, a port another
program holds, who may write where) is left to the start.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pydantic import BaseModel

from mapd.config.endpoints import Listener, listening, same_socket, socket_of
from mapd.config.paths import folder_problem, socket_problem
from mapd.config.plugin_tables import check_plugin_files, check_plugins
from mapd.config.sections import MIN_VIEW_TOKEN, MapdConfig, is_loopback, split_listen
from mapd.errors import ConfigError
from mapd.files.reading import read_capped
from mapd.identity import Identity, Roster, read_identity
from mapd.keys import read_key_file


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
    check_plugin_files(cfg, options)
    checked = Checked(options, read_keys(cfg), read_view_token(cfg))
    check_paths(cfg)
    check_listeners(cfg, options)
    return checked


def check_paths(cfg: MapdConfig) -> None:
    """ConfigError (one line naming the key) for a path the start could not make or use for what it
    is: the state directory, the control socket, the recording's folder.

    Only kinds are looked at (a file where a folder goes, a socket path too long), never made or
    written: a folder not there yet is made by the start, as the unit's StateDirectory= is. What is
    in the state directory is the daemon's data, not the config: its start says what is wrong there.
    """
    where = str(cfg.path) if cfg.path else "config"
    if problem := folder_problem(cfg.state.dir):
        raise ConfigError(f"{where}: state.dir: {problem}")
    key = "control.socket" if cfg.control.socket is not None else "state.runtime_dir"
    if problem := socket_problem(cfg.control_socket()):
        raise ConfigError(f"{where}: {key}: {problem}")
    if cfg.record.path is None:
        return
    if problem := folder_problem(cfg.record.path.parent):
        raise ConfigError(f"{where}: record.path: {problem}")
    try:  # what the recorder imports as the daemon starts (the optional [record] extra)
        import mcap.writer  # noqa: F401
        import rosbags.typesys  # noqa: F401
    except ModuleNotFoundError as exc:
        raise ConfigError(
            f"{where}: record.path: recording needs {exc.name} (pip install 'mapd[record]')"
        ) from None


def check_listeners(cfg: MapdConfig, options: dict[str, dict[str, BaseModel]]) -> None:
    """ConfigError (one line) when two parts of the config would listen on one socket: the second
    to start found its port taken by the first ("address already in use")."""
    where = str(cfg.path) if cfg.path else "config"
    # In the order the start opens them: transports, outputs, the view, then the source's session.
    parts = [("transports", n) for n in cfg.transports.use] + [("output", n) for n in cfg.output.use]
    listeners = [
        (sock, f"{section}.{name}", shown)
        for section, name in parts
        for ep, shown in listening(options[section].get(name))
        if (sock := socket_of(ep)) is not None
    ]
    if cfg.view.listen is not None:
        host, port = split_listen(cfg.view.listen)
        listeners.append((Listener("tcp", host, port), "view", cfg.view.listen))
    listeners += [
        (sock, f"source.{cfg.source.use}", shown)
        for ep, shown in listening(options["source"].get(cfg.source.use))
        if (sock := socket_of(ep)) is not None
    ]
    for i, (sock, who, shown) in enumerate(listeners):
        for first, first_who, first_shown in listeners[:i]:
            if first_who != who and same_socket(sock, first):
                raise ConfigError(
                    f"{where}: {who}.listen: {shown} is also where {first_who} listens ({first_shown})"
                )
