"""Sans-I/O: which peers ack this robot's maps at the radio while their daemon refuses them.

Over ``uwb`` a map is acked (``Delivered``) once its chunks are all in, before the receiving daemon
has looked at it; a daemon whose config drifted from ours (another codec model, a smaller
``limits.max_cells``, a roster without our key, ...) then refuses every map, says why once in its
own log, and our ``mapd status`` shows it as having "acked our" newest version all the same.

The relay's summaries tell. In a signed fleet with ``[transports.uwb] relay`` on (the defaults)
every robot broadcasts, each ``summary_period_s``, the newest version it *holds* of each origin,
that is the newest its daemon accepted (:meth:`~transports.uwb.forwarding.ForwardingCore.holds`).
A peer that acked our version ``v`` and whose summaries, heard well after, still say it holds less
than ``v`` of ours (or nothing) refuses our maps. Where relay is off or the fleet is unsigned no
summaries are sent: nothing is fed in, nothing is said, as before.

Only evidence that cannot be a race counts:

* A summary counts against an ack only when heard at least ``margin_s`` after it, by default
  three summary periods: a summary lives on the air at most two periods (its deadline, behind the
  map chunks), so one heard later was packed after the ack; the third period is the receiver's
  decode and save (the ack comes as the chunks are all in, the daemon holds the map only after
  decoding it) and its summary tick. With the default 10 s period that is 30 s after the ack,
  :data:`mapd.daemon.refusals.UNACKED_S`, when the zenoh path says the same of a peer.
* The discrepancy must last: two such summaries, the second at least a summary period after the
  first, with no progress between them. One late or odd summary says nothing alone.

It clears when a later summary shows the peer holds an acked version (the newest acked that
``margin_s`` ago or newer), or holds a newer map of ours than when the doubt began (its daemon took
one since: a delta refused for a missing base, healed by the keyframe it asked for, is no refusal).

A peer that only *missed* our newest version at the radio (never acked it) and holds an older one
is not refusing: only acked versions are judged. A peer that restarted may hold our maps from its
state dir without its summary listing them (a robot lists the maps it restored since
:meth:`~transports.uwb.forwarding.ForwardingCore.on_restored`; one from before listed only what
its daemon accepted since it started), so after a restart only versions newer than any this robot
offered before it are judged (a restart into a config that refuses ours is found with our next
version, not before).

A peer whose ``[transports.uwb] nodes`` gives this robot another link id lists our maps under that
id: it is said to refuse them, and its log says why (the nodes lists differ; it says so too).

Bounded: at most ``max_peers`` peers (the link's known nodes), a few acks each.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

#: Acks kept per peer (version, when first acked), oldest first. When full the newest two merge
#: into the later one: a later time for a version only delays the judgement, never hastens it.
MAX_ACKS = 16
#: Peers tracked at most (the transport feeds only the link's known nodes, at most 254).
MAX_PEERS = 255


@dataclass(frozen=True)
class Refused:
    """Peer ``peer`` acked our ``acked`` at the radio; its summaries say its daemon holds ``holds``
    (0: nothing of ours)."""

    peer: int
    acked: int
    holds: int


@dataclass(frozen=True)
class Cleared:
    """Peer ``peer``, said to refuse our maps, holds ``holds`` of ours now."""

    peer: int
    holds: int


@dataclass
class _Peer:
    acks: list[tuple[int, float]] = field(default_factory=list)  # (version, first acked), versions rising
    floor: int = 0  # acks of versions up to this are not judged (its restart: its state dir may hold them)
    doubt_at: float | None = None  # the first summary that held less than it acked, since the last progress
    doubt_holds: int = 0  # what that summary held
    doubts: int = 0  # summaries since doubt_at that held less
    refused: Refused | None = None


@dataclass
class RefusalCore:
    """Whose daemon refuses this robot's maps though its radio acks them (link ids throughout)."""

    summary_period_s: float
    #: how long after an ack a summary must be heard to judge it (default: three summary periods)
    margin_s: float | None = None
    max_peers: int = MAX_PEERS
    _peers: dict[int, _Peer] = field(default_factory=dict)
    _offered: int = 0  # the newest own version offered

    def __post_init__(self) -> None:
        if self.margin_s is None:
            self.margin_s = 3 * self.summary_period_s

    # --- inputs ---------------------------------------------------------------------------------
    def offered(self, version: int) -> None:
        """This robot offered its own ``version`` (the floor a restarted peer is judged above)."""
        self._offered = max(self._offered, version)

    def acked(self, peer: int, version: int, now: float) -> None:
        """``peer``'s radio acked our own ``version`` (all its chunks are in) at ``now``."""
        p = self._peer(peer)
        if p is None or version <= p.floor or (p.acks and version <= p.acks[-1][0]):
            return  # judged by the newer one acked already (a superseded version's late ack)
        if len(p.acks) >= MAX_ACKS:
            p.acks.pop()
        p.acks.append((version, now))

    def restarted(self, peer: int) -> None:
        """``peer`` restarted: judge only versions newer than any offered so far (what it held of
        ours may come back from its state dir, unlisted in its summaries), and start afresh."""
        if peer in self._peers or len(self._peers) < self.max_peers:
            self._peers[peer] = _Peer(floor=self._offered)

    def summary(self, peer: int, holds: int, now: float) -> Refused | Cleared | None:
        """``peer``'s summary heard at ``now`` says it holds ``holds`` of ours (0: nothing). Returns
        what changed: :class:`Refused` when it is found to refuse our maps, :class:`Cleared` when
        one found so holds an acked version now, else None."""
        p = self._peers.get(peer)
        if p is None:
            return None
        judged = self._judged(p, now)
        if judged is None:
            return None  # nothing acked long enough ago to judge
        if holds >= judged or (p.doubt_at is not None and holds > p.doubt_holds):
            # It holds what it acked, or took a newer map of ours since the doubt began.
            was = p.refused
            p.doubt_at, p.doubts, p.refused = None, 0, None
            return Cleared(peer, holds) if was is not None else None
        if p.doubt_at is None:
            p.doubt_at, p.doubt_holds, p.doubts = now, holds, 1
            return None
        p.doubts += 1
        if p.refused is None and p.doubts >= 2 and now - p.doubt_at >= self.summary_period_s:
            p.refused = Refused(peer, judged, holds)
            return p.refused
        if p.refused is not None:
            p.refused = Refused(peer, judged, holds)  # the figures move on; said once all the same
        return None

    # --- outputs --------------------------------------------------------------------------------
    def refusing(self) -> dict[int, Refused]:
        """Peer -> what it acked and holds, for the peers whose daemon refuses our maps now."""
        return {n: p.refused for n, p in sorted(self._peers.items()) if p.refused is not None}

    def stats(self, name: Callable[[int], str]) -> dict[str, Any]:
        """For the link's stats: ``refused_by_peers``, how many peers refuse our maps now (a link
        fault), and ``refused_by``, each one's ``name`` -> the version it acked and the one it holds."""
        refusing = self.refusing()
        return {
            "refused_by_peers": len(refusing),
            "refused_by": {name(n): {"acked": r.acked, "holds": r.holds} for n, r in refusing.items()},
        }

    # --- internals ------------------------------------------------------------------------------
    def _peer(self, peer: int) -> _Peer | None:
        p = self._peers.get(peer)
        if p is None:
            if len(self._peers) >= self.max_peers:
                return None
            p = self._peers[peer] = _Peer()
        return p

    def _judged(self, p: _Peer, now: float) -> int | None:
        """The newest version acked at least ``margin_s`` before ``now``; older acks are dropped."""
        assert self.margin_s is not None
        i = next((i for i in range(len(p.acks) - 1, -1, -1) if p.acks[i][1] <= now - self.margin_s), None)
        if i is None:
            return None
        del p.acks[:i]  # the older ones are judged by this one
        return p.acks[0][0]


def _v(version: int) -> str:
    """``v<number>`` as ``mapd status`` shows versions (the incarnation, the high 32 bits, left
    out: mapd.daemon.versions.label, a layer above this one); ``none`` for 0."""
    return f"v{version & 0xFFFFFFFF}" if version > 0 else "none"


def words(change: Refused | Cleared, peer: str) -> str:
    """The log line for ``change`` of ``peer`` (a warning when it refuses, else news)."""
    if isinstance(change, Refused):
        return (
            f"uwb: {peer} acks our maps at the radio but its daemon holds none of them (acked "
            f"{_v(change.acked)}, holds {_v(change.holds)}): it refuses them; its log and mapd "
            f"status say why"
        )
    return f"uwb: {peer} holds our {_v(change.holds)} now: its daemon takes our maps again"
