"""Sans-I/O multi-hop relay for the UWB channel: which held map to forward next, to whom, and when.

No robot hears every other in a building, so a map reaches robots two or more hops from its origin
only if a robot in between forwards it. This core decides that forwarding from cheap *summaries*:
every robot broadcasts, now and then, the newest version it holds of each origin and the link ids it
hears directly (:func:`pack_summary`). A robot forwards origin ``O``'s version ``v`` it holds when a
neighbour ``N`` (a robot whose summary it heard lately) holds less than ``v`` of ``O`` and does not
hear ``O`` itself: were ``N`` to hear ``O``, ``O``'s own publisher would serve it.

What is forwarded is the origin's envelope exactly as received, so it is still signed by its origin
and a relay cannot alter it; the receiver checks the signature as for a direct map. A delta is
forwarded only to a neighbour whose summary says it holds the delta's base, so the core keeps the
last :data:`CHAIN` envelopes of each origin (a far robot catches up one delta a relay, each on the
one before, as the origin made them), and the newest keyframe for neighbours further behind.

A neighbour further behind than the chain reaches, when no newer keyframe is held either, cannot be
served from what this robot holds; if this robot hears the origin it asks it for a whole map on the
neighbour's behalf (:meth:`ForwardingCore.keyframes_wanted`, at most once per ``retry_s`` per origin),
and forwards that keyframe when it comes. Without this, a far robot that missed more than
:data:`CHAIN` versions would wait for the origin's next scheduled keyframe.

Bounds, so relays never flood the channel:

* at most one relay in flight per robot, and one started per ``relay_period_s``;
* a relay gives up after :meth:`ForwardingCore.relay_deadline_s`: :data:`RELAY_FLOOR_S` plus
  :data:`RELAY_AIRTIMES` times the time its bytes take at this robot's share of the channel
  (``share_bps``), so that a neighbour that walked off mid-relay (still heard now and then through
  the walls, so never down) does not hold up this robot's next relay for the link's whole map
  deadline. On a fast channel that wait was most of what kept far robots stale;
* a forwarded (or overheard forwarded) ``(O, v)`` is not forwarded again for ``retry_s``, the time a
  neighbour's next summary needs to show whether it arrived;
* of several neighbours that could serve the same ``N``, the one with the lowest link id goes first;
  the others hold off ``rank * relay_period_s`` and, hearing its forward, suppress their own;
* of a robot's own candidates, the map that serves the most neighbours goes first, and among as
  many, that of the origin it relayed least lately, so no origin's maps starve behind another's.

Summaries ride on frames HMAC'd with the fleet link key, so only a key holder can send one; a lying
one can at worst cause bounded extra relays (claiming to lack a map) or a missed relay (claiming to
hold one), never a forged map: the map itself carries its origin's Ed25519 signature.

The core keeps no clock: every input takes ``now`` and :meth:`ForwardingCore.next_deadline` says
when to call :meth:`ForwardingCore.next_forward` again.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from mapd.errors import ProtocolError
from transports.uwb.arq import DEADLINE_AIRTIMES

#: Envelopes kept per origin (the newest ones, oldest first): a neighbour a few versions behind gets
#: the next delta in the chain rather than waiting for the origin's next keyframe.
CHAIN = 8
#: Bytes of envelopes kept, all origins together; past it the oldest of the longest chain goes.
MAX_HELD_BYTES = 8 << 20
#: A relay's deadline: this floor (a few TDMA cycles on a fast channel, for the acks to come
#: back; 15 s made a relay that failed hold the robot's one relay for 21 s at 200 kb/s, and two in
#: five did fail, their receivers gone; on a slow channel the airtimes below are most of it) ...
RELAY_FLOOR_S = 5.0
#: ... plus this many times its airtime at the robot's share of the channel (the air per coded byte
#: through walls, repairs and acks included, runs 2 to 5 in ``mapd bench swarm``).
RELAY_AIRTIMES = 4.0
#: The stream summaries ride on (unreliable, background; maps use 0..252, 254 poses, 255 control).
SUMMARY_STREAM = 253
_COUNT = struct.Struct("<B")
# origin link id, newest version held: all 64 bits (a daemon's versions carry its incarnation in the
# high bits, so low bits alone would never equal a delta's base and no delta would ever be relayed)
_HOLD = struct.Struct("<BQ")
_HEAR = struct.Struct("<B")


class SummaryError(ProtocolError):
    """A summary's bytes are malformed (a :class:`~mapd.errors.ProtocolError`, as every fault in
    bytes from a link is: counted, never fatal)."""


@dataclass(frozen=True)
class Summary:
    """What a robot says it holds (origin link id -> newest version) and whom it hears directly."""

    holds: dict[int, int]
    hears: frozenset[int]


def pack_summary(summary: Summary) -> bytes:
    """The wire form: count, (origin, version)*, count, link id* (at most 255 of each)."""
    holds = sorted(summary.holds.items())[:255]
    hears = sorted(summary.hears)[:255]
    out = [_COUNT.pack(len(holds))]
    out += [_HOLD.pack(o, v & 0xFFFFFFFFFFFFFFFF) for o, v in holds]
    out.append(_COUNT.pack(len(hears)))
    out += [_HEAR.pack(h) for h in hears]
    return b"".join(out)


def unpack_summary(data: bytes) -> Summary:
    """Parse :func:`pack_summary`'s bytes; :class:`SummaryError` when they are malformed."""
    try:
        (n,) = _COUNT.unpack_from(data, 0)
        off = _COUNT.size
        holds: dict[int, int] = {}
        for _ in range(n):
            o, v = _HOLD.unpack_from(data, off)
            holds[o] = v
            off += _HOLD.size
        (m,) = _COUNT.unpack_from(data, off)
        off += _COUNT.size
        hears = frozenset(_HEAR.unpack_from(data, off + i)[0] for i in range(m))
        off += m * _HEAR.size
    except struct.error as exc:
        raise SummaryError(f"uwb: truncated relay summary: {exc}") from None
    if off != len(data):
        raise SummaryError("uwb: trailing bytes after a relay summary")
    return Summary(holds, hears)


@dataclass(frozen=True)
class Relay:
    """Forward ``data`` (origin ``origin``'s envelope of ``version``, as received) to ``dests``, giving
    up after ``deadline_s`` (None: the link's own deadline for a message)."""

    origin: int
    version: int
    data: bytes
    dests: tuple[int, ...]
    deadline_s: float | None = None


@dataclass
class _Heard:
    summary: Summary
    at: float


@dataclass
class ForwardingCore:
    """Robot ``me``'s relay decisions (link ids throughout)."""

    me: int
    relay_period_s: float = 10.0
    #: A neighbour's summary older than this is forgotten (it moved away or went quiet).
    summary_timeout_s: float = 45.0
    #: How long a forwarded (O, v) is not forwarded again: a summary period or two.
    retry_s: float = 30.0
    #: Bits per second this robot may expect to send (its share of the channel: the link rate over
    #: the robots taking turns on it); None: relays take the link's own deadline.
    share_bps: float | None = None
    #: The longest a relay may take: the link's deadline for any message (None: no cap).
    max_relay_s: float | None = None
    _heard: dict[int, _Heard] = field(default_factory=dict)
    _kf: dict[int, tuple[int, bytes]] = field(default_factory=dict)  # origin -> newest keyframe
    #: origin -> its newest (version, base, envelope), oldest first, at most CHAIN
    _chain: dict[int, list[tuple[int, int, bytes]]] = field(default_factory=dict)
    _held_bytes: int = 0
    #: origin -> a version this robot holds from its state directory, with no bytes to forward: its
    #: summary lists it all the same, or after each restart its neighbours forwarded it every map
    #: it already held, a keyframe each, on a channel where one takes a robot's turns for minutes
    _restored: dict[int, int] = field(default_factory=dict)
    _forwarded: dict[tuple[int, int], float] = field(default_factory=dict)
    _need_since: dict[tuple[int, int, int], float] = field(default_factory=dict)
    _asked: dict[int, float] = field(default_factory=dict)  # origin -> when a keyframe was asked for
    #: origin -> when this robot last started a relay of its maps (bounded by the origins in _chain)
    _origin_started: dict[int, float] = field(default_factory=dict)
    _in_flight: bool = False
    _last_start: float | None = None
    _wake: float | None = None
    relays_started: int = 0
    keyframes_asked: int = 0

    @classmethod
    def for_summaries(
        cls,
        me: int,
        *,
        summary_period_s: float,
        relay_period_s: float,
        share_bps: float | None = None,
        max_relay_s: float | None = None,
    ) -> ForwardingCore:
        """The core for robots that send a summary every ``summary_period_s``: a neighbour is
        forgotten after three missed summaries, and a relay is not repeated before two have had
        time to show whether it arrived (the daemon's driver and ``mapd bench swarm`` alike)."""
        return cls(
            me,
            relay_period_s=relay_period_s,
            summary_timeout_s=3 * summary_period_s,
            retry_s=2 * summary_period_s,
            share_bps=share_bps,
            max_relay_s=max_relay_s,
        )

    # --- inputs ---------------------------------------------------------------------------------
    def on_summary(self, src: int, summary: Summary, now: float) -> None:
        """A neighbour's summary arrived (``src`` is heard directly: it is a neighbour)."""
        if src != self.me:
            self._heard[src] = _Heard(summary, now)

    def on_held(self, origin: int, version: int, base: int, envelope: bytes) -> None:
        """This robot accepted ``origin``'s ``version`` (a delta on ``base``, or a keyframe when
        ``base`` is 0; ``envelope``: the bytes as received, signed by the origin).

        The newest keyframe is kept for neighbours far behind; each delta of the chain only helps one
        that holds exactly its base (its summary says so), as a delta costs a fraction of a keyframe."""
        if origin == self.me:
            return  # own maps go out through the publisher, to everyone in range
        if base == 0 and version > self._kf.get(origin, (0, b""))[0]:
            old = self._kf.get(origin)
            self._kf[origin] = (version, envelope)
            self._held_bytes += len(envelope) - (len(old[1]) if old else 0)
        chain = self._chain.setdefault(origin, [])
        if chain and version <= chain[-1][0]:
            return  # not newer than what this robot holds (the receiver accepts only newer ones)
        chain.append((version, base, envelope))
        self._held_bytes += len(envelope)
        while len(chain) > CHAIN:
            self._held_bytes -= len(chain.pop(0)[2])
        while self._held_bytes > MAX_HELD_BYTES:
            longest = max(self._chain.values(), key=len)
            if len(longest) <= 1:
                break
            self._held_bytes -= len(longest.pop(0)[2])

    def on_restored(self, origin: int, version: int) -> None:
        """This robot holds ``origin``'s ``version`` from its state directory (its daemon restarted):
        listed in its summaries (:meth:`holds`), never forwarded (it has no envelope of it)."""
        if origin != self.me and version > self._restored.get(origin, 0):
            self._restored[origin] = version

    def on_overheard(self, origin: int, version: int, now: float) -> None:
        """Another robot forwarded ``origin``'s ``version``: do not forward the same one for a while."""
        self._forwarded[(origin, version)] = now

    def forget(self, origin: int) -> None:
        """Drop every map of ``origin`` held to forward (it was revoked: nobody takes them now)."""
        self._restored.pop(origin, None)
        self._origin_started.pop(origin, None)
        for _, _, data in self._chain.pop(origin, []):
            self._held_bytes -= len(data)
        kf = self._kf.pop(origin, None)
        if kf is not None:
            self._held_bytes -= len(kf[1])

    def relay_done(self) -> None:
        """The relay in flight was delivered, failed or closed: another may start."""
        self._in_flight = False

    # --- outputs --------------------------------------------------------------------------------
    def holds(self) -> dict[int, int]:
        """Origin -> newest version held (for this robot's own summary), restored ones included."""
        out = dict(self._restored)
        for o, chain in self._chain.items():
            if chain:
                out[o] = max(chain[-1][0], out.get(o, 0))
        return out

    def next_forward(self, now: float) -> Relay | None:
        """The relay to start now, if any (then it counts as in flight until :meth:`relay_done`)."""
        self._expire(now)
        self._wake = None
        if self._in_flight:
            return None
        if self._last_start is not None and now < self._last_start + self.relay_period_s:
            self._wake = self._last_start + self.relay_period_s
            return None
        # The most neighbours served first; among as many, the origin relayed least lately (with
        # the lowest link id first, a robot between two whose maps kept changing relayed only the
        # lower one's: its other neighbour held the other's 6th map of 39, measured in mapd demo).
        best: tuple[int, float, int, int] | None = None  # (-needing, origin last started, origin, -version)
        best_relay: Relay | None = None
        for origin in self._chain:
            for version, base, data in self._candidates(origin):
                if (origin, version) in self._forwarded:
                    continue
                dests = tuple(n for n in sorted(self._heard) if self._needs(n, origin, version, base, now))
                key = (-len(dests), self._origin_started.get(origin, -math.inf), origin, -version)
                if dests and (best is None or key < best):
                    best, best_relay = (
                        key,
                        Relay(origin, version, data, dests, self.relay_deadline_s(len(data))),
                    )
        if best_relay is None:
            return None
        self._in_flight = True
        self._last_start = now
        self._forwarded[(best_relay.origin, best_relay.version)] = now
        self._origin_started[best_relay.origin] = now
        self.relays_started += 1
        return best_relay

    def relay_deadline_s(self, nbytes: int) -> float | None:
        """How long a relay of ``nbytes`` may take before it is given up (None: no share known)."""
        if self.share_bps is None or not self.share_bps > 0:
            return self.max_relay_s
        airtime = 8.0 * nbytes / self.share_bps
        wanted = RELAY_FLOOR_S + RELAY_AIRTIMES * airtime
        if self.max_relay_s is None:
            return wanted
        # Never past the link's own deadline for a message of this size (arq R6: ``deadline_s``, or
        # twice its airtime if longer), which a relay of a map too long for ``deadline_s`` needs.
        return min(wanted, max(self.max_relay_s, DEADLINE_AIRTIMES * airtime))

    def keyframes_wanted(self, now: float, hears: frozenset[int] | set[int]) -> list[int]:
        """Origins (among ``hears``, the link ids this robot hears) to ask for a whole map now: a
        neighbour lacks their newest version and nothing held fits it (no delta on what it holds,
        no newer keyframe). Each origin at most once per ``retry_s``."""
        self._expire(now)
        out = []
        for origin, chain in self._chain.items():
            if origin not in hears or not chain:
                continue
            asked = self._asked.get(origin)
            if asked is not None and now - asked < self.retry_s:
                continue
            newest = chain[-1][0]
            for n, h in self._heard.items():
                s = h.summary
                have = s.holds.get(origin, 0)
                if n == origin or origin in s.hears or have >= newest:
                    continue
                if any(v > have and (base == 0 or base == have) for v, base, _ in self._candidates(origin)):
                    continue  # next_forward serves it
                out.append(origin)
                self._asked[origin] = now
                self.keyframes_asked += 1
                break
        return out

    def next_deadline(self) -> float | None:
        """When to call :meth:`next_forward` again if no input comes first (None: only on new input);
        as of the last :meth:`next_forward` call."""
        return self._wake

    # --- internals ------------------------------------------------------------------------------
    def _candidates(self, origin: int) -> list[tuple[int, int, bytes]]:
        """(version, base, envelope) this robot could forward of ``origin``: the chain, newest first,
        and the newest keyframe."""
        out = self._chain.get(origin, [])[::-1]
        kf = self._kf.get(origin)
        # (also where the chain holds that version as a delta: a whole map of it, asked for on a
        # neighbour's behalf, serves one the delta's base does not)
        if kf is not None and all(kf[0] != v or base != 0 for v, base, _ in out):
            out.append((kf[0], 0, kf[1]))
        return out

    def _needs(self, n: int, origin: int, version: int, base: int, now: float) -> bool:
        """Neighbour ``n`` lacks ``origin``'s ``version``, does not hear ``origin``, can use it (a
        keyframe, or a delta on the version it holds), and this robot's turn to serve it has come
        (lower link ids that could serve it go first)."""
        if n == origin:
            return False
        s = self._heard[n].summary
        have = s.holds.get(origin, 0)
        if have >= version or origin in s.hears or (base and have != base):
            return False
        # Neighbours of ours that n hears and that say they hold the version could serve n too; the
        # lowest link id goes first, the others hold off a relay period per rank, and normally hear
        # its forward (on_overheard) or n's next summary before their turn.
        rank = sum(
            1
            for r, h in self._heard.items()
            if r < self.me and r in s.hears and h.summary.holds.get(origin, 0) >= version
        )
        since = self._need_since.setdefault((n, origin, version), now)
        turn = since + rank * self.relay_period_s
        if now >= turn:
            return True
        self._wake = turn if self._wake is None else min(self._wake, turn)
        return False

    def _expire(self, now: float) -> None:
        for src in [s for s, h in self._heard.items() if now - h.at > self.summary_timeout_s]:
            del self._heard[src]
        for key in [k for k, t in self._forwarded.items() if now - t >= self.retry_s]:
            del self._forwarded[key]
        stale = [
            k
            for k in self._need_since
            if k[0] not in self._heard or all(c[0] != k[2] for c in self._candidates(k[1]))
        ]
        for need in stale:
            del self._need_since[need]  # the neighbour left, or a newer version superseded this one
