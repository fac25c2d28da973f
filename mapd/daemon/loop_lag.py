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

A hold has two causes that call for different fixes, so each tick also brings the CPU time the
loop's thread used while the watcher slept (``time.thread_time``, which only that thread's own work
advances). A loop that *ran* for a third of the hold or more was running code that belongs in a
worker (a bug of mapd or of a plugin: :func:`cause` says ``busy``); one that ran less was
*waiting*: for a core, for the GIL held by another thread, for memory swapped out, stopped, or
blocked in a call (a write to a slow disk made on the loop; ``waiting``).
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
#: A hold during which the loop's thread ran at least this share of the time was the loop's own
#: work. A third, not a half: on a computer that gives mapd a third of a core, a callback that runs
#: a whole second on the loop still holds it three, and is still the bug. A loop that only waits
#: runs its usual few per cent meanwhile.
BUSY_SHARE = 1 / 3


def finite(v: Any) -> float | None:
    """``v`` when it is a finite number, else None (a status document comes from another process)."""
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        return None
    return float(v)


def cause(lag_ms: Any, ran_ms: Any) -> str | None:
    """``busy`` when the loop's thread ran for at least :data:`BUSY_SHARE` of a hold of ``lag_ms``,
    ``waiting`` when it ran less, None when either is unknown (a daemon from before ``ran``, or a
    status document that is not numbers)."""
    lag, ran = finite(lag_ms), finite(ran_ms)
    if lag is None or ran is None or lag <= 0:
        return None
    return "busy" if ran >= BUSY_SHARE * lag else "waiting"


class LagMeter:
    """The event loop's lateness, fed by :func:`watch` (sans-I/O: no clock, no logging here)."""

    def __init__(self, period_s: float = PERIOD_S, recent_s: float = RECENT_S) -> None:
        self.period_s = period_s
        self.recent_s = recent_s
        #: (when, lag) of the ticks within ``recent_s``, oldest first (bounded by the tick rate too).
        self._recent: deque[tuple[float, float]] = deque(maxlen=int(recent_s / period_s) + 16)
        self.max_s = 0.0
        self.stalls = 0
        # (when it ended, how long, the loop thread's CPU time meanwhile or None when not measured)
        self.last_stall: tuple[float, float, float | None] | None = None
        self._said_at = -math.inf
        self._unsaid = 0  # stalls of SAY_S or more since the last one said

    def tick(self, lag_s: float, now: float, ran_s: float | None = None) -> str | None:
        """The watcher woke ``lag_s`` later than it asked to, at ``now`` (monotonic seconds), and
        the loop's thread used ``ran_s`` s of CPU time since the watcher went to sleep (None: not
        measured). Returns a warning to log when this was a stall worth saying, else None."""
        lag_s = max(0.0, lag_s)
        if ran_s is not None:
            ran_s = min(max(0.0, ran_s), lag_s + self.period_s)
        self.max_s = max(self.max_s, lag_s)
        self._recent.append((now, lag_s))
        self._trim(now)
        if lag_s < STALL_S:
            return None
        self.stalls += 1
        self.last_stall = (now, lag_s, ran_s)
        if lag_s < SAY_S:
            return None
        self._unsaid += 1
        if now - self._said_at < SAY_EVERY_S:
            return None
        more = self._unsaid - 1
        self._said_at, self._unsaid = now, 0
        since = f" ({more} more of {SAY_S:g} s or longer since the last said)" if more > 0 else ""
        held = f"the event loop was held {lag_s:.2f} s{since}"
        if ran_s is None:
            return (
                f"{held}: radio turns, acks and timers waited. Is the computer overloaded, swapping, "
                f"or was the process stopped? (mapd status: loop)"
            )
        if cause(lag_s, ran_s) == "busy":
            return (
                f"{held}, running code on it for {ran_s:.2f} s: radio turns, acks and timers waited on "
                f"work that belongs in a worker thread, a bug of mapd or of a plugin. Please report it "
                f"with this log; if it recurs, `systemctl kill -s USR1 mapd` while it is held writes "
                f"every thread's stack to the journal (mapd status: loop)"
            )
        return (
            f"{held}, waiting (it ran {ran_s:.2f} s of it): radio turns, acks and timers waited. Is the "
            f"computer overloaded or swapping, was the process stopped, or did a call on the loop block "
            f"(a slow disk)? (mapd status: loop)"
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
            # the loop thread's CPU time during the last stall: mostly its own work, or waiting
            "last_stall_ran_ms": round(last[2] * 1000) if last and last[2] is not None else None,
            "last_stall_ago_s": round(now - last[0], 1) if last else None,
        }

    def _trim(self, now: float) -> None:
        while self._recent and self._recent[0][0] <= now - self.recent_s:
            self._recent.popleft()


async def watch(
    meter: LagMeter,
    clock: Callable[[], float] = time.monotonic,
    cpu: Callable[[], float] = time.thread_time,
) -> None:
    """Sleep ``meter.period_s`` again and again, feeding ``meter`` how late each wake-up came and
    the CPU time the loop's thread used meanwhile (``cpu`` is read on that thread: this task runs
    there). The daemon's task ``loop-lag``; cancelled at stop."""
    while True:
        due, ran = clock() + meter.period_s, cpu()
        await asyncio.sleep(meter.period_s)
        now = clock()
        said = meter.tick(now - due, now, cpu() - ran)
        if said:
            log.warning(said)
