"""What peers take (their ``takes`` tokens), without a network: the key, its parser, the rules.

Before: a sender over zenoh knew nothing of its peers' ``limits.max_message_bytes``; there was no
``takes`` key, no :mod:`transports.zenoh.limits`, and nothing said a peer refused its maps.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mapd.daemon.headline import too_big_words
from transports.zenoh import keys, limits
from transports.zenoh.limits import Over, PeerLimits

F = "f"

# -- the key ---------------------------------------------------------------------------------------


def test_takes_key_round_trips_and_refuses_what_is_not_exactly_one() -> None:
    assert keys.takes_key(F, "r1", 65536) == "mapd/f/r1/takes/65536"
    assert keys.all_takes(F) == "mapd/f/*/takes/*"
    assert keys.parse_takes(F, keys.takes_key(F, "r-1_x", 8 << 20)) == ("r-1_x", 8 << 20)
    assert keys.parse_takes(F, keys.takes_key(F, "r", keys.MIN_TAKES)) == ("r", keys.MIN_TAKES)
    assert keys.parse_takes(F, keys.takes_key(F, "r", keys.MAX_TAKES)) == ("r", keys.MAX_TAKES)
    for bad in (
        "mapd/f/r/takes/1023",  # below the config's least
        f"mapd/f/r/takes/{keys.MAX_TAKES + 1}",
        "mapd/f/r/takes/" + "9" * 400,  # never handed to int()
        "mapd/f/r/takes/0065536",  # leading zeros: not how the key is built
        "mapd/f/r/takes/+65536",
        "mapd/f/r/takes/-65536",
        "mapd/f/r/takes/65_536",  # int() takes it; the key does not
        "mapd/f/r/takes/６５５３６",  # fullwidth digits: int() takes them too
        "mapd/f/r/takes/65536\n",
        "mapd/f/r/takes/",
        "mapd/f/r/takes/65536/x",
        "mapd/f/r/take/65536",
        "mapd/g/r/takes/65536",  # another fleet
        "mapd/f/r*/takes/65536",
        "mapd/f/" + "x" * 33 + "/takes/65536",
        "mapd/f/r",
    ):
        assert keys.parse_takes(F, bad) is None, bad
    for n in (0, keys.MIN_TAKES - 1, keys.MAX_TAKES + 1):
        with pytest.raises(ValueError):
            keys.takes_key(F, "r", n)
    with pytest.raises(ValueError):
        keys.takes_key(F, "a/b", 65536)


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=80))
def test_takes_parser_takes_any_string(text: str) -> None:
    got = keys.parse_takes(F, text)
    # Anything it accepts is exactly the key it would build: one shape, no other spelling.
    assert got is None or keys.takes_key(F, *got) == text


@settings(max_examples=300, deadline=None)
@given(st.from_regex(r"[A-Za-z0-9_-]{1,32}", fullmatch=True), st.text(max_size=30))
def test_takes_parser_takes_any_value_chunk(robot: str, value: str) -> None:
    got = keys.parse_takes(F, f"mapd/{F}/{robot}/takes/{value}")
    if got is not None:
        assert got[0] == robot and keys.MIN_TAKES <= got[1] <= keys.MAX_TAKES and str(got[1]) == value


def test_no_other_subscription_matches_a_takes_token_and_it_matches_no_other_key() -> None:
    """Older robots (and this one's other subscriptions) never see the new token; zenoh's own
    matching decides, so the check is zenoh's ``intersects``, not ours."""
    import zenoh

    token = zenoh.KeyExpr(keys.takes_key(F, "p", 65536))
    # Every subscription, liveliness subscription and queryable a link declares (link._open).
    for sub in (
        keys.all_updates(F),
        keys.acks_for(F, "me"),
        keys.acks_for(F, "takes"),
        keys.all_poses(F),
        keys.all_presence(F),
        keys.all_fleet_presence(),
        keys.latest_key(F, "me"),
    ):
        assert not zenoh.KeyExpr(sub).intersects(token), sub
    # ... and the new subscription sees none of the older keys (a robot named "takes" included).
    takes = zenoh.KeyExpr(keys.all_takes(F))
    for key in (
        keys.presence_key(F, "takes"),
        keys.update_key(F, "p"),
        keys.ack_key(F, "p", "r"),
        keys.ack_key(F, "takes", "r"),
        keys.pose_key(F, "p"),
        keys.latest_key(F, "p"),
        keys.global_key(F, "p"),
        keys.fleet_presence_key(F, "p"),
    ):
        assert not takes.intersects(zenoh.KeyExpr(key)), key
    assert takes.intersects(token)
    # The older parsers take it for none of theirs.
    text = str(token)
    assert keys.parse_presence(F, text) is None and keys.parse_update(F, text) is None
    assert keys.parse_ack(F, "65536", text) is None and keys.parse_pose(F, text) is None


# -- the rules -------------------------------------------------------------------------------------


def test_a_peer_over_its_limit_is_said_once_until_a_map_fits() -> None:
    pl = PeerLimits("a", max_peers=8)
    assert pl.offered(10**6).over == []  # nobody announced anything: as before
    pl.announced("b", 65536, True)
    pl.announced("c", 1 << 20, True)
    v = pl.offered(100_000, {"b", "c"})
    assert v.over == v.failed == [Over("b", 100_000, 65536)] and len(v.warnings) == 1
    line = v.warnings[0]
    assert "b takes messages up to 65536 bytes" in line and "a's map is 100000 bytes" in line
    assert "Raise limits.max_message_bytes on b to at least 100000" in line
    assert pl.stats() == {"too_big_for": {"b": {"size": 100_000, "limit": 65536}}, "too_big_peers": 1}
    # Over again: a Failed each time (the adapter), no new line; the stats follow the size.
    v = pl.offered(120_000)
    assert v.over == [Over("b", 120_000, 65536)] and v.warnings == []
    assert pl.stats()["too_big_for"] == {"b": {"size": 120_000, "limit": 65536}}
    # One fits: cleared; the next over is said again.
    assert pl.offered(1000).over == [] and pl.stats() == {"too_big_for": {}, "too_big_peers": 0}
    v = pl.offered(2 << 20, {"c", "x"})  # Failed only for the link's peers: b is none (yet)
    assert [o.peer for o in v.over] == ["b", "c"] and len(v.warnings) == 2
    assert [o.peer for o in v.failed] == ["c"]
    assert v.over[0].reason() == (
        "2097152 bytes, over b's limits.max_message_bytes (65536): raise it there to at least 2097152"
    )


def test_a_peers_token_gone_forgets_it_and_two_tokens_hold_it_to_the_smaller() -> None:
    pl = PeerLimits("a", max_peers=8)
    pl.announced("b", 65536, True)
    assert len(pl.offered(100_000).warnings) == 1
    pl.announced("b", 65536, False)  # b left (or restarted)
    assert pl.known() == {} and pl.stats()["too_big_for"] == {}
    assert pl.offered(100_000).over == []
    # A restart whose old session lingers: two tokens; the smaller holds until its token goes.
    pl.announced("b", 1 << 20, True)
    pl.announced("b", 65536, True)
    assert pl.known() == {"b": 65536} and len(pl.offered(100_000).warnings) == 1
    pl.announced("b", 65536, False)
    assert pl.known() == {"b": 1 << 20}
    assert pl.offered(100_000).over == [] and pl.stats()["too_big_for"] == {}
    # A new limit that is still too small is said anew (with its figure).
    pl.announced("b", 1 << 20, False)
    pl.announced("b", 80_000, True)
    v = pl.offered(100_000)
    assert len(v.warnings) == 1 and "up to 80000 bytes" in v.warnings[0]
    # A vanishing token never kept, a repeated one, and our own change nothing.
    pl.announced("x", 2048, False)
    pl.announced("b", 80_000, True)
    pl.announced("a", 2048, True)
    assert pl.known() == {"b": 80_000} and pl.offered(100_000).warnings == []


def test_made_up_limits_and_names_stay_bounded() -> None:
    """Tokens are unsigned: thousands of them keep at most max_peers names of MAX_VALUES limits."""
    pl = PeerLimits("a", max_peers=8)
    for i in range(2000):
        pl.announced(f"r{i}", keys.MIN_TAKES + i, True)
        pl.announced("r0", keys.MIN_TAKES + 10_000 + i, True)
    known = pl.known()
    assert len(known) == 8 and known["r0"] == keys.MIN_TAKES
    assert len(pl._peers["r0"].limits) == limits.MAX_VALUES
    v = pl.offered(1 << 20)
    assert len(v.over) == 8 and len(v.warnings) == 8  # one line per kept name, once
    assert pl.offered(1 << 20).warnings == []


def test_too_big_for_is_bounded_and_counted() -> None:
    pl = PeerLimits("a", max_peers=64)
    for i in range(40):
        pl.announced(f"r{i}", 2048, True)
    pl.offered(4096)
    st = pl.stats()
    assert len(st["too_big_for"]) == limits.MAX_SHOWN and st["too_big_peers"] == 40
    words = too_big_words(st)
    assert words is not None and words.endswith(f"; {40 - limits.MAX_SHOWN} more")
    assert "r0 takes 2048 B, ours 4096 B (raise it on r0 to at least 4096)" in words


def test_too_big_words_reads_a_status_document_warily() -> None:
    assert too_big_words({}) is None and too_big_words({"too_big_for": {}}) is None
    assert too_big_words({"too_big_for": "x"}) is None
    assert too_big_words({"too_big_for": {"b": 3}, "too_big_peers": "x"}) is None
    one = {"too_big_for": {"b": {"size": 5000, "limit": 4096}}, "too_big_peers": 1}
    assert too_big_words(one) == (
        "maps too big for peers' limits.max_message_bytes: b takes 4096 B, ours 5000 B "
        "(raise it on b to at least 5000)"
    )
