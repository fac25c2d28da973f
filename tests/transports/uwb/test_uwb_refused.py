"""The sans-I/O core that tells, from relay summaries, which peers' daemons refuse the maps their
radios ack (transports/uwb/refused.py), and the words and stats it gives the transport."""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.daemon.headline import link_faults
from transports.uwb.refused import MAX_ACKS, Cleared, RefusalCore, Refused, words

P = 10.0  # summary period (s): the margin is 3 P, the second summary a period after the first
V = 7 << 32  # incarnation 7: versions keep it in the high bits, as a daemon's do


def summaries(core: RefusalCore, peer: int, holds: int, start: float, n: int) -> list[object]:
    """``n`` summaries of ``peer`` holding ``holds``, one a period from ``start``: what each returned."""
    return [core.summary(peer, holds, start + i * P) for i in range(n)]


def test_a_peer_that_acks_but_never_holds_is_found_after_two_late_summaries_and_said_once() -> None:
    core = RefusalCore(P)
    core.offered(V + 1)
    core.acked(2, V + 1, 0.0)
    # Summaries before the margin (3 P) could predate its decode, or be one packed before the ack:
    # nothing, however many.
    assert summaries(core, 2, 0, 1.0, 3) == [None] * 3
    # The first one heard after the margin raises a doubt, the next one a period later decides.
    assert core.summary(2, 0, 3 * P) is None
    assert core.summary(2, 0, 3 * P + P / 2) is None  # two, but not yet a period apart
    found = core.summary(2, 0, 4 * P)
    assert found == Refused(2, V + 1, 0)
    assert core.refusing() == {2: Refused(2, V + 1, 0)}
    # Said once while it lasts: later summaries that say the same return nothing new.
    assert summaries(core, 2, 0, 5 * P, 5) == [None] * 5
    assert set(core.refusing()) == {2}


def test_it_clears_when_a_summary_shows_an_acked_version_held_and_is_said_again_only_when_back() -> None:
    core = RefusalCore(P)
    core.acked(2, V + 1, 0.0)
    assert summaries(core, 2, 0, 3 * P, 2)[-1] == Refused(2, V + 1, 0)
    # Fixed on its side (config reloaded): it takes our next map and its summary holds it.
    core.acked(2, V + 2, 5 * P)
    assert core.summary(2, V + 2, 5 * P + 1) == Cleared(2, V + 2)
    assert core.refusing() == {}
    assert summaries(core, 2, V + 2, 6 * P, 5) == [None] * 5  # nothing to say while it holds them
    # It refuses again (drifted again): found and said again, once.
    core.acked(2, V + 3, 11 * P)
    got = summaries(core, 2, V + 2, 14 * P, 4)
    assert got.count(Refused(2, V + 3, V + 2)) == 1 and got[1] == Refused(2, V + 3, V + 2)


def test_a_peer_that_missed_our_newest_at_the_radio_holds_an_older_one_and_is_not_refusing() -> None:
    """Only versions its radio acked are judged: holding v1 while we made v5 is a peer the radio
    has not reached yet (out of range, a busy channel), not a daemon that refuses."""
    core = RefusalCore(P)
    core.acked(2, V + 1, 0.0)
    for v in range(2, 6):
        core.offered(V + v)  # offered, never acked by 2
    assert summaries(core, 2, V + 1, 3 * P, 10) == [None] * 10
    assert core.refusing() == {}
    # Whereas a peer that acked v5 and keeps saying it holds v1 refuses v5 and on (max_cells, say,
    # once its map outgrew that robot's limit): "holds v1".
    core.acked(3, V + 1, 0.0)
    core.acked(3, V + 5, 1.0)
    assert summaries(core, 3, V + 1, 3 * P + 1, 2)[-1] == Refused(3, V + 5, V + 1)


def test_a_delta_refused_for_a_missing_base_then_healed_by_a_keyframe_is_no_refusal() -> None:
    """A peer whose daemon took a newer map of ours since the doubt began takes our maps: the doubt
    ends there, whatever it held of the newest acked one."""
    core = RefusalCore(P)
    core.acked(2, V + 3, 0.0)
    core.acked(2, V + 4, 1.0)  # a delta its daemon cannot decode (base lost): it asks for a keyframe
    assert core.summary(2, V + 2, 3 * P + 1) is None  # the doubt: holds v2, acked v4
    core.acked(2, V + 5, 3 * P + 2)  # the keyframe it asked for, decoded
    assert core.summary(2, V + 5, 4 * P + 1) is None  # progress: no refusal, doubt over
    assert core.summary(2, V + 5, 5 * P + 1) is None
    assert core.refusing() == {}


def test_a_restarted_peer_is_judged_only_on_versions_newer_than_any_offered_before() -> None:
    """A daemon restored from its state dir holds our v3 without its summary listing it (a summary
    lists what it accepted since it started), and takes our v3 again as a duplicate: no refusal."""
    core = RefusalCore(P)
    core.offered(V + 3)
    core.acked(2, V + 3, 0.0)
    assert core.summary(2, V + 3, 3 * P) is None
    core.restarted(2)
    core.acked(2, V + 3, 4 * P)  # the keyframe P4 sends it again
    assert summaries(core, 2, 0, 8 * P, 4) == [None] * 4
    # A version made after its restart is judged: a restart into a config that refuses ours is found.
    core.offered(V + 4)
    core.acked(2, V + 4, 12 * P)
    assert summaries(core, 2, 0, 15 * P, 2)[-1] == Refused(2, V + 4, 0)
    # A restart also ends a refusal found before it: judged afresh.
    core.restarted(2)
    assert core.refusing() == {}


def test_late_acks_of_superseded_versions_and_acks_from_a_flood_stay_bounded() -> None:
    core = RefusalCore(P, max_peers=4)
    for peer in range(1, 10):
        core.acked(peer, V + 1, 0.0)
    assert len(core._peers) == 4  # the link's known nodes, at most
    for v in range(1, 200):
        core.acked(1, V + v, v * 0.01)
    assert len(core._peers[1].acks) <= MAX_ACKS
    core.acked(1, V + 3, 3.0)  # a superseded version's late ack: judged by the newer ones
    assert core._peers[1].acks[-1][0] == V + 199
    # Merged into the newest (a later time only delays a judgement): judged all the same.
    assert summaries(core, 1, 0, 3 * P, 2)[-1] == Refused(1, V + 199, 0)


@settings(max_examples=200, deadline=None)
@given(
    events=st.lists(
        st.tuples(
            st.sampled_from(["ack", "summary", "restart"]),
            st.integers(0, 3),  # peer
            st.integers(0, 30),  # version number
            st.floats(0, 5 * P),  # time step
        ),
        max_size=60,
    )
)
def test_never_found_on_a_summary_heard_within_the_margin_of_the_version_it_is_said_to_refuse(
    events: list[tuple[str, int, int, float]],
) -> None:
    """Whatever the order, a refusal names a version acked at least the margin before the summary
    that found it, and a held version below it; found ones are said once until cleared."""
    core = RefusalCore(P, max_peers=3)
    now = 0.0
    first_ack: dict[tuple[int, int], float] = {}
    said: set[int] = set()
    for kind, peer, number, step in events:
        now += step
        if kind == "ack":
            core.acked(peer, V + number, now)
            first_ack.setdefault((peer, V + number), now)
        elif kind == "restart":
            core.restarted(peer)
            said.discard(peer)
        else:
            got = core.summary(peer, V + number if number else 0, now)
            if isinstance(got, Refused):
                assert got.peer not in said
                said.add(got.peer)
                assert got.holds < got.acked
                assert now - first_ack[(peer, got.acked)] >= 3 * P
            elif isinstance(got, Cleared):
                said.discard(got.peer)
        assert set(core.refusing()) == said
        assert len(core._peers) <= 3


def test_words_and_stats_name_the_peer_and_the_versions_and_make_a_link_fault() -> None:
    line = words(Refused(2, V + 12, 0), "robot1")
    assert line == (
        "uwb: robot1 acks our maps at the radio but its daemon holds none of them (acked v12, "
        "holds none): it refuses them; its log and mapd status say why"
    )
    assert "(acked v12, holds v9)" in words(Refused(2, V + 12, V + 9), "robot1")
    assert (
        words(Cleared(2, V + 13), "robot1")
        == "uwb: robot1 holds our v13 now: its daemon takes our maps again"
    )
    core = RefusalCore(P)
    assert core.stats(str) == {"refused_by_peers": 0, "refused_by": {}}
    assert link_faults(core.stats(str)) == []
    core.acked(2, V + 12, 0.0)
    summaries(core, 2, 0, 3 * P, 2)
    stats = core.stats(lambda n: f"robot{n - 1}")
    assert stats == {"refused_by_peers": 1, "refused_by": {"robot1": {"acked": V + 12, "holds": 0}}}
    assert link_faults(stats) == [
        "1 peers ack this robot's maps at the radio but their daemons refuse them (the log names "
        "them; their mapd status says why)"
    ]
