"""Mixed versions on one UWB channel (wire.py, *Features*): each node's HELLO announces the frames
it understands in its dst, and nothing a peer announced it lacks is sent to it.

``Lacking`` is a node that announces none of DONE, parity and LEND, and refuses them as a node
without them does (wire.py: a DONE is an unknown type, a parity chunk a DATA index past its count,
both counted ``bad_frames``): what this version will be to a later one that adds a feature. Without
the announcement (``Unheeding`` stands for a node that ignores it) a broadcast map never reached
such a node on a lossy channel, and its own maps never completed at new receivers: the repairs
came as parity, the COMPLETEs as DONEs.

``PreviousRelease`` sends HELLO to 255, as every node did before the announcement, and understands
DONE, parity and LEND: it announces nothing and must get all of them, as before (a first version of
the announcement took 255 for "none", and such a fleet crawled: found by review).
"""

from __future__ import annotations

import logging
import os
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.commands.status_text import render_status
from transports.base import TransportContext
from transports.uwb import arq, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.arq_tx import HELLO_REFRESH_S
from transports.uwb.arq_types import AckMode
from transports.uwb.faults import Faults
from transports.uwb.sim import SimNet
from transports.uwb.transport import FEATURES_SAY_S, UwbOptions, UwbTransport

RATE = 100_000.0
#: What the nodes here announce: their turns are not on a radio clock (ArqConfig.radio_time False).
OWN = wire.own_features(False)


class Says(ArqEndpoint):
    """A node whose HELLOs go to ``word`` instead of what this version announces."""

    word = wire.FEATURES_FLAG  # announces none

    def _build(self, kind: str, ref: Any, now: float) -> wire.Frame | None:
        frame = super()._build(kind, ref, now)
        return wire.Hello(self.node, self.word, self.session) if isinstance(frame, wire.Hello) else frame


class Lacking(Says):
    """A node that announces no optional frame and refuses DONE and parity (as one without them)."""

    parity_refused: int = 0

    def _on_body(self, body: bytes, now: float) -> None:
        frame = wire.parse(body)  # (unsigned here: the body is the frame)
        if isinstance(frame, wire.Done):
            self.counters.bad_frames += 1  # "unknown frame type"
            return
        if isinstance(frame, wire.Data) and frame.index >= frame.count:
            self.counters.bad_frames += 1  # "index past what count may have"
            self.parity_refused += 1
            return
        super()._on_body(body, now)


class PreviousRelease(Says):
    """The release before the announcement: everything this one understands, HELLO to 255."""

    word = wire.BROADCAST


class Unheeding(ArqEndpoint):
    """A new node that takes every peer to understand what it does (as before the announcement)."""

    def _understands(self, node: int, feature: int) -> bool:
        return True


def _closed(net: SimNet, node: int, msg: int) -> bool:
    return any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[node])


def _fleet(
    third: type[ArqEndpoint], drop: float, seed: int, new: type[ArqEndpoint] = ArqEndpoint
) -> tuple[SimNet, list[ArqEndpoint]]:
    acks: AckMode = "each" if third is Lacking else "auto"
    nodes: list[ArqEndpoint] = [
        new(ArqConfig(node_id=1, rate_bps=RATE, deadline_s=20.0, fec=True), session=901, seed=1),
        new(ArqConfig(node_id=2, rate_bps=RATE, deadline_s=20.0, fec=True), session=902, seed=2),
        third(
            ArqConfig(node_id=3, rate_bps=RATE, deadline_s=20.0, acks=acks, fec=third is not Lacking),
            session=903,
            seed=3,
        ),
    ]
    net = SimNet(nodes, faults=Faults(drop=drop), seed=seed, shared=True)
    net.run(1.0)
    return net, nodes


def _wait_closed(net: SimNet, node: int, msg: int, within: float = 30.0) -> None:
    net.run(net.now + within, stop=lambda: _closed(net, node, msg))


def _send(net: SimNet, sender: ArqEndpoint, dests: list[int], size: int = 20_000) -> tuple[int, bytes]:
    data = os.urandom(size)
    msg = sender.send(data, net.now, dests=dests)
    net.run(net.now + 40, stop=lambda: _closed(net, sender.node, msg))
    return msg, data


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_broadcast_to_a_new_and_a_lacking_node_reaches_both_without_parity(seed: int) -> None:
    net, nodes = _fleet(Lacking, 0.1, seed)
    sender, _, lacking = nodes
    assert sender.older_peers() == {3: OWN} and nodes[1].older_peers() == {3: OWN}
    assert arq.PeerFeatures(3, 0) in net.events[1]
    assert not [e for e in net.events[1] if isinstance(e, arq.PeerFeatures) and e.peer == 2]  # same version
    msg, data = _send(net, sender, [2, 3])
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    assert [m.data for m in net.received(2)] == [data] and [m.data for m in net.received(3)] == [data]
    assert sender.stats()["parity_tx"] == 0 and sender.stats()["resends"] > 0  # repaired, as before
    # it overhears node 2's DONEs to node 1 (dropped, harmless), never a parity chunk
    assert isinstance(lacking, Lacking) and lacking.parity_refused == 0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_lacking_nodes_broadcast_completes_at_new_receivers_acking_it_each(seed: int) -> None:
    net, nodes = _fleet(Lacking, 0.1, seed)
    msg, data = _send(net, nodes[2], [1, 2])
    assert arq.MessageClosed(msg, "delivered") in net.events[3]
    assert [m.data for m in net.received(1)] == [data] and [m.data for m in net.received(2)] == [data]
    assert nodes[0].stats()["completes_tx"] == 0 and nodes[1].stats()["completes_tx"] == 0  # no DONE


def test_without_the_announcement_the_lacking_node_gets_parity_it_refuses_and_dones_it_cannot_read() -> None:
    """The same fleets, once with new nodes that ignore what the lacking one announced (as every
    node did before): its repairs come as parity it refuses, so the map takes many more frames, and
    its own map is acked in DONEs it cannot read, so it is never delivered."""
    frames = {}
    for new in (ArqEndpoint, Unheeding):
        net, nodes = _fleet(Lacking, 0.2, 1, new=new)
        sender, _, lacking = nodes
        msg, data = _send(net, sender, [2, 3])
        assert [m.data for m in net.received(3)] == [data]  # (parity runs out: then chunks go again)
        assert isinstance(lacking, Lacking)
        frames[new.__name__] = (sender.stats()["data_tx"], lacking.parity_refused)
        msg, _ = _send(net, lacking, [1, 2])
        assert (arq.MessageClosed(msg, "delivered") in net.events[3]) is (new is ArqEndpoint)
        assert (nodes[0].stats()["completes_tx"] > 0) is (new is Unheeding)  # COMPLETEs in DONEs
    assert frames["ArqEndpoint"][1] == 0 and frames["Unheeding"][1] > 20, frames
    assert frames["Unheeding"][0] > 1.3 * frames["ArqEndpoint"][0], frames


@pytest.mark.parametrize("seed", [1, 2])
def test_the_release_before_the_announcement_gets_everything_as_before(seed: int) -> None:
    """Two new nodes and one of the release before (HELLO to 255, DONE and parity understood), 10 %
    loss, maps both ways: parity repairs, DONE acks, all delivered, nobody called older."""
    net, nodes = _fleet(PreviousRelease, 0.1, seed)
    assert all(n.older_peers() == {} for n in nodes) and not any(
        isinstance(e, arq.PeerFeatures) for ev in net.events.values() for e in ev
    )
    for sender, dests in ((nodes[0], [2, 3]), (nodes[2], [1, 2])):
        msg, data = _send(net, sender, dests)
        assert arq.MessageClosed(msg, "delivered") in net.events[sender.node]
        assert all([m.data for m in net.received(d)][-1] == data for d in dests)
    assert nodes[0].stats()["parity_tx"] > 0 and nodes[2].stats()["parity_tx"] > 0
    assert nodes[0].stats()["completes_tx"] > 0 and nodes[2].stats()["completes_tx"] > 0  # in DONEs
    assert all(n.stats()["bad_frames"] == 0 for n in nodes)


def test_parity_from_a_sender_that_announced_none_is_taken() -> None:
    """A sender whose word says no DONE nor parity (a stale or false word) repairs with parity all
    the same: the receiver, acking it each, takes the parity and switches to the gap reports and
    DONE such a sender expects, for its next maps too (its second map: 21 ACKs, 38 acked each)."""
    nodes = [
        Says(ArqConfig(node_id=1, rate_bps=RATE, deadline_s=20.0, fec=True), session=901, seed=1),
        ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE, deadline_s=20.0), session=902, seed=2),
        ArqEndpoint(ArqConfig(node_id=3, rate_bps=RATE, deadline_s=20.0), session=903, seed=3),
    ]
    net = SimNet(nodes, faults=Faults(drop=0.15), seed=4, shared=True)
    net.run(1.0)
    assert nodes[1].older_peers() == {1: OWN}
    msg, _data = _send(net, nodes[0], [2, 3])
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    # what it showed counts over what it said: DONE and parity from now on (LEND, TIME still unknown)
    later = wire.F_LEND
    assert nodes[1].older_peers() == {1: later} and nodes[2].older_peers() == {1: later}
    acks = sum(n.stats()["acks_tx"] for n in nodes[1:])
    msg, _data = _send(net, nodes[0], [2, 3])
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    assert sum(n.stats()["acks_tx"] for n in nodes[1:]) - acks < 30, acks  # 38 when acked each
    assert (
        nodes[0].stats()["parity_tx"] > 0
        and nodes[1].stats()["parity_rx"] + nodes[2].stats()["parity_rx"] > 0
    )
    assert nodes[1].stats()["bad_frames"] == 0 and nodes[2].stats()["bad_frames"] == 0


def test_a_newcomer_hears_a_busy_nodes_word_and_a_busy_node_repeats_it() -> None:
    """Node 3 (lacking) sends maps back to back to node 2, never silent for beacon_s; node 1 comes
    up 10 s in. Node 3 answers its first frame with a HELLO, so node 1 knows its word at once (it
    would never have heard one: a HELLO went only at start and after beacon_s of silence)."""

    def cfg(n: int, **kw: Any) -> ArqConfig:
        return ArqConfig(node_id=n, rate_bps=12_500.0, deadline_s=30.0, **kw)

    two = ArqEndpoint(cfg(2), session=902, seed=2)
    busy = Lacking(cfg(3, acks="each"), session=903, seed=3)
    net = SimNet([two, busy], seed=1, shared=True)
    net.run(1.0)
    for k in range(200):  # 2 kB maps, a new one as soon as the last is delivered: about 2 s each
        msg = busy.send(os.urandom(2000), net.now, dests=[2], stream=k % 2)
        _wait_closed(net, 3, msg)
        if net.now > 10.0:
            break
    hellos = busy.stats()["hellos_tx"]
    one = ArqEndpoint(cfg(1), session=901, seed=1)
    net.replace(1, one)
    for k in range(200):
        msg = busy.send(os.urandom(2000), net.now, dests=[2], stream=k % 2)
        _wait_closed(net, 3, msg)
        if one.older_peers() or net.now > 40.0:
            break
    assert one.older_peers() == {3: OWN}, (net.now, busy.stats()["hellos_tx"])
    assert net.now < 25.0 and busy.stats()["hellos_tx"] == hellos + 1
    # and however busy, it says it again within HELLO_REFRESH_S
    before = busy.stats()["hellos_tx"]
    end = net.now + HELLO_REFRESH_S + 5
    while net.now < end:
        msg = busy.send(os.urandom(2000), net.now, dests=[1, 2])
        _wait_closed(net, 3, msg)
    assert busy.stats()["hellos_tx"] >= before + 1


def test_a_hello_announces_features_in_its_dst_and_older_parsers_take_it_as_presence() -> None:
    new = ArqEndpoint(ArqConfig(node_id=4, mac="tdma", radio_time=True), session=44, seed=4)
    frame = wire.parse(_body(new.data_to_send(0.0)))
    assert isinstance(frame, wire.Hello) and frame.dst == wire.FEATURES_FLAG | wire.FEATURES
    assert wire.hello_features(frame) == wire.FEATURES
    # turns on the wall clock (clock = "system"): all but radio time
    own = ArqEndpoint(ArqConfig(node_id=4, mac="tdma", radio_time=False), session=45, seed=4)
    hello = wire.parse(_body(own.data_to_send(0.0)))
    assert isinstance(hello, wire.Hello) and wire.hello_features(hello) == wire.FEATURES & ~wire.F_TIME
    assert wire.hello_features(wire.Hello(4, wire.BROADCAST, 44)) is None  # from before: says nothing
    assert wire.hello_features(wire.Hello(4, 9, 44)) is None  # to one node: says nothing
    assert wire.hello_features(wire.Hello(4, wire.FEATURES_FLAG, 44)) == 0  # says it has none
    assert 1 <= frame.dst <= 254  # within what every version's parser takes for a HELLO
    assert wire.FEATURES < 0x40  # bit 6 clear: FEATURES_FLAG | every feature is never BROADCAST
    assert wire.feature_words(wire.F_PARITY | wire.F_DONE) == "DONE acks, parity repair"
    assert wire.feature_words(0) == "none"


def test_a_peer_restarted_as_another_version_is_held_to_its_new_word() -> None:
    a = ArqEndpoint(ArqConfig(node_id=1, rate_bps=RATE), session=11, seed=1)
    old = Lacking(ArqConfig(node_id=2, rate_bps=RATE, acks="each"), session=21, seed=2)
    net = SimNet([a, old], seed=1)
    net.run(2.0)
    assert a.older_peers() == {2: OWN}
    upgraded = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE), session=22, seed=2)
    net.replace(2, upgraded)
    net.run(4.0)
    assert a.older_peers() == {} and net.events[1][-2:] == [
        arq.PeerRestarted(2),
        arq.PeerFeatures(2, OWN),  # the upgrade is said across the restart
    ]
    assert a.stats()["older_peers"] == {}


def test_status_names_the_older_robots_on_a_link() -> None:
    doc = {
        "robot": "robot0",
        "links": {
            "uwb": {"rate_bps": 12500, "older_mapd": {"robot3": "DONE acks, parity repair, lent turns"}}
        },
    }
    text = render_status(doc)
    assert (
        "older mapd (not sent what it lacks): robot3 (lacks DONE acks, parity repair, lent turns)" in text
    ), text
    assert "FAULTS" not in text
    assert "older mapd" not in render_status({"robot": "robot0", "links": {"uwb": {"older_mapd": {}}}})


@pytest.mark.parametrize("first", ["lacking", "new"])
def test_turns_are_lent_only_to_a_node_that_announced_it_borrows(first: str) -> None:
    """TDMA with lending: node 1 has a map of many chunks, 2 and 3 idle. A node without LEND would
    let each lent slot's rest go empty: 2 and 3 lend to node 1 only when it announced it."""

    def cfg(n: int) -> ArqConfig:
        return ArqConfig(
            node_id=n, rate_bps=12_500, mac="tdma", slots=3, slot_index=n - 1, slot_s=0.3, lend=True
        )

    kind = Lacking if first == "lacking" else ArqEndpoint
    nodes = [
        kind(cfg(1), session=1001, seed=1),
        ArqEndpoint(cfg(2), session=1002, seed=2),
        ArqEndpoint(cfg(3), session=1003, seed=3),
    ]
    net = SimNet(nodes, shared=True)
    net.run(2.0)
    data = os.urandom(3000)
    msg = nodes[0].send(data, net.now, dests=[2, 3])
    assert net.run(60.0, stop=lambda: _closed(net, 1, msg))
    assert [r.data for r in net.received(2)] == [data] == [r.data for r in net.received(3)]
    lends = nodes[1].stats()["lends_tx"] + nodes[2].stats()["lends_tx"]
    assert (lends == 0) if first == "lacking" else (lends > 0), lends


def test_the_transport_says_an_older_robot_once_and_its_upgrade_and_names_it_in_stats(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2, "c": 3}, mac="tdma"), ctx)
    t._link = SimpleNamespace(stats=lambda: {"older_peers": {3: wire.F_PARITY | wire.F_LEND}})  # type: ignore[assignment]
    caplog.set_level(logging.INFO, logger="mapd.uwb")
    t._on_event(arq.PeerFeatures(3, wire.F_DONE))
    for _ in range(100):  # HELLOs that flip what they announce (forged): the log does not fill
        t._on_event(arq.PeerFeatures(3, wire.FEATURES))
        t._on_event(arq.PeerFeatures(3, 0))
    t._features_said[3] -= FEATURES_SAY_S  # later: the word it gives then is said
    t._on_event(arq.PeerFeatures(3, wire.FEATURES))
    said = [r.getMessage() for r in caplog.records if r.name == "mapd.uwb"]
    assert said == [
        "uwb: c runs a mapd from before parity repair, lent turns, radio time (its HELLO says so): no parity "
        "repair, lent turns go to it until it is upgraded, and maps it receives too are sent without them; "
        "it counts its TDMA turns on its own clock, not the fleet's radio clock; nothing needs setting",
        "uwb: c understands all of this link's frames now",
    ], said
    st = t.stats()
    assert st["older_mapd"] == {"c": "parity repair, lent turns"} and "older_peers" not in st


def _body(framed: bytes | None) -> bytes:
    from transports.uwb.framing import FrameReader

    assert framed is not None
    bodies = list(FrameReader(4096, crc=True).feed(framed))
    assert len(bodies) == 1
    return bodies[0]


def test_robots_starting_together_without_tdma_answer_newcomers_with_few_hellos() -> None:
    """32 robots on one channel without TDMA, all starting at once: each first hears 31 others.
    A HELLO for each one heard (measured: 1,184 in 30 s, and an 8 kB map to all of them sent half
    a second in took 14.0 s at 12.5 kb/s) crowded the channel; one HELLO answers every robot heard
    within HELLO_MIN_GAP_S (224 HELLOs, and the map 6.9 s)."""
    nodes = [ArqEndpoint(ArqConfig(node_id=i, rate_bps=RATE), session=900 + i, seed=i) for i in range(1, 33)]
    net = SimNet(nodes, seed=1, shared=True)
    net.run(30.0)
    hellos = sum(n.stats()["hellos_tx"] for n in nodes)
    assert hellos <= 10 * len(nodes), hellos  # a beacon every 5 s of silence, and one or two answers
    assert all(n.peers_up() == [m.node for m in nodes if m is not n] for n in nodes)

    nodes = [
        ArqEndpoint(ArqConfig(node_id=i, rate_bps=12_500.0), session=900 + i, seed=i) for i in range(1, 33)
    ]
    net = SimNet(nodes, seed=1, shared=True)
    net.run(0.5)
    start = net.now
    msg = nodes[0].send(os.urandom(8000), net.now, dests=[n.node for n in nodes[1:]])
    _wait_closed(net, 1, msg, within=60.0)
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    assert net.now - start < 10.0, net.now - start  # (virtual time)


def test_a_restarted_peer_hears_a_busy_nodes_word_and_is_unknown_until_it_says_its_own() -> None:
    """Node 3 (lacking) sends maps back to back to node 2. Node 2 restarts: node 3 answers its new
    session with a HELLO, so node 2 knows node 3's word at once. Then node 3 restarts as the release
    before the announcement (HELLO to 255): it understands everything, and is held to nothing."""

    def cfg(n: int, **kw: Any) -> ArqConfig:
        return ArqConfig(node_id=n, rate_bps=12_500.0, deadline_s=30.0, **kw)

    two = ArqEndpoint(cfg(2), session=902, seed=2)
    busy: ArqEndpoint = Lacking(cfg(3, acks="each"), session=903, seed=3)
    net = SimNet([two, busy], seed=1, shared=True)

    def keep_busy(until: float) -> None:
        k = 0
        while net.now < until:
            k += 1
            msg = busy.send(os.urandom(2000), net.now, dests=[2], stream=k % 2)
            _wait_closed(net, 3, msg)

    keep_busy(10.0)
    assert two.older_peers() == {3: OWN}
    again = ArqEndpoint(cfg(2), session=912, seed=12)
    net.replace(2, again)
    restarted_at = net.now
    keep_busy(restarted_at + 3.0)
    assert again.older_peers() == {3: OWN}, busy.stats()["hellos_tx"]
    previous = PreviousRelease(cfg(3), session=913, seed=13)
    net.replace(3, previous)
    net.run(net.now + 3.0)
    assert again.older_peers() == {} and arq.PeerRestarted(3) in net.events[2]


def test_a_map_on_its_way_when_a_receiver_says_it_lacks_parity_is_repaired_without_it() -> None:
    """Node 1 starts a 20 kB map to nodes 2 and 3 before node 3 is on the air (so before its
    HELLO): parity was on for it. Node 3, lacking parity, comes up half-way and misses the first
    chunks; once its HELLO is heard the map's repairs resend chunks (it refused the parity they
    were before, until the code's parity ran out)."""
    one = ArqEndpoint(ArqConfig(node_id=1, rate_bps=RATE, deadline_s=30.0, fec=True), session=901, seed=1)
    two = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE, deadline_s=30.0), session=902, seed=2)
    net = SimNet([one, two], seed=1, shared=True)
    net.run(0.5)
    data = os.urandom(20_000)
    msg = one.send(data, net.now, dests=[2, 3])
    net.run(net.now + 0.8)
    lacking = Lacking(ArqConfig(node_id=3, rate_bps=RATE, deadline_s=30.0, acks="each"), session=903, seed=3)
    net.replace(3, lacking)
    _wait_closed(net, 1, msg)
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    assert [m.data for m in net.received(3)] == [data] and lacking.parity_refused == 0


def test_a_robot_on_its_wall_clock_is_said_once_to_those_on_the_radio_clock_and_is_no_older_mapd(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """``clock = "system"`` on one robot of a radio-clock fleet: its turns are its own. Before, its
    HELLO announced radio time all the same: nobody could tell that its frames go out of turn as far
    as its wall clock is off."""

    def cfg(n: int, radio: bool) -> ArqConfig:
        return ArqConfig(node_id=n, rate_bps=RATE, mac="tdma", slots=2, slot_index=n - 1, radio_time=radio)

    radio, system = (
        ArqEndpoint(cfg(1, True), session=31, seed=1),
        ArqEndpoint(cfg(2, False), session=32, seed=2),
    )
    net = SimNet([radio, system], seed=3, shared=True)
    net.run(3.0)
    assert (
        radio.older_peers() == {2: wire.F_TIME}
        and arq.PeerFeatures(2, wire.FEATURES & ~wire.F_TIME) in net.events[1]
    )
    assert system.older_peers() == {} and not any(isinstance(e, arq.PeerFeatures) for e in net.events[2])
    # the adapter: a warning once with the fix, its name under "own clock" and not "older mapd"
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2}, mac="tdma"), ctx)
    t._link = SimpleNamespace(stats=lambda: {"older_peers": radio.older_peers()})  # type: ignore[assignment]
    caplog.set_level(logging.INFO, logger="mapd.uwb")
    t._on_event(arq.PeerFeatures(2, wire.FEATURES & ~wire.F_TIME))
    t._on_event(arq.PeerFeatures(2, wire.FEATURES & ~wire.F_TIME))
    said = [r for r in caplog.records if r.name == "mapd.uwb"]
    assert len(said) == 1 and said[0].levelno == logging.WARNING, said
    assert said[0].getMessage().startswith("uwb: b counts its TDMA turns on its own clock")
    assert (
        'clock = "system"' in said[0].getMessage() and "set one clock on every robot" in said[0].getMessage()
    )
    st = t.stats()
    assert st["own_clock"] == ["b"] and st["older_mapd"] == {}
    text = render_status({"robot": "a", "links": {"uwb": st}})
    assert "turns on their own clock, not this radio clock: b (set one clock on every robot)" in text, text
    assert "older mapd" not in text and "FAULTS" not in text
    # a robot on its wall clock itself says nothing of radio-clock robots
    caplog.clear()
    on_wall = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2}, mac="tdma", clock="system"), ctx)
    on_wall._on_event(arq.PeerFeatures(2, wire.FEATURES))
    assert [r.getMessage() for r in caplog.records if r.name == "mapd.uwb"] == [
        "uwb: b understands all of this link's frames now"
    ]
