"""One swarm run: N :class:`~mapd.bench.swarm.node.SwarmRobot` on one :class:`~mapd.bench.swarm.radio.Radio`, in virtual time.

The event loop (:mod:`mapd.bench.swarm.des`) carries four kinds of events: a robot's new map
version (from its stream), the end of a frame on the air (the radio says who got it; each receiver's
ARQ core takes the bytes and is serviced at once), a robot's wake-up (its ARQ timer or its
publisher's deadline; stale wake-ups are skipped by generation), and a links update every
``links_dt`` seconds (positions from the streams, range and walls from :mod:`~mapd.bench.swarm.links`).

Robot ``i``'s stream starts at a random phase in ``[0, start_spread)`` (default one period).
Versions are made for ``duration`` seconds; the run then goes on, with no new versions, until every
robot holds every other robot's last version (converged) or ``drain`` more seconds have passed.
"""

from __future__ import annotations

import math
import random
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mapd.bench.swarm.des import Event, EventLoop
from mapd.bench.swarm.links import hop_counts, link_matrices
from mapd.bench.swarm.node import KEYFRAME_EVERY, AcceptLog, SwarmRobot
from mapd.bench.swarm.policy import ACK_SCOPES, RELAYS
from mapd.bench.swarm.radio import Radio, Transmission
from mapd.bench.swarm.streams import Fleet, Payloads
from transports.uwb import arq
from transports.uwb.framing import decode_frame
from transports.uwb.pacing import SLOT_FRAMES


def default_slot_s(rate_bps: float, max_frame: int = 224, guard_s: float = 0.01) -> float:
    """The daemon's default TDMA slot (``transports.uwb.pacing.SLOT_FRAMES`` full frames plus guard)."""
    return SLOT_FRAMES * max_frame * 8 / rate_bps + guard_s


#: The fleet's link key when ``signed`` (any 32 bytes: the cost is the trailer, not the key).
SIM_KEY = bytes(range(32))


@dataclass(frozen=True)
class SwarmConfig:
    """One run's settings."""

    codec: str = "lossless"
    period: float = 30.0
    duration: float = 600.0
    drain: float = 300.0
    rate_bps: float = 12_500.0
    loss: float = 0.0
    wall_loss: float = 0.0
    range_m: float = math.inf
    mac: str = "tdma"
    signed: bool = True
    seed: int = 0
    relay: str = "none"
    acks: str = "configured"
    links_dt: float = 2.0
    slot_s: float | None = None  # tdma slot; None: the daemon's default (SLOT_FRAMES frames + guard)
    #: The publisher's in-flight timeout (the daemon's INFLIGHT_TIMEOUT_S), or INFLIGHT_PER_PEER_S
    #: per peer waited for, if longer.
    inflight_s: float = 30.0
    keyframe_every: int = KEYFRAME_EVERY  # the publisher's schedule (the daemon's default)
    ack_mode: str = "auto"  # the ARQ core's acks (ArqConfig.acks; the daemon's default)
    lend: bool = True  # TDMA: lend the rest of an idle own slot (ArqConfig.lend; the daemon's default)
    fec: bool = True  # NACK mode: repair with parity chunks (ArqConfig.fec; the daemon's default)
    #: The publisher supersedes a map only once it is wholly on the air (P1 on a paced link: the
    #: daemon's uwb transport).
    hold: bool = True
    #: What a robot does when another comes into range (``node.ARRIVALS``; default P6, the daemon's).
    arrival: str = "offer"
    #: Each robot starts at a random moment in [0, start_spread) (default: one period), so robots do
    #: not make versions, or start sending, in lockstep (perfectly equal timers would collide forever).
    start_spread: float | None = None
    #: How far the robots' clocks may disagree (TDMA counts slots on them): each robot's is off by a
    #: seeded draw in [-clock_skew_s / 2, clock_skew_s / 2]. 0: one clock, as the daemon assumes.
    clock_skew_s: float = 0.0
    #: The clock TDMA's turns are counted on (the daemon's ``[transports.uwb] clock``): ``radio``
    #: agrees one over the radio where the robots' clocks are skewed (without skew each robot's is
    #: taken as kept by a time service, and no TIME frame is sent); ``system``: each robot's own.
    clock: str = "radio"
    #: TDMA: the quiet time at the end of each slot (the daemon's ``guard_ms``), which the default
    #: slot adds to its frames' time.
    guard_s: float = 0.01


@dataclass(frozen=True)
class Timeline:
    """What a run draws and where its robots are: each robot's ARQ session and seed, its start
    phase, when it makes each version, and who hears whom at a time. The real run and the bound
    (``bound.py``) share it, so both see the same fleet."""

    fleet: Fleet
    config: SwarmConfig
    seeds: list[tuple[int, int]]  # (session, seed) per robot
    phase: list[float]
    made: list[list[float]]  # per robot: the times its versions are made

    @classmethod
    def draw(cls, fleet: Fleet, config: SwarmConfig) -> Timeline:
        rng = random.Random(config.seed)
        seeds = [(rng.getrandbits(32), rng.getrandbits(32)) for _ in fleet.robots]
        spread = config.period if config.start_spread is None else config.start_spread
        phase = [rng.uniform(0.0, spread) for _ in fleet.robots]
        made = [
            [t + ph for t in s.times if t + ph <= config.duration]
            for s, ph in zip(fleet.robots, phase, strict=True)
        ]
        return cls(fleet, config, seeds, phase, made)

    def links(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """(hears, walls) at ``now``: positions from the streams, range and walls from ``links``."""
        pos = np.array([s.position(now - ph) for s, ph in zip(self.fleet.robots, self.phase, strict=True)])
        building = self.fleet.building if self.config.wall_loss > 0 else None
        return link_matrices(pos, self.config.range_m, building)


@dataclass
class SwarmResult:
    """What a run produced, for :mod:`mapd.bench.swarm.metrics`."""

    n: int
    config: SwarmConfig
    made: list[list[float]]  # per origin: made time of version k + 1
    accepted: AcceptLog
    radio: Radio
    robots: list[SwarmRobot]
    end: float
    wall_s: float
    events: int
    hears_all_share: float  # share of link updates in which every robot heard every other
    #: share of (link update, robot) in which the robot heard every other: issue #22's building is
    #: one where no robot hears all others, so this is 0 there
    robot_hears_all_share: float
    mean_degree: float  # mean number of robots each robot hears, over link updates
    ever_heard: np.ndarray  # (N, N) bool: holder ever in range of origin during the run
    extra: dict[str, Any] = field(default_factory=dict)
    #: at each link update: (time, (N, N) radio hops between robots, -1 for no path)
    hops: list[tuple[float, np.ndarray]] = field(default_factory=list)


class Swarm:
    """Wires streams, robots, radio and links together and runs them."""

    def __init__(self, fleet: Fleet, payloads: Payloads, config: SwarmConfig) -> None:
        self.fleet = fleet
        self.cfg = config
        n = len(fleet.robots)
        if n > 254:
            raise ValueError("at most 254 robots share one UWB channel (link ids 1..254)")
        self.n = n
        self.loop = EventLoop()
        self.radio = Radio(
            n, rate_bps=config.rate_bps, loss=config.loss, wall_loss=config.wall_loss, seed=config.seed
        )
        self.accepted: AcceptLog = []
        self.timeline = tl = Timeline.draw(fleet, config)
        skew = random.Random(f"clock-{config.seed}")  # its own draws: a run without skew is unchanged
        self._clocks = [skew.uniform(-0.5, 0.5) * config.clock_skew_s for _ in range(n)]
        relay = RELAYS[config.relay]()
        acks = ACK_SCOPES[config.acks]()
        self.robots = [
            SwarmRobot(
                i,
                n,
                fleet.robots,
                payloads,
                self._arq_config(i),
                relay=relay,
                acks=acks,
                accepted=self.accepted,
                session=tl.seeds[i][0],
                seed=tl.seeds[i][1],
                inflight_s=config.inflight_s,
                keyframe_every=config.keyframe_every,
                hold=config.hold,
                arrival=config.arrival,
            )
            for i in range(n)
        ]
        for robot in self.robots:  # skewed clocks are no time service's (one clock is)
            robot.arq.set_clock_source(config.clock_skew_s == 0)
        self.made = tl.made
        self._gen = [0] * n
        self._wake_at: list[float | None] = [None] * n
        self._final = [len(m) for m in self.made]
        self._newest = np.zeros((n, n), dtype=np.int64)  # holder, origin
        self._done_pairs = 0
        self._pairs = sum(1 for h in range(n) for o in range(n) if h != o and self._final[o] > 0)
        self._links_seen = 0
        self._links_full = 0
        self._robot_full = 0.0
        self._degree = 0.0
        self._ever = np.zeros((n, n), dtype=bool)
        self._hops: list[tuple[float, np.ndarray]] = []

    def _arq_config(self, i: int) -> arq.ArqConfig:
        c = self.cfg
        mac = c.mac
        return arq.ArqConfig(
            node_id=i + 1,
            rate_bps=c.rate_bps,
            mac="none" if mac == "none" else "tdma" if mac == "tdma" else "backoff",
            slots=self.n,
            slot_s=c.slot_s if c.slot_s is not None else default_slot_s(c.rate_bps, guard_s=c.guard_s),
            guard_s=c.guard_s,
            slot_index=i,
            key=SIM_KEY if c.signed else None,
            max_peers=max(64, self.n),
            acks=c.ack_mode,  # type: ignore[arg-type]  # checked by ArqConfig
            lend=c.lend,
            fec=c.fec,
            clock_offset=self._clocks[i],
            radio_time=c.clock == "radio",
        )

    # --- the run --------------------------------------------------------------------------------
    def run(self) -> SwarmResult:
        t0 = time.perf_counter()
        loop = self.loop
        for i, times in enumerate(self.made):
            for k, t in enumerate(times):
                loop.schedule(t, ("version", i, k + 1))
        loop.schedule(0.0, ("links",))
        last_made = max((m[-1] for m in self.made if m), default=0.0)
        end = max(self.cfg.duration, last_made) + self.cfg.drain
        reached = loop.run(end, self._dispatch, stop=lambda: self._converged() and loop.now >= last_made)
        return SwarmResult(
            n=self.n, config=self.cfg, made=self.made, accepted=self.accepted, radio=self.radio,
            robots=self.robots, end=reached, wall_s=time.perf_counter() - t0, events=loop.dispatched,
            hears_all_share=self._links_full / max(1, self._links_seen),
            robot_hears_all_share=self._robot_full / max(1, self._links_seen),
            mean_degree=self._degree / max(1, self._links_seen),
            ever_heard=self._ever,
            hops=self._hops,
        )  # fmt: skip

    def _converged(self) -> bool:
        return self._done_pairs >= self._pairs

    def _dispatch(self, now: float, ev: Event) -> None:
        kind = ev[0]
        if kind == "end":
            tx: Transmission = ev[1]
            for d, data in self.radio.finish(tx, now):
                self.robots[d].receive(data, now)
                if data is tx.data and (tx.dst is None or tx.dst == d):
                    self._service(d, now)
                # else: garbled bytes, or an ack for another robot, only tell this one that the
                # channel was busy and the sender is alive, which can only make its next deadline
                # later: its wake-up stands (an early wake-up finds nothing to do and reschedules)
                # and the O(peers) timer scan is saved; this is what lets 64 robots run in minutes.
        elif kind == "wake":
            i, gen = ev[1], ev[2]
            if gen == self._gen[i]:
                self._wake_at[i] = None
                self._service(i, now)
        elif kind == "version":
            i = ev[1]
            self.robots[i].new_version(ev[2], now)
            self._service(i, now)
        elif kind == "links":
            self._update_links(now)
            self.loop.schedule(now + self.cfg.links_dt, ("links",))

    def _service(self, i: int, now: float) -> None:
        robot = self.robots[i]
        seen = len(self.accepted)

        def emit(frame: bytes, kind: str) -> float:
            dst = None
            if kind == "ack":  # the body's header is kind, src, dst (link ids)
                to = decode_frame(frame[:-1], crc=not self.cfg.signed)[2]
                dst = None if to == 255 else to - 1  # a DONE frame (R16) is for every sender in it
            tx = self.radio.transmit(i, frame, now, kind, dst)
            self.loop.schedule(tx.end, ("end", tx))
            return tx.end

        robot.service(now, self.radio.busy_until(i), emit)
        for _, h, o, v in self.accepted[seen:]:
            if v >= self._final[o] > self._newest[h, o]:
                self._done_pairs += 1
            self._newest[h, o] = max(self._newest[h, o], v)
        t = robot.next_wake()
        free = self.radio.busy_until(i)
        if free > now:
            # The radio is sending: come back when it is done (the core's timers then fire at most
            # one frame's airtime late; its send timer would otherwise be due again at once).
            t = free if t is None else max(t, free)
        if t is None:
            return
        t = max(t, now + 1e-6) if t <= now else t
        if self._wake_at[i] is not None and abs(self._wake_at[i] - t) < 1e-12:  # type: ignore[operator]
            return
        self._gen[i] += 1
        self._wake_at[i] = t
        self.loop.schedule(t, ("wake", i, self._gen[i]))

    def _update_links(self, now: float) -> None:
        hears, walls = self.timeline.links(now)
        self.radio.set_links(hears, walls)
        self._links_seen += 1
        self._ever |= hears.T  # [holder, origin]: the holder hears the origin
        self._hops.append((now, hop_counts(hears)))
        deg = hears.sum(axis=1)
        self._degree += float(deg.mean())
        self._robot_full += float((deg >= self.n - 1).mean())
        if bool((deg >= self.n - 1).all()):
            self._links_full += 1
