"""Replay marks and counters from the future (audit F1): one forged frame must not silence a robot
for a day, and the marks kept across restarts belong to the link key they were taken under."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from pathlib import Path

import pytest

from transports.uwb import arq, wire
from transports.uwb.arq import ArqConfig, ArqEndpoint
from transports.uwb.framing import encode_frame
from transports.uwb.link import UwbLink
from transports.uwb.signing import (
    MAX_AHEAD_S,
    CounterStore,
    ReplayStore,
    Signer,
    Verifier,
    clock_floor,
)
from transports.uwb.sim import SimNet

KEY = bytes(range(32))
HOUR = 3600.0


def _endpoint(node: int, key: bytes, wall: float, marks: dict[int, int] | None = None) -> ArqEndpoint:
    """An endpoint configured as the uwb transport configures one: counters checked against the
    wall clock (``wall`` at the simulation's time 0)."""
    cfg = ArqConfig(
        node_id=node,
        rate_bps=100_000.0,
        deadline_s=30.0,
        key=key,
        counter_start=clock_floor(wall),
        replay_marks=marks or {},
        check_counter_clock=True,
        clock_offset=wall,
    )
    ep = ArqEndpoint(cfg, session=1000 + node, seed=node)
    upto = ep.counter_reservation()
    assert upto is not None
    ep.confirm_counter(upto)  # what the adapter does once it saved the block
    return ep


def _delivered(a: ArqEndpoint, b: ArqEndpoint, payload: bytes) -> int:
    net = SimNet([a, b])
    a.send(payload, net.now, dests=[b.node])
    net.run(10)
    return sum(r.data == payload for r in net.received(b.node))


def _forged_hello(src: int, counter: int, key: bytes = KEY) -> bytes:
    forger = Signer(key, counter, block=1)
    forger.confirm(counter + 1)
    return encode_frame(forger.sign(wire.pack(wire.Hello(src, wire.BROADCAST, 1001), signed=True)), crc=False)


def test_one_forged_frame_a_day_ahead_no_longer_silences_the_real_sender() -> None:
    # Measured on main (audit F1): a link-key holder's one 20-byte HELLO with robot 1's link id and a
    # counter 23 h ahead was taken (up to a day ahead was), and every real frame of robot 1 was
    # then a "replay" for 23 h, across restarts (the marks are saved) and link-key rotations.
    wall = time.time()
    a, b = _endpoint(1, KEY, wall), _endpoint(2, KEY, wall)
    b.receive_data(_forged_hello(1, clock_floor(wall + 23 * HOUR)), 0.0)
    assert b.stats()["future"] == 1
    assert b.replay_marks().get(1, 0) < clock_floor(wall + MAX_AHEAD_S)
    assert _delivered(a, b, b"map-v2" * 50) == 1
    assert b.stats()["replayed"] == 0


def test_a_forged_counter_within_the_window_silences_the_sender_no_longer_than_the_window() -> None:
    wall = 1.8e9
    v = Verifier(KEY)
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    forger = Signer(KEY, clock_floor(wall + MAX_AHEAD_S - 1), block=1)
    forger.confirm(forger.next + 1)
    assert v.check(forger.sign(body), True, wall) is not None  # within the window: taken
    real = Signer(KEY, clock_floor(wall + MAX_AHEAD_S), block=64)  # the real sender, the window later
    real.confirm(real.next + 64)
    assert v.check(real.sign(body), True, wall + MAX_AHEAD_S) is not None


@pytest.mark.parametrize("ahead_s", [0.0, 0.041, 2.0, 60.0])
def test_a_sender_restarted_with_its_counter_ahead_of_its_clock_is_still_heard(ahead_s: float) -> None:
    # A sender starts at max(stored, clock floor): its saved block (4096 counters, 41 ms) or a
    # clock that a time service stepped back since it saved puts it ahead of the receiver's clock.
    wall = 1.8e9
    stored = clock_floor(wall + ahead_s)
    sender = Signer(KEY, max(stored, clock_floor(wall)))
    sender.confirm(sender.reservation() or 0)
    v = Verifier(KEY, {1: clock_floor(wall) - 10})
    body = wire.pack(wire.Hello(1, 2, 3), signed=True)
    assert all(v.check(sender.sign(body), True, wall + i / 10) is not None for i in range(20))
    assert v.stats.future == v.stats.replayed == 0


def test_marks_kept_under_another_link_key_are_not_loaded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "uwb-2.replay"
    store = ReplayStore(path)
    store.save({1: 5, 3: 9}, KEY)
    assert KEY.hex() not in path.read_text()  # a fingerprint of the key, not the key
    assert store.load(KEY) == {1: 5, 3: 9}
    assert caplog.records == []
    assert store.load(os.urandom(32)) == {}  # the link key was rotated: those marks are void
    assert len(caplog.records) == 1 and "another link key" in caplog.text


def test_marks_files_from_before_keys_are_still_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "uwb-2.replay"
    path.write_text('{"1": 5, "3": 9}')
    assert ReplayStore(path).load(KEY) == {1: 5, 3: 9}
    assert caplog.records == []
    path.write_text('{"key": 7, "marks": {"1": 5}}')  # damaged: one line, never the start
    assert ReplayStore(path).load(KEY) == {}
    assert len(caplog.records) == 1 and "damaged" in caplog.text


def _link(tmp_path: Path, key: bytes) -> UwbLink:
    cfg = arq.ArqConfig(node_id=2, rate_bps=100_000.0, key=key, check_counter_clock=True)
    return UwbLink(
        cfg,
        str(tmp_path / "no-radio"),  # not there: the link starts and waits for it
        counter_store=CounterStore(tmp_path / "uwb-2.counter"),
        replay_store=ReplayStore(tmp_path / "uwb-2.replay"),
        wait_for_port=True,
    )


def _marks_at_start(link: UwbLink) -> dict[int, int]:
    async def main() -> dict[int, int]:
        await link.start()
        try:
            assert link.core is not None
            return link.core.replay_marks()
        finally:
            await link.close()

    return asyncio.run(main())


def test_a_restart_with_a_rotated_link_key_forgets_the_poisoned_marks(tmp_path: Path) -> None:
    # The audit's remedy for a leaked link key is to rotate it: the marks a forger pushed ahead
    # under the old key were kept in uwb-<id>.replay and loaded again whatever the key.
    async def poisoned() -> dict[int, int]:
        link = _link(tmp_path, KEY)
        await link.start()
        assert link.core is not None
        now, wall = asyncio.get_running_loop().time(), time.time()
        link.core.set_clock_offset(wall - now)  # as the link's loop does each second
        link.core.receive_data(_forged_hello(1, clock_floor(wall + 200)), now)  # within the window
        link.core.receive_data(_forged_hello(3, clock_floor(wall)), now)
        marks = link.core.replay_marks()
        await link.close()  # saves them
        return marks

    assert set(asyncio.run(poisoned())) == {1, 3}
    assert set(_marks_at_start(_link(tmp_path, KEY))) == {1, 3}  # a restart under the same key keeps them
    new_key = os.urandom(32)
    assert _marks_at_start(_link(tmp_path, new_key)) == {}


def test_marks_beyond_what_the_clock_accepts_are_lowered_at_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A marks file from before the window shrank may hold a counter a day ahead: it is lowered to
    # the most a frame may be ahead now, so the real sender is heard again within the window.
    wall = time.time()
    path = tmp_path / "uwb-2.replay"
    path.write_text(json.dumps({"1": clock_floor(wall + 23 * HOUR), "3": clock_floor(wall - 10)}))
    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        marks = _marks_at_start(_link(tmp_path, KEY))
    assert marks[3] == clock_floor(wall - 10)
    assert clock_floor(wall + MAX_AHEAD_S) <= marks[1] <= clock_floor(time.time() + MAX_AHEAD_S)
    said = [r.getMessage() for r in caplog.records if "replay marks" in r.getMessage()]
    assert len(said) == 1 and "link id 1" in said[0]


def test_a_signing_counter_saved_far_ahead_of_the_clock_is_said_at_start(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Counters never go back (a restart must not reuse one), so a robot whose clock was set ahead
    # while it signed is refused by its peers until its clock reaches its counter: said, once.
    CounterStore(tmp_path / "uwb-2.counter").save(clock_floor(time.time() + HOUR))
    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        _marks_at_start(_link(tmp_path, KEY))
    said = [r.getMessage() for r in caplog.records if "signing counter" in r.getMessage()]
    assert len(said) == 1 and "ahead of the wall clock" in said[0]


def test_replay_marks_not_saved_are_said_once_an_outage_and_when_saved_again(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A failed save was said once a process: a second outage went unsaid, and the end of one
    too, so a log read later could not tell whether the marks were being saved."""
    path = tmp_path / "uwb-2.replay"

    async def main() -> None:
        link = _link(tmp_path, KEY)
        await link.start()
        assert link.core is not None
        now, wall = asyncio.get_running_loop().time(), time.time()
        link.core.set_clock_offset(wall - now)
        for outage, sender in ((1, 1), (2, 3)):
            path.unlink(missing_ok=True)
            path.mkdir()  # the save's rename onto it fails, as on a full or read-only disk
            for k in range(3):  # three tries, each with marks that changed
                link.core.receive_data(_forged_hello(sender, clock_floor(wall) + 10 * outage + k), now)
                await link._save_replay(force=True)
            path.rmdir()
            link.core.receive_data(_forged_hello(sender, clock_floor(wall) + 10 * outage + 5), now)
            await link._save_replay(force=True)
            assert link.stats()["replay_save_errors"] == 3 * outage
        await link.close()

    with caplog.at_level(logging.WARNING, logger="mapd.uwb"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records if "replay marks" in r.getMessage()]
    assert len([m for m in said if "cannot write replay marks" in m]) == 2, said
    assert len([m for m in said if "saved again" in m]) == 2, said


def test_a_counter_begun_from_a_clock_behind_goes_on_from_the_clock_once_ntp_steps_it(tmp_path: Path) -> None:
    """A robot that lost its state (its saved counter with it) and booted with its clock a month
    behind began signing a month below the marks its peers hold from before: every frame was
    "replayed" until a restart. When NTP steps its clock ahead, the counter goes on from it; a
    counter that was saved is never raised by a step (a wrong step ahead would push it into the
    future, where peers refuse it even after the clock is put right)."""
    wall = 1.8e9
    behind = _endpoint(1, KEY, wall - 30 * 86400)
    peer = _endpoint(2, KEY, wall, marks={1: clock_floor(wall) - 10})
    peer.set_clock_offset(wall)
    assert _delivered(behind, peer, b"map" * 40) == 0 and peer.stats()["replayed"] > 0
    assert behind.raise_counter(clock_floor(wall))
    upto = behind.counter_reservation()
    assert upto is not None and upto > clock_floor(wall)
    behind.confirm_counter(upto)  # what the link does once it saved the block
    assert _delivered(behind, peer, b"map" * 41) == 1

    async def stepped(saved: int) -> tuple[int, int]:
        """The link's counter reservations before and after a step ahead of 30 days."""
        now = [wall - 30 * 86400]
        store = CounterStore(tmp_path / f"uwb-2-{saved}.counter")
        if saved:
            store.save(saved)
        link = UwbLink(
            ArqConfig(node_id=2, rate_bps=100_000.0, key=KEY, check_counter_clock=True),
            str(tmp_path / "no-radio"),
            counter_store=store,
            wall_clock=lambda: now[0],
            wait_for_port=True,
        )
        await link.start()
        try:
            assert link.core is not None
            loop = asyncio.get_running_loop().time()
            link._follow_clock(link.core, loop)
            before = int(store.path.read_text())  # type: ignore[union-attr]
            now[0] = wall
            link._follow_clock(link.core, loop)
            after = link.core.counter_reservation() or 0
            return before, after
        finally:
            await link.close()

    before, after = asyncio.run(stepped(0))
    assert before < clock_floor(wall - 29 * 86400) and after > clock_floor(wall)
    before, after = asyncio.run(stepped(clock_floor(wall - 30 * 86400) + 5))
    assert after < clock_floor(wall - 29 * 86400)  # a saved counter: not raised
