"""The receiver's rules (mapd/daemon/receiver.py), on plain envelopes: no asyncio, no transports."""

from __future__ import annotations

import numpy as np

from mapd.daemon.intake import AskKeyframe, Decode, Drop
from mapd.daemon.receiver import Receiver
from mapd.daemon.versions import EPOCH, VersionBounds, incarnation_at, make
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import Identity, Roster

NOW = EPOCH + 1_000_000.0  # a wall clock, seconds
INC = incarnation_at(NOW - 3600)  # robot1 started an hour ago
B = Identity.generate("robot1")


def env(
    version: int, *, robot: str = "robot1", base: int = 0, w: int = 10, h: int = 10, signed: bool = False
) -> Envelope:
    e = Envelope(
        fleet="f", robot=robot, version=version, base_version=base, codec="raw", width=w, height=h,
        resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"",
    )  # fmt: skip
    return e.signed(B) if signed else e


def grid(version: int, w: int = 10, h: int = 10) -> OccupancyGrid:
    return OccupancyGrid(np.zeros((h, w), np.int8), 0.05, robot="robot1", version=version)


def rx(**kw: object) -> Receiver:
    return Receiver("robot0", "f", roster=Roster({"robot1": B.public_key}, allow_unsigned=True), **kw)  # type: ignore[arg-type]


def take(r: Receiver, version: int, now: float = NOW) -> None:
    r.accept(grid(version), env(version), "t", 100, now)


def test_first_map_keyframe_and_deltas_need_their_base() -> None:
    r = rx()
    assert r.plan(env(make(INC, 1)), "robot1", NOW) == Decode(None)
    take(r, make(INC, 1))
    plan = r.plan(env(make(INC, 2), base=make(INC, 1)), "robot1", NOW)
    assert isinstance(plan, Decode) and plan.base is not None
    assert r.plan(env(make(INC, 3), base=make(INC, 2)), "robot1", NOW) == AskKeyframe("robot1")


def test_duplicates_echoes_and_other_fleets_are_routine_drops() -> None:
    r = rx()
    take(r, make(INC, 5))
    for e, peer in [(env(make(INC, 5)), "robot1"), (env(make(INC, 1), robot="robot0"), "robot0")]:
        plan = r.plan(e, peer, NOW)
        assert isinstance(plan, Drop) and plan.routine and not plan.forget


def test_a_version_jump_is_refused_and_the_link_told_to_forget() -> None:
    r = rx(bounds=VersionBounds(max_jump=1000, max_rate=10.0))
    take(r, make(INC, 5), now=NOW - 60)  # heard a minute ago: 1000 + 600 versions may have passed
    assert isinstance(r.plan(env(make(INC, 5 + 1600)), "robot1", NOW), Decode)
    plan = r.plan(env(make(INC, 5 + 1700)), "robot1", NOW)
    assert isinstance(plan, Drop) and plan.forget and "jumps 1700 ahead" in plan.reason
    assert r.counters.refused_versions == 1
    future = make(incarnation_at(NOW + 3 * 86400), 1)  # three days ahead of our clock
    plan = r.plan(env(future), "robot1", NOW)
    assert isinstance(plan, Drop) and "future" in plan.reason


def test_a_new_incarnation_is_taken_at_once_and_forgets_old_bases() -> None:
    r = rx()
    take(r, make(INC, 900))
    restarted = incarnation_at(NOW)
    # said, so that the daemon sends it our next map whole: it lost ours with its state
    assert r.plan(env(make(restarted, 1)), "robot1", NOW) == Decode(None, new_incarnation=True)
    assert r.counters.new_incarnations == 1
    # a delta of the new incarnation against an old version cannot be decoded: ask for a keyframe
    assert r.plan(env(make(restarted, 2), base=make(INC, 900)), "robot1", NOW) == AskKeyframe(
        "robot1", new_incarnation=True
    )
    take(r, make(restarted, 2))
    assert r.plan(env(make(restarted, 3)), "robot1", NOW) == Decode(None)  # the same incarnation


def test_an_unsigned_map_must_come_from_its_own_robot_and_sizes_are_bounded() -> None:
    r = rx(max_cells=10_000)
    plan = r.plan(env(make(INC, 1)), "robot3", NOW)  # a third radio sending "robot1's" map
    assert isinstance(plan, Drop) and "came from 'robot3'" in plan.reason and r.counters.wrong_link == 1
    assert isinstance(
        r.plan(env(make(INC, 1), signed=True), "robot3", NOW), Decode
    )  # signed: relays are fine
    plan = r.plan(env(make(INC, 1), w=1000, h=1000), "robot1", NOW)
    assert isinstance(plan, Drop) and "over the 10000 allowed" in plan.reason


def test_robots_beyond_max_peers_and_off_the_roster_cost_nothing() -> None:
    r = Receiver("robot0", "f", roster=Roster({"robot1": B.public_key}), max_peers=1)
    r.presence("ghost", "zenoh", True)
    assert r.info == {}
    r.presence("robot1", "zenoh", True)
    assert list(r.info) == ["robot1"]
    take(r, make(INC, 1))
    plan = r.plan(env(make(INC, 1), robot="robot2"), "robot2", NOW)
    assert isinstance(plan, Drop) and "max_peers" in plan.reason and not plan.routine
    # robot2's next maps are refused the same, but said once (a fleet past max_peers sends many)
    again = r.plan(env(make(INC, 2), robot="robot2"), "robot2", NOW)
    assert isinstance(again, Drop) and again.routine and r.counters.too_many_robots == 2


def test_a_restored_peer_is_bound_from_when_its_map_was_saved() -> None:
    # Read back from the state directory, a map's stamp is 0: the bound counted from 1970 and let
    # any jump through (2^32 numbers in one step) after every restart.
    restored = grid(make(INC, 5))
    assert restored.stamp == 0.0
    r = rx(bounds=VersionBounds(max_jump=1000, max_rate=10.0))
    r.restore(restored, held_at=NOW - 60, now=NOW)  # saved a minute before
    assert isinstance(r.plan(env(make(INC, 5 + 1600)), "robot1", NOW), Decode)  # as if never stopped
    plan = r.plan(env(make(INC, 5 + 1700)), "robot1", NOW)
    assert isinstance(plan, Drop) and plan.forget and "jumps 1700 ahead" in plan.reason
    # saved "later" than now (the clock was set back): counted from now, not from the future
    r = rx(bounds=VersionBounds(max_jump=1000, max_rate=10.0))
    r.restore(restored, held_at=NOW + 3600, now=NOW)
    assert isinstance(r.plan(env(make(INC, 5 + 1000)), "robot1", NOW), Decode)
    assert isinstance(r.plan(env(make(INC, 5 + 1001)), "robot1", NOW), Drop)


def test_maps_refused_under_a_held_version_from_the_future_are_said_now_and_then() -> None:
    # A leaked key signed a version 23 h ahead (inside the day's tolerance): every real map of the
    # robot is "not newer". A routine duplicate said nothing, so the lock-out went unseen.
    r = rx()
    ahead = make(incarnation_at(NOW + 23 * 3600), 1)
    take(r, ahead)
    plan = r.plan(env(make(INC, 6)), "robot1", NOW)
    assert isinstance(plan, Drop) and not plan.routine and plan.warning
    assert "ahead of this robot's clock" in plan.reason and "23.0 h" in plan.reason
    assert r.counters.duplicates == 1
    again = r.plan(env(make(INC, 7)), "robot1", NOW + 60)
    assert isinstance(again, Drop) and again.routine  # rate-limited: said again after a while
    later = r.plan(env(make(INC, 8)), "robot1", NOW + 3600)
    assert isinstance(later, Drop) and not later.routine
    # a held version only seconds ahead (clocks that disagree a little) keeps duplicates routine
    r = rx()
    take(r, make(incarnation_at(NOW + 5), 3))
    plan = r.plan(env(make(incarnation_at(NOW + 5), 3)), "robot1", NOW)
    assert isinstance(plan, Drop) and plan.routine and not plan.warning


def test_a_robot_that_began_again_with_its_clock_behind_is_said_now_and_then() -> None:
    # A robot that lost its state and started again before NTP set its clock (a board without a
    # battery-backed clock boots at its image's date) makes versions below the one held: each of
    # its maps was dropped as a routine duplicate, said nowhere, for good.
    r = rx()
    take(r, make(INC, 40))
    behind = incarnation_at(NOW - 200 * 86400)  # its clock says 200 days ago
    plan = r.plan(env(make(behind, 1)), "robot1", NOW)
    assert isinstance(plan, Drop) and plan.warning and not plan.routine
    assert (
        "lost its state while its clock was behind" in plan.reason and "empty state directory" in plan.reason
    )
    assert isinstance(again := r.plan(env(make(behind, 2)), "robot1", NOW + 60), Drop) and again.routine
    assert not r.plan(env(make(behind, 3)), "robot1", NOW + 700).routine  # said again after a while
    # a copy of its older maps that another robot relays, and a plain duplicate, stay routine
    relayed = r.plan(env(make(behind, 4), signed=True), "robot2", NOW + 800)
    assert isinstance(relayed, Drop) and relayed.routine
    same = r.plan(env(make(INC, 39)), "robot1", NOW + 900)
    assert isinstance(same, Drop) and same.routine and not same.warning


def test_a_map_a_roster_robot_relayed_says_by_whom_and_a_direct_one_after_it_not() -> None:
    """mapd status showed 'via uwb' alike for a robot heard directly and one whose maps a neighbour
    forwarded: the one thing that says why a robot out of range is seconds behind."""
    C = Identity.generate("robot2")
    r = Receiver("robot0", "f", roster=Roster({"robot1": B.public_key, "robot2": C.public_key}))
    r.accept(grid(make(INC, 1)), env(make(INC, 1)), "uwb", 100, NOW, link_peer="robot2")
    assert r.status(NOW, {})["robot1"]["relayed_by"] == "robot2"
    r.accept(grid(make(INC, 2)), env(make(INC, 2)), "uwb", 100, NOW, link_peer="robot1")
    assert "relayed_by" not in r.status(NOW, {})["robot1"]
    # a name off the roster is a link that knows robot1 by another name (said apart), no relay
    r.accept(grid(make(INC, 3)), env(make(INC, 3)), "uwb", 100, NOW, link_peer="bot1")
    assert "relayed_by" not in r.status(NOW, {})["robot1"]
