"""A robot restarted on a state that lost its last word (a full disk, a kill) and its peers agree
on which version it holds: duplicates it offers again are acked, and only saved versions go out."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.codec.api import encode
from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import read_identity
from transports.base import Received


@pytest.mark.parametrize("relayed", [False, True])
def test_a_version_held_and_offered_again_by_its_robot_is_acked_again(
    tmp_path: Path, dk: SimpleNamespace, relayed: bool
) -> None:
    """A robot restarted with a state that lost our ack (a full disk, a kill) offers the version
    again and waits for an ack; the duplicate was dropped unacked, and it waited out its in-flight
    timeout (30 s). A copy another robot relays is not acked: its robot did not ask."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot1 = read_identity(tmp_path / "keys" / "robot1.key", "robot1")
    grid = OccupancyGrid(np.zeros((10, 10), np.int8), 0.05)
    env = Envelope(
        fleet="default", robot="robot1", version=make(incarnation_at(time.time() - 60), 4),
        base_version=0, codec="raw", width=10, height=10, resolution=0.05,
        origin=Pose2D(0, 0, 0), payload=encode(grid, "raw"),
    ).signed(robot1)  # fmt: skip
    link = dk.AckingLink()
    d.transports.append(link)
    acks = link.acks

    async def main() -> None:
        await d.inbound.handle(Received(link.name, "robot1", env.pack()))
        assert acks == [("robot1", env.version)]
        await d.inbound.handle(Received(link.name, "robot2" if relayed else "robot1", env.pack()))

    asyncio.run(main())
    assert d.receiver.counters.duplicates == 1
    assert acks == [("robot1", env.version)] * (1 if relayed else 2)


def test_a_late_joiner_is_answered_only_with_an_own_version_saved(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A version a full disk kept from being saved is not sent (after a restart its number could
    come again with another map), yet a zenoh keyframe query was answered with it."""
    from mapd.errors import StateError

    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    full = False
    save = d.store.save_own

    def save_own(grid: OccupancyGrid) -> None:
        if full:
            raise StateError("state: no room (a full disk)")
        save(grid)

    monkeypatch.setattr(d.store, "save_own", save_own)

    async def main() -> tuple[int | None, int | None, int | None]:
        nonlocal full
        await d._restore()
        tasks = [asyncio.create_task(d.outbound.take_source(source)), asyncio.create_task(d.outbound.run())]
        try:
            await source.queue.put(dk.growing_map(1))
            await dk.wait_for(lambda: d.outbound.saved is not None, what="the first map saved")
            first = await asyncio.to_thread(d.outbound.latest_keyframe)
            full = True
            await source.queue.put(dk.growing_map(2))
            await dk.wait_for(lambda: d.outbound.own is not d.outbound.saved, what="the second map made")
            await asyncio.sleep(0.2)  # (its save tried and failed)
            second = await asyncio.to_thread(d.outbound.latest_keyframe)
            own = d.outbound.own
            return (
                None if first is None else first.version,
                None if second is None else second.version,
                None if own is None else own.version,
            )
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)

    first, second, own = asyncio.run(main())
    assert first is not None and second == first and own is not None and own != first


@pytest.mark.parametrize("synced_after", [0.6, None], ids=["synchronized-later", "never"])
def test_a_new_state_waits_for_a_synchronized_clock_before_its_first_map(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture, synced_after: float | None
) -> None:
    """A new (or lost) state's versions start from the wall clock. A board without a battery-backed
    clock boots at its image's date until NTP sets it: a first map then made every version older
    than those of its lost state, which its peers hold, and they refused its maps for good. With
    ``[state] clock_wait_s`` the first map waits for the kernel to say the clock is synchronized;
    a clock never synchronized is said, and the map goes out when the wait is over."""
    import logging

    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    d.outbound.clock_wait_s = 1.5
    t0 = time.monotonic()
    d.outbound.clock_synchronized = lambda: synced_after is not None and time.monotonic() - t0 >= synced_after

    async def main() -> tuple[float, float]:
        await d._restore()
        task = asyncio.create_task(d.outbound.take_source(source))
        try:
            await source.queue.put(dk.growing_map(1))
            await asyncio.sleep(0.3)
            assert d.outbound.own is None  # not numbered while the clock is not synchronized
            await dk.wait_for(lambda: d.outbound.own is not None, 5.0, "the first map")
            first = time.monotonic() - t0
            await source.queue.put(dk.growing_map(2))  # the state is not new now: no wait
            t1 = time.monotonic()
            await dk.wait_for(lambda: d.outbound.own is not None and d.outbound.own.version % 2**32 == 2)
            return first, time.monotonic() - t1
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        first, second = asyncio.run(main())
    said = [r for r in caplog.records if "wall clock" in r.getMessage()]
    if synced_after is not None:
        assert synced_after <= first < 1.5, first
        assert [r.levelname for r in said] == ["INFO", "INFO"], [r.getMessage() for r in said]
    else:
        assert 1.5 <= first < 3.0, first
        assert said[-1].levelname == "WARNING" and "after 1.5 s" in said[-1].getMessage()
    assert second < 0.5


def test_a_new_states_versions_begin_again_when_the_clock_steps_ahead(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Without a wait for the clock (``clock_wait_s`` 0, the default), a new state's versions began
    from a clock a month behind, below those of the lost state its peers hold; NTP setting the
    clock later changed nothing, and every map stayed refused. A step ahead since they began makes
    them begin again from the clock: a newer incarnation, and numbers from 1."""
    import logging

    from mapd.daemon.versions import split

    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    clock = [1.8e9 - 30 * 86400]
    d.outbound.wall = lambda: clock[0]
    d.outbound.clock_synchronized = lambda: True

    async def main() -> list[int]:
        await d._restore()
        task = asyncio.create_task(d.outbound.take_source(source))
        versions: list[int] = []
        try:
            for n in (1, 2, 3, 4):
                if n == 3:
                    clock[0] = 1.8e9  # NTP sets the clock
                await source.queue.put(dk.growing_map(n))
                await dk.wait_for(lambda n=n: len(versions) < n and d.outbound.own is not None
                                  and d.outbound.own.version not in versions, what=f"map {n}")  # fmt: skip
                assert d.outbound.own is not None
                versions.append(d.outbound.own.version)
            return versions
        finally:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)

    with caplog.at_level(logging.WARNING, logger="mapd.daemon"):
        versions = asyncio.run(main())
    (inc0, n1), (inc1, n2), (inc2, n3), (inc3, n4) = (split(v) for v in versions)
    assert inc0 == inc1 < inc2 == inc3 and (n1, n2, n3, n4) == (1, 2, 1, 2), versions
    said = [r.getMessage() for r in caplog.records if "stepped" in r.getMessage()]
    assert len(said) == 1 and "2592000 s ahead" in said[0], said


def test_versions_begun_from_a_clock_not_synchronized_begin_again_once_it_is_after_a_restart(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """A robot that lost its state made its first maps with its clock a month behind, and was
    restarted before NTP set it: the step was never seen, and its versions stayed below those its
    peers hold. The state says its versions began from a clock the kernel did not say was
    synchronized; once the kernel says it is, they begin again from it, once."""
    import logging
    import os

    from mapd.daemon.versions import split

    synced = [False]
    clock = [1.8e9 - 30 * 86400]

    async def run(d: Any, source: Any, maps: list[int]) -> list[int]:
        d.outbound.wall = lambda: clock[0]
        d.outbound.clock_synchronized = lambda: synced[0]
        await d._restore()
        restored = [] if d.outbound.saved is None else [d.outbound.saved.version]
        tasks = [asyncio.create_task(d.outbound.take_source(source)), asyncio.create_task(d.outbound.run())]
        versions: list[int] = []
        try:
            for n in maps:
                await source.queue.put(dk.growing_map(n))
                await dk.wait_for(
                    lambda: (
                        d.outbound.saved is not None and d.outbound.saved.version not in versions + restored
                    ),
                    what=f"map {n} saved",
                )
                assert d.outbound.saved is not None
                versions.append(d.outbound.saved.version)
            return versions
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            if d._state_lock is not None:
                os.close(d._state_lock)  # (what the stop does: another run may take the directory)
                d._state_lock = None

    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    first = asyncio.run(run(d, source, [1, 2]))
    clock[0], synced[0] = 1.8e9, True  # NTP set the clock while the daemon was down
    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    with caplog.at_level(logging.WARNING, logger="mapd.daemon"):
        after = asyncio.run(run(d, source, [3, 4]))
    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    later = asyncio.run(run(d, source, [5]))  # began synchronized now: no new start again
    (i1, n1), (i2, n2), (i3, n3), (i4, n4), (i5, n5) = (split(v) for v in first + after + later)
    assert i1 == i2 < i3 == i4 == i5 and (n1, n2, n3, n4, n5) == (1, 2, 1, 2, 3), (first, after, later)
    said = [r.getMessage() for r in caplog.records if "not synchronized, and now it is" in r.getMessage()]
    assert len(said) == 1, said
