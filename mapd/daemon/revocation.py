"""A robot's key revoked (removed from the roster, or replaced by a reload): what it signed goes.

A key is removed or replaced because it leaked or its robot left; either way, what it signed may be
bad, including a version from the future signed to lock the real robot out. So the daemon drops,
everywhere it holds it, what the old key signed: the robot's map (held, fused, on its way in, and in
the state directory), its pose, and what each link knows of it; a new key's maps are taken from the
next on. :class:`Revocation` holds the parts that keep such things and does it on the event loop's
thread, the files on a worker.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from dataclasses import dataclass

from mapd.daemon.inbound import Inbound
from mapd.daemon.poses import PoseRelay
from mapd.daemon.receiver import Receiver
from mapd.daemon.state import StateStore
from mapd.errors import MapdError
from mapd.fusion.worker import FusionWorker
from transports.base import Transport

log = logging.getLogger("mapd.daemon")


@dataclass
class Revocation:
    """Everything of a robot that its revoked key signed, dropped (see the module docstring)."""

    receiver: Receiver
    fusion: FusionWorker
    poses: PoseRelay
    inbound: Inbound
    #: The daemon's list of links (the same list: filled once the transports start).
    transports: Sequence[Transport]
    store: StateStore

    def revoke(self, robot: str, *, rekeyed: bool = False) -> None:
        """Drop ``robot``'s map from the maps held and the global map, its pose, and a map of it
        on its way in, as after a restart without it. Its saved files go next (:meth:`remove_saved`)."""
        self.receiver.forget(robot)
        self.fusion.forget(robot)
        self.poses.forget(robot)
        self.inbound.revoked(robot)
        for t in self.transports:
            t.forget(robot)
        self.store.forget_peer(robot)
        self.store.forget_acked(robot)
        log.warning(
            "revoked %s%s: its map is out of the global map, its pose is dropped",
            robot,
            "'s old key" if rekeyed else "",
        )

    async def remove_saved(self, robot: str) -> None:
        """Remove a revoked robot's map from the state directory (on a worker: the disk may be slow),
        so no restart brings it back."""
        try:
            await asyncio.to_thread(self.store.remove_peer, robot)
        except MapdError as exc:
            log.warning("revoked %s: %s", robot, exc)
