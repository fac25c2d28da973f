"""Peers' keyframe queries of our own map: which ones the daemon heeds, and how many are answered.

The half of :class:`~transports.zenoh.core.ZenohCore` that faces askers, as a mixin over the core's
state (the core asks its own queries, in ``core.py``). The rules:

* **Heeded** (:meth:`AnswerSide.on_query`). A query of our own keyframe emits ``KeyframeNeeded``
  for its asker only when the roster admits the asker (an unknown name counts in ``unadmitted``),
  the asker signed it (else ``bad_signature``, or ``dropped`` with no valid nonce) and its nonce is
  above the last one heeded from that asker (else ``replayed``); see
  :mod:`transports.zenoh.queries` for the parameters.
* **Answered** (:meth:`AnswerSide.may_reply`). The adapter answers such queries all the same, as it
  answers any query while answers stay within their ration: a burst of ``REPLY_BURST``, then
  ``REPLY_RATE_HZ``; the rest are dropped unanswered and counted in ``queries_shed``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import Roster
from transports import signed_requests
from transports.base import KeyframeNeeded
from transports.zenoh import keys, queries
from transports.zenoh.core_types import NAME, CoreCounters, Step

#: Keyframe queries answered: a burst of this many, then REPLY_RATE_HZ. Anyone may query, and each
#: answer is a whole keyframe on the uplink and a job ahead of our own map updates; a late-joining
#: asker that is not answered still gets the keyframe its signed query makes the daemon publish.
REPLY_BURST = 16
REPLY_RATE_HZ = 4.0
#: Answers waiting for the job thread at most (the adapter holds the slots).
MAX_REPLIES_PENDING = 4


class AnswerSide:
    """What the core does with a peer's query of our keyframe (a mixin:
    :class:`~transports.zenoh.core.ZenohCore` owns the state declared here)."""

    robot: str
    fleet: str
    roster: Roster
    counters: CoreCounters
    # The last query nonce heeded from each asker, as the uwb transport keeps its requests'.
    _fresh: signed_requests.Freshness
    # The answers' ration: tokens left, and when it was last refilled (None: never).
    _reply_tokens: float
    _reply_at: float | None

    if TYPE_CHECKING:
        # The asker's slot in the core (None: the roster or max_peers leaves it none).
        def _state(self, robot: str) -> object | None: ...

    def on_query(self, asker: str | None, nonce: str | None = None, sig: str | None = None) -> Step:
        """A peer queried our latest keyframe with parameters ``from=asker;n=nonce;sig=sig``.

        ``KeyframeNeeded`` makes the daemon forget the asker's acked base and publish its next map
        whole, a keyframe's bytes for every robot on the bus, so it is emitted only for a signed,
        fresh query from a robot the roster admits (:mod:`transports.zenoh.queries`).
        """
        self.counters.queries_served += 1
        if asker is None or not keys.valid_name(asker) or asker == self.robot:
            return Step()
        if not self.roster.admits(asker):
            self.counters.unadmitted += 1
            return Step()
        try:
            n = queries.verify(
                self.roster, fleet=self.fleet, asker=asker, robot=self.robot, nonce=nonce, sig=sig
            )
        except SignatureError:
            self.counters.bad_signature += 1
            return Step()
        except EnvelopeError:
            self.counters.dropped += 1
            return Step()
        st = self._state(asker)
        if st is None:  # no room for another robot (max_peers): it is no peer of ours either
            return Step()
        if not self._fresh.fresh(asker, n):
            self.counters.replayed += 1
            return Step()
        return Step(events=[KeyframeNeeded(transport=NAME, peer=asker, robot=self.robot)])

    def may_reply(self, now: float, slot_free: bool = True) -> bool:
        """Whether to answer the query that just came (after :meth:`on_query`), or drop it unanswered.

        ``slot_free``: the adapter has room for one more answer waiting (MAX_REPLIES_PENDING).
        """
        if self._reply_at is not None and now > self._reply_at:
            self._reply_tokens = min(
                float(REPLY_BURST), self._reply_tokens + (now - self._reply_at) * REPLY_RATE_HZ
            )
        self._reply_at = now if self._reply_at is None else max(now, self._reply_at)
        if not slot_free or self._reply_tokens < 1.0:
            self.counters.queries_shed += 1
            return False
        self._reply_tokens -= 1.0
        return True
