"""``systemctl status mapd`` shows what the robot is doing: the daemon's STATUS= line (sd_notify).

Before, the daemon said ``STATUS=running`` once and nothing after, so the unit's status showed
neither the robot's map nor a fault until someone ran ``mapd status``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import socket
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.daemon.headline import MAX_LINE, status_line
from mapd.daemon.versions import make as compose
from mapd.grid.save import save_map
from mapd.mapping.synthetic import room_grid


def _doc(**kw: Any) -> dict[str, Any]:
    doc: dict[str, Any] = {
        "source": {"version": compose(1, 12)},
        "peers": {"beta": {"version": compose(3, 9)}, "gamma": {"version": compose(1, 4), "present": False}},
        "fusion": {"maps": 3, "global": {"width": 812, "height": 604}},
        "links": {"uwb": {"port_open": True, "reconnects": 0}},
        "security": {"signed": True},
    }
    doc.update(kw)
    return doc


def test_the_line_says_the_map_the_peers_and_the_global_map() -> None:
    assert status_line(_doc()) == "map v12; peers beta v9, gamma v4 (gone); global 3 maps 812x604"
    assert status_line({}) == status_line({"source": {"version": 0}}) == "no map yet; no peers yet"


def test_faults_come_first_in_the_words_mapd_status_uses() -> None:
    line = status_line(
        _doc(
            links={"uwb": {"port_open": False, "reconnects": 2}, "zenoh": {}},
            recording={"failures": 1},
            security={"signed": False},
        )
    )
    assert line.startswith(
        "FAULTS uwb serial port closed (reopening), port reopened 2 times, recording: messages not "
        "written, UNSIGNED fleet | map v12;"
    )


def test_a_large_fleet_or_many_faults_still_fit_one_line() -> None:
    peers = {f"robot{i:02d}": {"version": compose(1, i)} for i in range(40)}
    line = status_line(_doc(peers=peers, links={f"uwb{i}": {"write_stalls": 9} for i in range(10)}))
    assert len(line) <= MAX_LINE and line.endswith("...")
    assert "+36" in status_line(_doc(peers=peers))


@pytest.mark.slow
def test_a_daemon_under_systemd_keeps_its_status_line_current(tmp_path: Path, dk: SimpleNamespace) -> None:
    notify = tmp_path / "notify"
    save_map(room_grid(60, 80, seed=3), tmp_path / "map.yaml")
    (tmp_path / "config.toml").write_text(
        '[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        '[source]\nuse = "mapfile"\n[source.mapfile]\npath = "map.yaml"\npoll_s = 0.1\nsettle_s = 0.1\n'
        '[codec]\nuse = "raw"\n[state]\ndir = "state"\nruntime_dir = "run"\n'
    )
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind(str(notify))
        s.settimeout(1.0)
        said: list[str] = []
        env = {**os.environ, "NOTIFY_SOCKET": str(notify)}
        with dk.mapd_run(tmp_path / "config.toml", tmp_path / "daemon.log", env=env) as proc:
            deadline = time.monotonic() + 60
            while time.monotonic() < deadline and not any("global 1 map " in m for m in said):
                assert proc.poll() is None, (tmp_path / "daemon.log").read_text()[-2000:]
                with contextlib.suppress(TimeoutError):
                    said.append(s.recv(4096).decode())
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(30) == 0
    assert said[0] == "READY=1\nSTATUS=FAULTS UNSIGNED fleet | no map yet; no peers yet", said
    status = [m for m in said if m.startswith("STATUS=")]
    assert status and re.fullmatch(
        r"STATUS=FAULTS UNSIGNED fleet \| map v1; no peers yet; global 1 map \d+x\d+", status[-1]
    ), said
    assert len(status) == len(set(status)), "a line is said again only when it changed"


def test_a_status_bug_costs_the_line_not_the_daemon(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    import asyncio

    from mapd.daemon import notifier

    sent: list[str] = []
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody"))
    monkeypatch.setattr(notifier, "STATUS_PERIOD_S", 0.01)
    monkeypatch.setattr(notifier, "notify", sent.append)
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    calls = 0

    def broken() -> dict[str, Any]:
        nonlocal calls
        calls += 1
        if calls < 3:
            raise KeyError("a bug")
        return {"source": {"version": 0}}

    monkeypatch.setattr(d, "snapshot", broken)

    async def main() -> None:
        task = asyncio.create_task(d._systemd_status())
        await dk.wait_for(lambda: calls >= 3 and bool(sent), what="a line after two failures")
        assert not task.done() and sent == ["STATUS=no map yet; no peers yet"]
        task.cancel()

    asyncio.run(main())


def test_a_reload_keeps_the_status_line_not_running(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """READY=1 after a reload said STATUS=running, and the status loop, which says a line only when
    it changes, never said the real one again: a steady robot's FAULTS vanished from systemctl
    status at every reload."""
    import asyncio

    from mapd.daemon import notifier

    sent: list[str] = []
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody"))
    monkeypatch.setattr(notifier, "STATUS_PERIOD_S", 0.01)
    monkeypatch.setattr(notifier, "notify", sent.append)
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())

    async def main() -> None:
        task = asyncio.create_task(d._systemd_status())
        await dk.wait_for(lambda: any(m.startswith("STATUS=") for m in sent), what="a first line")
        line = sent[-1]
        assert await d.reload()
        assert sent[-2].startswith("RELOADING=1") and sent[-1] == "READY=1\n" + line
        n = len(sent)
        await asyncio.sleep(0.2)  # twenty turns of the status loop: nothing changed, nothing said
        assert len(sent) == n
        task.cancel()

    asyncio.run(main())


def _slow_start(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch, sent: list[str]
) -> tuple[Any, threading.Event, threading.Event]:
    """A daemon whose source's start pose blocks until ``release`` (``entered`` once it does), with
    sd_notify's messages collected in ``sent``."""
    from mapd.daemon import notifier

    monkeypatch.setattr(notifier, "notify", sent.append)
    d, source = dk.virtual_daemon(tmp_path, "robot0", dk.channel())
    entered, release = threading.Event(), threading.Event()

    def slow_start_pose() -> None:
        entered.set()
        release.wait(60)

    monkeypatch.setattr(source, "start_pose", slow_start_pose)
    return d, entered, release


def test_a_stop_during_start_up_ends_it_without_ready(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SIGTERM while the source was still reading its start pose (a large log, a world to build)
    waited for the whole start-up, then said READY=1 and only then stopped: systemctl stop of a
    slow start ran into TimeoutStopSec."""
    sent: list[str] = []
    d, entered, release = _slow_start(tmp_path, dk, monkeypatch, sent)

    async def main() -> None:
        task = asyncio.create_task(d.run())
        await dk.wait_for(entered.is_set, what="start-up under way")
        d.request_stop()
        await asyncio.wait_for(task, 30)  # returns with start_pose still blocked
        assert not release.is_set()
        # (let it go now: asyncio.run waits for the executor's threads, 60 s for this one)
        release.set()

    try:
        asyncio.run(main())
    finally:
        release.set()
    assert "STOPPING=1" in sent and not any(m.startswith("READY=1") for m in sent), sent
    assert d.transports == [] or all(not t.peers() for t in d.transports)


def test_a_cancelled_run_takes_its_start_up_with_it(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    """run() cancelled during start-up (a test's task.cancel(), Ctrl-C) left the start-up task
    running: it went on to make and start the transports after the shutdown had closed them."""
    d, entered, release = _slow_start(tmp_path, dk, monkeypatch, [])

    async def main() -> None:
        task = asyncio.create_task(d.run())
        await dk.wait_for(entered.is_set, what="start-up under way")
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.wait_for(task, 30)
        release.set()
        for _ in range(50):  # the start-up, were it still going, would make the transports now
            await asyncio.sleep(0.02)
        assert d.transports == []

    try:
        asyncio.run(main())
    finally:
        release.set()


def test_frames_from_beyond_the_clock_window_are_a_fault() -> None:
    """A counter over 5 minutes ahead: clocks far apart, or a link-key holder forging (audit F1)."""
    line = status_line(_doc(links={"uwb": {"future": 3}}))
    assert line.startswith("FAULTS uwb 3 frames signed with counters over 5 min ahead of this robot's clock")
    assert not status_line(_doc(links={"uwb": {"future": 0}})).startswith("FAULTS")


def _heard_through(scramble: bool, *, garbage: bytes = b"") -> dict[str, Any]:
    """The stats of a keyed uwb endpoint (link id 2) after a peer's map reached it: each frame
    scrambled as a wrong baud leaves it (``(b * 37 + 11) & 0xFF``: delimiters gone, bytes changed),
    or intact, with ``garbage`` (line noise) fed in before."""
    from transports.uwb.arq import ArqConfig, ArqEndpoint

    key = bytes(range(32))
    a, b = (ArqEndpoint(ArqConfig(node_id=n, key=key, rate_bps=1e6), session=n, seed=n) for n in (1, 2))
    for ep in (a, b):
        ep.confirm_counter(ep.counter_reservation() or 0)
    a.send(bytes(range(256)) * 20, 0.0, dests=[2])
    b.receive_data(garbage, 0.0)
    now = 0.0
    while now < 1.0:
        now += 0.01
        a.handle_timer(now)
        while frame := a.data_to_send(now):
            b.receive_data(bytes((x * 37 + 11) & 0xFF for x in frame) if scramble else frame, now)
    return b.stats()


def test_a_wrong_baud_is_damaged_frames_said_on_the_faults_line() -> None:
    """Audit finding 3: a wrong baud raised only cobs_errors and oversize, which `mapd status` never
    showed (crc_errors=0 bad_signature=0), and the peer merely looked gone."""
    from mapd.commands.status_text import render_status

    st = _heard_through(scramble=True)
    parts = ("crc_errors", "cobs_errors", "oversize", "runts", "bad_signature")
    total = sum(st[k] for k in parts)
    assert total > 0 and st["peers_up"] == 0 and st["crc_errors"] == st["bad_signature"] == 0
    shown = render_status({"links": {"uwb": st}}).splitlines()
    link = next(ln for ln in shown if ln.strip().startswith("uwb"))
    assert f"damaged={total} (" in link
    for k in parts:  # what caught them is said too, whichever counters are not zero
        assert (f"{k}={st[k]}" in link) == (st[k] > 0), link
    faults = [ln for ln in shown if "FAULTS" in ln]
    assert faults == [f"         FAULTS {total} damaged frames, no peer heard (wrong baud or noisy line?)"]
    line = status_line(_doc(links={"uwb": st}))
    assert line.startswith(
        f"FAULTS uwb {total} damaged frames, no peer heard (wrong baud or noisy line?) | map v12"
    )
    assert len(line) <= MAX_LINE


def test_damage_while_peers_are_heard_is_counted_but_not_a_fault() -> None:
    from mapd.commands.status_text import render_status

    st = _heard_through(scramble=False, garbage=bytes(range(1, 256)) * 3 + b"\x00")
    assert st["oversize"] + st["cobs_errors"] > 0 and st["peers_up"] == 1
    shown = render_status({"links": {"uwb": st}})
    assert f"damaged={st['oversize'] + st['cobs_errors']} (" in shown
    assert "FAULTS" not in shown and not status_line(_doc(links={"uwb": st})).startswith("FAULTS")
    # A clean line says damaged=0, and a link without serial framing (zenoh) no damaged= at all.
    clean = render_status({"links": {"uwb": _heard_through(scramble=False)}})
    assert "damaged=0 " in clean and "FAULTS" not in clean
    zenoh = render_status({"links": {"zenoh": {"session_open": True, "bad_signature": 2}}})
    assert "damaged=" not in zenoh and "bad_signature=2" in zenoh


def test_frames_failing_only_the_link_tag_suggest_another_link_key() -> None:
    # A peer keyed with another link key: every frame decodes and fails the tag, no COBS damage.
    st = {"port_open": True, "peers_up": 0, "crc_errors": 0, "cobs_errors": 0, "oversize": 0, "runts": 0,
          "bad_signature": 40, "damaged": 40, "damaged_since_valid": 40}  # fmt: skip
    line = status_line(_doc(links={"uwb": st}))
    assert line.startswith(
        "FAULTS uwb 40 frames failed the link tag, no peer heard (another link key, or a noisy line?)"
    )
    # A port that is closed says so; damage from before it closed is not the fault then.
    closed = status_line(_doc(links={"uwb": {**st, "port_open": False}}))
    assert closed.startswith("FAULTS uwb serial port closed (reopening) | ")


def test_damage_from_before_the_last_valid_frame_is_no_fault_once_the_robot_is_alone() -> None:
    """Robots go out of each other's range: noise long past, then good frames, then no peer heard
    is a robot alone, not a wrong baud; damage after the last good frame is a fault again."""
    from transports.uwb.arq import ArqConfig, ArqEndpoint

    key = bytes(range(32))
    a, b = (ArqEndpoint(ArqConfig(node_id=n, key=key, rate_bps=1e6), session=n, seed=n) for n in (1, 2))
    for ep in (a, b):
        ep.confirm_counter(ep.counter_reservation() or 0)
    b.receive_data(bytes(range(1, 256)) * 3 + b"\x00", 0.0)  # line noise first
    a.send(bytes(range(256)) * 4, 0.0, dests=[2])
    now = 0.0
    while now < 1.0:
        now += 0.01
        a.handle_timer(now)
        while frame := a.data_to_send(now):
            b.receive_data(frame, now)
    while now < 120.0:  # robot1 walks out of range: nothing heard from it any more
        now += 1.0
        b.handle_timer(now)
    st = b.stats()
    assert st["peers_up"] == 0 and st["oversize"] + st["cobs_errors"] > 0 and st["damaged_since_valid"] == 0
    assert not status_line(_doc(links={"uwb": st})).startswith("FAULTS")
    b.receive_data(bytes(range(1, 256)) * 3 + b"\x00", now)  # damage again, and no peer heard
    st = b.stats()
    assert st["damaged_since_valid"] > 0
    assert status_line(_doc(links={"uwb": st})).startswith(
        f"FAULTS uwb {st['damaged_since_valid']} damaged frames, no peer heard"
    )


def test_a_recording_that_failed_once_is_a_fault_only_while_it_fails() -> None:
    # A disk that filled once left "recording: messages not written" on every status line for the
    # rest of the run: the totals said so, whether it wrote again or not.
    over = status_line(_doc(recording={"failures": 3, "dropped": 1, "writing": True, "behind": False}))
    assert "recording" not in over and not over.startswith("FAULTS")
    for now in ({"writing": False, "behind": False}, {"writing": True, "behind": True}):
        line = status_line(_doc(recording={"failures": 3, "dropped": 1, **now}))
        assert line.startswith("FAULTS recording: messages not written |"), (now, line)


def test_a_zenoh_link_that_lost_its_router_is_a_fault_while_it_is_lost() -> None:
    # mapd status listed the peers as gone and said nothing of why: the router they are reached by
    lost = status_line(_doc(links={"zenoh": {"router_connected": False, "router_losses": 1}}))
    assert lost.startswith("FAULTS zenoh router lost (zenoh reconnects by itself) |"), lost
    for connected in (True, None):  # back, or a fleet of peers without a router
        line = status_line(_doc(links={"zenoh": {"router_connected": connected, "router_losses": 1}}))
        assert not line.startswith("FAULTS"), line


def test_a_relaying_link_says_what_it_forwarded_on_a_line_of_its_own() -> None:
    """The relay's figures came after the eight other counters the links line has room for: a
    relaying robot's mapd status never showed them."""
    from mapd.commands.status_text import render_status

    st = {"rate_bps": 12500, "goodput_bps": 900, **{f"c{i}": i for i in range(12)}, "relays_tx": 7,
          "relays_failed": 1, "relays_overheard": 3, "relay_keyframes_asked": 2, "relay_summaries_tx": 40,
          "relay_summaries_rx": 35, "relay_bad_summaries": 0}  # fmt: skip
    lines = render_status({"links": {"uwb": st}}).splitlines()
    relay = [ln.strip() for ln in lines if ln.strip().startswith("relay ")]
    assert relay == [
        "relay   forwarded 7 maps of other robots (1 given up, 3 overheard from neighbours), 2 whole "
        "maps asked for on a neighbour's behalf; summaries 40 sent, 35 heard"
    ], lines
    assert not any("relays_tx=" in ln for ln in lines)  # not twice
    # a zenoh link has no relay; a document from another process may say anything
    assert not any("relay " in ln for ln in render_status({"links": {"zenoh": {"rate_bps": 1}}}).splitlines())
    odd = render_status({"links": {"uwb": {"relays_tx": 2, "relays_failed": "x", "relay_bad_summaries": 4}}})
    assert "forwarded 2 maps of other robots (- given up" in odd and "heard (4 malformed)" in odd


def test_a_links_struggle_is_among_the_counters_shown_first() -> None:
    # 30 % frame loss showed "completes_tx=0" and seven more of the first counters in dict order,
    # and cut timeouts=13 and the failed messages: nothing on the line said the link struggled.
    from mapd.commands.status_text import render_status

    st = {"goodput_bps": 397, "resends": 26, "completes_tx": 0}
    st |= {f"counter{i}": i for i in range(10)}
    st |= {"timeouts": 13, "messages_failed": 2, "link_rate_bps": 12500}
    line = next(ln for ln in render_status({"links": {"uwb": st}}).splitlines() if ln.startswith("  uwb"))
    assert "timeouts=13" in line and "messages_failed=2" in line and "link_rate_bps=12500" in line, line


def test_a_peer_whose_ack_is_not_known_is_not_said_to_have_acked_v0() -> None:
    # Forgotten when it asked for a whole map (a relay's keyframe request), or never relayed back:
    # "acked our v0" read as an ack of a version it never had, of a robot that held our v31.
    from mapd.commands.status_text import render_status

    peers = {
        "robot1": {"present": True, "version": 5, "acked_our_version": 0},
        "robot2": {"acked_our_version": 1},
    }
    text = render_status({"peers": peers})
    line1 = next(ln for ln in text.splitlines() if ln.strip().startswith("robot1"))
    assert line1.endswith("acked our none known") and "v0" not in line1, line1
    assert next(ln for ln in text.splitlines() if ln.strip().startswith("robot2")).endswith("acked our v1")


def test_a_pose_of_a_robot_no_longer_heard_is_marked_so() -> None:
    # Relayed poses yield to maps: a peer's pose 40 s old was shown with nothing to say it was
    # where the robot had been. Marked by the link, not by the age: AMCL publishes only when the
    # robot moves, and a parked robot heard well has an old pose (found by review).
    from mapd.commands.status_text import render_status

    poses = {
        "robots": {
            "robot1": {"map": [1.0, 2.0, 0.0], "age_s": 40.0},
            "robot2": {"map": [0, 0, 0], "age_s": 90.0},
        }
    }
    peers = {"robot1": {"present": False}, "robot2": {"present": True}}
    lines = render_status({"poses": poses, "peers": peers}).splitlines()
    assert next(ln for ln in lines if ln.strip().startswith("robot1 ") and "map " in ln).endswith(
        "age 40s  (not heard now)"
    )
    assert next(ln for ln in lines if ln.strip().startswith("robot2 ") and "map " in ln).endswith("age 90s")
