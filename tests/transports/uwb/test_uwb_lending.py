"""R17 turn lending: an idle TDMA slot's rest goes to a robot with chunks left, one sender per slot."""

from __future__ import annotations

import os
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.errors import ProtocolError
from transports.uwb import arq, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.framing import FrameReader, encode_frame
from transports.uwb.lending import Backlogs
from transports.uwb.pacing import MediumAccess
from transports.uwb.sim import SimNet

RATE = 12_500.0  # the UWB channel: a slot carries a few frames, as in the field
SLOT = 0.3
SLOTS = 3


def ep(node: int, *, lend: bool, **kw: Any) -> ArqEndpoint:
    cfg = ArqConfig(
        node_id=node,
        rate_bps=RATE,
        mac="tdma",
        slots=SLOTS,
        slot_index=node - 1,
        slot_s=SLOT,
        lend=lend,
        **kw,
    )
    return ArqEndpoint(cfg, session=1000 + node, seed=node)


class LoggedNet(SimNet):
    """The shared channel, keeping every frame with its sender and start time."""

    def __init__(self, endpoints: list[ArqEndpoint]) -> None:
        super().__init__(endpoints, shared=True)
        self.frames: list[tuple[float, int, wire.Frame]] = []

    def _transmit(self, src: int, frame: bytes, rate: float) -> None:
        for body in FrameReader(1024, crc=True).feed(frame):
            self.frames.append((self.now, src, wire.parse(body)))
        super()._transmit(src, frame, rate)


def _run(lend: bool) -> tuple[LoggedNet, float]:
    nodes = [ep(i, lend=lend) for i in (1, 2, 3)]
    net = LoggedNet(nodes)
    net.run(2.0)  # HELLOs: everyone knows everyone
    data = os.urandom(3000)  # 16 chunks: several of node 1's own turns
    msg = nodes[0].send(data, net.now, dests=[2, 3])
    t0 = net.now
    assert net.run(
        60.0, stop=lambda: any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[1])
    )
    assert [r.data for r in net.received(2)] == [data] == [r.data for r in net.received(3)]
    return net, net.now - t0


def test_idle_slots_are_lent_to_the_robot_with_chunks_left_and_its_map_arrives_sooner() -> None:
    lent_net, lent_s = _run(lend=True)
    fixed_net, fixed_s = _run(lend=False)
    lenders = {src for _, src, f in lent_net.frames if isinstance(f, wire.Lend)}
    assert lenders == {2, 3}  # the idle robots lent, and only to the robot with chunks left
    assert all(f.dst == 1 for _, _, f in lent_net.frames if isinstance(f, wire.Lend))
    assert lent_net.nodes[1] is not None and lent_net.nodes[1].stats()["borrowed"] > 0
    assert not any(isinstance(f, wire.Lend) for _, _, f in fixed_net.frames)
    assert lent_s < 0.7 * fixed_s, (lent_s, fixed_s)


def test_one_sender_per_slot_the_owner_or_whom_it_named_after_its_lend() -> None:
    net, _ = _run(lend=True)
    assert sum(1 for t, src, _ in net.frames if int(t // SLOT) % SLOTS + 1 != src) >= 5  # borrowed frames
    owner_of = {}  # slot number -> (owner, when it lent, to whom)
    for t, src, f in net.frames:
        k = int(t // SLOT)
        owner = k % SLOTS + 1
        end = (k + 1) * SLOT
        assert t + 8 * 223 / RATE <= end + 1e-6 or src == owner  # a borrower's frames end in the slot
        if src == owner:
            assert k not in owner_of or owner_of[k][1] is None, "the owner sent after lending its slot"
            if isinstance(f, wire.Lend):
                assert f.slot == k % wire.SLOT_MOD
                owner_of[k] = (owner, t, f.dst)
            else:
                owner_of.setdefault(k, (owner, None, None))
        else:
            lent = owner_of.get(k)
            assert lent is not None and lent[1] is not None and lent[2] == src and lent[1] < t, (t, src, k)


def test_a_lend_is_taken_only_for_the_slot_it_names_and_only_by_whom_it_names() -> None:
    b = ep(2, lend=True)
    now = 0.05  # slot 0: node 1's
    late = wire.Lend(1, 2, 1001, (int(now // SLOT) - 1) % wire.SLOT_MOD)  # names a slot already over
    b.receive_data(encode_frame(wire.pack(late)), now)
    other = wire.Lend(1, 3, 1001, 0)  # for node 3
    b.receive_data(encode_frame(wire.pack(other)), now)
    assert b.stats()["borrowed"] == 0
    b.send(b"x" * 100, now, dests=[1])
    assert b.data_to_send(now) == b""  # still node 1's slot: nothing of b's goes
    b.receive_data(encode_frame(wire.pack(wire.Lend(1, 2, 1001, 0))), now)
    assert b.stats()["borrowed"] == 1
    assert b.data_to_send(now) != b""  # the rest of slot 0 is b's now
    nxt = SLOTS * SLOT + 0.01  # slot 3: node 1's again, and not lent
    assert b.data_to_send(nxt) == b""


def test_a_robot_that_does_not_lend_ignores_lends() -> None:
    b = ep(2, lend=False)
    b.receive_data(encode_frame(wire.pack(wire.Lend(1, 2, 1001, 0))), 0.05)
    assert b.stats()["borrowed"] == 0


def test_medium_access_lend_and_borrow() -> None:
    mac = MediumAccess("tdma", RATE, slot_s=SLOT, slots=SLOTS, slot_index=1, guard_s=0.01)
    airtime = 0.1
    assert mac.ready_at(8 * airtime, 0.0) == pytest.approx(SLOT)  # slot 1 is ours
    assert mac.own_slot_left(SLOT + 0.05) == pytest.approx(SLOT - 0.05 - 0.01)
    mac.lend(SLOT + 0.05)
    assert mac.own_slot_left(SLOT + 0.06) == 0.0
    assert mac.ready_at(10, SLOT + 0.06) == pytest.approx(SLOT + SLOTS * SLOT)  # the next cycle's slot
    mac.borrow(2 * SLOT + 0.01)  # slot 2 (another robot's)
    assert mac.ready_at(10, 2 * SLOT + 0.02) == 2 * SLOT + 0.02
    assert mac.ready_at(10, 3 * SLOT + 0.02) > 3 * SLOT + 0.02  # slot 3: not borrowed


def test_backlogs_pick_the_most_chunks_left_of_what_was_heard_lately() -> None:
    b = Backlogs(horizon_s=10.0)
    b.heard(4, msg=7, index=2, count=20, now=0.0)
    b.heard(5, msg=9, index=0, count=5, now=0.0)
    assert b.pick(1.0, [4, 5]) == 4 and b.left(4, 1.0) == 17
    b.heard(4, msg=7, index=1, count=20, now=1.0)  # a resend says nothing new about what is left
    assert b.left(4, 1.0) == 17
    b.heard(4, msg=6, index=0, count=50, now=1.0)  # an older message's chunk does not count
    assert b.left(4, 1.0) == 17
    assert b.pick(1.0, [5]) == 5  # only peers up
    assert b.pick(20.0, [4, 5]) is None  # all of it is older than the horizon
    b.heard(6, msg=1, index=0, count=18, now=20.0)
    b.heard(7, msg=1, index=0, count=18, now=20.0)
    b.lent(6, 20.0)
    assert b.pick(20.5, [6, 7]) == 7  # equal backlogs: the one lent to longest ago
    b.heard(7, msg=1, index=17, count=18, now=21.0)  # its last chunk: nothing left
    assert b.pick(21.0, [7]) is None
    b.heard(7, msg=0, index=0, count=9, now=40.0)  # an id "before" the last, but long after it
    assert b.left(7, 40.0) == 8
    b.forget(7)  # it restarted: ids from its new session say what it has left, whatever their value
    b.heard(7, msg=0xFFFFF0, index=0, count=5, now=40.5)
    assert b.left(7, 40.5) == 4


def test_lend_frames_round_trip_and_malformed_ones_are_refused() -> None:
    f = wire.Lend(3, 9, 0xABCDEF, 65535)
    assert wire.parse(wire.pack(f)) == f
    body = wire.pack(f)
    with pytest.raises(ProtocolError, match="LEND frame of"):
        wire.parse(body + b"\x00")
    with pytest.raises(ProtocolError, match="broadcast"):
        wire.parse(wire.pack(wire.Lend(3, wire.BROADCAST, 1, 0)))


@pytest.mark.parametrize("lend", [True, False])
def test_a_fresh_tdma_endpoint_on_the_wall_clock_asks_for_a_wake_up_and_sends_its_hello(lend: bool) -> None:
    # The daemon's adapter asks for the timer before the first input; an endpoint's clock then reads
    # minus infinity, which once overflowed the slot arithmetic and silenced the link for good.
    cfg = ArqConfig(node_id=1, mac="tdma", slots=3, slot_s=0.7268, clock_offset=1.8e9, lend=lend)
    e = ArqEndpoint(cfg, session=5)
    assert e.get_timer() is not None
    now = 1000.0
    for _ in range(10):
        if e.data_to_send(now):
            break
        t = e.get_timer()
        assert t is not None
        now = max(now, t)
    assert e.stats()["hellos_tx"] == 1


def test_tdma_counts_a_slot_from_the_end_of_the_robots_own_last_frame() -> None:
    # A link's write drains into the radio's buffer at once; the frame is on the air only after the
    # one before it. Counting from the write let a frame run past the slot into the next robot's.
    mac = MediumAccess("tdma", RATE, slot_s=SLOT, slots=SLOTS, slot_index=0, guard_s=0.01)
    frame = 224  # 143 ms at 12.5 kb/s
    assert mac.ready_at(frame, 0.0) == 0.0
    mac.sent(frame, 0.0)
    assert mac.ready_at(frame, 0.01) == pytest.approx(8 * frame / RATE)  # after the first is on the air
    mac.sent(frame, 8 * frame / RATE)
    # a third full frame would end at 430 ms, past the slot's 290 ms: the next cycle's slot
    assert mac.ready_at(frame, 0.15) == pytest.approx(SLOTS * SLOT)
    assert mac.ready_at(4, 0.15) == pytest.approx(2 * 8 * frame / RATE)  # a tiny one still fits


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(0.0, 2 * SLOTS * SLOT), st.integers(0, 0xFFFF), st.integers(1, 4)), max_size=12
    )
)
def test_hostile_lends_never_open_a_slot_that_is_neither_own_nor_the_one_named(
    lends: list[tuple[float, int, int]],
) -> None:
    b = ep(2, lend=True)  # slot index 1
    b.send(b"x" * 5000, 0.0, dests=[1])
    granted: set[int] = set()  # slot numbers a LEND for b named while they ran
    events = sorted(
        [(t, "lend", slot, dst) for t, slot, dst in lends] + [(i * 0.01, "probe", 0, 0) for i in range(180)]
    )
    own_sends = 0
    for t, what, slot, dst in events:
        k = int(t // SLOT)
        if what == "lend":
            b.receive_data(encode_frame(wire.pack(wire.Lend(1, dst, 1001, slot))), t)
            if dst == 2 and slot == k % wire.SLOT_MOD and k % SLOTS != 1:
                granted.add(k)
        elif b.data_to_send(t):
            assert k % SLOTS == 1 or k in granted, (t, k, granted)
            own_sends += k % SLOTS == 1
    # whatever the LENDs, b still sends in its own slots (it has 5000 bytes waiting)
    assert own_sends >= 1
