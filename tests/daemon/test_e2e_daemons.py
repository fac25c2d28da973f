"""Real daemons as processes: over zenoh and over socat through the fault relay, status, SIGTERM, kill -9."""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.commands.status_text import render_status
from mapd.daemon.state_lock import lock_state_dir
from mapd.daemon.versions import split
from mapd.demo.fleet import Fleet
from mapd.identity import Identity

#: The uwb cases run the daemons over socat pty pairs through the fault relay.
needs_socat = pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")

pytestmark = pytest.mark.slow


def num(version: int) -> int:
    """How many versions a robot made in its incarnation (versions carry it in their high bits)."""
    return split(version)[1]


def fleet(tmp: Path, transport: str, duration: float = 30.0, robots: int = 2) -> Fleet:
    args = argparse.Namespace(
        robots=robots, transport=transport, codec="lossless", log=None, seed=7, out=tmp, duration=duration
    )
    f = Fleet(args)
    f.prepare()
    return f


def holds_each_other(snaps: dict[str, dict[str, Any]], min_version: int = 3) -> bool:
    return len(snaps) == 2 and all(
        any(num(p.get("version", 0)) >= min_version for p in s.get("peers", {}).values())
        for s in snaps.values()
    )


PAIRS = (("robot0", "robot1"), ("robot1", "robot0"))


def _placed_pose(snaps: dict[str, Any], holder: str, robot: str) -> dict[str, Any] | None:
    """``robot``'s pose as ``holder`` knows it, if placed in the fleet frame."""
    p = ((snaps.get(holder, {}).get("poses") or {}).get("robots") or {}).get(robot)
    return p if isinstance(p, dict) and p.get("fleet") else None


@pytest.mark.parametrize("transport", ["zenoh", pytest.param("uwb", marks=needs_socat)])
def test_two_daemons_exchange_and_fuse(tmp_path: Path, transport: str, fk: SimpleNamespace) -> None:
    f = fleet(tmp_path, transport)
    f.start()
    try:
        snaps = fk.wait_for(holds_each_other, 90, f)
        # mapd status --json against a live daemon, as a user runs it
        sock = f.run_dir / "robot0" / "run" / "mapd.sock"
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--json", "--socket", str(sock)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert out.returncode == 0, out.stderr
        doc = json.loads(out.stdout)
        assert doc["robot"] == "robot0" and "robot1" in doc["peers"]
        assert doc["codec"]["deltas"] + doc["codec"]["keyframes"] >= 3
        # the peer acked our maps, so the link knows its round-trip time
        assert doc["peers"]["robot1"]["acked_our_version"] >= 1
        assert doc["peers"]["robot1"]["restored"] is False  # a live peer's map came over the link
        assert doc["links"][transport]["rtt_ms"] > 0
        fk.wait_for(lambda s: all(x.get("fusion", {}).get("maps", 0) >= 2 for x in s.values()), 60, f)
        # each robot's pose reached the other (signed, over the same link), placed in the fleet frame
        snaps = fk.wait_for(lambda s: all(_placed_pose(s, a, b) for a, b in PAIRS), 90, f)
        for holder, robot in PAIRS:
            p = _placed_pose(snaps, holder, robot)
            assert p is not None and p["age_s"] < 60
            g = snaps[holder]["fusion"]["global"]
            x0, y0 = g["origin"]["x"], g["origin"]["y"]  # inside the global map the robots are building
            assert x0 <= p["fleet"][0] <= x0 + g["width"] * g["resolution"], (p, g)
            assert y0 <= p["fleet"][1] <= y0 + g["height"] * g["resolution"], (p, g)
        text = fk.status_text(sock)
        assert "poses" in text and "robot1" in text
    finally:
        codes = f.stop(timeout=10)
    assert codes == {"robot0": 0, "robot1": 0}
    for name in f.names:
        assert (f.run_dir / name / "state" / "global" / "global.yaml").exists()


def test_sigterm_exits_cleanly_within_2s(tmp_path: Path, fk: SimpleNamespace) -> None:
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        fk.wait_for(lambda s: len(s) == 2 and all(x.get("peers") for x in s.values()), 60, f)
        p = f.procs["robot0"]
        t0 = time.monotonic()
        p.send_signal(signal.SIGTERM)
        assert p.wait(10) == 0
        assert time.monotonic() - t0 < 2.0
        assert not (f.run_dir / "robot0" / "run" / "mapd.sock").exists()
    finally:
        f.stop()


def test_kill_9_and_restart_resumes(tmp_path: Path, fk: SimpleNamespace) -> None:
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        fk.wait_for(holds_each_other, 90, f)
        # the crash must find a global map already written, so that there is one to restore
        fk.wait_for(lambda s: s.get("robot0", {}).get("fusion", {}).get("global") is not None, 60, f)
        before = f.status()["robot0"]
        v_own = before["source"]["version"]
        fk.kill9(f, "robot0")
        state = json.loads((f.run_dir / "robot0" / "state" / "state.json").read_text())
        assert state["own_version"] >= v_own - 1 and "robot1" in state["peers"]
        fk.restart(f, "robot0")  # the same daemon with the same state directory
        # The peer's map is restored before the status socket opens; the global map by the fusion
        # task, a little after it: wait for both.
        snaps = fk.wait_for(
            lambda s: (
                "robot0" in s
                and s["robot0"]["peers"].get("robot1", {}).get("version", 0) > 0
                and s["robot0"]["fusion"]["global"] is not None
            ),
            60,
            f,
        )
        after = snaps["robot0"]
        # it held the peer's map and the global map from before the crash, and its versions keep rising
        assert after["fusion"]["global"] is not None
        held = after["peers"]["robot1"]
        # at least the version the state directory held at the crash (received after it: newer)
        assert held["version"] >= state["peers"]["robot1"]["version"]
        assert held["restored"] == ("age_s" not in held)  # status says where the map came from
        snaps = fk.wait_for(
            lambda s: "robot0" in s and s["robot0"]["source"]["version"] > state["own_version"], 60, f
        )
        # the peer accepts the restarted robot's new versions (never a stale or repeated one)
        fk.wait_for(
            lambda s: (
                s.get("robot1", {}).get("peers", {}).get("robot0", {}).get("version", 0)
                > state["own_version"]
            ),
            60,
            f,
        )
    finally:
        codes = f.stop()
    assert codes["robot1"] == 0


@pytest.mark.parametrize("case", ["serial port", "key file", "state dir", "no key", "state in use"])
def test_bad_config_is_one_line(tmp_path: Path, case: str) -> None:
    (tmp_path / "file").write_text("x")
    # a port that is there but is no serial port (one not there yet is waited for: test_uwb_serial);
    # the other cases name one not there, which the config check (and so mapd run) takes
    port = str(tmp_path / ("file" if case == "serial port" else "no-such-tty"))
    state = tmp_path / "file" / "state" if case == "state dir" else tmp_path / "s"
    me = Identity.generate("a")
    me.write(tmp_path / "a.key")
    (tmp_path / "link.key").write_text("ab" * 32)
    key = {"key file": tmp_path / "no-such.key", "no key": None}.get(case, tmp_path / "a.key")
    key_line = f'key_file = "{key}"\n' if key else ""
    fleet = f'[fleet]\nlink_key_file = "{tmp_path / "link.key"}"\n[fleet.roster]\na = "{me.public_text}"\n'
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[robot]\nname = "a"\n{key_line}[source]\nuse = "sim"\n[transports]\nuse = ["uwb"]\n'
        f'[transports.uwb]\nport = "{port}"\n[transports.uwb.nodes]\na = 1\nb = 2\n'
        f'[state]\ndir = "{state}"\nruntime_dir = "{tmp_path / "r"}"\n{fleet}'
    )
    # another daemon (here this process) holds the state directory
    held = lock_state_dir(state) if case == "state in use" else None
    try:
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "run", "--config", str(cfg)],
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        if held is not None:
            os.close(held)
    assert out.returncode != 0
    lines = [ln for ln in out.stderr.splitlines() if ln.startswith("mapd: error:")]
    expect = {
        # refused by the check mapd check-config runs too, before the daemon starts anything
        "serial port": f"transports.uwb.port: {tmp_path / 'file'} is not a serial device",
        "key file": "no-such.key",
        "state dir": f"state.dir: {tmp_path / 'file'} is not a folder",
        "no key": "a signed fleet needs this robot's key",
        "state in use": f"is in use by another mapd (pid {os.getpid()})",
    }[case]
    assert len(lines) == 1 and expect in lines[0], out.stderr
    assert "Traceback" not in out.stderr


def test_second_sigint_forces_exit(tmp_path: Path, fk: SimpleNamespace) -> None:
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        fk.wait_for(lambda s: len(s) == 2, 60, f)
        p = f.procs["robot0"]
        p.send_signal(signal.SIGINT)
        p.send_signal(signal.SIGINT)
        code = p.wait(10)
        # 0 if the drain finished between the two signals, else 130 from the forced exit; never a hang
        assert code in (0, 130)
        assert f.procs["robot1"].poll() is None
    finally:
        f.stop()


def test_sigusr1_writes_every_thread_stack_and_the_daemon_runs_on(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    # A daemon that hangs (in a stop that never ends, or in a driver) shows where with
    # `systemctl kill -s USR1 mapd`; the fleet harness does it to a daemon that will not stop.
    f = fleet(tmp_path, "zenoh")
    f.start()
    try:
        fk.wait_for(lambda s: len(s) == 2, 60, f)
        log = f.run_dir / "robot0" / "daemon.log"
        f.procs["robot0"].send_signal(signal.SIGUSR1)
        deadline = time.monotonic() + 10
        while "mapd/daemon/process.py" not in log.read_text(errors="replace") and time.monotonic() < deadline:
            time.sleep(0.1)
        text = log.read_text(errors="replace")
        assert "Current thread" in text
        assert text.count("Thread 0x") >= 2 and "mapd/daemon/process.py" in text
        before = fk.held(f.status(), "robot0", "robot1")
        fk.wait_for(lambda s: fk.held(s, "robot0", "robot1") > before, 60, f)  # still at work
        # systemd's watchdog kills a daemon that stopped answering with SIGABRT: where it hung goes
        # to the journal too (before, it died without a word of where)
        f.procs["robot1"].send_signal(signal.SIGABRT)
        assert f.procs["robot1"].wait(10) == -signal.SIGABRT
        text = (f.run_dir / "robot1" / "daemon.log").read_text(errors="replace")
        assert "Fatal Python error: Aborted" in text and text.count("Thread 0x") >= 2, text[-2000:]
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": -signal.SIGABRT}


def _final_maps(f: Fleet) -> dict[str, Any]:
    """Each robot's last map, from its own deterministic sim run flat out (no daemon, no link)."""
    import asyncio

    from mapd import config, plugins
    from mapd.sources.base import SourceContext

    async def last(i: int, name: str) -> Any:
        tables = f._source_tables(i)
        cls = plugins.load("source", "sim")
        opts = config.validate(cls.Options, {**tables["source.sim"], "realtime": 0.0}, "test")
        maps = [grid async for grid in cls(opts, SourceContext(robot=name)).maps()]
        return maps[-1]

    return {name: asyncio.run(last(i, name)) for i, name in enumerate(f.names)}


def _same_on_lattice(a: Any, b: Any) -> str | None:
    """None if two global maps agree cell for cell on the fleet lattice (unknown outside each), else why."""
    import numpy as np

    res = a.resolution
    if abs(a.resolution - b.resolution) > 1e-12:
        return f"resolutions differ: {a.resolution} vs {b.resolution}"
    off = [(o2 - o1) / res for o1, o2 in ((a.origin.x, b.origin.x), (a.origin.y, b.origin.y))]
    if any(abs(o - round(o)) > 1e-6 for o in off):
        return f"origins are not on one lattice: {a.origin} vs {b.origin}"
    dc, dr = (round(o) for o in off)  # b's cell (r, c) is a's cell (r + dr, c + dc)
    r0, c0 = min(0, dr), min(0, dc)
    r1, c1 = max(a.height, dr + b.height), max(a.width, dc + b.width)
    big_a = np.full((r1 - r0, c1 - c0), -1, np.int8)
    big_b = big_a.copy()
    big_a[-r0 : -r0 + a.height, -c0 : -c0 + a.width] = a.data
    big_b[dr - r0 : dr - r0 + b.height, dc - c0 : dc - c0 + b.width] = b.data
    diff = int((big_a != big_b).sum())
    return None if diff == 0 else f"{diff} cells differ of {int((big_a >= 0).sum())} known"


@needs_socat
def test_uwb_faults_and_kill_9_mid_transfer_converge_to_the_fault_free_map(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """Over a lossy, bit-flipping link with an outage, robot0 is killed mid-transfer and restarted.

    Both sims are finite and deterministic, so the fault-free answer is known without a link: the
    merge of each robot's last map at the configured start poses. Both daemons must end there.
    """
    from mapd.fusion.merge import merge
    from mapd.grid import Pose2D
    from mapd.grid.load import load_map

    args = argparse.Namespace(
        robots=2, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0,
        drop=0.03, flip=1e-3, outage=["6:2"],
    )  # fmt: skip
    f = Fleet(args, sim_options={"duration": 60.0})
    f.prepare()
    f.start()
    try:
        # Kill robot0 while a map of its own is in flight on the serial link.
        def mid_transfer(s: dict[str, dict[str, Any]]) -> bool:
            r0 = s.get("robot0", {})
            link = r0.get("links", {}).get("uwb", {})
            return num(r0.get("source", {}).get("version", 0)) >= 3 and link.get("in_flight", 0) > 0

        fk.wait_for(mid_transfer, 90, f)
        fk.kill9(f, "robot0")
        fk.restart(f, "robot0")

        def exchanged_final(s: dict[str, dict[str, Any]]) -> bool:
            return len(s) == 2 and all(
                s[me]["source"].get("finished")
                and s[other]["peers"].get(me, {}).get("version") == s[me]["source"]["version"]
                for me, other in (("robot0", "robot1"), ("robot1", "robot0"))
            )

        snaps = fk.wait_for(exchanged_final, 150, f)
        final = _final_maps(f)
        poses = {r: Pose2D(*p) for r, p in f._start_poses().items()}
        expected = merge([final[r] for r in f.names], [poses[r] for r in f.names], "logodds")
        why: dict[str, str | None] = {}
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:  # the fusion worker debounces: give it a moment
            for name in f.names:
                got = load_map(f.run_dir / name / "state" / "global" / "global.yaml")
                why[name] = _same_on_lattice(expected, got)
            if not any(why.values()):
                break
            time.sleep(1.0)
        assert not any(why.values()), why
        links = [snaps[name]["links"]["uwb"] for name in f.names]
        assert sum(x["resends"] for x in links) > 0  # the faults cost resends ...
        # ... and were caught: by the CRC unsigned, by the tag signed, or by the parser
        caught = ("crc_errors", "bad_signature", "bad_frames")
        assert sum(x.get(k, 0) for x in links for k in caught) > 0
    finally:
        codes = f.stop()
    assert codes["robot1"] == 0
    stats = json.loads((f.run_dir / "uwb" / "relay-stats.json").read_text())
    assert stats["dropped"] > 0 and stats["flipped_bits"] > 0


@needs_socat
def test_one_daemon_runs_uwb_to_one_robot_and_zenoh_to_another(tmp_path: Path, fk: SimpleNamespace) -> None:
    """robot0 talks UWB (socat + relay) to robot1 and zenoh to robot2, both at once."""
    import tomllib

    from mapd.demo.fleet import write_config

    f = fleet(tmp_path, "zenoh", robots=3)
    relay = subprocess.Popen(
        [sys.executable, "-m", "transports.uwb.relay", "--robots", "2", "--dir", str(tmp_path / "uwb")],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    assert relay.stdout is not None
    ports = [relay.stdout.readline().split(":", 1)[1].strip() for _ in range(2)]
    cfgs = {n: tomllib.loads((f.run_dir / n / "config.toml").read_text()) for n in f.names}
    zenoh = {n: cfgs[n]["transports"]["zenoh"] for n in f.names}
    nodes = {"robot0": 1, "robot1": 2}
    cfgs["robot0"]["transports"] = {
        "use": ["uwb", "zenoh"],
        "uwb": {"port": ports[0], "nodes": nodes},
        "zenoh": {**zenoh["robot0"], "connect": zenoh["robot2"]["listen"]},
    }
    cfgs["robot1"]["transports"] = {"use": ["uwb"], "uwb": {"port": ports[1], "nodes": nodes}}
    cfgs["robot2"]["transports"] = {"use": ["zenoh"], "zenoh": {**zenoh["robot2"], "connect": []}}
    for n, c in cfgs.items():
        write_config(f.run_dir / n / "config.toml", c)
    f.start()
    try:

        def holds(s: dict[str, dict[str, Any]], who: str, of: str) -> bool:
            return num(s.get(who, {}).get("peers", {}).get(of, {}).get("version", 0)) >= 2

        snaps = fk.wait_for(
            lambda s: (
                holds(s, "robot0", "robot1")
                and holds(s, "robot0", "robot2")
                and holds(s, "robot1", "robot0")
                and holds(s, "robot2", "robot0")
            ),
            120,
            f,
        )
        r0 = snaps["robot0"]
        assert set(r0["links"]) == {"uwb", "zenoh"}
        assert r0["peers"]["robot1"]["link"] == "uwb" and r0["peers"]["robot2"]["link"] == "zenoh"
        # robot1 and robot2 share no link: neither hears the other directly
        assert "robot2" not in snaps["robot1"]["peers"]
    finally:
        codes = f.stop()
        relay.terminate()
        relay.wait(10)
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}


@needs_socat
def test_a_robot_out_of_range_gets_maps_through_a_relaying_daemon(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """Three daemons on one emulated UWB channel where robot0 and robot2 never hear each other:
    robot1, which hears both, forwards each one's signed maps to the other (multi-hop relay), so
    both hold each other's maps although no frame of either ever reaches the other."""
    args = argparse.Namespace(
        robots=3, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=40.0,
        out_of_range=["0-2"],
    )  # fmt: skip
    f = Fleet(args, sim_options={"duration": 40.0})
    f.prepare()
    f.start()

    def relayed(s: dict[str, dict[str, Any]]) -> bool:
        return len(s) == 3 and all(
            num(s[a].get("peers", {}).get(b, {}).get("version", 0)) >= 2
            for a, b in (("robot0", "robot2"), ("robot2", "robot0"))
        )

    try:
        snaps = fk.wait_for(relayed, 150, f)
        hop = snaps["robot1"]["links"]["uwb"]
        assert hop["relays_tx"] >= 2 and hop["relay_summaries_rx"] > 0
        # and mapd status says it, on a line of the link's own
        said = [ln.strip() for ln in fk.status_text(f.run_dir / "robot1" / "run" / "mapd.sock").splitlines()]
        relay = next((ln for ln in said if ln.startswith("relay   forwarded ")), None)
        assert relay is not None and int(relay.split()[2]) >= 2 and "summaries" in relay, said
        # TDMA with lending (the default): idle slots' rests went to robots with chunks left
        links = [snaps[r]["links"]["uwb"] for r in ("robot0", "robot1", "robot2")]
        assert sum(u["lends_tx"] for u in links) > 0 and sum(u["borrowed"] for u in links) > 0
        for a, b in (("robot0", "robot2"), ("robot2", "robot0")):
            heard = snaps[a]["links"]["uwb"]["peers"]
            assert "robot1" in heard and b not in heard  # b's map came, but b was never heard directly
            assert snaps[a]["peers"][b]["relayed_by"] == "robot1"  # and mapd status says through whom
            assert "relayed_by" not in snaps[a]["peers"]["robot1"]
        shown = fk.status_text(f.run_dir / "robot0" / "run" / "mapd.sock")
        assert any(
            ln.split()[0] == "robot2" and "via uwb (relayed by robot1)" in ln
            for ln in shown.splitlines()
            if ln.strip()
        ), shown
    finally:
        f.stop()
    stats = json.loads((f.run_dir / "uwb" / "relay-stats.json").read_text())
    assert stats["unheard"] > 0  # the emulated radio did keep robot0's and robot2's frames apart


THREE = ("robot0", "robot1", "robot2")


def _three_whole_map_daemons(args: argparse.Namespace) -> Fleet:
    """Three daemons started on the emulated radio ``args`` asks for, every version a whole map
    (several turns of a slot each)."""
    f = Fleet(args, sim_options={"duration": 40.0})
    f.prepare()
    for r in THREE:
        cfg = f.run_dir / r / "config.toml"
        cfg.write_text(cfg.read_text().replace("keyframe_every = 10", "keyframe_every = 1"))
    f.start()
    return f


def _all_hold_three(s: dict[str, dict[str, Any]], least: int = 3) -> bool:
    """Each of the three holds at least the ``least``-th map of each other."""
    return len(s) == 3 and all(
        num(s[a].get("peers", {}).get(b, {}).get("version", 0)) >= least
        for a in THREE
        for b in THREE
        if a != b
    )


@needs_socat
def test_three_daemons_share_one_tdma_channel_where_overlapping_frames_garble(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """The emulated radio garbles frames that overlap in the air (``--collisions``) and sends each
    robot's frames one at a time, as a radio does. Three daemons on TDMA with turn lending, every
    version a whole map (several turns each), exchange their maps, and their frames do not overlap:
    each robot counts its slot from the end of its own last frame, not from when the serial write
    drained, and a robot named in a LEND sends only in the rest of that slot. Before the first, a
    fifth of the frames overlapped. The radio times frames by when it reads them, so a loaded machine may
    see a rare overlap: the bound is 2 % of frames."""
    args = argparse.Namespace(
        robots=3, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=40.0,
        collisions=True,
    )  # fmt: skip
    f = _three_whole_map_daemons(args)
    try:
        # the fifth map of each: enough frames for the bound to mean something on a loaded machine
        # too (the third gave 100 to 150 frames)
        snaps = fk.wait_for(lambda s: _all_hold_three(s, 5), 150, f)
    finally:
        f.stop()
    stats = json.loads((f.run_dir / "uwb" / "relay-stats.json").read_text())
    sent = sum(p["frames_in"] for p in stats["ports"])  # frames the robots wrote
    assert sent > 100
    assert stats["collided"] <= sent // 50, stats
    # Their clocks agree, so none hears another in its own slot (R18), within the same bound: the
    # count is no false alarm on real serial lines (tests/transports/uwb/test_uwb_clock.py skews one).
    heard_out_of_turn = sum(snaps[r]["links"]["uwb"]["out_of_turn"] for r in THREE)
    assert heard_out_of_turn <= sent // 50, heard_out_of_turn


@needs_socat
def test_three_daemons_repair_lossy_broadcasts_with_parity(tmp_path: Path, fk: SimpleNamespace) -> None:
    """An emulated radio that loses 15 % of frames: each robot's maps go to the two others at once (a
    broadcast, gap reports and COMPLETEs: R16), and with ``fec`` on (the default) the repairs are
    parity chunks, each of use to both receivers. Every robot gets the others' maps, some chunks are
    rebuilt from parity, and no rebuilt map fails its hash."""
    args = argparse.Namespace(
        robots=3, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=40.0, drop=0.15
    )
    f = _three_whole_map_daemons(args)
    try:
        snaps = fk.wait_for(_all_hold_three, 150, f)
    finally:
        f.stop()
    links = [snaps[r]["links"]["uwb"] for r in THREE]
    assert sum(link["parity_tx"] for link in links) > 0
    # `mapd status` shows them among the first figures of the link's line
    sender = max(THREE, key=lambda r: snaps[r]["links"]["uwb"]["parity_tx"])
    line = next(x for x in render_status(snaps[sender]).splitlines() if x.strip().startswith("uwb"))
    assert f"parity_tx={snaps[sender]['links']['uwb']['parity_tx']}" in line and "recovered=" in line
    assert sum(link["recovered"] for link in links) > 0
    assert sum(link["hash_errors"] for link in links) == 0
    stats = json.loads((f.run_dir / "uwb" / "relay-stats.json").read_text())
    assert stats["dropped"] > 0


@needs_socat
def test_a_robot_that_joins_late_over_uwb_gets_a_map_that_no_longer_changes(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """robot0 maps, finishes, and its last map's send gives up (deadline_s 5 s) before robot1 even
    starts: robot0 offers it again when it first hears robot1 (P6), where a zenoh peer would query
    the late joiner's keyframe."""
    args = argparse.Namespace(
        robots=2, transport="uwb", codec="lossless", log=None, seed=7, out=tmp_path, duration=15.0
    )
    f = Fleet(args, sim_options={"duration": 15.0})
    f.prepare()
    cfg = f.run_dir / "robot0" / "config.toml"
    cfg.write_text(cfg.read_text().replace("[transports.uwb]\n", "[transports.uwb]\ndeadline_s = 5.0\n", 1))
    f.start(only=["robot0"])
    try:
        snaps = fk.wait_for(lambda s: s.get("robot0", {}).get("source", {}).get("finished"), 60, f)
        final = snaps["robot0"]["source"]["version"]
        # its last send gives up on robot1 (5 s, or twice its airtime; later on a loaded machine:
        # a fixed 8 s wait was once too short in a full run)
        snaps = fk.wait_for(
            lambda s: s.get("robot0", {}).get("links", {}).get("uwb", {}).get("messages_failed"), 60, f
        )
        before = snaps["robot0"]
        assert before["links"]["uwb"]["messages_failed"] > 0
        f.start(only=["robot1"])
        snaps = fk.wait_for(
            lambda s: s.get("robot1", {}).get("peers", {}).get("robot0", {}).get("version") == final, 60, f
        )
        assert snaps["robot0"]["source"]["version"] == final  # robot0 made nothing new meanwhile
        assert snaps["robot0"]["codec"]["keyframes"] > before["codec"]["keyframes"]  # offered again
        assert snaps["robot0"]["codec"]["reoffers"] > before["codec"]["reoffers"] == 0
        assert snaps["robot1"]["links"]["uwb"]["keyframe_requests_tx"] == 0  # unasked
    finally:
        f.stop()


@needs_socat
def test_a_radio_not_there_at_start_leaves_the_other_link_running(tmp_path: Path) -> None:
    """A robot with UWB and zenoh whose radio the kernel has not named yet at boot: the daemon
    runs, zenoh carries its map, and it says what it lacks (it stopped, zenoh and all, before)."""
    from mapd.demo.ports import free_endpoint
    from mapd.grid.save import save_map
    from mapd.mapping.synthetic import room_grid

    here = free_endpoint()
    procs = {}
    for name, uses, zenoh in (
        ("a", '["uwb", "zenoh"]', f'listen = ["{here}"]'),
        ("b", '["zenoh"]', f'connect = ["{here}"]'),
    ):
        root = tmp_path / name
        root.mkdir()
        save_map(room_grid(60, 80, seed=len(procs)), root / "map.yaml")
        (root / "config.toml").write_text(
            f'[robot]\nname = "{name}"\n[fleet]\nallow_unsigned = true\n'
            '[source]\nuse = "mapfile"\n[source.mapfile]\npath = "map.yaml"\npoll_s = 0.1\nsettle_s = 0.1\n'
            '[codec]\nuse = "raw"\n[state]\ndir = "state"\nruntime_dir = "run"\n'
            f'[transports]\nuse = {uses}\n[transports.zenoh]\nmode = "peer"\n{zenoh}\n'
            "multicast_scouting = false\n"
            f'[transports.uwb]\nport = "{tmp_path / "no-radio-yet"}"\nreopen_s = 0.2\n'
            "[transports.uwb.nodes]\na = 1\nb = 2\n"
        )
        with (root / "log").open("wb") as log:
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "mapd", "run", "--config", str(root / "config.toml")],
                stdout=log,
                stderr=subprocess.STDOUT,
            )

    def status(name: str, *flags: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [
                sys.executable,
                "-m",
                "mapd",
                "status",
                *flags,
                "--config",
                str(tmp_path / name / "config.toml"),
            ],
            capture_output=True,
            text=True,
            timeout=30,
        )

    try:
        end = time.monotonic() + 60
        while True:
            for name, p in procs.items():
                assert p.poll() is None, (tmp_path / name / "log").read_text()[-2000:]
            got = status("b", "--json")
            if got.returncode == 0 and (json.loads(got.stdout)["peers"].get("a") or {}).get("version"):
                break
            assert time.monotonic() < end, "b never got a's map over zenoh"
            time.sleep(0.3)
        a = json.loads(status("a", "--json").stdout)
        assert a["links"]["uwb"]["port_open"] is False and a["links"]["zenoh"]["peers"] == ["b"]
        assert "FAULTS serial port closed (reopening)" in status("a").stdout
        for p in procs.values():
            p.send_signal(signal.SIGTERM)
        assert [p.wait(30) for p in procs.values()] == [0, 0]
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(10)
