"""The sans-I/O core of the zenoh transport: what to do with each thing that arrives.

No zenoh, asyncio or clock in here: the adapter (:mod:`transports.zenoh.link`) feeds it key
expressions, payload bytes and ``now``, and carries out the
:class:`~transports.zenoh.core_types.Step` it gets back (events to emit, keyframe queries to send).
The rules:

* **Verify before anything.** An update or query reply is unpacked with the fleet's roster, fleet
  id and size limit; a signature the roster does not accept (missing, another robot's key) counts
  in ``bad_signature``, anything else malformed (or an envelope whose robot differs from the key it
  came on) in ``dropped``. Neither is ever emitted. A robot the roster does not admit gets no state
  at all: its liveliness token, updates and acks cost nothing, and its updates and replies are
  refused unread (``unadmitted``), before any verification. An update or reply over
  ``max_message_bytes`` is refused unread too, and said once per robot with the fix (its limits are
  larger than ours: :meth:`ZenohCore.oversize`, ``oversize_rx``).
* **Check, then apply.** Verification is split from the state it feeds so that the adapter can run
  it off the event loop: :meth:`ZenohCore.check` (unpack and verify; pure, touches nothing, safe on
  any thread) and :meth:`ZenohCore.on_update_checked` / :meth:`ZenohCore.on_reply_checked` (take its
  result and apply the rules below; loop only). :meth:`ZenohCore.on_update` and
  :meth:`ZenohCore.on_reply` do both, for callers with no thread to spare (tests, tools).
* **Bases.** Per robot, the core remembers the last version it passed on and the last
  ``base_window`` versions passed on. A keyframe newer than the last version is passed on. A delta
  newer than the last version is passed on when its base is one of the remembered versions (the
  sender codes against the newest version every peer *acked*, which may trail the newest one seen).
  Anything else newer is a **gap** (a lost update, a late join, an unknown base): it is dropped,
  counted, and the robot's latest keyframe is queried. Versions at or below the last one are stale
  (a duplicate, or a query reply older than what we hold) and are dropped.
* **Queries** go to ``mapd/<fleet>/<robot>/latest?from=<us>;n=<nonce>;sig=<signature>`` (see
  :mod:`transports.zenoh.queries`); at most one per robot is in flight
  until its replies end or ``query_timeout_s`` passes; a gap seen meanwhile asks once more when it
  ends (the reply may predate the gap). A peer that appears with no map known yet is
  queried at once (late join). ``request_keyframe`` (the daemon could not decode) forgets the
  robot's versions, so the keyframe that answers is accepted whatever its version. Peers' queries
  of our own keyframe (which are heeded, how many are answered) are
  :mod:`transports.zenoh.answers`.
* **Presence.** A liveliness token appearing gives ``PeerUp``, vanishing gives ``PeerDown`` and
  forgets the robot's versions. Tokens are not signed, so in a signed fleet :meth:`ZenohCore.peers`
  (the robots the daemon waits for) lists only robots that have also shown a verified message.
* **Acks** (their payload: :mod:`transports.zenoh.acks`). A valid ack of one of our own offered
  versions becomes ``Delivered``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Any

from mapd.envelope import Envelope, unpack
from mapd.errors import EnvelopeError, SignatureError
from mapd.identity import Identity, Roster
from transports import signed_requests
from transports.base import Delivered, PeerDown, PeerUp, Received
from transports.rtt import RttEstimator
from transports.zenoh import keys, queries
from transports.zenoh.acks import pack_ack, unpack_ack
from transports.zenoh.answers import REPLY_BURST, AnswerSide
from transports.zenoh.core_types import NAME, CoreCounters, Step

#: Own versions whose offer time is kept for RTT samples.
RTT_VERSIONS = 16
#: Robots whose maps over ``max_message_bytes`` are said and shown (``oversize_from``); maps of
#: more are only counted (an open roster admits any name, and names cost memory).
MAX_OVERSIZE_SHOWN = 16


@dataclass
class _Robot:
    last: int = 0
    bases: deque[int] = field(default_factory=deque)
    alive: bool = False
    #: It has shown a message its roster key verified (an update, a query reply or an ack).
    verified: bool = False
    query_until: float | None = None
    #: A gap came while a query was in flight; its reply may predate it, so ask again at the end.
    regap: bool = False

    def forget(self) -> None:
        self.last = 0
        self.bases.clear()


class ZenohCore(AnswerSide):
    """Receive-side state and counters of one robot's zenoh link (see the module docstring; peers'
    queries of our keyframe: :class:`~transports.zenoh.answers.AnswerSide`)."""

    def __init__(
        self,
        *,
        robot: str,
        fleet: str,
        identity: Identity | None,
        roster: Roster,
        max_message_bytes: int,
        query_timeout_s: float = 2.0,
        base_window: int = 8,
        max_peers: int = 64,
    ) -> None:
        if not keys.valid_name(robot) or not keys.valid_name(fleet):
            raise ValueError(f"robot '{robot}' or fleet '{fleet}' is not a valid id")
        self.robot = robot
        self.fleet = fleet
        self.identity = identity
        self.roster = roster
        self.max_message_bytes = max_message_bytes
        self.query_timeout_s = query_timeout_s
        self.base_window = base_window
        self.max_peers = max_peers
        self._robots: dict[str, _Robot] = {}
        self._max_offered = 0
        # When each recent own version was offered, for the offer-to-ack time (bounded: the oldest
        # go first; an ack of a forgotten version just gives no sample).
        self._offered_at: dict[int, float] = {}
        self._rtt = RttEstimator()
        self._nonces = signed_requests.NonceClock()
        # The last query nonce heeded from each asker, as the uwb transport keeps its requests'.
        self._fresh = signed_requests.Freshness()
        self._reply_tokens = float(REPLY_BURST)
        self._reply_at: float | None = None
        self.counters = CoreCounters()
        #: Robot -> the size of its largest map over max_message_bytes (at most MAX_OVERSIZE_SHOWN).
        self._oversize: dict[str, int] = {}

    # -- state -------------------------------------------------------------------------------------

    def _state(self, robot: str) -> _Robot | None:
        st = self._robots.get(robot)
        if st is None:
            # A robot the roster does not admit costs nothing: no slot, no query, no waiting.
            if len(self._robots) >= self.max_peers or not self.roster.admits(robot):
                return None
            st = self._robots[robot] = _Robot()
        return st

    def peers(self) -> list[str]:
        """Robots whose liveliness token is up and that have shown a signed message.

        A token alone is not enough: anyone on the network can declare one, and the daemon waits
        for acks from every peer listed here. A fleet that allows unsigned messages lists every token.
        """
        # A robot a reloaded roster no longer admits is no peer: its acks cannot verify any more.
        return sorted(
            r
            for r, st in self._robots.items()
            if st.alive and self.roster.admits(r) and (st.verified or self.roster.allow_unsigned)
        )

    def last_version(self, robot: str) -> int:
        """The last version of ``robot`` passed on (0: none, or forgotten)."""
        st = self._robots.get(robot)
        return st.last if st is not None else 0

    def stats(self) -> dict[str, Any]:
        """The counters by name, then ``peers`` (tokens up), ``rtt_ms`` (offer to ack, smoothed) and
        ``oversize_from`` (robot -> bytes of its largest map over ``max_message_bytes``)."""
        srtt = self._rtt.srtt
        rtt = round(1000 * srtt, 1) if srtt is not None else None
        return {
            **asdict(self.counters),
            "peers": len(self.peers()),
            "rtt_ms": rtt,
            "oversize_from": dict(self._oversize),
        }

    # -- inputs ------------------------------------------------------------------------------------

    def offered(self, envelope: Envelope, now: float | None = None) -> None:
        """Our daemon offered ``envelope``: acks up to its version are plausible from now on.

        With ``now``, an ack of this version later gives an RTT sample (offer to ack: publish,
        the peer's verify and decode, and the ack's way back).
        """
        if envelope.robot == self.robot:
            self._max_offered = max(self._max_offered, envelope.version)
            if now is not None:
                self._offered_at[envelope.version] = now
                while len(self._offered_at) > RTT_VERSIONS:
                    del self._offered_at[min(self._offered_at)]

    def update_robot(self, key_expr: str) -> str | None:
        """The robot whose update ``key_expr`` carries, or None when it is no peer's update key.

        Pure (reads only fixed settings), so the adapter can call it on zenoh's thread to refuse a
        sample before copying it. Whether the roster admits that robot is :meth:`admits`.
        """
        robot = keys.parse_update(self.fleet, key_expr)
        return None if robot is None or robot == self.robot else robot

    def admits(self, robot: str) -> bool:
        """Whether an update or reply of ``robot`` is worth verifying at all (thread-safe, cheap).

        A robot the roster does not admit could only fail verification, so its samples are refused
        unread: an 8 MiB sample under a made-up name costs no copy and no Ed25519 check.
        """
        return self.roster.admits(robot)

    def check(self, data: bytes) -> Envelope | EnvelopeError:
        """Unpack and verify ``data`` (msgpack parse, size limit, fleet id, Ed25519 signature).

        Pure: no state or counter is touched, and the roster is read whole (a reload swaps its keys
        atomically), so it may run on any thread. The result goes to :meth:`on_update_checked` or
        :meth:`on_reply_checked`, on the thread that owns this core.
        """
        try:
            return unpack(data, max_bytes=self.max_message_bytes, roster=self.roster, fleet=self.fleet)
        except EnvelopeError as exc:
            return exc

    def on_update(self, key_expr: str, data: bytes, now: float) -> Step:
        """A sample arrived on an update key: refuse, check and apply it in one go."""
        robot = self.update_robot(key_expr)
        if robot is None:
            self.counters.dropped += 1
            return Step()
        if not self.admits(robot):
            self.counters.unadmitted += 1
            return Step()
        return self.on_update_checked(robot, data, self.check(data), now)

    def on_update_checked(
        self, robot: str, data: bytes, checked: Envelope | EnvelopeError, now: float
    ) -> Step:
        """An update of ``robot`` (from :meth:`update_robot`) arrived, and :meth:`check` gave ``checked``."""
        return self._on_envelope(robot, data, checked, now, from_query=False)

    def oversize(self, robot: str, size: int) -> Step:
        """An update or reply of ``robot`` (admitted) was ``size`` bytes, over ``max_message_bytes``.

        It is refused unread, as :meth:`check` would refuse it, but not as one more ``dropped``:
        every map of a robot whose limits are larger than ours meets it, and only this side can
        tell (the sender hears no ack, nothing more). Said once per robot with the fix, counted in
        ``oversize_rx`` and shown in ``oversize_from``.
        """
        self.counters.oversize_rx += 1
        step = Step()
        if robot in self._oversize:
            # The largest: what its limit must be raised to (a late query reply may be smaller).
            self._oversize[robot] = max(self._oversize[robot], size)
        elif len(self._oversize) < MAX_OVERSIZE_SHOWN:
            self._oversize[robot] = size
            step.warnings.append(
                f"zenoh: maps of {robot} refused: {size} bytes, over this robot's "
                f"limits.max_message_bytes ({self.max_message_bytes}): raise it on {self.robot} to at "
                f"least {size} (the same on every robot), or make {robot}'s maps smaller"
            )
        return step

    def on_reply(self, robot: str, data: bytes, now: float) -> Step:
        """A reply to our keyframe query of ``robot`` arrived: check and apply it in one go."""
        if not self.admits(robot):
            self.counters.unadmitted += 1
            return Step()
        return self.on_reply_checked(robot, data, self.check(data), now)

    def on_reply_checked(
        self, robot: str, data: bytes, checked: Envelope | EnvelopeError, now: float
    ) -> Step:
        """A reply to our keyframe query of ``robot`` arrived, and :meth:`check` gave ``checked``."""
        return self._on_envelope(robot, data, checked, now, from_query=True)

    def query_done(self, robot: str, now: float) -> Step:
        """Our query of ``robot`` has ended (all replies in, or timed out)."""
        step = Step()
        st = self._robots.get(robot)
        if st is not None:
            st.query_until = None
            if st.regap:
                self._query(robot, st, now, step)
        return step

    def on_presence(self, key_expr: str, alive: bool, now: float) -> Step:
        """A liveliness token appeared (``alive``) or vanished."""
        robot = keys.parse_presence(self.fleet, key_expr)
        if robot is None or robot == self.robot:
            return Step()
        st = self._state(robot) if alive else self._robots.get(robot)
        if st is None:
            if alive:
                self.counters.dropped += 1
            return Step()
        step = Step()
        if alive and not st.alive:
            st.alive = True
            step.events.append(PeerUp(transport=NAME, peer=robot))
            if st.last == 0:
                self._query(robot, st, now, step)
        elif not alive and st.alive:
            # Forget it all: a restarted robot counts from 1 again, and its slot is free.
            del self._robots[robot]
            step.events.append(PeerDown(transport=NAME, peer=robot))
        return step

    def on_ack(self, key_expr: str, data: bytes, now: float | None = None) -> Step:
        """A peer's ack of one of our versions arrived (at ``now``, for the RTT)."""
        peer = keys.parse_ack(self.fleet, self.robot, key_expr)
        if peer is None or peer == self.robot:
            self.counters.dropped += 1
            return Step()
        try:
            version = unpack_ack(data, roster=self.roster, fleet=self.fleet, peer=peer, robot=self.robot)
        except EnvelopeError as exc:
            self._refused(exc)
            return Step()
        if version > self._max_offered:
            self.counters.dropped += 1  # an ack of a version we never sent: not a usable base
            return Step()
        st = self._state(peer)
        if st is None:
            # Past max_peers: in a fleet that allows unsigned acks anyone can ack under a made-up
            # name, and each Delivered would become a row the publisher and state.json keep for ever.
            self.counters.dropped += 1
            return Step()
        self.counters.acks_rx += 1
        st.verified = True
        sent = self._offered_at.get(version)
        if now is not None and sent is not None and now >= sent:
            self._rtt.sample(now - sent)  # smoothed as TCP does (RFC 6298)
        return Step(events=[Delivered(transport=NAME, peer=peer, robot=self.robot, version=version)])

    def query_parameters(self, robot: str, wall_ns: int) -> str:
        """The selector parameters of our next query of ``robot``'s keyframe, signed when we sign.

        ``wall_ns`` is the wall clock now in nanoseconds; nonces grow from it (see
        :class:`~transports.signed_requests.NonceClock`).
        """
        return queries.parameters(
            self.identity, fleet=self.fleet, asker=self.robot, robot=robot, nonce=self._nonces.next(wall_ns)
        )

    def request_keyframe(self, robot: str, now: float) -> Step:
        """The daemon cannot use what it holds of ``robot``: forget it and query a keyframe."""
        step = Step()
        if not keys.valid_name(robot) or robot == self.robot:
            return step
        st = self._state(robot)
        if st is not None:
            st.forget()
            self._query(robot, st, now, step)
        return step

    def ack(self, robot: str, version: int) -> tuple[str, bytes]:
        """Key and payload of our ack of ``robot``'s ``version``."""
        payload = pack_ack(version, identity=self.identity, fleet=self.fleet, peer=self.robot, robot=robot)
        return keys.ack_key(self.fleet, self.robot, robot), payload

    # -- rules -------------------------------------------------------------------------------------

    def _query(self, robot: str, st: _Robot, now: float, step: Step) -> None:
        if st.query_until is not None and now < st.query_until:
            st.regap = True
            return
        st.regap = False
        st.query_until = now + self.query_timeout_s
        self.counters.keyframe_queries += 1
        step.queries.append(robot)

    def _refused(self, exc: EnvelopeError) -> None:
        """Count an update, reply or ack that failed verification, by what was wrong with it."""
        if isinstance(exc, SignatureError):
            self.counters.bad_signature += 1
        else:
            self.counters.dropped += 1

    def _on_envelope(
        self, robot: str, data: bytes, checked: Envelope | EnvelopeError, now: float, *, from_query: bool
    ) -> Step:
        if isinstance(checked, EnvelopeError) and len(data) > self.max_message_bytes:
            return self.oversize(robot, len(data))  # (the adapter refuses these before the check)
        self.counters.bytes_rx += len(data)
        if isinstance(checked, EnvelopeError):
            self._refused(checked)
            return Step()
        env = checked
        st = self._state(robot)
        if env.robot != robot or st is None:
            self.counters.dropped += 1
            return Step()
        st.verified = True
        if env.version <= st.last:
            self.counters.stale += 1
            return Step()
        if env.is_keyframe or env.base_version in st.bases:
            st.last = env.version
            st.bases.append(env.version)
            while len(st.bases) > self.base_window:
                st.bases.popleft()
            self.counters.updates_rx += 1
            return Step(events=[Received(transport=NAME, peer=robot, data=data)])
        self.counters.gaps += 1
        step = Step()
        if not from_query:
            self._query(robot, st, now, step)
        return step
