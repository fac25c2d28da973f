"""How late the daemon's event loop runs: the ``loop`` line of ``mapd status``, and a warning when
it was held.

Everything time-bound in a robot's mapd waits on its one event loop: TDMA turns and the radio's
writes, acks and resends, zenoh's presence, the watchdog, ``mapd status``. Encode, decode, verify,
merge and file writes run in worker threads for that reason (``tests/daemon/test_loop_stall.py``
holds each callback's CPU time under 50 ms). What the tests cannot see is the robot itself: a
slow or overloaded computer (the SLAM stack beside mapd), a worker thread that holds the GIL,
memory swapped out, the process stopped (``SIGSTOP``, a debugger). There the loop runs late, and
nothing said so. So a watcher task sleeps :data:`PERIOD_S` and measures how late it wakes: that is
how long the loop could run nothing.

:class:`LagMeter` keeps the measurements (sans-I/O: each ``tick`` brings ``now``): the largest
since start, the largest and the 99th percentile over the last :data:`RECENT_S`, and the *stalls*,
lags of :data:`STALL_S` or more. A stall of :data:`SAY_S` or more is said as a warning, the first
at once and later ones at most once per :data:`SAY_EVERY_S` with how many there were, so an
overloaded robot's log says it without filling. Bounded: one sample per tick, the last
:data:`RECENT_S` of them.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

log = logging.getLogger("mapd.daemon")

#: How often the watcher wakes (its cost: ten timer callbacks a second).
PERIOD_S = 0.1
#: The window of the recent figures (about 600 samples).
RECENT_S = 60.0
#: A lag this long or longer counts as a stall: a TDMA turn is about 580 ms, so a quarter second
#: late can push a frame past its slot's end.
STALL_S = 0.25
#: A stall this long or longer is said in the log.
SAY_S = 1.0
#: After a stall was said, the next is said no sooner than this, with how many came between.
SAY_EVERY_S = 60.0


class LagMeter:
    """The event loop's lateness, fed by :func:`watch` (sans-I/O: no clock, no logging here)."""

    def __init__(self, period_s: float = PERIOD_S, recent_s: float = RECENT_S) -> None:
        self.period_s = period_s
        self.recent_s = recent_s
        #: (when, lag) of the ticks within ``recent_s``, oldest first (bounded by the tick rate too).
        self._recent: deque[tuple[float, float]] = deque(maxlen=int(recent_s / period_s) + 16)
        self.max_s = 0.0
        self.stalls = 0
        self.last_stall: tuple[float, float] | None = None  # (when it ended, how long)
        self._said_at = -math.inf
        self._unsaid = 0  # stalls of SAY_S or more since the last one said

    def tick(self, lag_s: float, now: float) -> str | None:
        """The watcher woke ``lag_s`` later than it asked to, at ``now`` (monotonic seconds).
        Returns a warning to log when this was a stall worth saying, else None."""
        lag_s = max(0.0, lag_s)
        self.max_s = max(self.max_s, lag_s)
        self._recent.append((now, lag_s))
        self._trim(now)
        if lag_s < STALL_S:
            return None
        self.stalls += 1
        self.last_stall = (now, lag_s)
        if lag_s < SAY_S:
            return None
        self._unsaid += 1
        if now - self._said_at < SAY_EVERY_S:
            return None
        more = self._unsaid - 1
        self._said_at, self._unsaid = now, 0
        since = f" ({more} more of {SAY_S:g} s or longer since the last said)" if more > 0 else ""
        return (
            f"the event loop was held {lag_s:.2f} s{since}: radio turns, acks and timers waited. "
            f"Is the computer overloaded, swapping, or was the process stopped? (mapd status: loop)"
        )

    def stats(self, now: float) -> dict[str, Any]:
        """For ``mapd status``: the lag's largest and 99th percentile over the last ``recent_s``,
        the largest since start, and the stalls (with the last one's length and age), in ms and s."""
        self._trim(now)
        lags = sorted(lag for _, lag in self._recent)
        p99 = lags[min(len(lags) - 1, math.ceil(0.99 * len(lags)) - 1)] if lags else 0.0
        last = self.last_stall
        return {
            "period_ms": round(self.period_s * 1000),
            "recent_s": self.recent_s,
            "lag_ms_recent_max": round((lags[-1] if lags else 0.0) * 1000, 1),
            "lag_ms_recent_p99": round(p99 * 1000, 1),
            "lag_ms_max": round(self.max_s * 1000, 1),
            "stall_ms": round(STALL_S * 1000),
            "stalls": self.stalls,
            "last_stall_ms": round(last[1] * 1000) if last else None,
            "last_stall_ago_s": round(now - last[0], 1) if last else None,
        }

    def _trim(self, now: float) -> None:
        while self._recent and self._recent[0][0] <= now - self.recent_s:
            self._recent.popleft()


async def watch(meter: LagMeter, clock: Callable[[], float] = time.monotonic) -> None:
    """Sleep ``meter.period_s`` again and again, feeding ``meter`` how late each wake-up came (the
    daemon's task ``loop-lag``; cancelled at stop)."""
    while True:
        due = clock() + meter.period_s
        await asyncio.sleep(meter.period_s)
        now = clock()
        said = meter.tick(now - due, now)
        if said:
            log.warning(said)
