"""TDMA and the fleet's clocks: frames heard in a robot's own slot are counted (R18), and the core
follows a clock that moved (the link that reads the wall clock is tested in test_uwb_serial)."""

from __future__ import annotations

import os

import pytest

from mapd.commands.status_text import render_status
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.pacing import MediumAccess
from transports.uwb.sim import SimNet

RATE = 12_500.0
SLOT = 0.6  # four full frames, as the daemon's default slot at this rate


def _node(node_id: int, offset: float) -> ArqEndpoint:
    cfg = ArqConfig(
        node_id=node_id, rate_bps=RATE, mac="tdma", slots=3, slot_index=node_id - 1, slot_s=SLOT,
        clock_offset=offset, deadline_s=60.0,
    )  # fmt: skip
    return ArqEndpoint(cfg, session=node_id, seed=node_id)


def _run(offsets: tuple[float, float, float]) -> list[ArqEndpoint]:
    """Three robots on one channel; robot 2 broadcasts a map of 20 frames' bytes."""
    nodes = [_node(i + 1, off) for i, off in enumerate(offsets)]
    net = SimNet(nodes, shared=True, seed=1)
    nodes[1].send(os.urandom(4000), 0.0, dests=[1, 3])
    net.run(until=30.0)
    assert len(net.received(1)) == 1 and len(net.received(3)) == 1  # it got through all the same
    return nodes


def test_robots_whose_clocks_agree_hear_nobody_in_their_own_slot() -> None:
    nodes = _run((0.0, 0.0, 0.0))
    assert [n.counters.out_of_turn for n in nodes] == [0, 0, 0]
    assert "out_of_turn_from" not in nodes[0].stats()


@pytest.mark.parametrize("skew", [0.25, 0.05, -0.25])
def test_a_robot_whose_clock_is_off_by_part_of_a_slot_is_heard_in_a_neighbours_slot(skew: float) -> None:
    # Robot 2's clock runs ahead (or behind): its turn starts in robot 1's slot (or runs into robot
    # 3's). 50 ms is five times the guard, and two thirds of a full frame's airtime.
    nodes = _run((0.0, skew, 0.0))
    intruded = nodes[0] if skew > 0 else nodes[2]
    assert intruded.counters.out_of_turn >= 2
    assert intruded.stats()["out_of_turn_from"] == 2
    # mapd status says it on the link's FAULTS line, where an operator looks.
    shown = render_status({"links": {"uwb": intruded.stats()}})
    assert "own TDMA slot (do the clocks agree?)" in shown and "FAULTS" in shown


def test_a_borrowed_turn_is_not_out_of_turn() -> None:
    # The rest of a slot lent in a LEND (R17) is the borrower's: its frames there are in turn.
    mac = MediumAccess("tdma", RATE, slot_s=SLOT, slots=3, slot_index=0, guard_s=0.01)
    assert mac.in_own_slot(0.2, 0.3) and not mac.in_own_slot(0.7, 0.9)
    assert mac.in_own_slot(0.55, 0.7) and not mac.in_own_slot(0.595, 0.7)  # the guard is nobody's
    assert not mac.in_own_slot(0.3, 0.2)  # an empty interval: a frame too short to be certain of
    mac.lend(0.25)
    assert not mac.in_own_slot(0.3, 0.4)
    assert mac.in_own_slot(3 * SLOT + 0.1, 3 * SLOT + 0.2)  # the next own slot is not lent


def test_the_core_follows_a_clock_that_moved() -> None:
    e = _node(1, 0.0)
    assert e._mac.ready_at(10, 0.7) == pytest.approx(3 * SLOT)  # 0.7 s is robot 2's turn: wait
    e.set_clock_offset(-0.7)  # the wall clock was stepped back: 0.7 s of the loop is now 0.0
    assert e._mac.ready_at(10, 0.7) == 0.7 and e.cfg.clock_offset == -0.7


def test_the_rx_latency_is_a_frames_time_on_the_serial_line_unless_configured() -> None:
    import asyncio

    from transports.base import TransportContext
    from transports.uwb.transport import UwbOptions, UwbTransport

    def slack(**kw: object) -> float:
        ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
        t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2}, mac="tdma", **kw), ctx)  # type: ignore[arg-type]
        loop = asyncio.new_event_loop()
        try:
            return t._config(loop).rx_slack_s
        finally:
            loop.close()

    assert slack() == pytest.approx(10 * 224 / 115200 + 0.005)  # 24.4 ms at the default baud
    assert slack(baud=921600) == pytest.approx(10 * 224 / 921600 + 0.005)
    assert slack(rx_latency_ms=60.0) == pytest.approx(0.060)  # a radio that buffers more


def test_the_kernels_word_on_the_clock_is_read_without_changing_it(monkeypatch: pytest.MonkeyPatch) -> None:
    import sys

    from mapd import wallclock

    got = wallclock.synchronized()  # the real call: asks, changes nothing (no privilege needed)
    assert isinstance(got, bool) if sys.platform.startswith("linux") else got is None
    for state, said in ((0, True), (1, True), (wallclock.TIME_ERROR, False), (-1, None)):
        monkeypatch.setattr(wallclock, "_adjtimex", lambda buf, s=state: s)
        assert wallclock.synchronized() is said, state
    monkeypatch.setattr(wallclock, "_adjtimex", None)  # not Linux
    assert wallclock.synchronized() is None


@pytest.mark.parametrize("synced", [True, False])
def test_a_tdma_link_says_whether_its_clock_is_synchronized(
    monkeypatch: pytest.MonkeyPatch, synced: bool
) -> None:
    from mapd import wallclock
    from transports.uwb.link import UwbLink

    monkeypatch.setattr(wallclock, "synchronized", lambda: synced)
    tdma = UwbLink(ArqConfig(node_id=1, mac="tdma", slots=2), "/dev/mapd-test-none").stats()
    assert tdma["clock_synchronized"] is synced
    faults = [ln for ln in render_status({"links": {"uwb": tdma}}).splitlines() if "FAULTS" in ln]
    said = any("wall clock not synchronized (TDMA turns need it: chrony)" in ln for ln in faults)
    assert said is not synced
    # A link without TDMA does not count on the clock: nothing said.
    assert "clock_synchronized" not in UwbLink(ArqConfig(node_id=1), "/dev/mapd-test-none").stats()
    # Nor does one whose turns follow the fleet's radio clock where no time service keeps its own.
    radio = UwbLink(ArqConfig(node_id=1, mac="tdma", slots=2, radio_time=True), "/dev/mapd-test-none")
    assert "clock_synchronized" not in radio.stats()
