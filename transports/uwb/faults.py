"""Seeded line faults, shared by the simulated wire (``sim.py``) and the pty relay (``relay.py``).

A :class:`FaultInjector` takes one frame's bytes (as cut at the 0x00 delimiter) and the time it
starts on the line, and returns what arrives: nothing (dropped, or cut by an outage), the bytes with
some bits flipped, a copy more (duplicated), or the bytes late (reordered behind later frames).
Outages are windows of time, relative to the start of the run, in which the line carries nothing; a
frame that straddles an outage's start arrives truncated, as a cut cable would leave it.
"""

from __future__ import annotations

import math
import random
from dataclasses import dataclass


@dataclass(frozen=True)
class Faults:
    """What the line does wrong. Probabilities are per frame, except ``flip`` (per byte)."""

    drop: float = 0.0
    dup: float = 0.0
    flip: float = 0.0
    reorder: float = 0.0
    reorder_delay_s: float = 0.05
    outages: tuple[tuple[float, float], ...] = ()  # (start s, duration s) from the run's start
    latency_s: float = 0.0

    @property
    def clean(self) -> bool:
        return not (self.drop or self.dup or self.flip or self.reorder or self.outages)


@dataclass
class FaultStats:
    frames: int = 0
    dropped: int = 0
    duplicated: int = 0
    flipped_bits: int = 0
    reordered: int = 0
    cut: int = 0


class FaultInjector:
    """Applies :class:`Faults` to frames with its own seeded random generator."""

    def __init__(self, faults: Faults, seed: int = 0, t0: float = 0.0) -> None:
        self.faults = faults
        self.t0 = t0
        self._rng = random.Random(seed)
        self.stats = FaultStats()
        #: Extra outages in absolute time (start, end), e.g. a relay's manual cut.
        self.cuts: list[tuple[float, float]] = []

    def windows(self) -> list[tuple[float, float]]:
        """Every outage as absolute (start, end)."""
        return [(self.t0 + s, self.t0 + s + d) for s, d in self.faults.outages] + self.cuts

    def outage_at(self, t: float) -> tuple[float, float] | None:
        """The outage window (absolute start, end) covering time ``t``, if any."""
        for start, end in self.windows():
            if start <= t < end:
                return start, end
        return None

    def _cut(self, data: bytes, t_start: float, t_end: float) -> bytes:
        """What of a frame on the line from ``t_start`` to ``t_end`` survives outages."""
        if self.outage_at(t_start) is not None:
            return b""
        for start, _end in self.windows():
            if t_start < start < t_end:
                keep = int(len(data) * (start - t_start) / (t_end - t_start))
                return data[:keep]
        return data

    def apply(self, data: bytes, t_start: float, t_end: float | None = None) -> list[tuple[float, bytes]]:
        """Deliveries for one frame: a list of (extra delay in s, bytes)."""
        f = self.faults
        rng = self._rng
        self.stats.frames += 1
        out = self._cut(data, t_start, t_start if t_end is None else t_end)
        if len(out) < len(data):
            self.stats.cut += 1
            if not out:
                return []
        if f.drop and rng.random() < f.drop:
            self.stats.dropped += 1
            return []
        if f.flip:
            buf = bytearray(out)
            # Geometric skips: the cost is per flip, not per byte.
            i = self._skip(f.flip)
            while i < len(buf):
                buf[i] ^= 1 << rng.randrange(8)
                self.stats.flipped_bits += 1
                i += 1 + self._skip(f.flip)
            out = bytes(buf)
        delay = f.latency_s
        if f.reorder and rng.random() < f.reorder:
            self.stats.reordered += 1
            delay += f.reorder_delay_s
        deliveries = [(delay, out)]
        if f.dup and rng.random() < f.dup:
            self.stats.duplicated += 1
            deliveries.append((delay, out))
        return deliveries

    def _skip(self, p: float) -> int:
        if p >= 1.0:
            return 0
        u = self._rng.random()
        denom = math.log1p(-p)
        if denom == 0.0:  # p too small to matter
            return 1 << 62
        return int(min(math.log1p(-u) / denom, 1 << 62))
