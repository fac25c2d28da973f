"""Whom to lend the rest of an own TDMA slot to (R17 in ``arq.py``), from what the node overhears; pure.

Every DATA frame says how far through its message the sender is (``index`` of ``count``), and every
node on a shared channel hears every frame, so each knows, without a byte more on the air, which
robots still have chunks to send. A robot whose own slot still has room but nothing to put in it
names one of them in a LEND frame, and that robot sends in the rest of the slot: TDMA stays
collision-free (one sender per slot, the owner or whom it named), while a robot with a large map
gets more than its fixed share of the channel when others have less to say. This is the idea of
Z-MAC's owner priority (Rhee et al., 2005) made explicit: the owner hands its slot over, rather
than letting non-owners contend for it, because carrier sense here only hears a frame once it ends.
"""

from __future__ import annotations

from dataclasses import dataclass

from transports.uwb.wire import msg_before


@dataclass
class _Seen:
    msg: int
    top: int  # highest chunk index heard of msg
    count: int
    when: float


class Backlogs:
    """What each peer has left to send, as last overheard, and the choice of a borrower."""

    def __init__(self, horizon_s: float, max_peers: int = 254) -> None:
        #: Only what was heard this recently counts (a peer with work sends at least once a cycle).
        self.horizon = horizon_s
        self.max_peers = max_peers
        self._seen: dict[int, _Seen] = {}
        self._lent_at: dict[int, float] = {}

    def heard(self, peer: int, msg: int, index: int, count: int, now: float) -> None:
        """A reliable DATA frame of ``peer``'s: chunk ``index`` of ``count`` of message ``msg``."""
        s = self._seen.get(peer)
        if s is not None and s.msg == msg:
            s.top, s.when = max(s.top, index), now
        elif s is None or now - s.when > self.horizon or not msg_before(msg, s.msg):
            # (an older message's resend says nothing new)
            if s is None and len(self._seen) >= self.max_peers:
                return
            self._seen[peer] = _Seen(msg, index, count, now)

    def left(self, peer: int, now: float) -> int:
        """Chunks ``peer`` had still to send when last heard (0: nothing known within the horizon)."""
        s = self._seen.get(peer)
        if s is None or now - s.when > self.horizon:
            return 0
        return s.count - 1 - s.top

    def pick(self, now: float, up: list[int]) -> int | None:
        """The peer to lend to: the most chunks left, then the one lent to longest ago; None: nobody."""
        best: tuple[int, float, int] | None = None
        for p in up:
            n = self.left(p, now)
            if n <= 0:
                continue
            key = (n, -self._lent_at.get(p, -1e18), p)
            if best is None or key[:2] > best[:2]:
                best = key
        return best[2] if best is not None else None

    def lent(self, peer: int, now: float) -> None:
        self._lent_at[peer] = now

    def forget(self, peer: int) -> None:
        """``peer`` restarted: its message ids start afresh."""
        self._seen.pop(peer, None)
        self._lent_at.pop(peer, None)
