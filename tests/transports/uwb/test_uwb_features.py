"""Mixed versions on one UWB channel (wire.py, *Features*): each node's HELLO announces the frames
it understands in its dst, and nothing it lacks is sent to it, so a fleet upgraded one robot at a
time needs no setting.

A node from before the announcement is emulated here as wire.py says such a node behaves: its HELLO
goes to 255, it acks each message (it knows no DONE), and its parser refuses a DONE frame as an
unknown type and a parity chunk (a DATA index at or past its count) as malformed, counting both
``bad_frames``. Before the announcement (``announce=False`` below stands for a new node that ignores
it) a broadcast map never reached such a node on a lossy channel, and its own maps never completed
at new receivers' side: the repairs came as parity, the COMPLETEs as DONEs.
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
from transports.uwb.faults import Faults
from transports.uwb.sim import SimNet
from transports.uwb.transport import FEATURES_SAY_S, UwbOptions, UwbTransport

RATE = 100_000.0


class OldNode(ArqEndpoint):
    """A mapd from before DONE, parity and the announcement, as the wire protocol describes it."""

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

    def _build(self, kind: str, ref: Any, now: float) -> wire.Frame | None:
        if kind == "hello":
            self.counters.hellos_tx += 1
            return wire.Hello(self.node, wire.BROADCAST, self.session)
        return super()._build(kind, ref, now)


class Unheeding(ArqEndpoint):
    """A new node that takes every peer to understand what it does (as before the announcement)."""

    def _understands(self, node: int, feature: int) -> bool:
        return True


def _fleet(announce: bool, drop: float, seed: int) -> tuple[SimNet, list[ArqEndpoint]]:
    new = ArqEndpoint if announce else Unheeding
    nodes: list[ArqEndpoint] = [
        new(ArqConfig(node_id=1, rate_bps=RATE, deadline_s=20.0, fec=True), session=901, seed=1),
        new(ArqConfig(node_id=2, rate_bps=RATE, deadline_s=20.0, fec=True), session=902, seed=2),
        OldNode(ArqConfig(node_id=3, rate_bps=RATE, deadline_s=20.0, acks="each"), session=903, seed=3),
    ]
    net = SimNet(nodes, faults=Faults(drop=drop), seed=seed, shared=True)
    net.run(6.0)  # every node's HELLO heard (at start, and after beacon_s of silence)
    return net, nodes


def _send(net: SimNet, sender: ArqEndpoint, dests: list[int]) -> tuple[int, bytes]:
    data = os.urandom(20_000)
    msg = sender.send(data, net.now, dests=dests)
    net.run(
        net.now + 40,
        stop=lambda: any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[sender.node]),
    )
    return msg, data


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_broadcast_to_a_new_and_an_old_node_reaches_both_without_parity(seed: int) -> None:
    net, nodes = _fleet(True, 0.1, seed)
    sender, _, old = nodes
    assert sender.older_peers() == {3: wire.FEATURES} and nodes[1].older_peers() == {3: wire.FEATURES}
    assert arq.PeerFeatures(3, 0) in net.events[1]
    assert not [e for e in net.events[1] if isinstance(e, arq.PeerFeatures) and e.peer == 2]  # same version
    msg, data = _send(net, sender, [2, 3])
    assert arq.MessageClosed(msg, "delivered") in net.events[1]
    assert [m.data for m in net.received(2)] == [data] and [m.data for m in net.received(3)] == [data]
    assert sender.stats()["parity_tx"] == 0 and sender.stats()["resends"] > 0  # repaired, as before
    # it overhears node 2's DONEs to node 1 (dropped, harmless, as before), never a parity chunk
    assert isinstance(old, OldNode) and old.parity_refused == 0


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_an_old_nodes_broadcast_completes_at_new_receivers_acking_it_each(seed: int) -> None:
    net, nodes = _fleet(True, 0.1, seed)
    old = nodes[2]
    msg, data = _send(net, old, [1, 2])
    assert arq.MessageClosed(msg, "delivered") in net.events[3]
    assert [m.data for m in net.received(1)] == [data] and [m.data for m in net.received(2)] == [data]
    assert (
        nodes[0].stats()["completes_tx"] == 0 and nodes[1].stats()["completes_tx"] == 0
    )  # acks it understands


def test_without_the_announcement_the_old_node_gets_neither_way() -> None:
    """The same fleet with new nodes that ignore what the old one announced (as every node did
    before): its broadcast repairs come as parity it refuses, and its own maps are acked in DONEs
    it cannot read."""
    net, nodes = _fleet(False, 0.1, 1)
    sender, _, old = nodes
    msg, _data = _send(net, sender, [2, 3])
    assert arq.MessageClosed(msg, "delivered") not in net.events[1]
    assert net.received(3) == [] and sender.stats()["parity_tx"] > 0
    assert isinstance(old, OldNode) and old.parity_refused > 0
    msg, _ = _send(net, old, [1, 2])
    assert arq.MessageClosed(msg, "delivered") not in net.events[3]
    assert nodes[0].stats()["completes_tx"] > 0  # its COMPLETEs went in DONEs


def test_a_hello_announces_features_in_its_dst_and_older_parsers_take_it_as_presence() -> None:
    new = ArqEndpoint(ArqConfig(node_id=4), session=44, seed=4)
    frame = wire.parse(_body(new.data_to_send(0.0)))
    assert isinstance(frame, wire.Hello) and frame.dst == wire.FEATURES_FLAG | wire.FEATURES
    assert wire.hello_features(frame) == wire.FEATURES
    assert wire.hello_features(wire.Hello(4, wire.BROADCAST, 44)) == 0  # from before: none for sure
    assert wire.hello_features(wire.Hello(4, 9, 44)) is None  # to one node: announces nothing
    assert 1 <= frame.dst <= 254  # within what every version's parser takes for a HELLO
    assert wire.feature_words(wire.F_PARITY | wire.F_DONE) == "DONE acks, parity repair"
    assert wire.feature_words(0) == "none"


def test_a_peer_restarted_as_another_version_is_held_to_its_new_hello() -> None:
    a = ArqEndpoint(ArqConfig(node_id=1, rate_bps=RATE), session=11, seed=1)
    old = OldNode(ArqConfig(node_id=2, rate_bps=RATE, acks="each"), session=21, seed=2)
    net = SimNet([a, old], seed=1)
    net.run(2.0)
    assert a.older_peers() == {2: wire.FEATURES}
    upgraded = ArqEndpoint(ArqConfig(node_id=2, rate_bps=RATE), session=22, seed=2)
    net.replace(2, upgraded)
    net.run(4.0)
    assert a.older_peers() == {} and net.events[1][-2:] == [
        arq.PeerRestarted(2),
        arq.PeerFeatures(2, wire.FEATURES),
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


def _body(framed: bytes | None) -> bytes:
    from transports.uwb.framing import FrameReader

    assert framed is not None
    bodies = list(FrameReader(4096, crc=True).feed(framed))
    assert len(bodies) == 1
    return bodies[0]


@pytest.mark.parametrize("first", ["old", "new"])
def test_turns_are_lent_only_to_a_node_that_announced_it_borrows(first: str) -> None:
    """TDMA with lending: node 1 has a map of many chunks, 2 and 3 idle. A node from before LEND
    would let each lent slot's rest go empty: 2 and 3 lend to node 1 only when it announced it."""

    def cfg(n: int) -> ArqConfig:
        return ArqConfig(
            node_id=n, rate_bps=12_500, mac="tdma", slots=3, slot_index=n - 1, slot_s=0.3, lend=True
        )

    kind = OldNode if first == "old" else ArqEndpoint
    nodes = [
        kind(cfg(1), session=1001, seed=1),
        ArqEndpoint(cfg(2), session=1002, seed=2),
        ArqEndpoint(cfg(3), session=1003, seed=3),
    ]
    net = SimNet(nodes, shared=True)
    net.run(2.0)
    data = os.urandom(3000)
    msg = nodes[0].send(data, net.now, dests=[2, 3])
    assert net.run(
        60.0, stop=lambda: any(isinstance(e, arq.MessageClosed) and e.msg == msg for e in net.events[1])
    )
    assert [r.data for r in net.received(2)] == [data] == [r.data for r in net.received(3)]
    lends = nodes[1].stats()["lends_tx"] + nodes[2].stats()["lends_tx"]
    assert (lends == 0) if first == "old" else (lends > 0), lends


def test_the_transport_says_an_older_robot_once_and_its_upgrade_and_names_it_in_stats(
    caplog: pytest.LogCaptureFixture,
) -> None:
    ctx = TransportContext(robot="a", fleet="f", max_message_bytes=1 << 20, emit=lambda e: None)
    t = UwbTransport(UwbOptions(nodes={"a": 1, "b": 2, "c": 3}), ctx)
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
        "uwb: c runs a mapd from before parity repair, lent turns (its HELLO says so): none go to it until "
        "it is upgraded, and maps it receives too are sent without them; nothing needs setting",
        "uwb: c understands all of this link's frames now",
    ], said
    st = t.stats()
    assert st["older_mapd"] == {"c": "parity repair, lent turns"} and "older_peers" not in st
