"""Hook points for what the UWB cores do not do yet: multi-hop relay and scalable acknowledgements.

The swarm drives the real :class:`~transports.uwb.arq.ArqEndpoint` and the daemon's real
:class:`~mapd.daemon.publisher.PublisherCore`; these two policies are the seams where a relay rule or
a cheaper ack scheme plugs into the simulation before (or while) the real cores learn them:

* :class:`RelayPolicy`: when a robot has accepted a version of another robot's map, may it send it
  on, and to whom? The robot adapter (:class:`~mapd.bench.swarm.node.SwarmRobot`) then sends that
  map as a keyframe on the origin's own stream (``1 + origin``), through the same ARQ core, and a
  receiver accepts a relayed version exactly as a direct one (newer than what it holds). The default,
  :class:`NoRelay`, is what the daemon does today. :class:`FloodRelay` is a naive example (every
  robot re-sends every newer version it hears to the peers it hears), for trying the hook, not a
  design.
* :class:`AckScope`: which peers must acknowledge a robot's map (the ``dests`` of
  :meth:`ArqEndpoint.send`, so every one of them costs COMPLETE acks and keeps the message open until
  it acks or the deadline passes). :class:`ConfiguredPeers` is the daemon's default (``transports.uwb.
  peers`` unset: every other robot in ``nodes``); :class:`PeersUp` asks only the peers heard lately.
  A scalable ack scheme (NACK-only, acks from a few designated peers, aggregated acks) belongs in the
  ARQ core; its effect on airtime shows here in the ``ack %`` column.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from transports.uwb.options import UwbOptions


@dataclass(frozen=True)
class Forward:
    """Send ``origin``'s ``version`` on to ``dests`` (link ids)."""

    origin: int
    version: int
    dests: tuple[int, ...]


class RelayPolicy(Protocol):
    name: str

    def on_accept(
        self, holder: int, origin: int, version: int, src: int, now: float, peers_up: list[int]
    ) -> Forward | None:
        """``holder`` accepted ``origin``'s ``version`` (heard from ``src``); what to send on, if anything."""
        ...


class NoRelay:
    """Today's daemon: a robot sends only its own map."""

    name = "none"

    def on_accept(
        self, holder: int, origin: int, version: int, src: int, now: float, peers_up: list[int]
    ) -> Forward | None:
        return None


class FloodRelay:
    """Naive flooding: re-send every newer version heard to every peer heard (except origin and sender)."""

    name = "flood"

    def on_accept(
        self, holder: int, origin: int, version: int, src: int, now: float, peers_up: list[int]
    ) -> Forward | None:
        dests = tuple(p for p in peers_up if p not in (origin, src))
        return Forward(origin, version, dests) if dests else None


class SummaryRelay:
    """The UWB relay (:mod:`transports.uwb.forwarding`): robots broadcast summaries of who holds which
    version every ``summary_period_s`` and forward held maps, unaltered, to neighbours that lack them
    and do not hear their origin, at most one per ``relay_period_s``. The robot adapter drives the
    real :class:`~transports.uwb.forwarding.ForwardingCore`; this hook only marks the choice. The
    timers are the daemon's defaults (``[transports.uwb]``), so the bench measures what runs."""

    name = "summary"
    summary_period_s: float = UwbOptions.model_fields["summary_period_s"].default
    relay_period_s: float = UwbOptions.model_fields["relay_period_s"].default

    def on_accept(
        self, holder: int, origin: int, version: int, src: int, now: float, peers_up: list[int]
    ) -> Forward | None:
        return None  # the forwarding core decides, from summaries, not on each accept


class AckScope(Protocol):
    name: str

    def dests(self, me: int, configured: list[int], peers_up: list[int]) -> list[int]:
        """The link ids that must ack this robot's next map (empty: send nothing now)."""
        ...


class ConfiguredPeers:
    """The daemon's default: every other robot configured on the channel."""

    name = "configured"

    def dests(self, me: int, configured: list[int], peers_up: list[int]) -> list[int]:
        return configured


class PeersUp:
    """Only the robots heard within ``peer_timeout_s`` (the daemon with ``peers`` set to them)."""

    name = "up"

    def dests(self, me: int, configured: list[int], peers_up: list[int]) -> list[int]:
        return peers_up


RELAYS: dict[str, type[NoRelay] | type[FloodRelay] | type[SummaryRelay]] = {
    "none": NoRelay,
    "flood": FloodRelay,
    "summary": SummaryRelay,
}
ACK_SCOPES: dict[str, type[ConfiguredPeers] | type[PeersUp]] = {"configured": ConfiguredPeers, "up": PeersUp}
