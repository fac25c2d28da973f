"""Robots of other fleets on the same zenoh network: said once per fleet, shown in the link's stats.

Every name a robot uses lives under ``mapd/<fleet>/`` (:mod:`transports.zenoh.keys`), so two robots
whose ``robot.fleet`` differ share a zenoh network and see nothing of each other: each just runs
alone, and nothing said why. So each link also declares one liveliness token outside its fleet,
``mapd/@fleets/<fleet>/<robot>``, and subscribes to those tokens only (``mapd/@fleets/*/*``),
never to another fleet's maps, poses or acks. A robot that sees a token of another fleet says so
once per fleet and run, as a WARNING that names that fleet, one of its robots and the fix, and
:meth:`OtherFleets.stats` shows them (``other_fleets``). Fleets kept apart on purpose on one
network are no fault: the line is said once, and ``mapd status`` shows no FAULTS for it.

The tokens are not signed, and need not be: a token carries no authority. It makes no state the
link acts on (no peer, no query, no ack awaited; compare the signed requests of
:mod:`transports.signed_requests`, which make a robot send a keyframe), only a log line and the
names in ``stats``. Anyone on the network can declare such tokens, thousands of them, so what is
kept is bounded: :data:`MAX_FLEETS_SHOWN` fleets of :data:`MAX_ROBOTS_SHOWN` robots each, and at
most :data:`MAX_FLEETS_SAID` lines in a run; past that, tokens are only counted
(``other_fleet_tokens``). A router whose ACL fences one fleet (``deploy/zenoh/router-tls.json5``)
drops these tokens too unless a rule lets ``mapd/@fleets/**`` tokens through.

Called on zenoh's threads and read on the loop's, hence the lock; no I/O here (the caller logs).
"""

from __future__ import annotations

import threading
from typing import Any

from transports.zenoh import keys

#: Other fleets whose robots ``stats`` names at once; tokens of more are only counted.
MAX_FLEETS_SHOWN = 8
#: Robots named per other fleet; more of that fleet are only counted.
MAX_ROBOTS_SHOWN = 8
#: Other fleets said in one run at most (a peer making up fleet names cannot fill the log).
MAX_FLEETS_SAID = 16


class OtherFleets:
    """The other fleets' robots one link sees (see the module docstring); thread-safe."""

    def __init__(self, fleet: str, robot: str) -> None:
        self.fleet = fleet
        self.robot = robot
        self._lock = threading.Lock()
        #: fleet -> its robots whose token is up now, as far as they are kept (insertion order).
        self._now: dict[str, dict[str, None]] = {}
        self._said: set[str] = set()
        #: Tokens of other fleets' robots seen appearing, kept or not.
        self._tokens = 0

    def seen(self, key_expr: str, alive: bool) -> str | None:
        """A fleet token appeared (``alive``) or vanished: the line to say now, or None.

        The line comes once per other fleet and run, the first time one of its robots is seen.
        """
        parsed = keys.parse_fleet_presence(key_expr)
        if parsed is None or parsed[0] == self.fleet:
            return None  # not a fleet token, or one of ours (the fleet's own token says that)
        fleet, robot = parsed
        with self._lock:
            robots = self._now.get(fleet)
            if not alive:
                if robots is not None:
                    robots.pop(robot, None)
                    if not robots:
                        del self._now[fleet]
                return None
            self._tokens += 1
            if robots is None and len(self._now) < MAX_FLEETS_SHOWN:
                robots = self._now[fleet] = {}
            if robots is not None and len(robots) < MAX_ROBOTS_SHOWN:
                robots[robot] = None
            if fleet in self._said or len(self._said) >= MAX_FLEETS_SAID:
                return None
            self._said.add(fleet)
        return self.line(fleet, robot)

    def line(self, fleet: str, robot: str) -> str:
        """What a robot of ``fleet`` seen on our network is said as: the cause and both fixes."""
        return (
            f"zenoh: robot '{robot}' of fleet '{fleet}' is on this zenoh network, and this robot "
            f"'{self.robot}' is of fleet '{self.fleet}': robots of different fleets see none of each "
            f"other's maps. Set robot.fleet the same on every robot of one fleet, or, if they are "
            f"meant to be apart, nothing is wrong (give each fleet its own zenoh network or router "
            f"ACL to keep them from meeting at all)"
        )

    def stats(self) -> dict[str, Any]:
        """``other_fleets``: fleet -> its robots seen now (bounded); ``other_fleet_tokens``: all seen."""
        with self._lock:
            return {
                "other_fleets": {f: list(r) for f, r in self._now.items()},
                "other_fleet_tokens": self._tokens,
            }
