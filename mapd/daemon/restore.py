"""What a previous run left in the state directory, read back and sorted out before the daemon starts.

Blocking (it reads files): the daemon runs :func:`read_saved_state` in a worker thread. Every saved
peer map is trusted only through what its YAML holds (version, digest, the roster key it was taken
under), and a map that the roster changed the standing of while the daemon was down is handled as a
reload would have handled it then: a robot removed or re-keyed loses its saved map and its files,
so no later start restores it either.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from mapd.daemon.state import StateStore
from mapd.daemon.state_records import SavedPeer
from mapd.errors import MapdError
from mapd.grid import OccupancyGrid
from mapd.identity import Roster

log = logging.getLogger("mapd.daemon")


@dataclass
class SavedState:
    """The own map, the base its deltas were coded against, and the peers' maps to restore."""

    own: OccupancyGrid | None = None
    base: OccupancyGrid | None = None
    peers: list[SavedPeer] = field(default_factory=list)


def read_saved_state(
    store: StateStore, me: str, roster: Roster, key_of: Callable[[str], str | None]
) -> SavedState:
    """Open ``store`` and read what it holds for robot ``me``; ``key_of(robot)`` is the roster's
    key of a robot now (its text), None when it has none (an unsigned fleet)."""
    store.open()
    own = store.own_map()
    peers = []
    # The robots state.json names, and roster robots whose map was saved just before a kill that
    # came before state.json named them (their first map).
    unrecorded = [r for r in store.unrecorded_peers() if r != me]
    for robot in [*store.data.peers, *unrecorded]:
        if not roster.admits(robot):
            # Revoked while the daemon was down: as a reload would have, leave its map out.
            revoked_at_start(store, robot, "it is no longer on the roster")
            continue
        if robot in unrecorded and robot not in roster:
            continue  # (an unsigned fleet admits any name: only the roster's are looked for)
        try:
            saved = store.saved_peer(robot)
        except MapdError as exc:  # a name no folder can have, in a damaged state.json
            log.warning("not restoring %s's map: %s", robot, exc)
            saved = None
        if saved is None:
            store.forget_peer(robot)
            continue
        key = key_of(robot)
        if saved.key is not None and saved.key != key:
            # Given a new key while the daemon was down: what the old key signed goes, as a reload
            # would have taken it (its version too, which may lock the real robot out).
            revoked_at_start(store, robot, "it was signed by a key the roster has replaced")
            continue
        if robot in unrecorded and saved.key is None and key is not None:
            # No key in it: saved by an earlier release, whose revocations left the files (a robot
            # removed, then added again under a new key). Only state.json vouched for it.
            revoked_at_start(store, robot, "state.json does not name it, nor does it name its key")
            continue
        peers.append(saved)
    return SavedState(own, store.base_map(), peers)


def revoked_at_start(store: StateStore, robot: str, why: str) -> None:
    """Leave ``robot``'s saved map out, and remove it, so no later start restores it either."""
    log.warning("not restoring %s's map: %s", robot, why)
    try:
        store.remove_peer(robot)
    except MapdError as exc:
        log.warning("revoked %s: %s", robot, exc)
    store.forget_acked(robot)
