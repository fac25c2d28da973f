"""An optimistic bound on a fleet's staleness: one scheduler that knows everything (``--bound``).

The real protocol pays for what robots do not know: acks, HELLOs, summaries, keyframe requests, maps
resent after a timeout, slots nobody needed. This module asks how stale the same fleet would be on
the same channel (the same map streams, paths, walls, codec and slot) if a single scheduler knew
every robot's position and every map each one holds, and spent the channel as well as it can:

* Time is cut into the daemon's TDMA slots; a slot carries :data:`~transports.uwb.pacing.SLOT_FRAMES`
  chunks of the real ARQ core's chunk size (after frame headers and, signed, the link trailer). A
  message is the real signed envelope (:class:`~mapd.bench.swarm.streams.Payloads`) and its hash.
* At each slot, every robot not already sending is offered the channel, best offer first. Its offer
  is the *item* that sheds the most squared staleness per slot it costs: its own newest version,
  whole or as a delta on any version a neighbour holds, or any map of another robot it holds,
  unaltered (a relay may not re-code a map: the origin signed it). An item serves every neighbour
  that lacks that version and can decode it (holds its base), and sheds for each the square of the
  age of the oldest version it misses (so the stalest holders weigh most, as they do in the p95).
* ``turns`` keeps the daemon's TDMA: slot ``k`` belongs to robot ``k % n``, an item goes one slot
  per own turn, and a robot with nothing to send lends its turn to the one with the most slots left
  (R17). It prices the fixed turns, against ``one``.
* ``one`` admits one sender in the whole building at a time (TDMA with perfect turn lending);
  ``reuse`` admits more while no sender hears another and no receiver served hears two (spatial
  reuse, with no carrier-sense or slot-assignment cost).
* ``reach`` drops the channel altogether: every slot, each robot gets the newest of every map held or
  made by anyone connected to it over any number of hops. What staleness is left comes from robots
  with no path between them at the time, which no radio of that range can fix.
* Walls cost airtime, not maps: an item's slots are divided by ``(1 - wall_loss) ** walls`` for the
  worst-placed neighbour it serves, the cost of a perfect repair. Frame loss (``--loss``) likewise.
* Nothing else is sent: no acks, HELLOs, summaries or requests.

The scheduler is greedy, so it is not optimal and its figure is no proof; but it pays none of the
real protocol's costs and knows what no robot can know, so a protocol close to it has little left to
gain from scheduling, and a target well below it needs more capacity (spatial reuse, a faster radio,
fewer bytes per map) rather than a better protocol. The report gives the same staleness figures as a
real run (:func:`~mapd.bench.swarm.metrics.staleness_samples`), so the two read side by side.
"""

from __future__ import annotations

import bisect
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mapd.bench.swarm.metrics import convergence, staleness_samples
from mapd.bench.swarm.sim import SwarmConfig, Timeline, default_slot_s
from mapd.bench.swarm.streams import Fleet, Payloads
from transports.uwb import arq
from transports.uwb.pacing import SLOT_FRAMES
from transports.uwb.sending import HASH_LEN

#: Messages of each other robot a robot keeps to forward (the relay core's chain, plus slack).
KEEP = 8
MODES = ("turns", "one", "reuse", "reach")

#: An item: (origin, version, base); base 0 is a whole map.
Item = tuple[int, int, int]


@dataclass
class BoundResult:
    """What the scheduler did: the accept log (as a real run's), and how it used the slots."""

    n: int
    mode: str
    slot_s: float
    made: list[list[float]]
    accepted: list[tuple[float, int, int, int]]
    slots: int
    busy_slots: int
    sender_slots: int
    #: (first slot, end slot, sender, item, served): every transmission, for checks
    schedule: list[tuple[int, int, int, Item, tuple[int, ...]]] = field(default_factory=list)
    wall_s: float = 0.0


class Bound:
    """The scheduler over one fleet; :meth:`run` once."""

    def __init__(self, fleet: Fleet, payloads: Payloads, config: SwarmConfig, mode: str) -> None:
        if mode not in MODES:
            raise ValueError(f"bound mode {mode!r}: one of {', '.join(MODES)}")
        self.fleet, self.pay, self.cfg, self.mode = fleet, payloads, config, mode
        n = self.n = len(fleet.robots)
        self.timeline = Timeline.draw(fleet, config)  # the real run's start phases and versions
        self.made = self.timeline.made
        self.slot_s = (
            config.slot_s
            if config.slot_s is not None
            else default_slot_s(config.rate_bps, guard_s=config.guard_s)
        )
        probe = arq.ArqEndpoint(
            arq.ArqConfig(node_id=1, rate_bps=config.rate_bps, key=bytes(32) if config.signed else None),
            session=0,
        )
        self.slot_bytes = SLOT_FRAMES * probe.chunk_size
        self.newest = np.zeros((n, n), dtype=np.int64)  # [holder, origin]
        self.held: list[list[set[int]]] = [[set() for _ in range(n)] for _ in range(n)]
        self.kept: list[dict[int, list[tuple[int, int]]]] = [{} for _ in range(n)]  # origin -> (v, base)
        self.hears = np.zeros((n, n), dtype=bool)
        self.walls = np.zeros((n, n), dtype=np.int32)
        self._sizes: dict[Item, int] = {}

    # --- the run --------------------------------------------------------------------------------
    def run(self) -> BoundResult:
        t0 = time.perf_counter()
        cfg = self.cfg
        last = max((m[-1] for m in self.made if m), default=0.0)
        slots = math.ceil((max(cfg.duration, last) + cfg.drain) / self.slot_s)
        links_every = max(1, round(cfg.links_dt / self.slot_s))
        res = BoundResult(self.n, self.mode, self.slot_s, self.made, [], slots, 0, 0)
        if self.mode == "reach":
            return self._run_reach(res, links_every, last, t0)
        if self.mode == "turns":
            return self._run_turns(res, links_every, last, t0)
        busy_until = [0] * self.n
        on_air: list[tuple[int, int, Item, tuple[int, ...]]] = []  # (end slot, sender, item, served)
        for k in range(slots):
            now = k * self.slot_s
            if k % links_every == 0:
                self._links(now)
            for tx in [tx for tx in on_air if tx[0] <= k]:
                on_air.remove(tx)
                self._deliver(tx[2], tx[3], now, res.accepted)
            offers = []
            for s in range(self.n):
                if busy_until[s] <= k:
                    best = self._offer(s, now)
                    if best is not None:
                        offers.append((best[0], s, best[1], best[2], best[3]))
            offers.sort(key=lambda o: (-o[0], o[1]))
            for _, s, item, served, cost in offers:
                if not self._admit(s, served, on_air):
                    continue
                busy_until[s] = k + cost
                on_air.append((k + cost, s, item, served))
                res.schedule.append((k, k + cost, s, item, served))
            if on_air:
                res.busy_slots += 1
                res.sender_slots += len(on_air)
            if not on_air and now > last and self._converged():
                res.slots = k + 1
                break
        return self._finish(res, t0)

    def _run_turns(self, res: BoundResult, links_every: int, last: float, t0: float) -> BoundResult:
        """The daemon's TDMA turns: slot ``k`` is robot ``k % n``'s, its item advances one slot per
        turn, and an owner with nothing to send lends its turn to the robot with the most slots left
        on its item (R17's choice)."""
        current: list[list[Any] | None] = [None] * self.n  # [slots left, first slot, item, served]
        for k in range(res.slots):
            now = k * self.slot_s
            if k % links_every == 0:
                self._links(now)
            s = k % self.n
            if current[s] is None:
                offer = self._offer(s, now)
                if offer is not None:
                    current[s] = [offer[3], k, offer[1], offer[2]]
            if current[s] is None:
                left = [(c[0], -i) for i, c in enumerate(current) if c is not None]
                if not left:
                    if now > last and self._converged():
                        res.slots = k + 1
                        break
                    continue
                s = -max(left)[1]
            item = current[s]
            assert item is not None
            res.busy_slots += 1
            res.sender_slots += 1
            item[0] -= 1
            if item[0] <= 0:
                current[s] = None
                self._deliver(item[2], item[3], now + self.slot_s, res.accepted)
                res.schedule.append((item[1], k + 1, s, item[2], item[3]))
        return self._finish(res, t0)

    def _run_reach(self, res: BoundResult, links_every: int, last: float, t0: float) -> BoundResult:
        """An unlimited channel: every slot, each robot gets the newest of every map that anyone
        connected to it (over any number of hops) holds or makes."""
        labels = np.zeros(self.n, dtype=np.int64)
        for k in range(res.slots):
            now = k * self.slot_s
            if k % links_every == 0:
                self._links(now)
                labels = _components(self.hears)
            for o in range(self.n):
                self.newest[o, o] = bisect.bisect_right(self.made[o], now)
            for c in np.unique(labels):
                members = np.flatnonzero(labels == c)
                best = self.newest[members].max(axis=0)
                for r in members:
                    for gain in np.flatnonzero(best > self.newest[r]):
                        res.accepted.append((now, int(r), int(gain), int(best[gain])))
                self.newest[members] = best
            res.busy_slots += 1
            if now > last and self._converged():
                res.slots = k + 1
                break
        res.sender_slots = res.busy_slots
        return self._finish(res, t0)

    # --- internals ------------------------------------------------------------------------------
    def _finish(self, res: BoundResult, t0: float) -> BoundResult:
        self.pay.flush()  # payload sizes encoded for the first time, kept for the next run
        res.accepted.sort()
        res.wall_s = time.perf_counter() - t0
        return res

    def _links(self, now: float) -> None:
        self.hears, self.walls = self.timeline.links(now)

    def _size(self, item: Item) -> int:
        n = self._sizes.get(item)
        if n is None:
            o, v, b = item
            n = self._sizes[item] = self.pay.size(self.fleet.robots[o], v, b) + HASH_LEN
        return n

    def _candidates(self, s: int, nbrs: np.ndarray, now: float) -> list[Item]:
        out: list[Item] = []
        own = bisect.bisect_right(self.made[s], now)  # own versions made by now
        if own:
            bases = {0} | {int(b) for b in self.newest[nbrs, s] if 0 < b < own} if self.pay.uses_base else {0}
            out += [(s, own, b) for b in sorted(bases)]
        for o, kept in self.kept[s].items():
            out += [(o, v, b) for v, b in kept]
        return out

    def _offer(self, s: int, now: float) -> tuple[float, Item, tuple[int, ...], int] | None:
        """(staleness shed per slot, item, neighbours served, slots) of robot ``s``'s best item."""
        nbrs = np.flatnonzero(self.hears[s])
        if nbrs.size == 0:
            return None
        best: tuple[float, Item, tuple[int, ...], int] | None = None
        best_key = (-math.inf, 0)
        for o, v, b in self._candidates(s, nbrs, now):
            served = tuple(
                int(r) for r in nbrs
                if r != o and self.newest[r, o] < v and (b == 0 or b in self.held[r][o])
            )  # fmt: skip
            if not served:
                continue
            # squared ages weigh the stalest holders most, as the p95 does (of sum, square, cube,
            # max and count of holders, the square gave the lowest p95 in the building at 16 robots)
            shed = sum(
                max(1.0, now - self.made[o][min(int(self.newest[r, o]), len(self.made[o]) - 1)]) ** 2
                for r in served
            )
            worst = max(int(self.walls[s, r]) for r in served)
            ok = (1.0 - self.cfg.loss) * (1.0 - self.cfg.wall_loss) ** worst
            size = self._size((o, v, b))
            cost = max(1, math.ceil(size / self.slot_bytes / max(ok, 1e-3)))
            key = (shed / cost, -size)  # of items costing as many slots, the fewer bytes
            if key > best_key:
                best, best_key = (key[0], (o, v, b), served, cost), key
        return best

    def _admit(
        self, s: int, served: tuple[int, ...], on_air: list[tuple[int, int, Item, tuple[int, ...]]]
    ) -> bool:
        if not on_air:
            return True
        if self.mode == "one":
            return False
        hears = self.hears
        for _, a, _, a_served in on_air:
            if (
                a == s
                or hears[s, a]
                or any(hears[a, r] for r in served)
                or any(hears[s, r] for r in a_served)
            ):
                return False
        return True

    def _deliver(
        self, item: Item, served: tuple[int, ...], now: float, log: list[tuple[float, int, int, int]]
    ) -> None:
        o, v, b = item
        for r in served:
            if self.newest[r, o] >= v or (b and b not in self.held[r][o]):
                continue  # another sender got there first, or the base went (it does not here)
            self.held[r][o].add(v)
            self.newest[r, o] = v
            kept = self.kept[r].setdefault(o, [])
            kept.append((v, b))
            del kept[:-KEEP]
            log.append((now, r, o, v))

    def _converged(self) -> bool:
        finals = np.array([len(m) for m in self.made])
        off = ~np.eye(self.n, dtype=bool)
        return bool((self.newest >= finals[None, :])[off & (finals[None, :] > 0)].all())


def _components(hears: np.ndarray) -> np.ndarray:
    """A label per robot: robots with the same label are connected over any number of hops."""
    n = len(hears)
    labels = np.full(n, -1, dtype=np.int64)
    for start in range(n):
        if labels[start] >= 0:
            continue
        labels[start] = start
        stack = [start]
        while stack:
            r = stack.pop()
            for m in np.flatnonzero(hears[r] & (labels < 0)):
                labels[m] = start
                stack.append(int(m))
    return labels


def summarize_bound(res: BoundResult, config: SwarmConfig) -> dict[str, Any]:
    """One row of the bound's table (and JSON), with the staleness figures of a real run's row."""
    st = staleness_samples(res.made, res.accepted, config.duration)
    p50, p95, mx = (float(np.percentile(st, q)) for q in (50, 95, 100)) if st.size else (0.0, 0.0, 0.0)
    return {
        "robots": res.n,
        "codec": config.codec,
        "senders": res.mode,
        "stale_p50_s": p50,
        "stale_p95_s": p95,
        "stale_max_s": mx,
        "stale_p95_periods": p95 / config.period,
        "converge_s": convergence(res.made, res.accepted, res.n),
        "versions": sum(len(m) for m in res.made),
        "accepted": len(res.accepted),
        "sends": len(res.schedule),
        "busy_share": res.busy_slots / max(1, res.slots),
        "senders_per_slot": res.sender_slots / max(1, res.busy_slots),
        "wall_s": res.wall_s,
    }
