"""When may the next frame go out: rate pacing and medium access, both pure (``now`` comes in).

:class:`Pacer` keeps the bytes a node writes at or under ``rate_bps`` over *every* window of
``window_s`` (1 s), resends and acks included. Two rules together: a token bucket one frame deep keeps
frames evenly spaced (a radio's small buffer never floods), and a log of the last window's writes
makes the bound exact, where a token bucket alone would allow ``rate + burst`` in some windows.

:class:`MediumAccess` shares one half-duplex channel between robots:

* ``none``: send whenever the pacer allows (a point-to-point link, or a radio with its own MAC);
* ``tdma``: time is cut into ``slots`` slots of ``slot_s`` seconds on a clock all robots share (the
  adapter passes the offset from its loop clock to wall time); a robot sends only in its own slot, and
  only a frame that ends ``guard_s`` before the slot does. An owner that has nothing more to send
  may lend the rest of its slot (:meth:`~MediumAccess.lend`): it sends nothing more in it, and the
  robot it named, told by a LEND frame, may send until the slot's end (:meth:`~MediumAccess.borrow`);
* ``backoff``: listen before talk: after hearing the channel busy, wait until it was quiet for
  ``sense_s`` plus a random backoff drawn from ``[backoff_min_s, backoff_max_s]`` (new after every
  frame), so two robots waiting for the same frame to end rarely start together. A robot that heard
  nothing recently sends at once, so a lone sender pays nothing. Carrier sense here means "bytes
  arrived": a radio that hands over a frame only once it is complete hides a frame still in the air,
  which is what TDMA avoids.
"""

from __future__ import annotations

import math
import random
from collections import deque
from typing import Literal

MacMode = Literal["none", "tdma", "backoff"]
#: Frames a default TDMA slot carries (583 ms at 12.5 kb/s and 224-byte frames, with the guard).
#: A 250 ms slot carried one, so a robot's own answers (gap reports, COMPLETEs, HELLO) took its
#: map's place, and 32 robots could use at most 57 % of the channel (the swarm bench, issue #22).
#: Five (727 ms) carry a median delta in one turn even after a DONE, but without turn lending
#: (R17 in ``arq.py``) whole maps (zstd) got staler, and with it four are as good at 32 robots
#: and better below (24 robots: p95 staleness 0.47 periods against 0.90).
SLOT_FRAMES = 4
_EPS = 1e-9


class ByteWindow:
    """Bytes written in the last ``window_s`` seconds, and the most any such window has held.

    The pacer bounds it; the adapter and the fault relay measure what really went over a line with
    it, so "peak bytes in any 1 s" means the same thing in all three.
    """

    def __init__(self, window_s: float = 1.0) -> None:
        self.window = window_s
        #: (time, bytes) of each write still inside the window, oldest first.
        self.entries: deque[tuple[float, int]] = deque()
        self.bytes = 0
        self.peak = 0

    def add(self, n: int, now: float) -> None:
        """Record ``n`` bytes written at ``now`` (times never go backwards)."""
        while self.entries and self.entries[0][0] <= now - self.window:
            self.bytes -= self.entries.popleft()[1]
        self.entries.append((now, n))
        self.bytes += n
        self.peak = max(self.peak, self.bytes)


class Pacer:
    """Token bucket (one frame deep) plus an exact sliding-window byte budget."""

    def __init__(self, rate_bps: float, burst_bytes: int, window_s: float = 1.0) -> None:
        if rate_bps <= 0 or burst_bytes <= 0:
            raise ValueError("pacer rate and burst must be positive")
        self.rate = rate_bps / 8.0  # bytes per second
        self.burst = float(burst_bytes)
        self.window = window_s
        self.budget = self.rate * window_s  # bytes allowed in any window
        if self.budget < burst_bytes:
            raise ValueError(
                f"a {window_s} s window at {rate_bps} b/s cannot carry a {burst_bytes}-byte frame"
            )
        self._tokens = self.burst
        self._t: float | None = None
        self._sent = ByteWindow(window_s)
        self.bytes_total = 0

    @property
    def peak_window_bytes(self) -> int:
        """The most bytes written in any one window so far."""
        return self._sent.peak

    def _tokens_at(self, now: float) -> float:
        if self._t is None:
            return self.burst
        return min(self.burst, self._tokens + max(0.0, now - self._t) * self.rate)

    def ready_at(self, n: int, now: float) -> float:
        """The earliest time (>= now) at which ``n`` bytes may be written (pure: state is unchanged)."""
        tokens = self._tokens_at(now)
        t_bucket = now if tokens >= n else now + (n - tokens) / self.rate + _EPS
        live = [(t_e, n_e) for t_e, n_e in self._sent.entries if t_e > now - self.window]
        excess = sum(n_e for _, n_e in live) + n - self.budget
        t_window = now
        if excess > 0:
            freed = 0
            for t_e, n_e in live:
                freed += n_e
                if freed >= excess:
                    t_window = t_e + self.window + _EPS
                    break
        return max(t_bucket, t_window)

    def consume(self, n: int, now: float) -> None:
        """Record that ``n`` bytes were written at ``now`` (callers check :meth:`ready_at` first)."""
        self._tokens = self._tokens_at(now) - n
        self._t = now
        self._sent.add(n, now)
        self.bytes_total += n


class MediumAccess:
    """Decides when this robot may start a frame on a shared channel (see the module docstring)."""

    def __init__(
        self,
        mode: MacMode,
        rate_bps: float,
        *,
        slot_s: float = 0.25,
        slots: int = 1,
        slot_index: int = 0,
        guard_s: float = 0.01,
        clock_offset: float = 0.0,
        sense_s: float = 0.02,
        backoff_min_s: float = 0.0,
        backoff_max_s: float = 0.1,
        rng: random.Random | None = None,
    ) -> None:
        self.mode = mode
        self.byte_time = 8.0 / rate_bps
        self.slot_s = slot_s
        self.slots = max(1, slots)
        self.slot_index = slot_index % self.slots
        self.guard_s = guard_s
        self.clock_offset = clock_offset
        self.sense_s = sense_s
        self.backoff_min_s = backoff_min_s
        self.backoff_max_s = backoff_max_s
        self._rng = rng or random.Random(0)
        self._heard = -1e18
        self._backoff = self._draw()
        # When the own radio is done with the frames handed to it: a link drains a write into the
        # radio's buffer long before the frame is on the air, and TDMA must count from the end.
        self._tx_end = -math.inf
        self._lent = -1  # the own slot (its number) whose rest was lent
        self._borrowed = -1  # the other's slot (its number) whose rest is ours

    def _draw(self) -> float:
        return self._rng.uniform(self.backoff_min_s, self.backoff_max_s)

    def heard(self, now: float) -> None:
        """Bytes arrived from the channel at ``now`` (carrier sense)."""
        self._heard = max(self._heard, now)

    def ready_at(self, n: int, now: float) -> float:
        """The earliest time (>= now) at which an ``n``-byte frame may start."""
        airtime = n * self.byte_time
        if self.mode == "tdma":
            return self._tdma(airtime, max(now, self._tx_end))
        if self.mode == "backoff":
            return max(now, self._heard + self.sense_s + self._backoff)
        return now

    def slot_number(self, now: float) -> int:
        """The number of the TDMA slot ``now`` falls in, on the shared clock (slots since its epoch;
        -1 before the first ``now``, which an endpoint holds as minus infinity)."""
        t = now + self.clock_offset
        return math.floor(t / self.slot_s) if math.isfinite(t) else -1

    def own_slot_left(self, now: float) -> float:
        """Seconds this robot may still send in its own slot at ``now`` (0: not its slot, or lent)."""
        if self.mode != "tdma" or not math.isfinite(now):
            return 0.0
        now = max(now, self._tx_end)  # the next frame starts once the radio is done
        k = self.slot_number(now)
        if k % self.slots != self.slot_index or k == self._lent:
            return 0.0
        return max(0.0, (k + 1) * self.slot_s - self.guard_s - (now + self.clock_offset))

    def in_own_slot(self, t0: float, t1: float) -> bool:
        """Whether the interval ``[t0, t1]`` (loop times) overlaps this robot's own TDMA slot, one
        it did not lend, before the slot's guard."""
        if self.mode != "tdma" or not (math.isfinite(t0) and math.isfinite(t1)) or t1 < t0:
            return False
        for k in range(self.slot_number(t0), self.slot_number(t1) + 1):
            if k % self.slots != self.slot_index or k == self._lent:
                continue
            start = k * self.slot_s - self.clock_offset
            if t1 > start and t0 < start + self.slot_s - self.guard_s:
                return True
        return False

    def lend(self, now: float) -> None:
        """The rest of the own slot at ``now`` is lent: send nothing more in it."""
        self._lent = self.slot_number(now)

    def borrow(self, now: float) -> None:
        """The rest of the (other robot's) slot at ``now`` is ours."""
        self._borrowed = self.slot_number(now)

    def _tdma(self, airtime: float, now: float) -> float:
        cycle = self.slots * self.slot_s
        t = now + self.clock_offset
        if not math.isfinite(t):
            return now  # no time yet: nothing is due before the first real one
        k = self.slot_number(now)
        if k == self._borrowed and t + airtime <= (k + 1) * self.slot_s - self.guard_s:
            return now
        phase = t % cycle
        start = self.slot_index * self.slot_s
        end = start + self.slot_s - self.guard_s
        if start <= phase and phase + airtime <= end and k != self._lent:
            return now
        return self.next_own_slot(now)

    def next_own_slot(self, now: float) -> float:
        """When this robot's next own slot starts (the one after the current, if in it)."""
        cycle = self.slots * self.slot_s
        t = now + self.clock_offset
        phase = t % cycle
        start = self.slot_index * self.slot_s
        nxt = t - phase + (start if phase < start else cycle + start)
        return nxt - self.clock_offset + _EPS

    def sent(self, n: int, now: float) -> None:
        """A frame of ``n`` bytes was handed to the radio at ``now``: it is on the air from then, or
        from the end of the one before; draw the next backoff."""
        self._tx_end = max(now, self._tx_end) + n * self.byte_time
        self._backoff = self._draw()
