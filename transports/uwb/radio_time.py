"""One TDMA clock for a fleet that has no time service, kept over the radio (sans-I/O).

TDMA cuts time into turns on each robot's clock, so the clocks must agree within the guard
(10 ms). A fleet whose robots run chrony against one source has that; one that works where no
network reaches (a basement, a mine, a site without Wi-Fi) does not, and its turns collide. This
core keeps a *link clock* for the turns, ``local + correction``, where ``local`` is the robot's
own wall clock, agreed over the radio the way FTSP does it (Maroti et al., "The Flooding Time
Synchronization Protocol", SenSys 2004), with NTP's two-way delay measurement:

* **Who leads.** Each node's clock has a key: ``(0, id)`` when a time service keeps it (the kernel
  says so: ``mapd.wallclock``), a *source*, else ``(1, id)``. The fleet follows the smallest key it
  hears: a source before any other, then the lowest id. A source never follows anyone: its own
  clock is the reference, and sources agree with one another through their time service.
* **Beacons.** The leader sends a TIME frame every :data:`PERIOD_S`; each frame's ``stamp`` is its
  sender's link time when it went on the air, its ``seq`` the leader's link time in quarter
  seconds (so it rises across a restart of the leader too). A node that hears a better leader, or
  a newer ``seq`` of its own, reads ``stamp - arrival`` and adds the path delay: its correction is
  the largest of its last :data:`SAMPLES` readings (a reading is only ever late, never early: a
  frame queued behind another, a busy serial line), each carried forward by the rate its clock
  runs at against the leader's (FTSP's regression; here the median of the readings' pairwise
  slopes, robust to late ones). It passes each newer ``seq`` on when a node follows it (a TIME
  frame names its ``parent``) or leads with a worse clock, so a building's robots keep one clock
  over hops; and every :data:`LEAF_EVERY` periods it sends its own, so its parent knows it.
  A leader silent for :data:`LOST_PERIODS` periods is gone: the node leads with the clock it has
  (the turns do not jump), and takes that leader back only with a newer ``seq`` than it last
  had, so a gone leader's time does not go round a loop of robots (no count to infinity).
* **Delay.** Each TIME frame echoes the last stamp heard within a period from one neighbour, and
  how long it was held (in seconds of the link clock): a child that follows the sender first, the
  one echoed longest ago first. The neighbour, hearing its own stamp, has a round trip
  ``t4 - t1 - hold``, half of which is its path delay (serial lines, radio buffers and the air:
  the same both ways, as every TIME frame has one size), and keeps the smallest of its last
  :data:`DELAY_SAMPLES` for that neighbour (NTP's clock filter: queueing never adds less than
  nothing). A round trip counts only where both frames went on one clock (at start the turns
  overlap and frames wait). Until it has one to its parent, a robot counts the smallest it
  measured to others (its own radio's), else the frame's airtime at the link's rate. Followers
  send their own beacons spread over the interval by id, so their parent has fresh stamps to
  echo, and one that took no newer seq for 2.5 periods beacons, so its parent hears it still
  follows.
* **Steps.** A leader whose link clock jumps (a time service started, or stepped its wall clock)
  raises its ``epoch``; followers drop the readings from before. A leader without a time service
  whose wall clock is stepped keeps its link clock where it was.
* **Cost.** A source sends TIME frames only while it heard, within :data:`LOST_PERIODS` periods, a
  node that follows it or leads with a worse clock: a fleet whose every robot runs chrony sends
  none. A leader beacons every period while it hears any peer (1, 2, 4 and 8 s apart when it starts
  to lead, so one lost in the first collisions costs seconds, not a period).

Times here are seconds: ``local`` is the robot's wall clock (the endpoint's ``now`` plus its wall
offset), and the link clock is ``local + correction_at(local)``.
"""

from __future__ import annotations

import statistics
from collections import OrderedDict, deque
from typing import Any

from transports.uwb import wire

#: A leader's beacon interval (s): crystals 100 ppm apart drift 1.5 ms in it, which the rate
#: estimate takes out; a fleet of 16 or 32 robots without a time service spends about a hundredth
#: of 12.5 kb/s on TIME frames (``mapd bench swarm --clock-skew 300``).
PERIOD_S = 15.0
#: A follower's own beacon, however little it is needed, every this many periods: its parent
#: learns it follows (and so passes the leader's beacons on) and echoes its stamp.
LEAF_EVERY = 4
#: A leader silent for this many periods (plus two TDMA cycles: a beacon waits for its turn) is
#: gone; so is the need for this node's beacons that a node heard this long ago made.
LOST_PERIODS = LEAF_EVERY + 1
#: Readings whose largest counts (a late one is passed over); readings the rate is estimated from.
SAMPLES = 3
RATE_SAMPLES = 8
#: The rate estimate is used once its readings span this many periods, and never past this many
#: parts per million (a crystal's worst; a larger one is noise).
RATE_SPAN_PERIODS = 2
MAX_RATE = 200e-6
#: Round trips per neighbour whose smallest counts.
DELAY_SAMPLES = 5
#: A round trip longer than this is no measurement (a stale stamp that matched by chance), nor
#: one whose echo was held longer than this many periods (and two TDMA cycles).
MAX_RTT_S = 2.0
MAX_HOLD_PERIODS = 1.5
#: A follower that took no newer seq for this many periods beacons (once a period) so its parent
#: knows it still follows.
STALE_PERIODS = 2.5
#: A leader answers a node that leads with a worse clock this soon, however recently it beaconed,
#: and a node that starts to lead beacons this long after its first beacon, then twice as long
#: after each until the period: at start the robots' turns are still apart, and a first beacon
#: lost in a collision (seen on the emulated radio) cost the fleet a whole period without one clock.
ANSWER_GAP_S = 1.0
#: Stamps of this node's own frames an echo may still name (by their low 32 bits); neighbours
#: whose delays, and whose last stamps to echo, are kept.
_SENT_KEPT = 8
_NEIGHBOURS_KEPT = 32
#: A source's wall clock moving this much at once is a step its followers are told of (``epoch``).
STEP_S = 0.005
_US = 1_000_000


def _seq_newer(a: int, b: int) -> bool:
    """Whether beacon seq ``a`` comes after ``b`` (16-bit serial-number arithmetic)."""
    return 0 < ((a - b) & 0xFFFF) < 0x8000


class RadioTime:
    """One node's side of the fleet's radio clock (see the module docstring).

    The endpoint feeds it the TIME frames it hears (:meth:`heard`), asks when a beacon is due
    (:meth:`due`) and builds it (:meth:`beacon`), and keeps its TDMA turns on ``local +``
    :meth:`correction_at`.
    """

    def __init__(
        self, node: int, *, session: int = 0, cycle_s: float = 0.0, period_s: float = PERIOD_S
    ) -> None:
        self.node = node
        self.period = period_s
        self.cycle = cycle_s
        self.lost_s = LOST_PERIODS * period_s + 2 * cycle_s
        # a child's leaf beacon comes every LEAF_EVERY periods: one lost must not stop the relaying
        self.need_s = 2 * LEAF_EVERY * period_s + 2 * cycle_s
        #: This node's clock is kept by a time service (it leads, never follows).
        self.source = False
        self._base = 0.0  # the correction while leading
        # own clock steps (while leading); from the session, so a restart is a step to followers too
        self._epoch = session & 0xFF
        self._root: tuple[int, int] = (1, node)
        self._root_epoch = 0
        self.hops = 0
        self.parent: int | None = None
        self._seq: int | None = None  # the leader's seq this node holds (its own, when it leads)
        self._synced_at = -float("inf")  # local time of the last newer seq taken
        #: (local at arrival, stamp - local, sender, the frame's airtime): readings of the leader's
        #: clock less the path delay, added when read (it may be measured later)
        self._samples: deque[tuple[float, float, int, float]] = deque(maxlen=RATE_SAMPLES)
        self._rate = 0.0  # how much faster the leader's clock runs than ours (s/s)
        #: neighbour -> path delays measured to it, one way (s)
        self._delay_to: OrderedDict[int, deque[float]] = OrderedDict()
        self._air = 0.0  # a TIME frame's airtime at the link's rate (the delay until measured)
        #: leaders timed out: key -> (last seq, until): not taken back without a newer seq
        self._gone: dict[tuple[int, int], tuple[int, float]] = {}
        #: stamp low -> (local at send, the clock followed then)
        self._sent: OrderedDict[int, tuple[float, tuple[int, int]]] = OrderedDict()
        #: neighbour -> (its last stamp's low bits, local at arrival, it follows this node)
        self._echo: OrderedDict[int, tuple[int, float, bool]] = OrderedDict()
        self._echoed_at: dict[int, float] = {}  # neighbour -> when this node last echoed it
        self._needed_until = -float("inf")
        self._relay = False  # a newer seq to pass on
        self._next = float("inf")  # when the next beacon is due (local)
        self._last_beacon = -float("inf")
        self._ramp = 0  # beacons sent since this node began to lead
        self._first_leaf = False  # the next beacon is the first since a new leader was taken
        self.beacons_tx = 0
        self.steps = 0  # leaders changed to a better one

    # --- the clock --------------------------------------------------------------------------------
    def correction_at(self, local: float) -> float:
        """Seconds to add to the local clock at ``local`` for the link clock."""
        if self.parent is None or not self._samples:
            return self._base
        recent = list(self._samples)[-SAMPLES:]
        return max(raw + self._delay(src, air) + self._rate * (local - at) for at, raw, src, air in recent)

    def _delay(self, src: int, air: float) -> float:
        """The path delay of ``src``'s TIME frames, one way: measured to it; else the smallest of
        those measured to others (this robot's own radio and line; queueing only adds); else
        ``air``, its airtime."""
        mine = self._delay_to.get(src)
        if mine:
            return min(mine)
        others = [min(d) for d in self._delay_to.values() if d]
        return min(others) if others else air

    def _estimate_rate(self) -> None:
        pts = [(at, raw + self._delay(src, air)) for at, raw, src, air in self._samples]
        if len(pts) < 3 or pts[-1][0] - pts[0][0] < RATE_SPAN_PERIODS * self.period:
            self._rate = 0.0
            return
        slopes = [
            (b[1] - a[1]) / (b[0] - a[0])
            for i, a in enumerate(pts)
            for b in pts[i + 1 :]
            if b[0] - a[0] > 1.0
        ]
        # A slope past any crystal's is a late reading's, dropped before the median: clamped after
        # it, three late readings of eight made a clock with no skew run at 200 ppm (review).
        sane = [r for r in slopes if abs(r) <= MAX_RATE]
        self._rate = statistics.median(sane) if len(sane) * 2 > len(slopes) else 0.0

    # --- what leads ------------------------------------------------------------------------------
    @property
    def root(self) -> int:
        """The id whose clock this node keeps its turns on (its own when it leads)."""
        return self._root[1]

    @property
    def root_is_source(self) -> bool:
        return self._root[0] == 0

    def _lead(self, local: float) -> None:
        """Lead with the link clock this node has (its leader is gone, or it became a source)."""
        if self.parent is not None:
            self._gone[self._root] = (self._seq or 0, local + 2 * self.lost_s)
            self._base = self.correction_at(local)
        self._root, self.hops, self.parent = (0 if self.source else 1, self.node), 0, None
        self._ramp = 0
        self._samples.clear()
        self._rate = 0.0

    def set_source(self, source: bool, local: float) -> None:
        """Whether a time service keeps this node's wall clock (it is the reference if so)."""
        if source == self.source:
            return
        self.source = source
        if source or self.parent is None:
            self._lead(local)
        if source and self._base != 0.0:
            self._base = 0.0  # the wall clock itself is the reference now: the link clock steps
            self._epoch = (self._epoch + 1) & 0xFF

    def wall_moved(self, delta: float) -> None:
        """The local clock jumped by ``delta`` s (NTP): a follower's link clock stays where it was
        (its leader's did not move), and so does that of a leader without a time service; a
        source's moves with its wall clock, a step its followers are told of (``epoch``)."""
        if self.parent is not None:
            moved = ((at + delta, raw - delta, src, air) for at, raw, src, air in self._samples)
            self._samples = deque(moved, RATE_SAMPLES)
        elif self.source:
            if abs(delta) >= STEP_S:  # (a slew passed on is no step for followers to start over)
                self._epoch = (self._epoch + 1) & 0xFF
        else:
            self._base -= delta
        self._sent = OrderedDict((k, (at + delta, r)) for k, (at, r) in self._sent.items())
        self._echo = OrderedDict((k, (stamp, at + delta, c)) for k, (stamp, at, c) in self._echo.items())
        self._echoed_at = {k: at + delta for k, at in self._echoed_at.items()}
        self._gone = {k: (seq, until + delta) for k, (seq, until) in self._gone.items()}
        self._next += delta
        self._last_beacon += delta
        self._synced_at += delta
        self._needed_until += delta

    # --- input -----------------------------------------------------------------------------------
    def heard(self, f: wire.Time, local: float, airtime: float) -> bool:
        """A TIME frame of ``airtime`` s on the air (at the link's rate) whose last byte arrived at
        ``local``. True when this node now follows its sender's reading."""
        self._air = airtime
        key = (0 if f.source else 1, f.root)
        if f.echo_id == self.node and key == self._root:
            self._echoed(f.src, f.echo, f.hold, local)
        mine = self._root
        child = f.parent == self.node and key == mine
        worse = key > mine and not key[0] == mine[0] == 0  # (sources agree through their service)
        self._echo[f.src] = (f.stamp & 0xFFFFFFFF, local, child)
        self._echo.move_to_end(f.src)
        while len(self._echo) > _NEIGHBOURS_KEPT:
            self._echo.popitem(last=False)
        if child or worse:
            # a node that follows this one, or would: it needs our beacons
            self._needed_until = local + self.need_s
            if worse and self.parent is None:  # it leads with a worse clock: answer soon
                self._next = min(self._next, max(local, self._last_beacon + ANSWER_GAP_S))
        if self.source or f.root == self.node:
            return False
        gone = self._gone.get(key)
        if gone is not None:
            if local > gone[1] or _seq_newer(f.seq, gone[0]):
                del self._gone[key]
            else:
                return False  # a gone leader's last time, still going round
        better = key < mine
        if not better and not (key == mine and (self._seq is None or _seq_newer(f.seq, self._seq))):
            return False
        if better:
            self._root = key
            self._samples.clear()
            self.steps += 1
            self._next = min(self._next, local + ANSWER_GAP_S)  # so the new parent echoes us soon
            self._first_leaf = True
        elif f.epoch != self._root_epoch:
            self._samples.clear()  # the leader's clock stepped: readings from before are off
        self._root_epoch = f.epoch
        self._seq, self.hops, self.parent = f.seq, f.hops + 1, f.src
        self._samples.append((local, f.stamp / _US - local, f.src, airtime))
        self._estimate_rate()
        self._synced_at = local
        self._relay = True
        if self._next == float("inf"):
            self._next = local + LEAF_EVERY * self.period
        return True

    def _echoed(self, src: int, stamp: int, hold: int, local: float) -> None:
        """A round trip to ``src``: counted only where both frames went on one clock (before, the
        turns of the two may have overlapped, and a frame queued: a round trip four times too long
        set a robot's delay, and through the median of others' that of its parent; review), and
        held for no longer than a period or so. The hold comes in seconds of the link clock, which
        both count at the leader's rate, and is taken into this robot's seconds by the rate it
        estimated: counted on the echoer's own crystal, 100 ppm apart biased the delay by 0.7 ms a
        hop (review)."""
        sent = self._sent.get(stamp)
        if sent is None or sent[1] != self._root:
            return
        # the hold is in seconds of the link clock (the leader's crystal): in ours
        held = hold / _US / (1.0 + self._rate)
        if held > MAX_HOLD_PERIODS * self.period + 2 * self.cycle:
            return
        rtt = (local - sent[0]) - held
        if 0.0 <= rtt < MAX_RTT_S:
            self._delay_to.setdefault(src, deque(maxlen=DELAY_SAMPLES)).append(rtt / 2)
            self._delay_to.move_to_end(src)
            while len(self._delay_to) > _NEIGHBOURS_KEPT:
                self._delay_to.popitem(last=False)

    # --- output ----------------------------------------------------------------------------------
    def due(self, local: float, peers: bool) -> float | None:
        """When (local time) the next beacon is due; None while none is. ``peers``: any peer is
        up (a lone node has nobody to keep time with)."""
        if self.parent is not None and local - self._synced_at > self.lost_s:
            self._lead(local)  # its leader went silent: lead with the clock we have
            self._next = local
        if not peers:
            return None
        if self.parent is None:
            if self.source and local >= self._needed_until:
                return None  # every node heard keeps a time service's clock too
            if self._next == float("inf"):
                self._next = local
            return self._next
        if self._relay and local < self._needed_until:
            return min(self._next, local)
        if local - self._synced_at > STALE_PERIODS * self.period:
            # no newer seq for a while: beacon, so a parent that forgot us (a lost leaf beacon)
            # passes the leader's on again before we time out (at most once a period)
            return max(min(self._next, local), self._last_beacon + self.period)
        return self._next

    def beacon(self, local: float, src: int, session: int) -> wire.Time:
        """The TIME frame to send now; ``local``: when it goes on the air (its stamp)."""
        correction = self.correction_at(local)
        if self.parent is None:
            seq = round((local + correction) * 4) & 0xFFFF  # quarter seconds of the link clock
            # (the first is the link time's: an unset seq taken for 0 made one in the upper half of
            # the range "older", and the leader counted beacons instead for hours; review)
            self._seq = seq if self._seq is None or _seq_newer(seq, self._seq) else (self._seq + 1) & 0xFFFF
        stamp = min(wire.MAX_STAMP, max(0, round((local + correction) * _US)))
        echo_id = echo = hold = 0
        # Of the stamps heard within a period (a long hold is counted on the other's crystal), a
        # child's first, then the one of the neighbour echoed longest ago.
        fresh = [n for n, (_, at, _) in self._echo.items() if local - at <= self.period]
        if fresh:
            echo_id = min(fresh, key=lambda n: (not self._echo[n][2], self._echoed_at.get(n, -float("inf"))))
            echo, at, _ = self._echo.pop(echo_id)
            # (in seconds of the link clock, which runs at the leader's rate: see _echoed)
            hold = min(0xFFFFFFFF, max(0, round((local - at) * (1.0 + self._rate) * _US)))
            self._echoed_at[echo_id] = local
            if len(self._echoed_at) > 2 * _NEIGHBOURS_KEPT:
                self._echoed_at.pop(min(self._echoed_at, key=self._echoed_at.__getitem__))
        self._sent[stamp & 0xFFFFFFFF] = (local, self._root)
        while len(self._sent) > _SENT_KEPT:
            self._sent.popitem(last=False)
        self._relay = False
        self._last_beacon = local
        if self.parent is None:
            self._next = local + min(self.period, ANSWER_GAP_S * 2**self._ramp)
            self._ramp += 1
        else:
            # Spread over the leaf interval by id: followers that took a leader at one moment beaconed
            # in step, so their parent had fresh stamps to echo once a minute, one child each time.
            spread = 1.0 + (LEAF_EVERY - 1) * ((self.node * 0.6180339887) % 1.0)
            self._next = local + self.period * (spread if self._first_leaf else LEAF_EVERY)
            self._first_leaf = False
        self.beacons_tx += 1
        return wire.Time(
            src, wire.BROADCAST, session, self.root, self.root_is_source, self.hops, self.parent or 0,
            self._epoch if self.parent is None else self._root_epoch, self._seq or 0, stamp, echo_id, echo, hold,
        )  # fmt: skip

    def stats(self, local: float) -> dict[str, Any]:
        """What ``mapd status`` shows of the radio clock."""
        measured = self.parent is not None and bool(self._delay_to.get(self.parent))
        return {
            "role": "source" if self.source else "leads" if self.parent is None else "follows",
            "root": self.root,
            "root_is_source": self.root_is_source,
            "hops": self.hops,
            "parent": self.parent,
            "correction_ms": round(1000 * self.correction_at(local), 3),
            "delay_ms": None if self.parent is None else round(1000 * self._delay(self.parent, self._air), 3),
            "delay_measured": measured,
            "rate_ppm": round(1e6 * self._rate, 1) + 0.0,  # (no "-0.0")
            "synced_ago_s": None if self.parent is None else round(local - self._synced_at, 1),
            "time_beacons_tx": self.beacons_tx,
            "time_root_changes": self.steps,
        }
