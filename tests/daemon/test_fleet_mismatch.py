"""Robots of one fleet whose configs disagree: what each side says, once, and what ``mapd status`` shows.

In a real fleet configs drift apart: a roster lacks a robot's key or holds its old one, a robot
has another ``robot.fleet``, smaller ``limits``, or a ``[transports.uwb] nodes`` list of its own.
Measured before (real daemons, zenoh on loopback and uwb over socat; the report of the audit):

* zenoh, a roster without robot1's key (or with its old one): both robots silent, in the log and
  in ``mapd status``; robot1's maps sent once per 30 s in-flight timeout (each waiting for robot0's
  ack), none taken, and a third robot, whose config agrees, got robot1's maps that seldom too.
* uwb, the same: one INFO line per map robot1 sends ("dropped envelope from robot1: ..."), and no
  word in ``mapd status`` but a counter.
* uwb, another ``robot.fleet``: silent both ways (a routine drop), only ``foreign_fleet`` counted.
* a peer map over ``limits.max_cells``: an INFO line per offer, naming no fix.
* uwb ``nodes`` lists that differ: silent; the robot's maps taken, but the link knows it as
  ``uwb-3`` (or another name), so acks, poses and relays go astray.
* maps made with a codec model this robot lacks: a line per map.

Now each cause is one warning per robot that names it and the fix, and ``mapd status`` (text,
``--json`` and the systemd line) shows it on the side that can tell; the side that cannot see why
(a zenoh peer taking none of its maps) says that too, once.
"""

from __future__ import annotations

import asyncio
import json
import logging
import shutil
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd.codec import encode
from mapd.codec.api import pack_payload
from mapd.commands.status_text import render_status
from mapd.daemon.headline import link_faults, status_line
from mapd.daemon.intake import Drop
from mapd.daemon.receiver import Receiver
from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import Identity, Roster, read_identity
from transports.base import Received

FLEET = "default"  # the fleet of the conftest's configs


def _map(
    robot: str, n: int, *, fleet: str = FLEET, signer: Identity | None = None, size: int = 40
) -> Envelope:
    """Map number ``n`` of ``robot`` (a raw keyframe of a small room), signed by ``signer``."""
    grid = OccupancyGrid(np.zeros((size, size), np.int8), 0.05)
    grid.data[0, :] = 100
    env = Envelope(
        fleet=fleet, robot=robot, version=make(incarnation_at(time.time() - 60), n), base_version=0,
        codec="raw", width=size, height=size, resolution=0.05, origin=Pose2D(0, 0, 0),
        payload=encode(grid, "raw"),
    )  # fmt: skip
    return env.signed(signer) if signer is not None else env


def _feed(d: Any, *events: Received) -> None:
    async def run() -> None:
        for ev in events:
            await d.inbound.handle(ev)

    asyncio.run(run())


def _said(caplog: pytest.LogCaptureFixture, *words: str) -> list[str]:
    """Lines at INFO or above that hold all ``words``."""
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno >= logging.INFO and all(w in r.getMessage() for w in words)
    ]


def _key(tmp_path: Path, robot: str) -> Identity:
    return read_identity(tmp_path / "keys" / f"{robot}.key", robot)


# -- refusals the daemon sees (uwb, virtual), in one process -------------------------------------


def test_a_robot_off_the_roster_is_said_once_with_the_fix_and_shown_in_status(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """robot7 runs, signs its maps, and robot0's roster lacks it: before, one INFO line per map
    ("dropped envelope from robot7: ...") and nothing in ``mapd status`` but a counter."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot7 = Identity.generate("robot7")
    with caplog.at_level(logging.DEBUG, logger="mapd.daemon"):
        _feed(d, *(Received("virtual", "robot7", _map("robot7", n, signer=robot7).pack()) for n in (1, 2, 3)))
    said = _said(caplog, "robot7")
    assert len(said) == 1, said
    assert "[fleet.roster]" in said[0] and "mapd keygen robot7 --public" in said[0], said
    assert [r.levelno for r in caplog.records if r.getMessage() == said[0]] == [logging.WARNING]
    st = d.snapshot()
    refused = st["peers"]["robot7"]["refused"]
    assert (
        refused["maps"] == 3
        and refused["why"] == "not on this roster"
        and st["counters"]["bad_signature"] == 3
    )
    json.dumps(st)  # mapd status --json prints it as it is
    text = render_status(st)
    assert "FAULTS 3 maps refused" in text and "robot7 is not on this robot's [fleet.roster]" in text, text
    assert status_line(st).startswith("FAULTS maps of robot7 refused (not on this roster) | ")


def test_a_refused_name_from_unverified_bytes_cannot_break_the_log_line(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """The robot a refused envelope names is read from bytes nobody verified: a name with a newline
    made a second, forged log line ("dropped envelope from ...: envelope from 'x\\n<anything>'")."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    forged = _map("x\nmapd.daemon: all is well", 1)
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        _feed(d, Received("virtual", "robot7", forged.pack()))
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]
    assert len(said) == 1 and "\n" not in said[0] and "maps of robot7 refused" in said[0], said


def test_an_old_key_is_said_once_and_the_right_key_ends_it(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """robot1 was re-keyed and robot0's roster still holds its old key: before, a line per map."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    new_key = Identity.generate("robot1")
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        _feed(d, *(Received("virtual", "robot1", _map("robot1", n, signer=new_key).pack()) for n in (1, 2)))
        said = _said(caplog, "robot1")
        assert len(said) == 1 and "is not the one its maps are signed with" in said[0], said
        assert "mapd keygen robot1 --public" in said[0], said
        assert d.snapshot()["peers"]["robot1"]["refused"]["maps"] == 2
        # the roster's key again (robot0's roster updated, or robot1 back on its key): taken, said
        _feed(d, Received("virtual", "robot1", _map("robot1", 3, signer=_key(tmp_path, "robot1")).pack()))
    assert _said(caplog, "maps of robot1 taken again, after 2 refused")
    st = d.snapshot()
    assert "refused" not in st["peers"]["robot1"] and st["peers"]["robot1"]["version"] > 0
    assert not status_line(st).startswith("FAULTS")


def test_a_robot_of_another_fleet_name_is_said_once_on_both_sides(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """robot1's config says ``fleet = "other"``: over uwb each robot dropped the other's maps as a
    routine drop, said nowhere (only ``foreign_fleet`` counted)."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot1 = _key(tmp_path, "robot1")
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        _feed(
            d,
            *(
                Received("virtual", "robot1", _map("robot1", n, fleet="other", signer=robot1).pack())
                for n in (1, 2, 3)
            ),
        )
    said = _said(caplog, "robot1", "fleet")
    assert len(said) == 1 and "set robot.fleet the same on every robot" in said[0], said
    assert "'other'" in said[0] and f"'{FLEET}'" in said[0]
    st = d.snapshot()
    assert (
        st["peers"]["robot1"]["refused"]["why"] == "of fleet 'other'" and st["counters"]["foreign_fleet"] == 3
    )
    assert "maps of robot1 refused (of fleet 'other')" in status_line(st)


def test_a_sender_the_nodes_list_does_not_name_is_said_once(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """robot1's uwb link id is 3 in its own ``nodes`` and 2 in robot0's: robot0's link names it
    ``uwb-3``. Its maps are signed, so they were taken, and nothing said that robot0's maps, acks
    and poses for it went to a link id nobody has."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot1 = _key(tmp_path, "robot1")
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        _feed(d, *(Received("virtual", "uwb-3", _map("robot1", n, signer=robot1).pack()) for n in (1, 2, 3)))
    said = _said(caplog, "uwb-3")
    assert len(said) == 1 and "nodes lists differ" in said[0] and "robot1" in said[0], said
    st = d.snapshot()
    assert st["peers"]["robot1"]["heard_as"] == "uwb-3" and st["peers"]["robot1"]["updates"] == 3
    assert "robot1 heard as 'uwb-3' (nodes lists differ?)" in status_line(st)
    assert "its link knows it as 'uwb-3'" in render_status(st)


def test_a_codec_model_this_robot_lacks_is_said_once(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    """Maps made with another model of a codec fail to decode, every one: a line per map before."""
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    robot1 = _key(tmp_path, "robot1")
    body = bytes(40 * 40)
    payload = pack_payload(
        "raw", "model-b", height=40, width=40, resolution=0.05, origin=(0, 0, 0), body=body
    )
    maps = [
        Envelope(
            fleet=FLEET, robot="robot1", version=make(incarnation_at(time.time() - 60), n), base_version=0,
            codec="raw", width=40, height=40, resolution=0.05, origin=Pose2D(0, 0, 0), payload=payload,
        ).signed(robot1)
        for n in (1, 2, 3)
    ]  # fmt: skip
    with caplog.at_level(logging.INFO, logger="mapd.daemon"):
        _feed(d, *(Received("virtual", "robot1", m.pack()) for m in maps))
    said = _said(caplog, "cannot decode")
    assert len(said) == 1 and "variant 'model-b'" in said[0] and "use one on every robot" in said[0], said
    assert d.snapshot()["peers"]["robot1"]["refused"]["maps"] == 3


# -- the receiver's rules, on plain envelopes --------------------------------------------------

NOW = 1.8e9
ROBOT1 = Identity.generate("robot1")


def test_maps_over_max_cells_are_said_once_with_the_size_needed() -> None:
    r = Receiver("robot0", FLEET, roster=Roster({"robot1": ROBOT1.public_key}), max_cells=1000)
    first = r.plan(_map("robot1", 1, signer=ROBOT1), "robot1", NOW)
    assert isinstance(first, Drop) and not first.routine and first.warning, first
    assert "limits.max_cells: raise it on robot0 to at least 1600" in first.reason, first.reason
    again = r.plan(_map("robot1", 2, signer=ROBOT1), "robot1", NOW + 5)
    assert isinstance(again, Drop) and again.routine  # the next maps: counted, not said
    st = r.status(NOW + 6, {})["robot1"]["refused"]
    assert st["maps"] == 2 and st["why"] == "over limits.max_cells" and st["for_s"] == 6.0


def test_unsigned_maps_from_another_link_name_are_said_once_with_the_nodes_hint() -> None:
    """An unsigned fleet whose nodes lists differ: every map refused, a line per map before."""
    r = Receiver("robot0", FLEET, roster=Roster({}, allow_unsigned=True))
    plans = [r.plan(_map("robot1", n), "uwb-3", NOW) for n in (1, 2, 3)]
    assert all(isinstance(p, Drop) for p in plans) and r.counters.wrong_link == 3
    said = [p for p in plans if isinstance(p, Drop) and not p.routine]
    assert len(said) == 1 and "nodes lists differ" in said[0].reason


def test_a_peer_that_takes_none_of_our_maps_while_its_own_come_is_said_once() -> None:
    """zenoh: a peer whose roster lacks our key refuses our maps in its transport, unlogged; we
    take its maps and wait for its acks, which never come. Only this side can say it."""
    from mapd.daemon.refusals import UNACKED_S

    r = Receiver("robot1", FLEET)
    t0 = NOW
    assert r.unacked("zenoh", "robot0", True, t0) is None
    assert r.unacked("zenoh", "robot0", True, t0 + UNACKED_S - 1) is None  # acks can take a while
    line = r.unacked("zenoh", "robot0", True, t0 + UNACKED_S)
    assert line is not None and "robot0 has taken none of this robot's maps" in line
    assert "robot1's key in its [fleet.roster]" in line and "limits.max_message_bytes" in line
    assert r.unacked("zenoh", "robot0", True, t0 + UNACKED_S + 5) is None  # once
    assert r.status(t0 + UNACKED_S + 5, {})["robot0"]["takes_ours"] is False
    assert r.acked("zenoh", "robot0") == "robot0 takes this robot's maps again over zenoh"
    assert "takes_ours" not in r.status(t0 + UNACKED_S + 6, {}).get("robot0", {})
    # refusing only now and then (each keyframe over its limit): said again not before 10 minutes
    t1 = t0 + 100
    r.unacked("zenoh", "robot0", True, t1)
    assert r.unacked("zenoh", "robot0", True, t1 + UNACKED_S) is None
    assert r.acked("zenoh", "robot0") is None  # its end was not said either
    # an offer that no longer waits for it (acked, or timed out while it was away) starts over
    assert r.unacked("zenoh", "robot0", False, t1 + 40) is None


def test_what_a_zenoh_link_refuses_for_the_roster_is_said_once_and_is_a_fault() -> None:
    """robot0's roster lacks robot1: its zenoh link refuses robot1's maps, poses and acks unread
    and counts them (``unadmitted``, ``bad_signature``). Nothing said it, nor ``mapd status``."""
    from mapd.daemon.inbound import LinkRefusals

    look = LinkRefusals()
    zenoh = {"unadmitted": 3, "bad_signature": 1}
    lines = look.look({"zenoh": zenoh}, 100.0)
    assert len(lines) == 1 and lines[0].startswith(
        "zenoh: messages refused for this robot's [fleet.roster] (4 so far)"
    )
    assert look.look({"zenoh": {"unadmitted": 30, "bad_signature": 9}}, 102.0) == []  # going on: said
    assert look.look({"zenoh": {"unadmitted": 30, "bad_signature": 9}}, 900.0) == []  # quiet since
    assert len(look.look({"zenoh": {"unadmitted": 31, "bad_signature": 9}}, 1000.0)) == 1  # anew
    # a serial link's bad_signature is damage (the link tag), which mapd status says otherwise
    assert look.look({"uwb": {"bad_signature": 5, "damaged": 5}}, 0.0) == []
    assert link_faults(zenoh) == [
        "4 messages refused by this roster (a robot's key missing there, or old; or forged?)"
    ]
    assert link_faults({"bad_signature": 5, "damaged": 5, "damaged_since_valid": 0}) == []


# -- real daemons --------------------------------------------------------------------------------


@pytest.mark.slow
def test_zenoh_robots_whose_roster_lacks_a_key_say_so_on_both_sides_and_the_others_go_on(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """Three ``mapd run`` over zenoh, robot0's roster without robot1. Before: robot0 and robot1
    silent, in the log and in ``mapd status``, for as long as they ran; and robot1's maps reached
    robot2 once per 30 s, each offer waiting out its in-flight timeout for robot0's ack."""
    f = fk.demo_fleet(tmp_path, 3, edit={"robot0": lambda c: c["fleet"]["roster"].pop("robot1")})
    logs = {n: f.run_dir / n / "daemon.log" for n in f.names}

    def lines(robot: str, *words: str) -> list[str]:
        return [
            ln for ln in logs[robot].read_text(errors="replace").splitlines() if all(w in ln for w in words)
        ]

    f.start()
    try:
        # robot0, the side that can tell, within a map period (1.25 s here): its status ...
        snaps = fk.wait_for(
            lambda s: "robot0" in s and status_line(s["robot0"]).startswith("FAULTS zenoh ")
            and "refused by this roster" in status_line(s["robot0"]), 30, f
        )  # fmt: skip
        # ... and robot1, which sees only that robot0 acks none of its maps, once that lasted UNACKED_S
        snaps = fk.wait_for(
            lambda s: s.get("robot1", {}).get("peers", {}).get("robot0", {}).get("takes_ours") is False, 60, f
        )
        sock = f.run_dir / "robot1" / "run" / "mapd.sock"
        text = fk.status_text(sock)
        assert "FAULTS takes none of this robot's maps" in text, text
        assert status_line(snaps["robot1"]).startswith("FAULTS robot0 takes none of this robot's maps")
        # robot2, whose config agrees with robot1's, gets its maps as they come again (3 in 15 s,
        # where one offer per 30 s got there before)
        had = fk.held(snaps, "robot2", "robot1")
        fk.wait_for(lambda s: fk.held(s, "robot2", "robot1") >= had + 3, 15, f)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}
    said0 = lines("robot0", "WARNING", "[fleet.roster]")
    assert len(said0) == 1 and "zenoh: messages refused for this robot's [fleet.roster]" in said0[0], said0
    said1 = lines("robot1", "WARNING", "has taken none of this robot's maps")
    assert len(said1) == 1 and "robot0" in said1[0] and "robot1's key in its [fleet.roster]" in said1[0], (
        said1
    )
    # robot2 agrees with both: nothing to say about either
    assert not lines("robot2", "WARNING", "robot0") and not lines("robot2", "WARNING", "robot1")
    for n in f.names:
        assert "Traceback" not in logs[n].read_text(errors="replace")


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
def test_uwb_robots_whose_nodes_and_roster_disagree_say_so_once(tmp_path: Path, fk: SimpleNamespace) -> None:
    """Two ``mapd run`` over socat ptys and the emulated radio: robot0's ``nodes`` call robot1
    ``bot1``, and robot1's roster lacks robot0. Before: robot0 silent (robot1's signed maps taken,
    its acks and poses put down to ``bot1``), robot1 a line per map robot0 sent."""
    f = fk.demo_fleet(
        tmp_path,
        2,
        transport="uwb",
        edit={
            "robot0": lambda c: c["transports"]["uwb"].update(nodes={"robot0": 1, "bot1": 2}),
            "robot1": lambda c: c["fleet"]["roster"].pop("robot0"),
        },
    )
    logs = {n: f.run_dir / n / "daemon.log" for n in f.names}
    f.start()
    try:

        def told(s: dict[str, Any]) -> bool:
            r0 = s.get("robot0", {}).get("peers", {}).get("robot1", {})
            r1 = s.get("robot1", {}).get("peers", {}).get("robot0", {})
            return r0.get("heard_as") == "bot1" and (r1.get("refused") or {}).get("maps", 0) >= 3

        snaps = fk.wait_for(told, 60, f)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    assert snaps["robot1"]["peers"]["robot0"]["refused"]["why"] == "not on this roster"
    assert "maps of robot0 refused (not on this roster)" in status_line(snaps["robot1"])
    assert "robot1 heard as 'bot1' (nodes lists differ?)" in status_line(snaps["robot0"])
    said0 = [ln for ln in logs["robot0"].read_text().splitlines() if "'bot1'" in ln]
    assert len(said0) == 1 and "WARNING" in said0[0] and "nodes lists differ" in said0[0], said0
    said1 = [ln for ln in logs["robot1"].read_text().splitlines() if "robot0" in ln and "refused" in ln]
    assert len(said1) == 1 and "WARNING" in said1[0] and "mapd keygen robot0 --public" in said1[0], said1
