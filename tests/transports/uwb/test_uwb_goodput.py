"""``goodput_bps`` in ``mapd status``: what the link delivered lately, not the last message's burst.

Audit finding 6: it was the rate of the last message delivered, kept for ever (``goodput_bps=9743``
beside "serial port closed" through a 45 s outage), and a 162 B delta sent in the pacer's first
burst over a fast line showed 73928 b/s on a 12.5 kb/s link.
"""

from __future__ import annotations

import os

import pytest

from transports.uwb import arq
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.arq_acks import GOODPUT_WINDOW_S, GoodputWindow
from transports.uwb.sim import SimNet

RATE = 12_500.0


def _pair() -> tuple[ArqEndpoint, SimNet]:
    """Robot 1, and the simulated line to robot 2."""
    a, b = (ArqEndpoint(ArqConfig(node_id=n, rate_bps=RATE), session=n, seed=n) for n in (1, 2))
    # The serial line between robot and radio is far faster than the radio: the pacer's first
    # burst (two frames) leaves at once, as on the audit's ptys.
    return a, SimNet([a, b], rate_bps=1_000_000.0)


def _deliver(net: SimNet, a: ArqEndpoint, data: bytes, stream: int = 0) -> None:
    msg = a.send(data, net.now, dests=[2], stream=stream)
    assert net.run(net.now + 60, stop=lambda: arq.MessageClosed(msg, "delivered") in net.events[1])


def test_a_small_message_is_not_shown_as_many_times_the_link_rate() -> None:
    a, net = _pair()
    _deliver(net, a, os.urandom(162))
    assert 0 < a.stats()["goodput_bps"] <= RATE


def test_goodput_follows_what_was_delivered_lately_and_decays_to_zero() -> None:
    a, net = _pair()
    for i in range(3):  # a map every few seconds, each some 11 s of the link
        _deliver(net, a, os.urandom(18_000), stream=i)
    busy = a.stats()["goodput_bps"]
    assert 0.5 * RATE < busy <= RATE
    net.run(net.now + GOODPUT_WINDOW_S / 2)  # nothing more to send: half the window idle
    assert 0 < a.stats()["goodput_bps"] < busy
    net.run(net.now + GOODPUT_WINDOW_S)  # an outage, or nothing new: 0, not the last figure
    assert a.stats()["goodput_bps"] == 0


def test_the_window_spreads_a_long_message_over_its_life_and_stays_bounded() -> None:
    w = GoodputWindow(window_s=30.0)
    assert w.rate_bps(0.0) == 0
    w.add(150_000, 0.0, 100.0)  # 150 kB over 100 s, delivered at once at its end
    assert w.rate_bps(100.0) == pytest.approx(8 * 150_000 * 30 / 100 / 30)  # 12 kb/s, not 40
    assert w.rate_bps(115.0) == pytest.approx(8 * 150_000 * 15 / 100 / 30)
    assert w.rate_bps(130.0) == 0
    for i in range(100_000):
        w.add(10, float(i), i + 0.5)
    assert len(w) <= w.max_items
