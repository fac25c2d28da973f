"""The publisher core's rules (P1-P7 in mapd/daemon/publisher.py), with a fake clock and no asyncio."""

from __future__ import annotations

import numpy as np

from mapd.daemon.publisher import PACED_HOLD, EncodeJob, PublisherCore
from mapd.daemon.receiver import KEEP_PEER_VERSIONS
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D

PEERS = {"uwb": ["robot1", "robot2"], "zenoh": ["robot1", "robot2"]}


def grid(version: int) -> OccupancyGrid:
    return OccupancyGrid(np.zeros((4, 4), np.int8), 0.05, robot="robot0", version=version)


def envelope(job: EncodeJob) -> Envelope:
    """What the adapter's worker would make of ``job`` (the payload does not matter to the core)."""
    base = job.base.version if job.base is not None else 0
    return Envelope(
        fleet="f", robot="robot0", version=job.grid.version, base_version=base, codec="lossless",
        width=4, height=4, resolution=0.05, origin=Pose2D(0, 0, 0), payload=b"x",
    )  # fmt: skip


def code(core: PublisherCore, now: float, peers: dict[str, list[str]] = PEERS) -> tuple[EncodeJob, Envelope]:
    job = core.poll(now, peers)
    assert job is not None
    env = envelope(job)
    assert core.encoded(job, env, now, peers) == job.transports
    return job, env


def ack_all(c: PublisherCore, version: int) -> None:
    """Every peer acks ``version`` on every transport."""
    for t in PEERS:
        for p in PEERS[t]:
            c.acked(t, p, version)


def core(**kw: object) -> PublisherCore:
    return PublisherCore(uses_base=True, keyframe_every=50, **kw)  # type: ignore[arg-type]


def test_nothing_to_code_before_the_first_version() -> None:
    c = core()
    assert c.poll(0.0, PEERS) is None and c.next_deadline() is None


def test_first_version_is_a_keyframe_for_every_transport() -> None:
    c = core()
    c.new_version(grid(1))
    job, env = code(c, 0.0)
    assert job.base is None and job.transports == ("uwb", "zenoh")
    assert c.counters.keyframes_sent == 1 and c.cached_keyframe(1) is env and c.cached_keyframe(2) is None


def test_busy_link_codes_nothing_until_every_peer_acked_then_the_newest_as_a_delta() -> None:
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    for v in (2, 3, 4):
        c.new_version(grid(v))
        assert c.poll(1.0, PEERS) is None  # P1: both links still carry v1
    assert c.acked("uwb", "robot1", 1) == (False, True)  # robot2 has not acked on uwb yet
    assert c.poll(1.0, PEERS) is None
    assert c.acked("uwb", "robot2", 1) == (True, True)
    # uwb is free; robot1 and robot2 both hold v1, so v4 goes as a delta against v1 (P2, P3)
    job, _ = code(c, 2.0)
    assert job.grid.version == 4 and job.base is not None and job.base.version == 1
    assert job.transports == ("uwb",)  # zenoh is still busy with v1
    assert c.counters.deltas_sent == 1


def test_peers_holding_different_versions_get_a_delta_on_the_newest_they_all_hold() -> None:
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    ack_all(c, 1)
    c.new_version(grid(2))
    code(c, 1.0)
    c.acked("uwb", "robot1", 2)  # robot2 still holds v1 only
    c.failed("uwb", "robot2", 2)
    c.failed("zenoh", "robot1", 2)
    c.failed("zenoh", "robot2", 2)
    c.new_version(grid(3))
    job, _ = code(c, 2.0)
    assert job.base is not None and job.base.version == 1  # P3: both hold v1; v2 only robot1


def test_a_peer_without_a_version_in_common_gets_a_keyframe() -> None:
    c = core()
    peers = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, peers)
    c.acked("uwb", "robot1", 1)
    c.new_version(grid(2))
    job, _ = code(c, 1.0, {"uwb": ["robot1", "robot2"]})  # robot2 is new: it holds nothing
    assert job.base is None


def test_a_base_the_peer_no_longer_keeps_is_not_used() -> None:
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    ack_all(c, 1)
    # robot1 acks versions 2..KEEP_PEER_VERSIONS + 1 and keeps only that many: v1 dropped out
    for v in range(2, KEEP_PEER_VERSIONS + 2):
        c.new_version(grid(v))
        code(c, float(v), {"uwb": ["robot1"]})
        c.acked("uwb", "robot1", v)
    c.new_version(grid(50))
    job, _ = code(c, 100.0)  # robot2 holds only v1, robot1 no longer keeps it
    assert job.base is None


def test_an_offer_that_never_settles_frees_its_link_at_the_deadline() -> None:
    c = core(inflight_timeout_s=30.0)
    c.new_version(grid(1))
    code(c, 100.0)
    assert c.next_deadline() is None  # nothing newer waits for the link
    c.new_version(grid(2))
    assert c.next_deadline() == 130.0
    assert c.poll(129.9, PEERS) is None
    job, _ = code(c, 130.0)
    assert job.grid.version == 2 and job.base is None  # nobody acked v1: whole again
    assert c.next_deadline() is None


def test_a_peer_that_goes_out_of_reach_is_not_waited_for() -> None:
    c = core(inflight_timeout_s=30.0)
    c.new_version(grid(1))
    code(c, 100.0)
    c.new_version(grid(2))
    c.acked("uwb", "robot1", 1)
    assert c.poll(101.0, PEERS) is None  # uwb waits for robot2, zenoh for both
    assert not c.peer_gone("uwb", "robot1")  # it already acked: nothing changes
    assert c.peer_gone("uwb", "robot2")  # the last one uwb waited for left: uwb is free
    gone = {"uwb": ["robot1"], "zenoh": PEERS["zenoh"]}
    job = c.poll(101.0, gone)
    assert job is not None and job.transports == ("uwb",) and job.grid.version == 2
    assert not c.peer_gone("zenoh", "robot3")  # never waited for


def test_keyframe_schedule() -> None:
    c = PublisherCore(uses_base=True, keyframe_every=3)
    peers = {"zenoh": ["robot1"]}
    kinds = []
    for v in range(1, 8):
        c.new_version(grid(v))
        job, _ = code(c, float(v), peers)
        kinds.append("K" if job.base is None else "D")
        c.acked("zenoh", "robot1", v)
    assert "".join(kinds) == "KDDKDDK"


def test_a_codec_without_bases_always_sends_keyframes() -> None:
    c = PublisherCore(uses_base=False, keyframe_every=50)
    for v in (1, 2):
        c.new_version(grid(v))
        job, _ = code(c, float(v), {"zenoh": ["robot1"]})
        c.acked("zenoh", "robot1", v)
        assert job.base is None


def test_keyframe_request_resends_whole_on_every_transport() -> None:
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    ack_all(c, 1)
    assert c.poll(1.0, PEERS) is None  # everyone has v1
    assert c.keyframe_needed("robot2")  # P4
    job, _ = code(c, 2.0)
    assert job.grid.version == 1 and job.base is None and job.transports == ("uwb", "zenoh")


def test_restored_own_map_is_sent_on_a_keyframe_request_and_the_base_is_kept() -> None:
    c = core(keep_versions=2)
    c.restore(grid(7), grid(5), {"robot1": 5, "robot2": 5})
    assert c.poll(0.0, PEERS) is None  # restored, not new: nothing to send until asked or changed
    for v in (8, 9, 10):
        c.new_version(grid(v))
    job = c.poll(0.0, PEERS)
    assert job is not None and job.grid.version == 10
    assert job.base is not None and job.base.version == 5  # P5: the persisted base outlives pruning
    c2 = core()
    c2.restore(grid(7), None, {})
    assert c2.keyframe_needed("robot1")
    job = c2.poll(0.0, PEERS)
    assert job is not None and job.grid.version == 7 and job.base is None


def test_base_to_save_when_every_peer_acked_the_same_version() -> None:
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    c.acked("uwb", "robot1", 1)
    assert c.base_to_save(["robot1", "robot2"]) is None
    c.acked("uwb", "robot2", 1)
    base = c.base_to_save(["robot1", "robot2"])
    assert base is not None and base.version == 1
    c.set_base(1)
    assert c.base_to_save(["robot1", "robot2"]) is None  # already saved


def test_a_late_joiner_keyframe_never_replaces_a_newer_one() -> None:
    c = core()
    c.new_version(grid(2))
    _, env2 = code(c, 0.0)
    old = envelope(EncodeJob(grid(1), None, ()))
    c.remember_keyframe(old)
    assert c.cached_keyframe(2) is env2


def test_a_peer_that_already_holds_the_version_is_not_waited_for() -> None:
    """A late joiner's query reply carried v3 and it acked v3 before the publisher offered v3 whole:
    it drops the offer as stale and never acks again, so waiting for it would stall the link 30 s."""
    c = core()
    c.new_version(grid(1))
    code(c, 0.0)
    ack_all(c, 1)
    c.new_version(grid(3))
    assert c.acked("zenoh", "robot1", 3)[1]  # acked off the reply, before any offer of v3
    c.keyframe_needed("robot2")
    job, _ = code(c, 1.0)
    assert job.grid.version == 3
    assert c.acked("zenoh", "robot2", 3)[0]  # robot2 alone was waited for on zenoh


def test_a_paced_offer_is_not_superseded_before_it_is_wholly_on_the_air() -> None:
    # uwb gives each robot a share of one slow channel: a keyframe can take longer than the timeout
    # to go out, and superseding it then would start the next one over from nothing (P1).
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    c.new_version(grid(1))
    code(c, 100.0)
    c.new_version(grid(2))
    assert c.next_deadline() == 130.0  # zenoh's offer times out as before
    job, _ = code(c, 130.0)
    assert job.transports == ("zenoh",)  # uwb still holds v1: it is not wholly on the air yet
    assert c.poll(200.0, PEERS) is None
    assert not c.on_air("uwb", 2, 210.0)  # a version uwb was never offered changes nothing
    assert c.on_air("uwb", 1, 210.0)
    assert not c.on_air("uwb", 1, 215.0)  # said once, kept
    job, _ = code(c, 210.0)  # past its timeout once on the air: free at once
    assert job.transports == ("uwb",) and job.grid.version == 2


def test_offers_say_what_each_transport_waits_for() -> None:
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    c.new_version(grid(1))
    code(c, 100.0)
    c.acked("zenoh", "robot1", 1)
    assert c.offers(112.5) == {
        "uwb": {"version": 1, "age_s": 12.5, "waiting": ["robot1", "robot2"], "on_air": False},
        "zenoh": {"version": 1, "age_s": 12.5, "waiting": ["robot2"], "on_air": None},  # not paced
    }
    c.on_air("uwb", 1, 113.0)
    c.acked("zenoh", "robot2", 1)
    assert c.offers(114.0) == {
        "uwb": {"version": 1, "age_s": 14.0, "waiting": ["robot1", "robot2"], "on_air": True},
    }


def test_a_paced_offer_on_the_air_early_keeps_its_timeout() -> None:
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    c.new_version(grid(1))
    code(c, 100.0, {"uwb": ["robot1"]})
    c.new_version(grid(2))
    assert c.on_air("uwb", 1, 105.0)
    assert c.next_deadline() == 130.0
    assert c.poll(129.9, {"uwb": ["robot1"]}) is None  # repairs may still reach robot1
    assert code(c, 130.0, {"uwb": ["robot1"]})[0].grid.version == 2


def test_a_paced_offer_never_said_on_the_air_times_out_after_the_hold() -> None:
    # A link that lost the message without a word cannot hold the publisher for ever.
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    c.new_version(grid(1))
    code(c, 100.0, {"uwb": ["robot1"]})
    c.new_version(grid(2))
    assert c.next_deadline() == 100.0 + PACED_HOLD * 30.0
    assert c.poll(100.0 + PACED_HOLD * 30.0 - 0.1, {"uwb": ["robot1"]}) is None
    assert code(c, 100.0 + PACED_HOLD * 30.0, {"uwb": ["robot1"]})[0].grid.version == 2


def test_a_paced_offer_settled_by_every_peer_frees_its_link_before_it_is_on_the_air() -> None:
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    c.new_version(grid(1))
    code(c, 100.0, {"uwb": ["robot1"]})
    c.new_version(grid(2))
    free, _ = c.acked("uwb", "robot1", 1)
    assert free
    job, _ = code(c, 101.0, {"uwb": ["robot1"]})
    assert job.grid.version == 2 and job.base is not None and job.base.version == 1


def test_a_peer_back_in_reach_is_offered_the_newest_version_again() -> None:
    # P6: on uwb nothing else brings a robot that comes into range the newest map; without the
    # offer it would wait for the next version, and robots passing in a corridor part before that.
    # (The transport says Arrived only when no map on its way reaches the robot.)
    c = core()
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, uwb)
    c.acked("uwb", "robot1", 1)
    c.new_version(grid(2))
    code(c, 30.0, uwb)  # a delta on v1
    c.acked("uwb", "robot1", 2)
    assert c.poll(31.0, uwb) is None  # everyone in reach holds v2
    assert not c.arrived("uwb", "robot1")  # back, but it holds the newest
    assert c.arrived("uwb", "robot2")  # robot2 comes into range with nothing
    job, _ = code(c, 32.0, {"uwb": ["robot1", "robot2"]})
    assert job.grid.version == 2 and job.base is None  # whole: robot2 holds no version
    assert c.offers(32.0)["uwb"]["waiting"] == ["robot2"]  # robot1 holds it: not waited for
    assert not c.arrived("uwb", "robot2")  # already waited for by the offer in flight
    c.acked("uwb", "robot2", 2)
    assert c.poll(33.0, {"uwb": ["robot1", "robot2"]}) is None


def test_a_peer_back_in_reach_gets_a_delta_on_what_it_still_holds() -> None:
    c = core()
    both = {"uwb": ["robot1", "robot2"]}
    c.new_version(grid(1))
    code(c, 0.0, both)
    c.acked("uwb", "robot1", 1)
    c.acked("uwb", "robot2", 1)
    for v in (2, 3):  # robot2 is out of range: robot1 alone gets them
        c.new_version(grid(v))
        code(c, 30.0 * v, {"uwb": ["robot1"]})
        c.acked("uwb", "robot1", v)
    assert c.arrived("uwb", "robot2")
    job, _ = code(c, 95.0, both)
    assert job.grid.version == 3 and job.base is not None and job.base.version == 1


def test_an_arrival_waits_for_a_busy_link() -> None:
    c = core(inflight_timeout_s=30.0)
    c.new_version(grid(1))
    code(c, 0.0)  # offered on uwb and zenoh; nobody acks yet
    assert c.arrived("uwb", "robot3")
    three = {**PEERS, "uwb": ["robot1", "robot2", "robot3"]}
    assert c.poll(10.0, three) is None  # uwb is busy with v1 for robot1 and robot2 until it times out
    assert c.next_deadline() == 30.0  # then poll again: robot3 still lacks v1
    job, _ = code(c, 30.0, three)
    assert job.transports == ("uwb",) and job.grid.version == 1
    # robot3 leaves and comes back 10 s later; robot1 and robot2 ack: the link is free, but offers
    # for arrivals go once per timeout (a link-key holder could fake arrivals: docs/security.md)
    c.peer_gone("uwb", "robot3")
    assert c.arrived("uwb", "robot3")
    c.acked("uwb", "robot1", 1)
    c.acked("uwb", "robot2", 1)
    assert c.poll(42.0, three) is None
    assert c.next_deadline() == 60.0
    assert code(c, 60.0, three)[0].grid.version == 1


def test_a_keyframe_asked_for_while_one_is_on_its_way_is_not_sent_twice() -> None:
    # On uwb a robot that comes into range asks for a whole map as P6 offers it one: one is enough.
    c = core()
    c.new_version(grid(1))
    code(c, 0.0, {"uwb": ["robot1"]})
    c.acked("uwb", "robot1", 1)
    c.new_version(grid(2))
    code(c, 30.0, {"uwb": ["robot1"]})  # a delta on v1
    c.acked("uwb", "robot1", 2)
    assert c.arrived("uwb", "robot2")  # robot2 comes into range: P6 offers it v2, whole
    job, _ = code(c, 31.0, {"uwb": ["robot1", "robot2"]})
    assert job.base is None
    assert not c.keyframe_needed("robot2")  # v2 whole is on its way to it
    c.acked("uwb", "robot2", 2)
    assert c.poll(32.0, {"uwb": ["robot1", "robot2"]}) is None  # and sent once
    # a delta in flight does not help a robot that lost everything
    c.new_version(grid(3))
    code(c, 60.0, {"uwb": ["robot1", "robot2"]})
    assert c.keyframe_needed("robot2")


def test_an_arrival_that_acks_the_offer_in_flight_is_not_offered_it_again() -> None:
    c = core(inflight_timeout_s=30.0)
    c.new_version(grid(1))
    code(c, 0.0, {"uwb": ["robot1"]})
    assert c.arrived("uwb", "robot2")
    c.acked("uwb", "robot2", 1)  # the offer reached it
    free, _ = c.acked("uwb", "robot1", 1)
    assert free and c.poll(1.0, {"uwb": ["robot1", "robot2"]}) is None
    assert c.next_deadline() is None
    # one that leaves again before the link is free is not offered it either
    c.new_version(grid(2))
    code(c, 30.0, {"uwb": ["robot1", "robot2"]})
    assert c.arrived("uwb", "robot3")
    assert c.next_deadline() == 60.0  # v2's offer frees the link then: robot3 would get it
    assert not c.peer_gone("uwb", "robot3")
    assert c.next_deadline() is None  # nothing is wanted of the link any more
    assert c.poll(61.0, {"uwb": ["robot1", "robot2", "robot3"]}) is None


def test_after_a_restart_an_arrival_gets_the_map_that_no_longer_changes() -> None:
    # A robot that finished mapping and restarted makes no new version; a robot that comes into
    # range later still gets its last map (as a zenoh peer's late-join query would).
    c = core()
    c.restore(grid(7), None, {"robot1": 7})
    assert c.poll(0.0, {"uwb": ["robot1"]}) is None  # nothing new to send
    assert not c.arrived("uwb", "robot1")  # it holds v7
    assert c.arrived("uwb", "robot2")
    job, _ = code(c, 1.0, {"uwb": ["robot1", "robot2"]})
    assert job.grid.version == 7 and job.base is None


def test_a_robot_that_seems_to_arrive_again_and_again_costs_one_offer_per_timeout() -> None:
    # A link-key holder can make a robot of the fleet seem to come into range every second (HELLOs
    # with its link id after a silence; docs/security.md). It never acks, so each offer holds the
    # link until it is on the air and its timeout has passed: no more offers than versions cost.
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    peers = {"uwb": ["robot1", "ghost"]}
    c.new_version(grid(1))
    code(c, 0.0, {"uwb": ["robot1"]})
    c.acked("uwb", "robot1", 1)
    offers = []
    for t in range(1, 301):
        c.peer_gone("uwb", "ghost")  # silent long enough to be down, then heard again
        c.arrived("uwb", "ghost")
        job = c.poll(float(t), peers)
        if job is not None:
            c.encoded(job, envelope(job), float(t), peers)
            c.on_air("uwb", 1, float(t) + 5.0)  # its last chunk goes 5 s later
            offers.append(t)
    assert offers == list(range(1, 301, 30))  # every 30 s: one timeout each
    assert c.counters.reoffers == len(offers) and c.counters.keyframes_sent == 1 + len(offers)


def test_a_failed_offer_to_a_peer_still_in_reach_is_offered_again() -> None:
    # The audit's one-way link: robot0 heard robot1 throughout (so robot1 never "arrived" again),
    # while robot1 heard nothing of robot0 until the map's deadline passed. The map no longer
    # changes: without P7 robot1 would never get it, and mapd status would show no offer.
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, uwb)
    assert c.on_air("uwb", 1, 100.0)
    assert c.failed("uwb", "robot1", 1)  # the link gave up on it (its deadline)
    assert c.counters.failed == {"uwb": 1}
    assert c.next_deadline() is not None and c.next_deadline() <= 150.0  # type: ignore[operator]
    job, _ = code(c, 150.0, uwb)  # robot1 is still in reach: v1 goes out again, whole
    assert job.grid.version == 1 and job.base is None and job.transports == ("uwb",)
    assert c.offers(150.0)["uwb"]["waiting"] == ["robot1"]
    assert c.counters.reoffers == 1
    c.acked("uwb", "robot1", 1)
    assert c.poll(200.0, uwb) is None and c.next_deadline() is None  # delivered: nothing more


def test_a_failed_offer_is_not_offered_again_to_a_peer_gone_or_holding_it() -> None:
    c = core(inflight_timeout_s=30.0)
    both = {"uwb": ["robot1", "robot2"]}
    c.new_version(grid(1))
    code(c, 0.0, both)
    c.failed("uwb", "robot1", 1)
    c.failed("uwb", "robot2", 1)
    c.acked("uwb", "robot2", 1)  # a late COMPLETE: robot2 holds it after all
    assert c.poll(200.0, {"uwb": []}) is None  # robot1 is out of reach now: P6 offers it on return
    assert c.poll(300.0, {"uwb": ["robot2"]}) is None
    assert c.arrived("uwb", "robot1")  # back in range
    assert code(c, 301.0, both)[0].grid.version == 1


def test_offers_that_fail_at_once_go_again_once_per_timeout() -> None:
    # A link that fails every offer at once (a map over its message limit, a peer refusing it) is
    # tried again no more often than the in-flight timeout: a dead link never spins the coder.
    c = core(inflight_timeout_s=30.0)
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    offers = []
    for t in range(0, 200):
        job = c.poll(float(t), uwb)
        if job is not None:
            c.encoded(job, envelope(job), float(t), uwb)
            c.failed("uwb", "robot1", 1)
            offers.append(t)
    assert offers == [0, 30, 60, 90, 120, 150, 180]
    assert c.counters.failed == {"uwb": len(offers)}


def test_after_a_failed_offer_a_newer_version_wins() -> None:
    c = core(inflight_timeout_s=30.0)
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, uwb)
    c.failed("uwb", "robot1", 1)
    c.new_version(grid(2))
    job, _ = code(c, 1.0, uwb)  # the link is free: the newest goes, not v1 again
    assert job.grid.version == 2 and c.counters.reoffers == 0
    c.acked("uwb", "robot1", 2)
    assert c.poll(100.0, uwb) is None and c.next_deadline() is None


def test_a_paced_offer_is_held_for_its_link_s_deadline_when_that_is_longer() -> None:
    # A map longer on the air than PACED_HOLD timeouts (uwb: 187 kB at 12.5 kb/s, about 150 s):
    # its link gives it a deadline that grows with its size (uwb arq R6) and says so; a newer
    # version superseding it half sent would start over from nothing and never arrive either.
    c = core(inflight_timeout_s=30.0, paced={"uwb"})
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, uwb)
    c.hold("uwb", 1, 556.0)
    c.new_version(grid(2))
    assert c.poll(PACED_HOLD * 30.0 + 1.0, uwb) is None  # past the hold's timeouts, not the link's
    assert c.next_deadline() == 556.0
    assert c.on_air("uwb", 1, 170.0)  # wholly on the air: its timeout applies as before
    job, _ = code(c, 170.0, uwb)
    assert job.grid.version == 2
    c.hold("uwb", 2, 200.0)  # a link deadline shorter than the hold changes nothing
    c.hold("uwb", 1, 900.0)  # nor one for an offer no longer in flight
    c.new_version(grid(3))
    assert c.poll(170.0 + PACED_HOLD * 30.0 - 1.0, uwb) is None
    assert c.next_deadline() == 170.0 + PACED_HOLD * 30.0


def test_an_offer_refused_for_its_size_is_not_offered_again_until_a_new_version() -> None:
    # A map over the peer's (or this link's) message limit is refused the same way every time: P7
    # offered that very version again at every in-flight timeout, each try certain to fail. A
    # failure that says it is final is settled without a re-offer; the next version still goes.
    c = core(inflight_timeout_s=30.0)
    uwb = {"uwb": ["robot1"]}
    c.new_version(grid(1))
    code(c, 0.0, uwb)
    assert c.failed("uwb", "robot1", 1, again=False)
    assert c.poll(100.0, uwb) is None and c.counters.reoffers == 0
    c.new_version(grid(2))
    assert code(c, 101.0, uwb)[0].grid.version == 2
