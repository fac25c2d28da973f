"""A simulated channel with a fake clock for :class:`~transports.uwb.arq.ArqEndpoint` nodes.

Each frame a node writes occupies its line for ``len * 8 / rate`` seconds, then reaches every other
node through a seeded :class:`~transports.uwb.faults.FaultInjector` of its own (so receivers of a
broadcast lose different frames). With ``shared=True`` all nodes share one channel's airtime, as on a
half-duplex radio. Runs are exact and repeatable: the tests use it to check delivery rules under
loss, duplication, reordering, corruption and outages in milliseconds of real time.
"""

from __future__ import annotations

import heapq
import random
from collections.abc import Callable

from transports.uwb.arq import ArqEndpoint, Event, MessageReceived
from transports.uwb.faults import FaultInjector, Faults


class SimNet:
    """Endpoints joined by a simulated line; ``now`` is the fake clock."""

    def __init__(
        self,
        endpoints: list[ArqEndpoint],
        *,
        faults: Faults | None = None,
        seed: int = 0,
        rate_bps: float | None = None,
        shared: bool = False,
        split: bool = False,
    ) -> None:
        self.nodes: dict[int, ArqEndpoint | None] = {ep.node: ep for ep in endpoints}
        self.faults = faults or Faults()
        self.seed = seed
        self.rate_bps = rate_bps
        self.shared = shared
        self.split = split
        self.now = 0.0
        self._rng = random.Random(seed)
        self._queue: list[tuple[float, int, int, bytes]] = []
        self._seq = 0
        self._busy: dict[int, float] = {}
        self._inj: dict[tuple[int, int], FaultInjector] = {}
        self.events: dict[int, list[Event]] = {n: [] for n in self.nodes}
        self.tx_log: dict[int, list[tuple[float, int]]] = {n: [] for n in self.nodes}

    def injector(self, src: int, dst: int) -> FaultInjector:
        key = (src, dst)
        if key not in self._inj:
            self._inj[key] = FaultInjector(self.faults, seed=hash((self.seed, src, dst)) & 0xFFFFFFFF)
        return self._inj[key]

    def replace(self, node: int, endpoint: ArqEndpoint | None) -> None:
        """Swap a node's endpoint (a restart), or take it off the channel (None)."""
        self.nodes[node] = endpoint
        self.events.setdefault(node, [])
        self.tx_log.setdefault(node, [])

    def received(self, node: int) -> list[MessageReceived]:
        return [e for e in self.events[node] if isinstance(e, MessageReceived)]

    def _transmit(self, src: int, frame: bytes, rate: float) -> None:
        lane = 0 if self.shared else src
        start = max(self.now, self._busy.get(lane, 0.0))
        end = start + len(frame) * 8 / rate
        self._busy[lane] = end
        self.tx_log[src].append((self.now, len(frame)))
        for dst in self.nodes:
            if dst == src:
                continue
            for delay, data in self.injector(src, dst).apply(frame, start, end):
                self._push(end + delay, dst, data)

    def _push(self, t: float, dst: int, data: bytes) -> None:
        pieces = [data]
        if self.split and len(data) > 2:
            cut = sorted(self._rng.sample(range(1, len(data)), k=min(2, len(data) - 1)))
            pieces = [data[a:b] for a, b in zip([0, *cut], [*cut, len(data)], strict=True)]
        for piece in pieces:
            self._seq += 1
            heapq.heappush(self._queue, (t, self._seq, dst, piece))

    def _pump(self) -> None:
        for node, ep in self.nodes.items():
            if ep is None:
                continue
            rate = self.rate_bps or ep.cfg.rate_bps
            while frame := ep.data_to_send(self.now):
                self._transmit(node, frame, rate)
            self.events[node].extend(ep.events())

    def run(self, until: float, stop: Callable[[], bool] | None = None, max_steps: int = 2_000_000) -> bool:
        """Advance the clock to ``until`` or until ``stop()`` is true (returned); raise on a livelock."""
        steps = same = 0
        while True:
            self._pump()
            if stop is not None and stop():
                return True
            timers = [t for ep in self.nodes.values() if ep is not None and (t := ep.get_timer()) is not None]
            nxt = min([*timers, self._queue[0][0]] if self._queue else timers, default=None)
            if nxt is None or nxt > until:
                self.now = until
                self._pump()
                return stop() if stop is not None else False
            if nxt <= self.now:
                same += 1
                if same > 10_000:
                    raise RuntimeError(f"sim: livelock at t={self.now}: timers do not advance")
            else:
                same = 0
            self.now = max(self.now, nxt)
            while self._queue and self._queue[0][0] <= self.now:
                _, _, dst, data = heapq.heappop(self._queue)
                ep = self.nodes.get(dst)
                if ep is not None:
                    ep.receive_data(data, self.now)
            for ep in self.nodes.values():
                if ep is not None and (t := ep.get_timer()) is not None and t <= self.now:
                    ep.handle_timer(self.now)
            steps += 1
            if steps > max_steps:
                raise RuntimeError("sim: too many steps")
