"""A peer that takes less than our maps: the sender says it, shows it, and stops waiting for it.

Before (two real sessions on loopback, b's ``limits.max_message_bytes`` 64 KiB, a's 4 MiB, a map
of about 65 KiB offered by a): b refused it and said so, but a said nothing, showed nothing in its
stats, and emitted no event: its publisher waited for b's ack on every offer until the in-flight
timeout (30 s). Between hosts zenoh drops a map more than 64 KiB over b's limit before b's mapd
sees it, so nobody said anything at all. Now each link announces what it takes
(``mapd/<fleet>/<robot>/takes/<bytes>``), and the sender says it once per peer with the fix, shows
it in ``too_big_for`` (a FAULTS line in ``mapd status``) and emits ``Failed(again=False)``.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.commands.status_text import render_status
from mapd.daemon.headline import status_line
from mapd.daemon.publisher import PublisherCore
from mapd.grid import OccupancyGrid
from transports.base import Failed, Received
from transports.zenoh import keys, limits
from transports.zenoh.link import ZenohTransport

LOGGER = "transports.zenoh.link"
DEPLOY = Path(__file__).resolve().parents[3] / "deploy" / "zenoh"
LIMIT = 64 << 10


def run(coro) -> None:  # type: ignore[no-untyped-def]
    asyncio.run(asyncio.wait_for(coro, 60))


def said(caplog: pytest.LogCaptureFixture, *words: str) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == LOGGER and all(w in r.getMessage() for w in words)]


def failed(bot) -> list[Failed]:  # type: ignore[no-untyped-def]
    return bot.of(Failed)


def test_a_map_over_a_peers_announced_limit_is_said_shown_and_failed_for_it(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, logger=LOGGER)

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])  # 4 MiB
            b = await f.start("b", connect=[f.ep], max_message_bytes=LIMIT)
            c = await f.start("c", connect=[f.ep])  # 4 MiB: takes what b does not
            await zk.meet(a, b, c)
            await a.wait(lambda: a.t._limits.known() == {"b": LIMIT, "c": 4 << 20})
            await b.wait(lambda: b.t._limits.known() == {"a": 4 << 20, "c": 4 << 20})  # not its own

            big = zk.envelope("a", 1, payload=bytes(LIMIT + 1000))
            size = len(big.pack())
            a.offer(big)
            # Said once, as a WARNING, naming b, the map's size, b's limit and the fix.
            lines = said(caplog, "b takes messages up to")
            assert len(lines) == 1 and lines[0].levelno == logging.WARNING
            line = lines[0].getMessage()
            assert f"up to {LIMIT} bytes" in line and f"a's map is {size} bytes" in line, line
            assert f"Raise limits.max_message_bytes on b to at least {size}" in line, line
            assert not said(caplog, "c takes messages up to")
            # Shown, and the publisher told not to wait for b (for c it still does).
            st = a.t.stats()
            assert st["too_big_for"] == {"b": {"size": size, "limit": LIMIT}} and st["too_big_peers"] == 1
            assert failed(a) == [
                Failed("zenoh", "b", "a", 1, f"{size} bytes, over b's limits.max_message_bytes ({LIMIT}): "
                       f"raise it there to at least {size}", again=False)
            ]  # fmt: skip
            text = render_status({"links": {"zenoh": st}})
            assert (
                "maps too big for peers' limits.max_message_bytes: b takes "
                f"{LIMIT} B, ours {size} B (raise it on b to at least {size})"
            ) in text, text
            assert "FAULTS 1 peers take smaller messages than this robot's maps" in text, text
            assert "too_big_peers=" not in text
            # It is published all the same: c takes it (b refuses it, as before).
            await c.wait(lambda: c.received("a") == [("a", 1, 0)])
            await b.wait(lambda: b.t.stats()["oversize_rx"] >= 1)

            # Over again: Failed again, no new line.
            a.offer(zk.envelope("a", 2, payload=bytes(LIMIT + 2000)))
            assert [e.version for e in failed(a)] == [1, 2] and len(said(caplog, "b takes")) == 1
            # One that fits clears it: no Failed, no fault, b takes it.
            a.offer(zk.envelope("a", 3))
            assert [e.version for e in failed(a)] == [1, 2]
            assert a.t.stats()["too_big_for"] == {} and a.t.stats()["too_big_peers"] == 0
            assert "FAULTS" not in render_status({"links": {"zenoh": a.t.stats()}})
            await b.wait(lambda: ("a", 3, 0) in b.received("a"))
            # ... and the next one over is said again.
            a.offer(zk.envelope("a", 4, payload=bytes(LIMIT + 3000)))
            assert [e.version for e in failed(a)] == [1, 2, 4] and len(said(caplog, "b takes")) == 2
            assert all(not e.again and e.peer == "b" for e in failed(a))

            # b leaves: forgotten, as a peer that never announced.
            await b.t.close()
            await a.wait(lambda: a.t._limits.known() == {"c": 4 << 20})
            assert a.t.stats()["too_big_for"] == {}
            a.offer(zk.envelope("a", 5, payload=bytes(LIMIT + 4000)))
            assert [e.version for e in failed(a)] == [1, 2, 4] and len(said(caplog, "b takes")) == 2

    run(main())


def test_the_publisher_stops_waiting_for_the_peer_that_refuses(zk: SimpleNamespace) -> None:
    """The link's Failed fed to the real publisher core: the offer waits for c only, and once c
    acks, the link is free for the next version at once (before: b held it for 30 s)."""
    import numpy as np

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])
            b = await f.start("b", connect=[f.ep], max_message_bytes=LIMIT)
            c = await f.start("c", connect=[f.ep])
            await zk.meet(a, b, c)
            await a.wait(lambda: set(a.t._limits.known()) == {"b", "c"})
            pub = PublisherCore(uses_base=False, keyframe_every=1)
            peers = {"zenoh": a.t.peers()}
            assert peers == {"zenoh": ["b", "c"]}
            pub.new_version(OccupancyGrid(np.zeros((4, 4), np.int8), 0.05, robot="a", version=1))
            job = pub.poll(0.0, peers)
            assert job is not None
            env = zk.envelope("a", 1, payload=bytes(LIMIT + 1000))
            for t in pub.encoded(job, env, 0.0, peers):
                assert t == "zenoh"
                a.offer(env)
            assert pub.offers(0.0)["zenoh"]["waiting"] == ["b", "c"]
            for e in failed(a):
                pub.failed(e.transport, e.peer, e.version, again=e.again)
            assert pub.offers(0.0)["zenoh"]["waiting"] == ["c"]
            await c.wait(lambda: c.received("a") == [("a", 1, 0)])
            c.t.ack("a", 1)
            await a.wait(lambda: a.t.stats()["acks_rx"] == 1)
            assert pub.acked("zenoh", "c", 1)[0]  # free: nobody left to wait for
            pub.new_version(OccupancyGrid(np.zeros((4, 4), np.int8), 0.05, robot="a", version=2))
            assert pub.poll(1.0, peers) is not None  # 1 s on, not 30
            assert pub.counters.failed == {"zenoh": 1}

    run(main())


def test_a_peer_that_announces_nothing_is_taken_as_before(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    """b as a robot from before the token: a says nothing, shows nothing, fails nothing; b still
    refuses the map and says so itself."""
    caplog.set_level(logging.INFO, logger=LOGGER)

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep])
            with monkeypatch.context() as m:
                m.setattr(ZenohTransport, "_announce", lambda self, session, ents: None)
                b = await f.start("b", connect=[f.ep], max_message_bytes=LIMIT)
            c = await f.start("c", connect=[f.ep])
            await zk.meet(a, b, c)
            await a.wait(lambda: a.t._limits.known() == {"c": 4 << 20})  # c's came; b has none
            a.offer(zk.envelope("a", 1, payload=bytes(LIMIT + 1000)))
            await b.wait(lambda: b.t.stats()["oversize_rx"] >= 1)
            await c.wait(lambda: c.received("a") == [("a", 1, 0)])
            assert a.t._limits.known() == {"c": 4 << 20}
            assert not failed(a) and a.t.stats()["too_big_for"] == {} and not said(caplog, "takes messages")
            assert len(said(caplog, "maps of a refused")) == 1  # b's own line, as before
            assert not b.of(Received)

    run(main())


def test_forged_takes_tokens_stay_bounded_and_say_nothing_for_names_off_the_roster(
    zk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Tokens are unsigned. In a signed fleet, 2000 made-up names off the roster keep nothing and
    say nothing (counted ``unadmitted``); absurd or malformed values never parse (``dropped``); 50
    limits forged for one roster name keep MAX_VALUES; and the worst a forged limit for a roster
    robot does is a false line: no Failed for a robot that is no peer here (a present one would
    skip a wait: the documented cost)."""
    caplog.set_level(logging.INFO, logger=LOGGER)
    ghosts = 2000

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", listen=[f.ep], signed=True)
            with zk.raw_session(f.ep, watch="a") as raw:
                await a.wait(lambda: bool(raw.seen))
                lv = raw.session.liveliness()
                base = a.t.stats()
                tokens = [
                    lv.declare_token(keys.takes_key(zk.FLEET, f"ghost{i}", 1024)) for i in range(ghosts)
                ]
                bad = [
                    f"mapd/{zk.FLEET}/b/takes/{'9' * 60}",
                    f"mapd/{zk.FLEET}/b/takes/{keys.MAX_TAKES + 1}",
                    f"mapd/{zk.FLEET}/b/takes/0",
                    f"mapd/{zk.FLEET}/b/takes/0001024",
                    f"mapd/{zk.FLEET}/b/takes/-1",
                    f"mapd/{zk.FLEET}/b/takes/many",
                ]
                tokens += [lv.declare_token(k) for k in bad]
                tokens += [lv.declare_token(keys.takes_key(zk.FLEET, "b", 2048 + i)) for i in range(50)]
                await a.wait(
                    lambda: (
                        a.t.stats()["unadmitted"] - base["unadmitted"] >= ghosts
                        and a.t.stats()["dropped"] - base["dropped"] >= len(bad)
                    ),
                    timeout=30,
                )
                await a.wait(
                    lambda: len(a.t._limits._peers.get("b", limits._Peer()).limits) == limits.MAX_VALUES
                )
                known = a.t._limits.known()  # b's smallest kept, nothing of the ghosts
                assert set(known) == {"b"} and 2048 <= known["b"] < 2048 + 50, known
                assert a.t.stats()["unadmitted"] - base["unadmitted"] == ghosts
                a.offer(zk.envelope("a", 1, payload=bytes(4096), signer=zk.ident("a")))
                lines = said(caplog, "takes messages up to")
                assert len(lines) == 1 and lines[0].getMessage().startswith("zenoh: b takes"), lines
                assert not a.of(Failed)  # b is no peer of a's: nothing to stop waiting for
                assert list(a.t.stats()["too_big_for"]) == ["b"]
                for tok in tokens:
                    tok.undeclare()
                await a.wait(lambda: a.t._limits.known() == {}, timeout=30)
                assert a.t.stats()["too_big_for"] == {}

    run(main())


def test_the_token_passes_a_router_acl_that_fences_the_fleets_key_space(zk: SimpleNamespace) -> None:
    """The example router's access-control rules (deploy/zenoh/router-tls.json5: default deny,
    mapd's messages allowed on ``mapd/<fleet>/**``), over tcp here (no certificates): a and b are
    its clients, and a learns b's limit through it."""
    import json

    import zenoh

    example = zenoh.Config.from_file(str(DEPLOY / "router-tls.json5"))
    acl = json.loads(example.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    fleet_rule, presence_rule = acl["rules"]
    assert fleet_rule["key_exprs"] == ["mapd/myfleet/**"] and presence_rule["key_exprs"] == [
        "mapd/@fleets/**"
    ]
    fleet_rule["key_exprs"] = [f"mapd/{zk.FLEET}/**"]  # the test fleet's key space
    for subject in acl["subjects"]:
        subject["link_protocols"] = ["tcp"]
    ep = zk.endpoint(zk.free_port())
    conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([ep]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("access_control", json.dumps(acl))
    router = zenoh.open(conf)

    async def main() -> None:
        async with zk.fleet() as f:
            a = await f.start("a", connect=[ep], mode="client")
            b = await f.start("b", connect=[ep], mode="client", max_message_bytes=LIMIT)
            await zk.meet(a, b)
            await a.wait(lambda: a.t._limits.known() == {"b": LIMIT})
            a.offer(zk.envelope("a", 1, payload=bytes(LIMIT + 1000)))
            assert [(e.peer, e.again) for e in failed(a)] == [("b", False)]

    try:
        run(main())
    finally:
        router.close()


@pytest.mark.slow
def test_a_daemon_says_once_that_a_peer_takes_none_of_its_maps(tmp_path, fk: SimpleNamespace) -> None:  # type: ignore[no-untyped-def]
    """Two ``mapd run`` over zenoh on loopback: robot0 with ``limits.max_message_bytes = 1024`` (no
    map of its own), robot1 with the default. Before: robot1's log and status said nothing of it
    (robot0 refused each map, and its status said so), and robot1's offers waited for robot0."""
    from typing import Any

    def limited(cfg: dict[str, Any]) -> None:
        cfg["limits"] = {"max_message_bytes": 1024}
        cfg["source"] = {"use": "none"}

    f = fk.demo_fleet(tmp_path, 2, duration=30.0, edit={"robot0": limited})
    f.start()

    def link(s: dict[str, Any]) -> dict[str, Any]:
        return s.get("robot1", {}).get("links", {}).get("zenoh", {})

    try:
        # Two maps at least, so "said once" means once for several.
        snaps = fk.wait_for(
            lambda s: (
                "robot0" in link(s).get("too_big_for", {})
                and (s.get("robot1", {}).get("codec", {}).get("failed") or {}).get("zenoh", 0) >= 2
            ),
            30,
            f,
        )
        st = link(snaps)
        assert st["too_big_for"]["robot0"]["limit"] == 1024 and st["too_big_for"]["robot0"]["size"] > 1024
        assert st["too_big_peers"] == 1
        text = render_status(snaps["robot1"])
        assert "FAULTS 1 peers take smaller messages than this robot's maps" in text, text
        assert "maps too big for peers' limits.max_message_bytes: robot0 takes 1024 B" in text, text
        # ... and under the peer, where its "acked our" is read
        peer_lines = text.split("\npeers\n", 1)[1].split("\nlinks\n", 1)[0]
        size = st["too_big_for"]["robot0"]["size"]
        assert (
            f"FAULTS takes messages up to 1024 B, this robot's maps are {size} B: raise "
            f"limits.max_message_bytes on robot0 to at least {size}"
        ) in peer_lines, text
        # ... and on the one line systemd shows (sd_notify STATUS=)
        assert status_line(snaps["robot1"]).startswith("FAULTS zenoh 1 peers take smaller messages")
        # The publisher does not wait for robot0's ack: no offer waits for it.
        assert all(
            "robot0" not in o.get("waiting", []) for o in (snaps["robot1"].get("offers") or {}).values()
        )
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    log = (f.run_dir / "robot1" / "daemon.log").read_text(errors="replace")
    lines = [ln for ln in log.splitlines() if "robot0 takes messages up to 1024 bytes" in ln]
    assert len(lines) == 1 and "WARNING" in lines[0], lines
    assert "Raise limits.max_message_bytes on robot0 to at least" in lines[0], lines
    assert "Traceback" not in log
