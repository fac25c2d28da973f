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
* **Beacons.** The root sends a TIME frame every :data:`PERIOD_S` with a rising ``seq``; each
  frame's ``stamp`` is the sender's link time when the frame went on the air. A node that hears a
  better root, or a newer ``seq`` of its own, takes the stamp plus the path delay as the link time
  at the frame's arrival. Its correction is the largest of its last :data:`SAMPLES` readings of
  ``stamp - arrival`` plus the delay its parent announces now (a reading is only ever late, never
  early: a frame queued behind another, a busy serial line; and a delay measured since counts for
  the readings taken before it).
  It passes the seq on (a newer one only, so a dead root's time dies out instead of counting to
  infinity) when it heard a node further from the root than itself, so multi-hop fleets keep
  one clock; and every :data:`LEAF_EVERY` periods it sends its own, so the node it follows knows
  it is there and can measure the delay to it.
* **Delay.** A beacon echoes the last stamp its sender took from the node it follows and how long
  it held it; that node, hearing the echo, has a round trip ``t4 - t1 - hold`` whose half is the
  path delay (serial lines, radio buffers and the air, the same both ways for TIME frames of one
  size), and announces the smallest of its last readings in its beacons (NTP's clock filter: what
  queueing adds is never less than nothing). Until one is announced, a receiver counts the
  frame's airtime at the link's rate.
* **Cost.** A source beacons only while it heard a node that is not one, within :data:`LOST_S`
  periods: a fleet whose every robot runs chrony sends no TIME frame at all. A node that is its own
  root beacons every period while it hears any peer (so a better root hears it and answers).
  A node whose root goes silent for :data:`LOST_S` periods leads with the clock it had, so the
  turns do not jump when a root leaves.

Times here are seconds: ``local`` is the robot's wall clock (the endpoint's ``now`` plus its wall
offset), and the link clock is ``local + correction``.
"""

from __future__ import annotations

from collections import OrderedDict, deque
from typing import Any

from transports.uwb import wire

#: A root's beacon interval (s). At the 50 ppm a crystal may be off, clocks drift 0.75 ms apart in
#: 15 s, well within the 10 ms guard; a fleet of 16 or 32 robots without a time service spends
#: about a hundredth of 12.5 kb/s on TIME frames (``mapd bench swarm --clock-skew 300``).
PERIOD_S = 15.0
#: A follower's own beacon, however little it is needed, every this many periods: its parent
#: learns it exists (and so passes the root's beacons on) and measures the delay from its echo.
LEAF_EVERY = 4
#: A root silent for this many periods (plus two TDMA cycles: a beacon waits for its turn) is gone;
#: so is the need for this node's beacons that a node heard this long ago made.
LOST_PERIODS = LEAF_EVERY + 1
#: Readings of the root's time (and of the delay) whose best counts: a late one (a frame queued on
#: the air, a busy serial line, a scheduler) is passed over. Three periods are few enough that two
#: clocks 50 ppm apart drift only 2 ms in them.
SAMPLES = 3
DELAY_SAMPLES = 5
#: A root answers a node that leads with a worse clock this soon, however recently it beaconed.
#: A node that starts to lead beacons this long after its first beacon, then twice as long after
#: each until the period: at start the robots' turns are still apart, and a first beacon lost in a
#: collision (seen on the emulated radio) cost the fleet a whole period without one clock.
ANSWER_GAP_S = 1.0
#: Stamps this node sent that an echo may still name (by their low 32 bits).
_SENT_KEPT = 8
_US = 1_000_000


def _seq_newer(a: int, b: int) -> bool:
    """Whether beacon seq ``a`` comes after ``b`` (16-bit serial-number arithmetic)."""
    return 0 < ((a - b) & 0xFFFF) < 0x8000


class RadioTime:
    """One node's side of the fleet's radio clock (see the module docstring).

    The endpoint feeds it the TIME frames it hears (:meth:`heard`), asks when a beacon is due
    (:meth:`due`) and builds it (:meth:`beacon`), and keeps its TDMA turns on ``local +``
    :attr:`correction`.
    """

    def __init__(self, node: int, *, cycle_s: float = 0.0, period_s: float = PERIOD_S) -> None:
        self.node = node
        self.period = period_s
        self.lost_s = LOST_PERIODS * period_s + 2 * cycle_s
        #: This node's clock is kept by a time service (it leads, never follows).
        self.source = False
        #: Seconds added to the local clock to get the link clock.
        self.correction = 0.0
        self._root: tuple[int, int] = (1, node)
        self.hops = 0
        self.parent: int | None = None
        self._seq = 0  # the root's seq this node holds (its own, when it is the root)
        self._own_seq = 0
        self._synced_at = -float("inf")  # local time of the last newer seq taken
        self._samples: deque[float] = deque(maxlen=SAMPLES)  # stamp - local at arrival (s)
        self._parent_delay: float | None = None  # announced by the node followed (s)
        self._delays: deque[float] = deque(maxlen=DELAY_SAMPLES)  # measured by echoes (s)
        self._last_parent: tuple[int, int, float] | None = None  # (id, stamp us, local at receipt)
        self._sent: OrderedDict[int, float] = OrderedDict()  # stamp & 0xFFFFFFFF -> local at send
        self._needed_until = -float("inf")
        self._relay = False  # a newer seq to pass on
        self._next = float("inf")  # when the next beacon is due (local)
        self._last_beacon = -float("inf")
        self._ramp = 0  # beacons sent since this node began to lead
        self.beacons_tx = 0
        self.steps = 0  # corrections taken from a new root

    # --- what leads ------------------------------------------------------------------------------
    @property
    def root(self) -> int:
        """The id whose clock this node keeps its turns on (its own when it leads)."""
        return self._root[1]

    @property
    def root_is_source(self) -> bool:
        return self._root[0] == 0

    def _own_key(self) -> tuple[int, int]:
        return (0 if self.source else 1, self.node)

    def _lead(self) -> None:
        """Lead with the link clock this node has (its root is gone, or it became a source)."""
        self._root, self.hops, self.parent = self._own_key(), 0, None
        self._ramp = 0
        self._samples.clear()
        self._parent_delay = None
        self._last_parent = None

    def set_source(self, source: bool) -> None:
        """Whether a time service keeps this node's wall clock (it is the reference if so)."""
        if source == self.source:
            return
        self.source = source
        if source:
            self.correction = 0.0  # the wall clock itself is the reference now
        if source or self.parent is None:
            self._lead()

    def wall_moved(self, delta: float) -> None:
        """The local clock jumped by ``delta`` s (NTP): a follower keeps its link clock where it was
        (its root's clock did not move); a leader's moves with its own."""
        if self.parent is not None:
            self.correction -= delta
            self._samples = deque((s - delta for s in self._samples), maxlen=SAMPLES)
            if self._last_parent is not None:
                pid, stamp, at = self._last_parent
                self._last_parent = (pid, stamp, at + delta)
        self._sent = OrderedDict((k, v + delta) for k, v in self._sent.items())
        self._next += delta
        self._last_beacon += delta
        self._synced_at += delta
        self._needed_until += delta

    # --- input -----------------------------------------------------------------------------------
    def heard(self, f: wire.Time, local: float, model_delay: float) -> bool:
        """A TIME frame whose last byte arrived at ``local``; ``model_delay``: its airtime, used
        until the sender announces a measured delay. True when the correction changed."""
        if f.echo_src == self.node:
            self._echoed(f, local)
        key = (0 if f.source else 1, f.root)
        mine = self._root
        if (key > mine and not key[0] == mine[0] == 0) or (key == mine and f.hops > self.hops):
            # a node further from the best clock than this one: it may need our beacons (not one
            # on another time service's clock: the two agree through their time services)
            self._needed_until = local + self.lost_s
            if key > mine and self.parent is None:  # it leads with a worse clock: answer soon
                self._next = min(self._next, max(local, self._last_beacon + ANSWER_GAP_S))
        if self.source or f.root == self.node:
            return False
        better = key < mine
        if not better and not (key == mine and _seq_newer(f.seq, self._seq)):
            return False
        if better:
            self._root = key
            self._samples.clear()
            self.steps += 1
        self._seq, self.hops, self.parent = f.seq, f.hops + 1, f.src
        self._parent_delay = None if f.delay == wire.DELAY_UNKNOWN else f.delay * wire.DELAY_UNIT_S
        delay = model_delay if self._parent_delay is None else self._parent_delay
        self._samples.append(f.stamp / _US - local)
        self._synced_at = local
        self._last_parent = (f.src, f.stamp, local)
        self._relay = True
        if local < self._needed_until:
            self._next = min(self._next, local)
        elif self._next == float("inf"):
            self._next = local + LEAF_EVERY * self.period
        before, self.correction = self.correction, max(self._samples) + delay
        return self.correction != before

    def _echoed(self, f: wire.Time, local: float) -> None:
        sent = self._sent.get(f.echo)
        if sent is None:
            return
        rtt = (local - sent) - f.hold / _US
        if 0 <= rtt < 2 * wire.DELAY_UNKNOWN * wire.DELAY_UNIT_S:
            self._delays.append(rtt / 2)

    # --- output ----------------------------------------------------------------------------------
    def due(self, local: float, peers: bool) -> float | None:
        """When (local time) the next beacon is due; None while none is. ``peers``: any peer is
        up (a lone node has nobody to keep time with)."""
        if self.parent is not None and local - self._synced_at > self.lost_s:
            self._lead()  # its root went silent: lead with the clock we have
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
        return self._next

    def beacon(self, local: float, src: int, session: int) -> wire.Time:
        """The TIME frame to send now; ``local``: when it goes on the air (its stamp)."""
        if self.parent is None:
            self._own_seq = (self._own_seq + 1) & 0xFFFF
            self._seq = self._own_seq
        stamp = max(0, round((local + self.correction) * _US))
        echo_src = echo = hold = 0
        if self._last_parent is not None:
            pid, pstamp, at = self._last_parent
            held = round((local - at) * _US)
            if 0 <= held <= 0xFFFFFFFF:
                echo_src, echo, hold = pid, pstamp & 0xFFFFFFFF, held
        self._sent[stamp & 0xFFFFFFFF] = local
        while len(self._sent) > _SENT_KEPT:
            self._sent.popitem(last=False)
        delay = wire.DELAY_UNKNOWN
        if self._delays:
            delay = min(wire.DELAY_UNKNOWN - 1, round(min(self._delays) / wire.DELAY_UNIT_S))
        self._relay = False
        self._last_beacon = local
        if self.parent is None:
            self._next = local + min(self.period, ANSWER_GAP_S * 2**self._ramp)
            self._ramp += 1
        else:
            self._next = local + LEAF_EVERY * self.period
        self.beacons_tx += 1
        return wire.Time(
            src, wire.BROADCAST, session, self.root, self.root_is_source, self.hops, self._seq,
            delay, stamp, echo_src, echo, hold,
        )  # fmt: skip

    def stats(self, local: float) -> dict[str, Any]:
        """What ``mapd status`` shows of the radio clock."""
        delay = min(self._delays) if self._delays else self._parent_delay
        return {
            "role": "source" if self.source else "leads" if self.parent is None else "follows",
            "root": self.root,
            "root_is_source": self.root_is_source,
            "hops": self.hops,
            "parent": self.parent,
            "correction_ms": round(1000 * self.correction, 3),
            "delay_ms": None if delay is None else round(1000 * delay, 3),
            "synced_ago_s": None if self.parent is None else round(local - self._synced_at, 1),
            "time_beacons_tx": self.beacons_tx,
            "time_root_changes": self.steps,
        }
