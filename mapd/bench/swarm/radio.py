"""A broadcast radio medium, sans-I/O: airtime at a rate, collisions at receivers, loss, range and walls.

No clock: every call takes ``now``. The caller (the swarm's event loop) asks :meth:`Radio.transmit`
to put a frame on the air, gets back its :class:`Transmission` (start and end), and calls
:meth:`Radio.finish` at the end time, which says which receivers got the bytes. The model:

* **Airtime.** A frame of ``n`` bytes occupies its sender for ``8 n / rate`` seconds. A node's radio
  sends one frame at a time; a frame handed over while it is busy starts when the previous ends.
* **Who hears whom.** :meth:`set_links` gives, for every ordered pair, whether the receiver is in
  range of the sender and through how many walls (see :mod:`mapd.bench.swarm.links`). Out of range:
  nothing arrives and nothing interferes.
* **Collisions.** A frame is lost at a receiver when any other frame it can hear overlaps it in time
  (no capture effect), or when the receiver is itself sending then (half-duplex: ``deaf``).
* **Loss.** A frame that survived collisions is lost with probability ``1 - (1 - loss) (1 -
  wall_loss) ** walls``, drawn per (frame, receiver) from one seeded generator.
* **Carrier sense.** A receiver learns of a frame only when its bytes arrive (the end of the frame),
  as :class:`transports.uwb.pacing.MediumAccess` assumes. A collided frame arrives garbled (one byte
  changed, so its CRC fails and the core counts a CRC error), as the project's fault relay delivers
  frames that overlap in the air: the bytes still tell the receiver the channel was busy. Frames
  lost to range, walls or loss arrive not at all.

Links are taken at the frame's start. ``busy`` intervals (sender, start, end) are kept for the
channel-use figure; the caller reads and clears them.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)
class Transmission:
    """One frame on the air."""

    src: int
    data: bytes
    start: float
    end: float
    kind: str  # data, ack, hello, control: for the airtime split
    hears: np.ndarray  # bool per receiver: in range of src at the start
    walls: np.ndarray  # walls between src and each receiver at the start
    dst: int | None = None  # the one receiver an ack is for (None: data and hellos are for all)


@dataclass
class RadioCounters:
    """Frames and (frame, receiver) outcomes, for the report."""

    frames: int = 0
    bytes: int = 0
    airtime_s: float = 0.0
    delivered: int = 0
    collided: int = 0
    deaf: int = 0
    lost: int = 0
    by_kind: dict[str, float] = field(default_factory=dict)  # airtime per kind


class Radio:
    """One shared channel for ``n`` nodes (indices 0..n-1)."""

    def __init__(
        self, n: int, *, rate_bps: float = 12_500.0, loss: float = 0.0, wall_loss: float = 0.0, seed: int = 0
    ) -> None:
        if rate_bps <= 0:
            raise ValueError("rate must be positive")
        if not (0.0 <= loss <= 1.0 and 0.0 <= wall_loss <= 1.0):
            raise ValueError("loss probabilities must lie in [0, 1]")
        self.n = n
        self.rate = rate_bps
        self.loss = loss
        self.wall_loss = wall_loss
        self._rng = random.Random(seed)
        self.hears = ~np.eye(n, dtype=bool)  # hears[src, dst]
        self.walls = np.zeros((n, n), dtype=np.int32)
        self._tx_free = [0.0] * n
        self._air: list[Transmission] = []  # frames that may still overlap one not yet finished
        self.counters = RadioCounters()
        self.intervals: list[tuple[float, float]] = []

    def set_links(self, hears: np.ndarray, walls: np.ndarray | None = None) -> None:
        """Who hears whom from now on (``hears[src, dst]``; the diagonal is ignored) and through how many walls."""
        h = np.array(hears, dtype=bool)
        np.fill_diagonal(h, False)
        self.hears = h
        self.walls = (
            np.zeros((self.n, self.n), dtype=np.int32) if walls is None else np.asarray(walls, np.int32)
        )

    def airtime(self, nbytes: int) -> float:
        return 8.0 * nbytes / self.rate

    def busy_until(self, node: int) -> float:
        """When ``node``'s radio is free to start another frame."""
        return self._tx_free[node]

    def transmit(
        self, src: int, data: bytes, now: float, kind: str = "data", dst: int | None = None
    ) -> Transmission:
        """Put ``data`` on the air from ``src`` as soon as its radio is free."""
        start = max(now, self._tx_free[src])
        end = start + self.airtime(len(data))
        self._tx_free[src] = end
        tx = Transmission(src, data, start, end, kind, self.hears[src].copy(), self.walls[src].copy(), dst)
        self._air.append(tx)
        c = self.counters
        c.frames += 1
        c.bytes += len(data)
        c.airtime_s += end - start
        c.by_kind[kind] = c.by_kind.get(kind, 0.0) + (end - start)
        self.intervals.append((start, end))
        return tx

    def finish(self, tx: Transmission, now: float) -> list[tuple[int, bytes]]:
        """``tx`` has ended (``now`` is its end): ``(receiver, bytes)`` for every receiver that got
        bytes (``tx.data`` intact, or garbled by a collision)."""
        others = [o for o in self._air if o is not tx and o.start < tx.end and o.end > tx.start]
        # Forget frames that can no longer overlap anything unfinished.
        horizon = min((o.start for o in self._air if o.end >= now and o is not tx), default=now)
        self._air = [o for o in self._air if o.end > horizon]  # tx stays while it overlaps one unfinished
        got: list[tuple[int, bytes]] = []
        c = self.counters
        for dst in np.flatnonzero(tx.hears):
            d = int(dst)
            if any(o.src == d for o in others):
                c.deaf += 1
                continue
            if any(o.hears[d] for o in others):
                c.collided += 1
                got.append((d, garble(tx.data)))
                continue
            keep = (1.0 - self.loss) * (1.0 - self.wall_loss) ** int(tx.walls[d])
            if keep < 1.0 and self._rng.random() >= keep:
                c.lost += 1
                continue
            c.delivered += 1
            got.append((d, tx.data))
        return got


def garble(data: bytes) -> bytes:
    """``data`` with its middle byte changed (never to the 0x00 delimiter): a frame that fails its CRC."""
    if len(data) < 3:
        return data
    k = len(data) // 2
    b = data[k] ^ 0xA5 or 0x01
    return data[:k] + bytes([b]) + data[k + 1 :]


def channel_use(intervals: list[tuple[float, float]], t0: float, t1: float) -> float:
    """Share of [t0, t1] during which at least one frame was on the air (the union of intervals)."""
    if t1 <= t0:
        return 0.0
    busy = 0.0
    cur_s = cur_e = None
    for s, e in sorted(intervals):
        s, e = max(s, t0), min(e, t1)
        if e <= s:
            continue
        if cur_e is None or s > cur_e:
            if cur_e is not None and cur_s is not None:
                busy += cur_e - cur_s
            cur_s, cur_e = s, e
        else:
            cur_e = max(cur_e, e)
    if cur_e is not None and cur_s is not None:
        busy += cur_e - cur_s
    return busy / (t1 - t0)
