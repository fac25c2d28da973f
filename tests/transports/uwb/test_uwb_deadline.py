"""A message's deadline grows with its size (R6): a map longer on the air than ``deadline_s`` at the
robot's share of the channel still crosses, and small maps keep the configured deadline."""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
from typing import Any

import pytest

from mapd.envelope import Envelope
from mapd.grid import Pose2D
from transports.base import TransportContext
from transports.uwb import arq
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.faults import Faults
from transports.uwb.relay import FaultRelay
from transports.uwb.sim import SimNet
from transports.uwb.transport import UwbOptions, UwbTransport

RATE = 12_500.0  # the paper's radio: the size that fits a deadline depends on it


def ep(node: int, **kw: Any) -> ArqEndpoint:
    kw.setdefault("rate_bps", RATE)
    return ArqEndpoint(ArqConfig(node_id=node, **kw), session=1000 + node, seed=node)


def closed(net: SimNet, node: int, msg: int) -> bool:
    return any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[node])


def of(net: SimNet, node: int, cls: type) -> list[Any]:
    return [e for e in net.events[node] if isinstance(e, cls)]


def test_a_map_longer_on_the_air_than_the_deadline_still_crosses() -> None:
    # The audit's 1000 x 1000 map: a 187,045-byte keyframe between two robots (slots 2, as the
    # daemon configures a channel of two) on a 12.5 kb/s link with a little loss. With the fixed
    # 120 s deadline it failed before it was even wholly on the air.
    a, b = ep(1, slots=2), ep(2, slots=2)
    net = SimNet([a, b], faults=Faults(drop=0.02), seed=5)
    data = os.urandom(187_045)
    msg = a.send(data, 0.0, dests=[2])
    assert net.run(2000.0, stop=lambda: closed(net, 1, msg))
    assert of(net, 1, arq.MessageFailed) == []
    assert [r.data for r in net.received(2)] == [data]
    assert of(net, 1, arq.MessageDelivered) == [arq.MessageDelivered(msg, 2)]
    assert net.now > 120.0  # it needed longer than the configured deadline_s
    assert a.message_deadline_s(len(data)) > net.now


def test_small_maps_keep_the_configured_deadline() -> None:
    # A keyframe of a few kB among 16 robots (a sixteenth of the channel each): under twice its
    # airtime at that share is less than deadline_s, so nothing changes for it (mapd bench swarm).
    a = ep(1, slots=16)
    assert a.message_deadline_s(0) == a.message_deadline_s(4000) == 120.0
    net = SimNet([a])
    msg = a.send(os.urandom(4000), 0.0, dests=[9])  # a peer that never answers
    net.run(500.0, stop=lambda: closed(net, 1, msg))
    assert of(net, 1, arq.MessageFailed) == [arq.MessageFailed(msg, 9, "deadline")]
    assert 120.0 <= net.now <= 120.01


def test_a_large_map_to_nobody_fails_at_twice_its_airtime_at_the_share() -> None:
    # Bounded still: a map no peer takes fails, later for a larger map, and for the same map later
    # where more robots share the channel.
    n = 60_000
    frames = -(-(n + 16) // ep(1).chunk_size)
    for slots in (1, 2, 16):
        a = ep(1, slots=slots)
        airtime = frames * a.frame_size * 8 / (RATE / slots)
        want = max(120.0, arq.DEADLINE_AIRTIMES * airtime)
        assert a.message_deadline_s(n) == pytest.approx(want)
        if slots == 1:
            assert want == 120.0  # 40 s on the air alone: within deadline_s
            continue
        net = SimNet([a])
        msg = a.send(os.urandom(n), 0.0, dests=[9])
        net.run(2 * want, stop=lambda: closed(net, 1, msg))  # noqa: B023 (run before the next pass)
        assert of(net, 1, arq.MessageFailed) == [arq.MessageFailed(msg, 9, "deadline")]
        assert want <= net.now <= want + 0.01
    assert ep(1, slots=16).message_deadline_s(n) > ep(1, slots=2).message_deadline_s(n)


def test_an_explicit_deadline_is_kept_whatever_the_size() -> None:
    # Relays, poses and `mapd link send --deadline` give their own.
    a = ep(1, slots=16)
    net = SimNet([a])
    msg = a.send(os.urandom(60_000), 0.0, dests=[9], deadline=30.0)
    net.run(500.0, stop=lambda: closed(net, 1, msg))
    assert 30.0 <= net.now <= 30.01


@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
@pytest.mark.timeout(60)
def test_a_map_longer_on_the_air_than_the_deadline_is_said_once(caplog: pytest.LogCaptureFixture) -> None:
    # The transport warns once, in one line, when a map takes longer than deadline_s at the robot's
    # share of the link: peers get such maps late (and before, they never got them at all).
    def env(version: int, size: int) -> Envelope:
        return Envelope(
            fleet="f", robot="alpha", version=version, base_version=0, codec="raw", width=10, height=10,
            resolution=0.05, origin=Pose2D(0.0, 0.0, 0.0), seq=version, payload=os.urandom(size),
        )  # fmt: skip

    async def main() -> None:
        async with FaultRelay(rate_bps=200_000, faults=Faults(), seed=1) as relay:
            ctx = TransportContext(robot="alpha", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
            opts = UwbOptions(
                port=relay.ports[0], nodes={"alpha": 1, "beta": 2}, link_rate_bps=4000, deadline_s=5.0
            )
            t = UwbTransport(opts, ctx)
            await t.start()
            try:
                t.offer(env(1, 100))  # 0.4 s on the air at 2000 b/s: nothing to say
                assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
                t.offer(env(2, 3000))  # about 14 s at this robot's share
                # the publisher holds the offer for the link's deadline for it (P1)
                core = t._link.core if t._link is not None else None
                assert core is not None
                held = t.offer_deadline_s(env(2, 3000))
                assert held == core.message_deadline_s(len(env(2, 3000).pack()))
                assert held is not None and held > 2 * 14.0 > opts.deadline_s
                assert t.offer_deadline_s(env(1, 100)) is None  # not the map it sent last
                t.offer(env(3, 4000))  # said once, not for every map
                warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
                assert len(warnings) == 1
                line = warnings[0].getMessage()
                assert "v2" in line and "deadline_s" in line and "\n" not in line
            finally:
                await t.close()

    caplog.set_level(logging.INFO, logger="mapd.uwb")
    asyncio.run(main())
