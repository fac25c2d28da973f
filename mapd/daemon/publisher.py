"""Which own version to code, against which base, and for which links: the publisher's rules, sans-I/O.

:class:`PublisherCore` owns what the daemon knows about its own maps on their way out: the recent
versions kept as delta bases, what each transport was offered and still has in flight, what each
peer acknowledged, and the newest keyframe (for late joiners). It reads no clock and does no I/O:
the adapter in :mod:`mapd.daemon.server` feeds it events with ``now`` and asks :meth:`poll` what to
do, then runs the encode in a worker and reports the result with :meth:`encoded`.

The rules:

* **P1 Code only what a link can take now.** A version is coded when some transport has not been
  offered it and is free: its previous offer is acked by every peer it was meant for and still in
  reach (one whose presence timed out is not waited for), failed, or older than
  ``inflight_timeout_s`` (or :data:`INFLIGHT_PER_PEER_S` per peer waited for, if
  longer). A peer that already acked a version (a late joiner's keyframe query got it first) is
  not waited for when that version is offered: it drops it as stale. So a slow link never queues
  stale maps, and versions that would be replaced unsent are never coded. On a *paced* link
  (:attr:`~transports.base.Transport.paced`: uwb, a share of one slow channel) an offer times out
  no sooner than it is wholly on the air (:meth:`on_air`), or ``PACED_HOLD`` timeouts after it
  went out if the link never says so. Superseding a map half sent starts the next one over from
  nothing: in a building where each of 16 robots gets a sixteenth of 12.5 kb/s, keyframes took
  longer than the timeout to go out, so hardly a map reached anyone while versions were made
  (issue #22 in the README). If the link says by when it puts the map on the air or gives it up
  (:meth:`hold`; uwb's deadline grows with a map's size), the offer is held until then if later.
  Holding the link a TDMA cycle longer for repairs was measured too,
  and delivered fewer maps than moving on at once. (Freeing a broadcast
  link as soon as its last byte is on the air, NORM-style, was measured and made 32 robots on one
  channel staler, not fresher: the next delta then goes against an older base, so it is larger,
  and under loss it supersedes repairs; see issue #22 in the README.)
* **P2 Latest wins.** Only the newest own version is ever coded; older unsent ones are dropped.
* **P3 Delta against what every peer holds.** The base is the newest own version that *every*
  peer the transports see has acknowledged and still keeps (among the
  :data:`~mapd.daemon.receiver.KEEP_PEER_VERSIONS` newest it acknowledged), and that this robot
  still keeps; so a peer that missed the last version or two does not turn the next one into a
  keyframe for the whole fleet. Peers with no version in common, or none at all, get a keyframe.
* **P4 Keyframes on schedule and on demand.** Every ``keyframe_every``-th coded version is whole; a
  peer that asks for a keyframe or restarts (its link says so, or its maps come from a new
  incarnation: it lost its state) forgets its acks, and the newest version goes out whole on every
  transport, also those that had it already.
* **P5 The delta base survives restarts.** When every peer acked the same version, that version is
  the base to persist (:meth:`base_to_save`); it is kept in memory however old it gets.
* **P6 A peer that comes into reach gets the newest version.** A link whose peers cannot fetch it
  themselves says when a peer came into reach that no offer on its way will reach
  (:class:`~transports.base.Arrived`: uwb, where robots pass in and out of radio range; zenoh's
  late joiners query the latest keyframe instead). If that peer lacks the newest own version, it
  is offered again as soon as the link is free (unless the peer acked it by then), as a delta on
  a version every peer still holds when there is one. Otherwise it would wait for the next
  version, up to a period (never, for a map that no longer changes), and two robots that pass each
  other in a corridor often part before then (issue #22 in the README: 4 robots in the building
  accept a fifth more maps). Such offers go at most once per ``inflight_timeout_s`` on a
  transport, however many peers seem to come and go (a holder of the link key could fake them).
* **P7 A failed offer goes again while its peer stays in reach.** When the link gives up on the
  newest version for a peer (uwb: the message's deadline, after a long burst of loss or one-way
  interference) and that peer is still in reach, it is offered again as P6 offers it to an
  arrival: no sooner than ``inflight_timeout_s`` after the failed offer went out, so a link that
  fails every offer at once does not spin, and a newer version still wins. Otherwise a robot that
  heard its peer throughout never saw it "arrive", and a map that no longer changes (a parked
  robot, a base station) never reached it (``counters.failed`` says how many offers failed).
  A failure the transport calls final (``Failed.again`` False: refused for its size, by the peer
  or by the link's own limit, as it would be every time) is not offered again; the next version is.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

from mapd.daemon.receiver import KEEP_PEER_VERSIONS
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid

#: Own versions kept in memory as possible delta bases.
KEEP_VERSIONS = 16
#: A transport gets the next version only when the previous one is acked by every peer, failed,
#: or older than this. Superseding a half-sent map with every new version starves a slow link.
INFLIGHT_TIMEOUT_S = 30.0
#: ... or this many seconds per peer the offer waits for, if longer: on a shared radio channel every
#: peer answers in its own turn, so a broadcast offer to 31 peers legitimately takes several times
#: longer than one to a single peer, and superseding it early turns every next version into a
#: keyframe (the swarm bench, issue #22). Up to 6 peers it changes nothing.
INFLIGHT_PER_PEER_S = 5.0
#: A paced link's offer not yet wholly on the air times out after this many timeouts all the same
#: (its link may have lost it without a word), or when the link said it would give it up, if later
#: (:meth:`PublisherCore.hold`: the uwb ARQ fails it at its deadline anyway).
PACED_HOLD = 4.0


@dataclass(frozen=True)
class EncodeJob:
    """Code ``grid`` against ``base`` (None: a keyframe), then offer it on ``transports``."""

    grid: OccupancyGrid
    base: OccupancyGrid | None
    transports: tuple[str, ...]


@dataclass
class InFlight:
    """One transport's current offer: the version, when it went out, the peers yet to settle it."""

    version: int
    since: float
    unsettled: set[str]
    timeout: float = INFLIGHT_TIMEOUT_S
    #: On a paced link: when the offer was wholly on the air (None: not yet).
    on_air: float | None = None
    #: On a paced link: by when the link says the offer is on the air or gives it up, if it said
    #: (uwb: its deadline for a map of that size; None: not said).
    hold_until: float | None = None
    paced: bool = False
    keyframe: bool = False  # the offer is a whole map

    def expires(self) -> float:
        """When the offer stops holding its link though peers have not settled it (P1)."""
        if not self.paced:
            return self.since + self.timeout
        if self.on_air is None:
            hold = self.since + PACED_HOLD * self.timeout
            return hold if self.hold_until is None else max(hold, self.hold_until)
        return max(self.since + self.timeout, self.on_air)


@dataclass
class PublisherCounters:
    """What the publisher did, for ``mapd status``."""

    keyframes_sent: int = 0
    deltas_sent: int = 0
    #: Versions offered again, for peers that came into reach lacking them (P6) or whose offer
    #: failed while they stayed in reach (P7).
    reoffers: int = 0
    #: Per transport, offers that could not reach a peer (one per peer; P7).
    failed: dict[str, int] = field(default_factory=dict)


@dataclass
class PublisherCore:
    """The publisher's state and rules (P1-P7 above). Not thread-safe: one caller at a time."""

    uses_base: bool
    keyframe_every: int
    inflight_timeout_s: float = INFLIGHT_TIMEOUT_S
    keep_versions: int = KEEP_VERSIONS
    #: Transports whose offers are held until wholly on the air (P1; the adapter fills it in).
    paced: set[str] = field(default_factory=set)
    counters: PublisherCounters = field(default_factory=PublisherCounters)
    #: The newest own keyframe coded, for late joiners.
    keyframe: Envelope | None = None
    _sent: dict[int, OccupancyGrid] = field(default_factory=dict)
    _latest: OccupancyGrid | None = None
    _restored: OccupancyGrid | None = None
    _base_version: int | None = None
    #: Per peer, the newest own versions it acknowledged (ascending), as many as it keeps (P3); the
    #: last is the newest it holds.
    _held: dict[str, list[int]] = field(default_factory=dict)
    _inflight: dict[str, InFlight] = field(default_factory=dict)
    _offered: dict[str, int] = field(default_factory=dict)
    #: Per transport, peers that came into reach lacking the newest version (or whose offer of it
    #: failed), and when the newest was last offered again for such peers (P6, P7).
    _arrived: dict[str, set[str]] = field(default_factory=dict)
    _reoffered: dict[str, float] = field(default_factory=dict)
    _since_keyframe: int = 0

    # ------------------------------------------------------------------ inputs
    def restore(
        self, own: OccupancyGrid | None, base: OccupancyGrid | None, acked: Mapping[str, int]
    ) -> None:
        """Resume from the state directory: the last own map, the persisted base, the acks."""
        if base is not None:
            self._sent[base.version] = base
            self._base_version = base.version
        if own is not None:
            self._sent[own.version] = own
            self._restored = own
        self._held = {p: [v] for p, v in acked.items()}

    def new_version(self, grid: OccupancyGrid) -> None:
        """A new own version is saved and is now the one to publish (P2)."""
        self._sent[grid.version] = grid
        for v in sorted(self._sent)[: -self.keep_versions]:
            if v != self._base_version:
                del self._sent[v]
        self._latest = grid

    def acked(self, transport: str, peer: str, version: int) -> tuple[bool, bool]:
        """``peer`` holds own ``version`` (heard on ``transport``).

        Returns ``(free, newer)``: whether the transport became free (poll again) and whether the
        peer's acked version moved forward (the base may change: see :meth:`base_to_save`).
        """
        free = self._settle(transport, peer, version)
        newer = version > self._newest(peer)
        held = self._held.setdefault(peer, [])
        if version not in held:
            held.append(version)
            held.sort()
            del held[:-KEEP_PEER_VERSIONS]
        return free, newer

    def failed(self, transport: str, peer: str, version: int, *, again: bool = True) -> bool:
        """An offer could not reach ``peer``; True when the transport became free (poll again).

        If it was the newest version and ``peer`` is still in reach when the link is free, it is
        offered again, a timeout after the failed offer went out at the soonest (P7); not when the
        failure was final (``again`` False: refused for its size, as it would be every time)."""
        self.counters.failed[transport] = self.counters.failed.get(transport, 0) + 1
        busy = self._inflight.get(transport)
        latest = self._newest_own()
        if (
            again
            and busy is not None
            and busy.version == version
            and peer in busy.unsettled
            and latest is not None
            and latest.version == version
            and self._newest(peer) < version
        ):
            # As an arrival (P6): poll() forgets it if it is out of reach by then (it is offered
            # again when it comes back), and the failed offer counts as the last one made for it.
            self._arrived.setdefault(transport, set()).add(peer)
            self._reoffered[transport] = max(self._reoffered.get(transport, -math.inf), busy.since)
        return self._settle(transport, peer, version)

    def peer_gone(self, transport: str, peer: str) -> bool:
        """``peer`` went out of reach on ``transport`` (its presence timed out): the offer in flight
        stops waiting for it (P1). True when the transport became free (poll again)."""
        self._arrived.get(transport, set()).discard(peer)
        busy = self._inflight.get(transport)
        if busy is None or peer not in busy.unsettled:
            return False
        busy.unsettled.discard(peer)
        return not busy.unsettled

    def arrived(self, transport: str, peer: str) -> bool:
        """``peer`` came into reach on ``transport``, and no offer on its way there reaches it (P6).
        True when it lacks the newest version, so the adapter polls: :meth:`poll` offers it again
        once the link is free, unless the peer acked it by then."""
        latest = self._newest_own()
        if latest is None or self._newest(peer) >= latest.version:
            return False
        busy = self._inflight.get(transport)
        if busy is not None and busy.version == latest.version and peer in busy.unsettled:
            return False  # the offer in flight waits for it already
        self._arrived.setdefault(transport, set()).add(peer)
        return True

    def on_air(self, transport: str, version: int, now: float) -> bool:
        """Own ``version`` is wholly on the air on ``transport`` at ``now`` (P1). True when the
        offer's timeout moved: the adapter waits anew (the link may be free at once)."""
        busy = self._inflight.get(transport)
        if busy is None or busy.version != version or not busy.paced or busy.on_air is not None:
            return False
        busy.on_air = now
        return True

    def hold(self, transport: str, version: int, until: float) -> None:
        """A paced ``transport`` says it puts own ``version`` wholly on the air, or gives it up, by
        ``until`` (P1): its offer is not superseded before then, if that is later than
        ``PACED_HOLD`` timeouts. Else a map longer on the air than that (uwb: about 150 kB at 12.5
        kb/s) that changes meanwhile would start over, half sent, every time, and never arrive."""
        busy = self._inflight.get(transport)
        if busy is not None and busy.version == version and busy.paced:
            busy.hold_until = until

    def keyframe_needed(self, peer: str) -> bool:
        """``peer`` lost what it held or asked for a whole map (P4); True when there is one to send.

        Not when a whole map of the newest version is on its way to ``peer`` already (a relay may
        ask on a neighbour's behalf while it is): the channel would carry both."""
        self._held.pop(peer, None)
        latest = self._newest_own()
        if latest is None:
            return False
        v = latest.version
        if any(f.keyframe and f.version == v and peer in f.unsettled for f in self._inflight.values()):
            return False
        self._since_keyframe = self.keyframe_every
        self._offered.clear()  # even a transport that had the newest version gets it whole
        return True

    def set_base(self, version: int) -> None:
        """The adapter persisted ``version`` as the delta base (P5): keep it however old it gets."""
        self._base_version = version

    # ------------------------------------------------------------------ decisions
    def poll(self, now: float, peers: Mapping[str, Collection[str]]) -> EncodeJob | None:
        """What to code now, given each transport's name -> the peers it sees; None for nothing (P1)."""
        latest = self._latest
        if latest is None:
            return None
        for t, arrived in self._arrived.items():
            arrived.intersection_update(peers.get(t, ()))  # gone again: offered when it comes back
        free = tuple(t for t in peers if self._wants(t, latest.version, now) and not self._busy(t, now))
        if not free:
            return None
        return EncodeJob(latest, self._choose_base(peers), free)

    def encoded(
        self, job: EncodeJob, envelope: Envelope, now: float, peers: Mapping[str, Collection[str]]
    ) -> tuple[str, ...]:
        """``job`` was coded into ``envelope``; returns the transports to offer it to."""
        if envelope.is_keyframe:
            self._since_keyframe = 0
            self.counters.keyframes_sent += 1
            self.keyframe = envelope
        else:
            self._since_keyframe += 1
            self.counters.deltas_sent += 1
        again = [t for t in job.transports if self._offered.get(t, 0) >= envelope.version]
        if again:
            self.counters.reoffers += 1  # for arrivals only (P6): at most one per timeout and link
        self._reoffered.update(dict.fromkeys(again, now))
        for t in job.transports:
            self._offered[t] = envelope.version
            self._arrived.pop(t, None)
            # a peer that already holds this version (a late joiner's query got it) will not ack it again
            waiting = {p for p in peers.get(t, ()) if self._newest(p) < envelope.version}
            timeout = max(self.inflight_timeout_s, INFLIGHT_PER_PEER_S * len(waiting))
            self._inflight[t] = InFlight(
                envelope.version, now, waiting, timeout, paced=t in self.paced, keyframe=envelope.is_keyframe
            )
        return job.transports

    def offers(self, now: float) -> dict[str, dict[str, Any]]:
        """Each transport's offer still waited for, for ``mapd status``: the version, its age, the
        peers it waits for, and on a paced link whether it is wholly on the air yet (P1)."""
        return {
            t: {
                "version": f.version,
                "age_s": round(now - f.since, 1),
                "waiting": sorted(f.unsettled),
                "on_air": (f.on_air is not None) if f.paced else None,
            }
            for t, f in sorted(self._inflight.items())
            if f.unsettled
        }

    def next_deadline(self) -> float | None:
        """When an offer still in flight times out while a newer version (or a peer that came into
        reach, P6, or whose offer failed, P7) waits for its link, or None.

        Poll again then: the link is free for the newer version (P1).
        """
        latest = self._latest
        if latest is None:
            return None
        v = latest.version
        times = [
            f.expires() for t, f in self._inflight.items() if f.unsettled and self._offered.get(t, 0) < v
        ]
        for t in self._arrived:  # P6: once the link is free and the last such offer a timeout old
            if self._offered.get(t, 0) >= v and self._arrivals_lack(t, v):
                f = self._inflight.get(t)
                busy = f.expires() if f is not None and f.unsettled else 0.0
                times.append(max(busy, self._reoffered.get(t, -math.inf) + self.inflight_timeout_s))
        return min(times) if times else None

    def base_to_save(self, peers: Collection[str]) -> OccupancyGrid | None:
        """The version to persist as the delta base, when every peer acked the same one (P5)."""
        versions = {self._newest(p) for p in (peers or self._held)}
        if len(versions) != 1:
            return None
        v = versions.pop()
        if v == self._base_version:
            return None
        return self._sent.get(v)

    def remember_keyframe(self, envelope: Envelope) -> None:
        """A keyframe coded outside :meth:`poll` (a late joiner's query); an older one never replaces a newer."""
        if self.keyframe is None or envelope.version > self.keyframe.version:
            self.keyframe = envelope

    def cached_keyframe(self, version: int) -> Envelope | None:
        """The keyframe of own ``version`` if one was coded, else None."""
        kf = self.keyframe
        return kf if kf is not None and kf.version == version else None

    # ------------------------------------------------------------------ internals
    def _newest(self, peer: str) -> int:
        """The newest own version ``peer`` acknowledged (0: none)."""
        held = self._held.get(peer)
        return held[-1] if held else 0

    def _newest_own(self) -> OccupancyGrid | None:
        """The newest own version; after a restart with none made yet, the one restored (a map that
        no longer changes still goes to a peer that asks for it or comes into reach)."""
        if self._latest is None:
            self._latest = self._restored
        return self._latest

    def _arrivals_lack(self, transport: str, version: int) -> bool:
        """Whether a peer that came into reach on ``transport`` (or whose offer failed) still lacks
        own ``version`` (P6, P7)."""
        return any(self._newest(p) < version for p in self._arrived.get(transport, ()))

    def _wants(self, transport: str, version: int, now: float) -> bool:
        """Whether ``transport`` is to be offered own ``version`` at ``now``: it never was (P1, P2),
        or a peer that came into reach since (or whose offer failed, P7) still lacks it and the last
        offer made for such peers is a timeout old (P6)."""
        if self._offered.get(transport, 0) < version:
            return True
        if now < self._reoffered.get(transport, -math.inf) + self.inflight_timeout_s:
            return False
        return self._arrivals_lack(transport, version)

    def _busy(self, transport: str, now: float) -> bool:
        busy = self._inflight.get(transport)
        return busy is not None and bool(busy.unsettled) and now < busy.expires()

    def _settle(self, transport: str, peer: str, version: int) -> bool:
        busy = self._inflight.get(transport)
        if busy is None or version < busy.version:
            return False
        busy.unsettled.discard(peer)
        return not busy.unsettled

    def _choose_base(self, peers: Mapping[str, Collection[str]]) -> OccupancyGrid | None:
        if not self.uses_base or self._since_keyframe + 1 >= self.keyframe_every:
            return None
        everyone = set().union(*peers.values()) if peers else set()
        if not everyone:
            return None
        common = set(self._sent)
        for p in everyone:
            common.intersection_update(self._held.get(p, ()))
            if not common:
                return None  # no version every peer still holds: only a keyframe suits them all
        return self._sent[max(common)]
