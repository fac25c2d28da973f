"""The one check ``mapd run`` and ``mapd check-config`` share: plugin tables and files, keys, view token.

:func:`check` validates every plugin table (:mod:`mapd.config.plugin_tables`), has the chosen
plugins read the files they name, reads the robot's key, the roster and the uwb link key
(:func:`read_keys`) and the live view's token (:func:`read_view_token`), each refusal one
:class:`~mapd.errors.ConfigError` line naming the file and the key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from pydantic import BaseModel

from mapd.config.plugin_tables import check_plugin_files, check_plugins
from mapd.config.sections import MIN_VIEW_TOKEN, MapdConfig, is_loopback, split_listen
from mapd.errors import ConfigError
from mapd.files import read_capped
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
    return Checked(options, read_keys(cfg), read_view_token(cfg))
