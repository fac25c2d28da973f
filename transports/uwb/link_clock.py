"""How a :class:`~transports.uwb.link.UwbLink` follows the wall clock: TDMA slots and the signing
counters' clock check count on it, while the link's loop runs on the event loop's monotonic clock,
so the link reads the wall clock's offset as it runs and passes each change to the core, with
whether a time service keeps it (the core's radio clock, R19, lets such a robot lead the turns).

A change within what a time service slews is followed quietly; a faster one is a step (NTP setting
a clock that booted behind), counted and logged. A step ahead also lets a signing counter that began
from the clock (none was saved) go on from the clock, so peers' marks from before do not refuse it.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from transports.uwb import arq
from transports.uwb.signing import clock_floor

log = logging.getLogger("mapd.uwb")

#: TDMA: the wall clock is read at least this often, so a step (NTP) moves the slots within it.
CLOCK_CHECK_S = 1.0
#: A change of the wall clock against the loop's smaller than this is scheduling jitter: followed,
#: but not counted or logged as a step.
CLOCK_STEP_S = 0.005
#: The fastest a time service slews the wall clock (chrony's maxslewrate is 83,333 ppm; ntpd's
#: 500 ppm): a change between two reads within this rate, plus CLOCK_STEP_S, is a slew (followed,
#: not counted); only a faster one is a step. A host slewing at 5 ms a second was logged as stepping.
MAX_SLEW_RATE = 0.1
#: Smaller changes than this are the two clocks read a few microseconds apart: not passed on.
CLOCK_FOLLOW_S = 1e-4


class ClockSide:
    """The wall clock's half of a link (a mixin: :class:`~transports.uwb.link.UwbLink` owns the
    state declared here)."""

    port: str
    _wall: Callable[[], float]
    #: Whether a time service keeps the wall clock (``mapd.wallclock.synchronized``; a test's own).
    _time_service: Callable[[], bool | None]
    #: When (loop time) the time service was last asked: once per CLOCK_CHECK_S, not every pass.
    _source_at: float
    _clock_read: tuple[float, float] | None
    clock_steps: int
    #: The signing counter began from the wall clock, none being saved.
    _counter_from_clock: bool

    def _follow_clock(self, core: arq.ArqEndpoint, now: float) -> None:
        """Pass the wall clock's offset from the loop's to the core when it moved (slew or step),
        and whether a time service keeps it (with radio time such a robot leads, never follows)."""
        # (asked only where a radio clock listens: a syscall a second for nothing otherwise)
        if core.cfg.radio_time and core.cfg.mac == "tdma" and now - self._source_at >= CLOCK_CHECK_S:
            self._source_at = now
            core.set_clock_source(self._time_service() is True)
        offset = self._wall() - now
        last, self._clock_read = self._clock_read, (now, offset)
        if abs(offset - core.cfg.clock_offset) >= CLOCK_FOLLOW_S:
            core.set_clock_offset(offset)
        if last is None:  # the first read (a config built without the offset is no step)
            return
        jump = offset - last[1]
        if abs(jump) >= CLOCK_STEP_S + MAX_SLEW_RATE * max(0.0, now - last[0]):
            self.clock_steps += 1
            log.warning("uwb %s: the wall clock stepped %+.3f s; TDMA slots follow it", self.port, jump)
            # A step ahead (NTP setting a clock that booted behind) left a counter begun from the
            # clock behind, with no saved one (a new or lost state), under the marks peers hold
            # from before: all its frames were "replayed" until a restart. It goes on from the
            # clock. Not a counter that was saved: a wrong step ahead (a GPS glitch) would put it
            # in the future, where peers refuse it even once the clock is right again.
            if jump > 0 and self._counter_from_clock and core.raise_counter(clock_floor(now + offset)):
                log.warning("uwb %s: the signing counter (begun from the clock) goes on from it", self.port)
