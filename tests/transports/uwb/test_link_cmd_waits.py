"""How long ``mapd link`` waits, as sans-I/O rules over the core's events and the clock: ``recv``
answers the sender until it goes quiet, ``send`` gives up on a receiver that fell silent (audit
finding 5). The commands over real ptys are in test_link_cmd."""

from __future__ import annotations

from mapd.commands.link_waits import Quiet, Silence
from transports.uwb import arq


def test_recv_stays_while_the_sender_talks_and_leaves_once_it_is_quiet() -> None:
    q = Quiet(12.0, 60.0, now=100.0)
    q.heard(5000, 100.0)
    assert not q.over(111.0)
    q.heard(5040, 111.0)  # a probe 11 s on: its COMPLETE may have been lost, answer it
    assert not q.over(122.0) and q.over(123.0)
    q = Quiet(12.0, 60.0, now=0.0)
    for t in range(0, 70, 4):  # a sender probing every 4 s for ever, never hearing us
        q.heard(t, float(t))
        if q.over(float(t)):
            break
    assert t == 60  # at most 60 s in all
    assert Quiet(0.0, 60.0, now=5.0).over(5.0)  # --linger 0: gone at once


def _silence(*events: tuple[float, arq.Event]) -> Silence:
    s = Silence([2], timeout_s=20.0, silent_s=40.0)
    for now, e in events:
        s.event(e, now)
    return s


def test_send_gives_up_on_a_receiver_silent_since_the_file_was_on_the_air() -> None:
    s = _silence((0.5, arq.PeerUp(2)), (10.0, arq.MessageFlushed(7)), (31.0, arq.PeerDown(2)))
    # last heard about 11 s (PeerDown minus the timeout), after the flush: silent 40 s from there
    assert not s.gave_up(50.0) and s.gave_up(51.0)
    # heard again meanwhile (a lossy line's HELLO got through): the transfer goes on
    s = _silence(
        (0.5, arq.PeerUp(2)), (10.0, arq.MessageFlushed(7)), (31.0, arq.PeerDown(2)), (45.0, arq.PeerUp(2))
    )
    assert not s.gave_up(200.0)
    # silent since before the flush: counted from the flush (the last chunks were still going out)
    s = _silence((0.5, arq.PeerUp(2)), (21.0, arq.PeerDown(2)), (30.0, arq.MessageFlushed(7)))
    assert not s.gave_up(69.0) and s.gave_up(70.0)


def test_send_waits_for_a_receiver_never_heard_or_a_file_not_yet_out() -> None:
    never = _silence((10.0, arq.MessageFlushed(7)))  # its recv may not have started yet
    assert not never.gave_up(1000.0)
    sending = _silence((0.5, arq.PeerUp(2)), (21.0, arq.PeerDown(2)))  # no flush: chunks still to send
    assert not sending.gave_up(1000.0)
    done = _silence((0.5, arq.PeerUp(2)), (10.0, arq.MessageFlushed(7)), (11.0, arq.MessageDelivered(7, 2)))
    assert not done.gave_up(1000.0) and not done.pending
