"""The log lines for robots that come, go and restart (sans-I/O: ``now`` comes in, lines go out).

``mapd status`` showed a peer ``gone`` and ``up`` again, but the log said nothing: after a radio
outage, or a robot killed and started again, an operator reading the journal found no trace of
either. Each change is now one info line (``robot1 not heard on uwb any more``, ``robot1 back on
uwb after 27 s``, ``robot1 restarted``). A robot at the edge of range comes and goes every few
seconds: past :data:`FLAP_CHANGES` changes in :data:`FLAP_WINDOW_S` on one link, that is said once
and its changes go unlogged for a window (``mapd status`` still shows where it is), so the
journal never fills with them.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

#: Changes of one robot on one link within FLAP_WINDOW_S seconds past which they go unlogged.
FLAP_CHANGES = 6
FLAP_WINDOW_S = 600.0
#: A robot's restart is said at most this often (seconds): forged HELLOs cannot fill the log.
RESTART_SAY_S = 60.0


@dataclass
class _Seen:
    present: bool
    since: float
    changes: deque[float] = field(default_factory=lambda: deque(maxlen=FLAP_CHANGES + 1))
    quiet_until: float = 0.0


class PresenceLog:
    """Which robots were last said present on which link; :meth:`change` gives the line to log."""

    def __init__(self) -> None:
        self._seen: dict[tuple[str, str], _Seen] = {}
        self._restart_said: dict[str, float] = {}

    def change(self, robot: str, transport: str, present: bool, now: float) -> str | None:
        """The line for ``robot`` coming (``present``) or going on ``transport`` at ``now``; None
        when it is no change, or one of a robot that keeps coming and going (said once)."""
        key = (robot, transport)
        seen = self._seen.get(key)
        if seen is None:
            self._seen[key] = _Seen(present, now)
            return f"{robot} heard on {transport}" if present else None
        if seen.present == present:
            return None
        gone_for = now - seen.since
        seen.present, seen.since = present, now
        seen.changes.append(now)
        if now < seen.quiet_until:
            return None
        if len(seen.changes) > FLAP_CHANGES and now - seen.changes[0] <= FLAP_WINDOW_S:
            seen.quiet_until = now + FLAP_WINDOW_S
            return (
                f"{robot} comes and goes on {transport} ({len(seen.changes)} changes in "
                f"{now - seen.changes[0]:.0f} s: at the edge of its range?); its comings and goings go "
                f"unlogged for {FLAP_WINDOW_S / 60:.0f} minutes (mapd status shows it)"
            )
        if present:
            return f"{robot} back on {transport} after {gone_for:.0f} s"
        return f"{robot} not heard on {transport} any more"

    def restarted(self, robot: str, transport: str, now: float) -> str | None:
        """The line for ``robot`` restarting (a new session on ``transport``), at most once per
        :data:`RESTART_SAY_S`."""
        if now - self._restart_said.get(robot, -RESTART_SAY_S) < RESTART_SAY_S:
            return None
        self._restart_said[robot] = now
        return f"{robot} restarted (a new session on {transport}): it gets this robot's next map whole"

    def forget(self, robot: str) -> None:
        """Drop a robot (revoked): it is no longer one of the fleet's."""
        for key in [k for k in self._seen if k[0] == robot]:
            del self._seen[key]
        self._restart_said.pop(robot, None)
