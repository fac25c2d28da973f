"""``systemctl reload mapd`` (SIGHUP): read the config again and take the fleet's roster from it.

Adding a robot to a fleet changes one table in every robot's config, ``[fleet.roster]``; a reload
lets the running daemons take it without a restart, so no link drops and no map waits. What a
reload applies is the roster's keys: robots added, removed or given a new key. Every holder of the
daemon's :class:`~mapd.identity.Roster` (the receiver, the transports, the pose relay) verifies
with the new keys from the next message on. The live view's token (``[view] token_file``, its
path or what the file holds) is applied too: a leaked one is rotated by writing a new one and
reloading; the view checks every request against the new token and ends the streams opened with
the old one (unless ``[view] listen`` changed as well: then both wait for the restart).

Everything else that differs from the running config (transports, codec, this robot's own key, the
link key, ``allow_unsigned``, ...) is named, key by key, as needing a restart, and left as it runs:
a half-applied transport or codec change would be worse than none. A config that does not load or
check (what ``mapd check-config`` checks) is refused whole; the daemon keeps running on what it had
and says why in one line, in its log and in ``mapd status``.

:func:`read` does the blocking part (files, key files) and runs on a worker thread; :class:`Reloads`
keeps the applied config and the last outcome for ``mapd status``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from mapd import config as configmod
from mapd.errors import ConfigError


@dataclass(frozen=True)
class Plan:
    """What a new config changes: the roster's part (applied) and the rest (needs a restart)."""

    added: list[str] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    rekeyed: list[str] = field(default_factory=list)
    #: Dotted keys that differ and only take effect on a restart, e.g. ``codec.use``.
    restart: list[str] = field(default_factory=list)
    #: The live view's token from now on (the daemon hands it to the running view; None: none).
    view_token: str | None = None
    #: Whether ``view_token`` differs from the token the view ran with.
    view_token_changed: bool = False

    @property
    def roster_changed(self) -> bool:
        return bool(self.added or self.removed or self.rekeyed)

    def summary(self) -> str:
        """One line: what changed in the roster, and what waits for a restart."""
        parts = [f"{what} {', '.join(names)}" for what, names in self._roster_parts() if names]
        said = "roster: " + "; ".join(parts) if parts else "roster unchanged"
        if self.view_token_changed:
            said += "; view: new token in force" if self.view_token else "; view: token removed"
        if self.restart:
            said += f"; needs a restart to take effect: {', '.join(self.restart)}"
        return said

    def _roster_parts(self) -> list[tuple[str, list[str]]]:
        return [("added", self.added), ("removed", self.removed), ("new key for", self.rekeyed)]


def _flat(doc: Any, prefix: str = "") -> dict[str, Any]:
    """``{"codec": {"use": "x"}}`` as ``{"codec.use": "x"}``, down to the leaves."""
    if not isinstance(doc, dict):
        return {prefix: doc}
    out: dict[str, Any] = {}
    for key, value in doc.items():
        out.update(_flat(value, f"{prefix}.{key}" if prefix else str(key)))
    return out


def _view_token_live(running: configmod.MapdConfig, new: configmod.MapdConfig) -> bool:
    """Whether the running view takes the new config's token: it serves the same ``listen``.

    A token checked against another ``listen`` is no token for this one (none is needed on
    loopback, one is off it), so with ``listen`` changed the token waits for the restart too.
    """
    return new.view.listen is not None and new.view.listen == running.view.listen


def plan(running: configmod.MapdConfig, new: configmod.MapdConfig) -> Plan:
    """Compare ``new`` with the ``running`` config (both validated; no files read)."""
    old_r, new_r = running.fleet.roster, new.fleet.roster
    a = _flat(running.model_dump(mode="json"))
    b = _flat(new.model_dump(mode="json"))
    live = {"view.token_file"} if _view_token_live(running, new) else set()
    restart = sorted(
        key
        for key in a.keys() | b.keys()
        if not key.startswith("fleet.roster.") and key not in live and a.get(key) != b.get(key)
    )
    return Plan(
        added=sorted(set(new_r) - set(old_r)),
        removed=sorted(set(old_r) - set(new_r)),
        rekeyed=sorted(r for r in set(old_r) & set(new_r) if old_r[r] != new_r[r]),
        restart=restart,
    )


def read(
    running: configmod.MapdConfig, keys: configmod.Keys, view_token: str | None = None
) -> tuple[configmod.MapdConfig, configmod.Keys, Plan]:
    """Load and check the running config's file again (blocking), and plan what it changes.

    Raises what loading or checking raises (:class:`~mapd.errors.ConfigError` and its kin, one line):
    so a token file gone missing, or holding a token too short, refuses the reload and the view
    keeps the token it has. The key files are read again too: a changed own key or link key under
    the same path is a change that needs a restart, like any other. ``view_token``: the token the
    running view checks (None: no view, or one without a token); the plan's ``view_token`` is the
    one it checks from now on.
    """
    if running.path is None:
        raise ConfigError("this daemon was not started from a config file: nothing to reload")
    new = configmod.load(running.path)
    checked = configmod.check(new)
    p = plan(running, new)
    restart = list(p.restart)
    own_old = keys.identity.public_text if keys.identity else None
    own_new = checked.keys.identity.public_text if checked.keys.identity else None
    if own_old != own_new and "robot.key_file" not in restart:
        restart.append("robot.key_file (the key in it changed)")
    if keys.link_key != checked.keys.link_key and "fleet.link_key_file" not in restart:
        restart.append("fleet.link_key_file (the key in it changed)")
    token = checked.view_token if _view_token_live(running, new) else view_token
    return new, checked.keys, Plan(p.added, p.removed, p.rekeyed, sorted(restart), token, token != view_token)


@dataclass
class Reloads:
    """The reloads a daemon did: the config the roster now comes from, and the last outcome."""

    config: configmod.MapdConfig
    count: int = 0
    refused: int = 0
    last_at: float | None = None
    last_ok: bool | None = None
    last_message: str = ""

    def applied(self, new: configmod.MapdConfig, p: Plan, now: float | None = None) -> str:
        """Record a reload whose roster (and view token) was taken; the restart-only keys keep their
        running values."""
        # Later reloads compare against the roster (and the view's token file) now in force, and the
        # rest as it runs.
        update: dict[str, Any] = {
            "fleet": self.config.fleet.model_copy(update={"roster": dict(new.fleet.roster)})
        }
        if _view_token_live(self.config, new):
            update["view"] = self.config.view.model_copy(update={"token_file": new.view.token_file})
        self.config = self.config.model_copy(update=update)
        return self._record(True, p.summary(), now)

    def failed(self, message: str, now: float | None = None) -> str:
        self.refused += 1
        return self._record(False, f"refused, still running on the previous config: {message}", now)

    def _record(self, ok: bool, message: str, now: float | None) -> str:
        self.count += 1
        self.last_at = time.time() if now is None else now
        self.last_ok = ok
        self.last_message = message
        return message

    def status(self) -> dict[str, Any]:
        """``mapd status``'s ``reload``: how many, and what the last one did."""
        return {
            "count": self.count,
            "refused": self.refused,
            "last_at": self.last_at,
            "last_ok": self.last_ok,
            "last": self.last_message,
        }
