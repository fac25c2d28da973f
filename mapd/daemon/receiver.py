"""Peers' maps in: the rules for taking a peer's map, and the maps taken. The decisions are plain
methods; the daemon runs the CPU work (:mod:`~mapd.daemon.intake`: the steps in order, and the
plan's answers).

The receiver keeps, per peer robot, the newest map, up to :data:`KEEP_PEER_VERSIONS` recent
versions (a sender may code a delta against a version it saw acked while newer ones were still in
flight), and what ``mapd status`` shows about it (:class:`~mapd.daemon.intake.PeerInfo`).

**Configs that disagree.** Robots of one fleet whose configs drifted apart (a roster without a
robot's key or with its old one, another ``robot.fleet``, smaller ``limits``, ``[transports.uwb]
nodes`` lists that differ) refuse each other's maps with every map they send. Each such cause is
said once per robot (:class:`~mapd.daemon.refusals.Refusal`: a warning naming the robot and the fix), not once per map,
and ``mapd status`` shows it on that robot's line until one of its maps is taken again. A peer
that takes our maps no more (its acks stopped while its own maps keep coming, :meth:`Receiver.unacked`)
is said the same way, on the side that cannot see why.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, TypeVar

from mapd.daemon.intake import AskKeyframe, Decode, Drop, PeerInfo, ReceiverCounters
from mapd.daemon.refusals import (
    MAX_REFUSED_NAMES,
    MAX_REFUSED_SHOWN,
    UNACKED_S,
    Refusal,
    envelope_refusal,
    shown,
)
from mapd.daemon.versions import EPOCH, VersionBounds, check_step, incarnation_at, split
from mapd.envelope import Envelope
from mapd.errors import EnvelopeError, SignatureError
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid
from mapd.identity import Roster

KEEP_PEER_VERSIONS = 8
K = TypeVar("K")
#: A held version whose incarnation is this far ahead of our clock is more than clocks that
#: disagree a little (chrony keeps them within milliseconds): its robot's maps refused as not newer
#: are said, every :data:`FUTURE_SAID_EVERY_S` at most per robot.
FUTURE_MARGIN_S = 60.0
FUTURE_SAID_EVERY_S = 600.0


def _incarnation_date(incarnation: int) -> str:
    """When a robot's state began, from its versions' incarnation (UTC, to the minute)."""
    import datetime

    at = datetime.datetime.fromtimestamp(EPOCH + incarnation, tz=datetime.UTC)
    return at.strftime("%Y-%m-%d %H:%M UTC")


def _due(said: dict[K, float], about: K, now: float) -> bool:
    """Whether a warning ``about`` a robot (or a link and robot) is due (none in the last
    :data:`FUTURE_SAID_EVERY_S`, or the clock went back since); if so, noted as said now."""
    last = said.get(about)
    due = last is None or not 0 <= now - last < FUTURE_SAID_EVERY_S
    if due:
        said[about] = now
    return due


#: Robots refused for want of room whose name is kept, so that each is logged once.
MAX_OVER_LIMIT_NAMES = 256


@dataclass
class Receiver:
    """Peers' maps held by one robot, and the rules for taking new ones."""

    me: str
    fleet: str
    roster: Roster = field(default_factory=Roster.open)
    bounds: VersionBounds = field(default_factory=VersionBounds)
    max_peers: int = 64
    max_cells: int = DEFAULT_MAX_CELLS
    #: A peer's map may grow to this many times its last one's cells (plus a floor) per update.
    max_growth: float = 4.0
    counters: ReceiverCounters = field(default_factory=ReceiverCounters)
    maps: dict[str, OccupancyGrid] = field(default_factory=dict)
    info: dict[str, PeerInfo] = field(default_factory=dict)
    _history: dict[str, dict[int, OccupancyGrid]] = field(default_factory=dict)
    _held_at: dict[str, float] = field(default_factory=dict)
    _over_limit: set[str] = field(default_factory=set)
    #: robot -> when a map refused under a held version from the future was last said
    _future_said: dict[str, float] = field(default_factory=dict)
    #: robot -> when its maps of an older incarnation than the one held were last said
    _older_said: dict[str, float] = field(default_factory=dict)
    #: robot -> why its maps are refused now (said once; cleared when one is taken)
    refusals: dict[str, Refusal] = field(default_factory=dict)
    #: robot -> the name its link knows it by when that is no robot of the roster (uwb: its link
    #: id is not in this robot's ``nodes``, or under another name): said once
    aliases: dict[str, str] = field(default_factory=dict)
    #: (link, robot) -> since when its maps arrive while it acks none of ours (see :meth:`unacked`)
    _ack_wait: dict[tuple[str, str], float] = field(default_factory=dict)
    #: (link, robot) -> since when it has acked none of our maps while its maps arrived, once that
    #: lasted UNACKED_S (until it acks one again)
    deaf: dict[tuple[str, str], float] = field(default_factory=dict)
    #: (link, robot) -> when that was last said: a peer that refuses only some maps (each keyframe
    #: over its message limit) would otherwise be said with each of them
    _deaf_said: dict[tuple[str, str], float] = field(default_factory=dict)

    def restore(self, grid: OccupancyGrid, *, held_at: float, now: float) -> None:
        """A peer's map from the state directory, taken at wall time ``held_at`` (when it was saved).

        The bound on the peer's next version counts from then, as if this robot had never stopped:
        from the restore time instead, a peer that kept mapping through a long downtime would be
        refused for hours; from the map's stamp (0 when read back) there was no bound at all. A
        ``held_at`` after ``now`` (the clock was set back) counts from ``now``.
        """
        self.maps[grid.robot] = grid
        self._history[grid.robot] = {grid.version: grid}
        self._held_at[grid.robot] = min(held_at, now)

    def forget(self, robot: str) -> bool:
        """Drop ``robot``'s maps and what is known of it (revoked); False if nothing was held."""
        held = robot in self.maps or robot in self.info
        for d in (
            self.maps,
            self.info,
            self._history,
            self._held_at,
            self._future_said,
            self._older_said,
            self.refusals,
            self.aliases,
        ):
            d.pop(robot, None)
        for key in [k for k in (*self._ack_wait, *self.deaf, *self._deaf_said) if k[1] == robot]:
            for times in (self._ack_wait, self.deaf, self._deaf_said):
                times.pop(key, None)
        return held

    def refuse(self, robot: str, why: str, fix: str, now: float) -> bool:
        """Note that a map of ``robot`` was refused for ``why``; True when that is to be said (the
        first such refusal since one of its maps was last taken, or a new cause)."""
        if robot == self.me:
            return False  # bytes that claim to be ours: not a config of ours to fix (counted)
        r = self.refusals.get(robot)
        if r is not None and r.why == why:
            r.maps += 1
            r.last = now
            return False
        if r is None and len(self.refusals) >= MAX_REFUSED_NAMES:
            return False  # counted by the caller's counter all the same
        self.refusals[robot] = Refusal(why, fix, since=now, last=now)
        return True

    def refused_bytes(self, exc: EnvelopeError, robot: str, now: float) -> str | None:
        """:func:`~mapd.daemon.intake.open_envelope` refused bytes that name ``robot`` (or came from
        it): count why; the line to say with the fix, or None when it was said already."""
        self.refused(exc)
        why, fix = envelope_refusal(exc, robot, self.me)
        return fix if self.refuse(robot, why, fix, now) else None

    def stranger_link(self, env: Envelope, link_peer: str) -> str | None:
        """A signed map of ``env.robot`` (a roster robot) came straight from ``link_peer``, a name
        its link gives and the roster does not know: the link knows that robot by another name or
        id than its own config does. The line to say once, else None."""
        if (
            env.robot == link_peer
            or not env.sig
            or link_peer in self.roster
            or self.aliases.get(env.robot) == link_peer
        ):
            return None
        self.aliases[env.robot] = link_peer
        return (
            f"maps of {env.robot} come from '{link_peer}' on its link, a name this robot's roster does "
            f"not know: the robots' [transports.uwb] nodes lists differ (its link id, or its name); "
            f"its maps are taken (it signed them), but acks, poses and relays to and from it go "
            f"astray: make nodes the same on every robot"
        )

    def acked(self, link: str, robot: str) -> str | None:
        """``robot`` acked one of our maps on ``link``: if it was said to take none, the line that
        says it takes them again."""
        self._ack_wait.pop((link, robot), None)
        since = self.deaf.pop((link, robot), None)
        said = self._deaf_said.get((link, robot))
        if since is None or said is None or said < since:
            return None  # not said this time: its coming back is not either
        return f"{robot} takes this robot's maps again over {link}"

    def unacked(self, link: str, robot: str, waiting: bool, now: float) -> str | None:
        """A map of ``robot`` came over ``link`` (``now``: wall seconds) while our offer on that link
        waits (``waiting``) or not for its ack. When it has acked none of our maps for
        :data:`UNACKED_S` while its own keep coming, it refuses them (its roster lacks our key or has
        an old one, its limits are smaller than our maps, ...): the line to say once, else None.
        Only for links whose acks mean the peer took the map (zenoh), not a radio's frame acks."""
        key = (link, robot)
        if not waiting:
            self._ack_wait.pop(key, None)
            return None
        since = self._ack_wait.setdefault(key, now)
        if key in self.deaf or now - since < UNACKED_S:
            return None
        self.deaf[key] = since
        if not _due(self._deaf_said, key, now):
            return None
        return (
            f"{robot} has taken none of this robot's maps for {now - since:.0f} s while its own maps "
            f"keep coming over {link}: it refuses them (or does not get them). On {robot}: is "
            f"{self.me}'s key in its [fleet.roster], and the current one (the line 'mapd keygen "
            f"{self.me} --public <key file>' prints here)? are its limits.max_message_bytes and "
            f"limits.max_cells as large as this robot's maps?"
        )

    def refused(self, exc: Exception) -> None:
        """:func:`~mapd.daemon.intake.open_envelope` refused the bytes: count why."""
        if isinstance(exc, SignatureError):
            self.counters.bad_signature += 1
        else:
            self.counters.bad_envelopes += 1

    def plan(self, env: Envelope, link_peer: str, now: float) -> Decode | AskKeyframe | Drop:
        """What to do with a verified envelope that came from ``link_peer`` (``now``: wall seconds)."""
        if env.fleet != self.fleet:
            self.counters.foreign_fleet += 1
            # Signed by a robot of our roster: one of ours, configured with another robot.fleet (a
            # robot of another fleet that shares the radio could not sign as one of ours).
            robot, fleet = shown(env.robot), shown(env.fleet)
            cause = f"of fleet '{fleet}'" if fleet == env.fleet else f"of fleet {fleet}"  # (quoted)
            fix = (
                f"maps of {robot} refused: {robot} is {cause}, this robot of fleet '{self.fleet}': "
                f"set robot.fleet the same on every robot of one fleet"
            )
            said = self.refuse(env.robot, cause, fix, now)
            return Drop(
                fix, routine=not said, warning=bool(env.sig) and env.robot in self.roster, refusal=True
            )
        if env.robot == self.me:
            return Drop("our own map", routine=True)
        if env.robot != link_peer and not (env.sig and env.robot in self.roster):
            # Only a signature shows who made a map that another robot carries; unsigned, the link is all.
            self.counters.wrong_link += 1
            robot = shown(env.robot)
            fix = (
                f"an unsigned map of '{robot}' came from '{link_peer}' on its link, and unsigned, "
                f"only the link says who sent it: refused (if '{link_peer}' is {robot}, the robots' "
                f"[transports.uwb] nodes lists differ: make them the same on every robot)"
            )
            said = self.refuse(env.robot, f"came from '{link_peer}'", fix, now)
            return Drop(fix, routine=not said, warning=True, refusal=True)
        held = self.maps.get(env.robot)
        if held is None and len(self.maps) >= self.max_peers:
            self.counters.too_many_robots += 1
            # Said once per robot (a fleet larger than max_peers sends every robot's every map);
            # the counter keeps the count. The names kept are bounded, then all go unsaid.
            said = env.robot in self._over_limit or len(self._over_limit) >= MAX_OVER_LIMIT_NAMES
            if not said:
                self._over_limit.add(env.robot)
            return Drop(f"already {self.max_peers} robots (limits.max_peers)", routine=said)
        if held is not None and env.version <= held.version:
            self.counters.duplicates += 1
            return self._not_newer(env, held.version, now, direct=env.robot == link_peer)
        why = check_step(
            held.version if held else 0, self._held_at.get(env.robot, now), env.version, now, self.bounds
        )
        if why is not None:
            self.counters.refused_versions += 1
            return Drop(why, forget=True)
        cells = env.width * env.height
        allowed = (
            self.max_cells
            if held is None
            else min(self.max_cells, int(held.cells * self.max_growth) + (1 << 20))
        )
        if cells > allowed:
            self.counters.refused_sizes += 1
            if allowed == self.max_cells:
                cause = "over limits.max_cells"
                fix = (
                    f"maps of {shown(env.robot)} refused: a map of {env.width} x {env.height} = {cells} cells "
                    f"is over the {allowed} allowed by this robot's limits.max_cells: raise it on "
                    f"{self.me} to at least {cells} (the same on every robot)"
                )
            else:
                assert held is not None
                cause = "over limits.max_growth"
                fix = (
                    f"maps of {shown(env.robot)} refused: a map of {env.width} x {env.height} = {cells} cells "
                    f"is over the {allowed} allowed by this robot's limits.max_growth "
                    f"({self.max_growth:g}) after one of {held.cells}: raise it on {self.me}"
                )
            said = self.refuse(env.robot, cause, fix, now)
            return Drop(fix, routine=not said, warning=True, refusal=True)
        restarted = held is not None and split(env.version)[0] != split(held.version)[0]
        if restarted:
            # The robot lost its state and started again: what we hold of it is no base any more.
            self.counters.new_incarnations += 1
            self._history.pop(env.robot, None)
        if env.is_keyframe:
            return Decode(None, new_incarnation=restarted)
        base = self._history.get(env.robot, {}).get(env.base_version)
        if base is None:
            self.counters.keyframe_requests += 1
            return AskKeyframe(env.robot, new_incarnation=restarted)
        return Decode(base)

    def _not_newer(self, env: Envelope, held: int, now: float, *, direct: bool) -> Drop:
        """A duplicate, routine; but not when what is held comes from our clock's future, nor when
        the robot itself (``direct``) sends an older incarnation (:meth:`_older_incarnation`).

        A key that leaked can sign a version up to ``clock_tolerance_s`` ahead; held, it has every
        real map of that robot refused as not newer until the robot's clock passes it (re-keying
        the robot revokes it). Honest robots' clocks are seconds apart, so this is said: rarely,
        as the robot keeps sending.
        """
        ahead = split(held)[0] - incarnation_at(now)
        if ahead <= FUTURE_MARGIN_S and direct and split(env.version)[0] < split(held)[0]:
            return self._older_incarnation(env, held, now)
        if ahead <= FUTURE_MARGIN_S:
            return Drop(f"v{env.version} is not newer than v{held}", routine=True, held=env.version == held)
        return Drop(
            f"not newer than the version held, whose incarnation is {ahead / 3600:.1f} h ahead of this "
            f"robot's clock: a clock set wrong, or a leaked key (re-key the robot in the roster and "
            f"reload to revoke it)",
            routine=not _due(self._future_said, env.robot, now),
            warning=True,
        )

    def _older_incarnation(self, env: Envelope, held: int, now: float) -> Drop:
        """The robot itself sends maps of an incarnation older than the one held: it lost its state
        and began again while its clock was behind (a board without a battery-backed clock, before
        NTP set it). Its versions stay below the held one, so every map it makes is refused, which
        a routine duplicate said nowhere: said now and then, with the fix."""
        return Drop(
            f"its maps are of a state begun {_incarnation_date(split(env.version)[0])}, before the one "
            f"held ({_incarnation_date(split(held)[0])}): it lost its state while its clock was behind, "
            f"and every map it makes is refused as older; set its clock, then restart it with an "
            f"empty state directory",
            routine=not _due(self._older_said, env.robot, now),
            warning=True,
        )

    def undecodable(self, env: Envelope, base: OccupancyGrid | None) -> AskKeyframe | None:
        """The payload did not decode; a delta may decode after a keyframe, so ask for one."""
        self.counters.decode_errors += 1
        if base is None:
            return None
        self.counters.keyframe_requests += 1
        return AskKeyframe(env.robot)

    def accept(
        self,
        grid: OccupancyGrid,
        env: Envelope,
        transport: str,
        nbytes: int,
        now: float,
        link_peer: str | None = None,
    ) -> Refusal | None:
        """Keep a decoded map (``now``: wall-clock seconds, for the age ``mapd status`` shows;
        ``link_peer``: whom the link had it from, another roster robot when it was relayed);
        returns the refusal of its robot's maps this ends, if any."""
        self.maps[env.robot] = grid
        history = self._history.setdefault(env.robot, {})
        history[env.version] = grid
        for v in sorted(history)[:-KEEP_PEER_VERSIONS]:
            del history[v]
        self.counters.updates_received += 1
        self._held_at[env.robot] = now
        info = self.info.setdefault(env.robot, PeerInfo())
        info.version = env.version
        info.received_at = now
        info.link = transport
        info.present = True
        info.bytes += nbytes
        info.updates += 1
        info.last_kind = "keyframe" if env.is_keyframe else "delta"
        # (a name off the roster is a link that knows its robot by another name, said apart)
        relayed = link_peer is not None and link_peer != env.robot and self.roster.admits(link_peer)
        info.relayed_by = link_peer if relayed else None
        return self.refusals.pop(env.robot, None)

    def presence(self, peer: str, transport: str, present: bool) -> None:
        """A transport saw ``peer`` come or go (robots the roster does not admit, or too many, are not kept)."""
        if peer not in self.info and (not self.roster.admits(peer) or len(self.info) >= self.max_peers):
            return
        info = self.info.setdefault(peer, PeerInfo())
        info.present = present
        info.link = transport

    def status(self, now: float, acked: dict[str, int]) -> dict[str, dict[str, Any]]:
        """Per peer robot: what ``mapd status`` shows."""
        peers = {}
        # Robots off the roster (their names unverified) only with a refusal, and a few at most.
        strangers = sorted(
            (r for r in self.refusals if r not in self.info and r not in self.maps),
            key=lambda r: -self.refusals[r].last,
        )[:MAX_REFUSED_SHOWN]
        deaf_robots = {r for _, r in self.deaf}
        for robot in sorted(set(self.info) | set(self.maps) | set(strangers) | deaf_robots):
            info = self.info.get(robot, PeerInfo()).to_json()
            received_at = info.pop("received_at", None)
            if received_at is not None:
                info["age_s"] = round(now - received_at, 1)
            held = self.maps.get(robot)
            if held is not None:
                # The version we hold, also for a peer restored from the state directory that has
                # sent nothing since this start (its counters are then empty, its map is not).
                info["version"] = held.version
                info["restored"] = "age_s" not in info  # nothing received from it since this start
            info["acked_our_version"] = acked.get(robot, 0)
            if (refusal := self.refusals.get(robot)) is not None:
                info["refused"] = refusal.to_json(now)
            if robot in self.aliases:
                info["heard_as"] = self.aliases[robot]
            deaf = {link: since for (link, r), since in self.deaf.items() if r == robot}
            if deaf:
                # it acks none of our maps while its own come: it refuses them (said once)
                info["takes_ours"] = False
                info["unacked_s"] = round(now - min(deaf.values()), 1)
            peers[robot] = info
        return peers
