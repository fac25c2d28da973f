"""Attacks on a running fleet, with real daemons over zenoh and a rogue zenoh process beside them.

Each attack was measured on main before the fleet was signed per robot (see docs/security.md); each
test asserts what the user wants instead: transfers go on, maps stay right, nothing is locked out,
and robots that are not on the roster cost nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import signal
import subprocess
import time
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from mapd import envelope as envelope_mod
from mapd.codec import encode
from mapd.daemon.versions import make, split
from mapd.demo.fleet import Fleet, write_config
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import Identity, read_identity

pytestmark = pytest.mark.slow
FLEET = "demo"


def start_fleet(tmp: Path, *, extra_roster: dict[str, str] | None = None) -> Fleet:
    """The demo's two signed robots over zenoh; ``extra_roster`` adds robots to every roster."""
    args = argparse.Namespace(
        robots=2, transport="zenoh", codec="lossless", log=None, seed=7, out=tmp, duration=60.0
    )
    f = Fleet(args)
    f.prepare()
    if extra_roster:
        for name in f.names:
            path = f.run_dir / name / "config.toml"
            cfg = tomllib.loads(path.read_text())
            cfg["fleet"]["roster"].update(extra_roster)
            write_config(path, cfg)
    f.start()
    return f


def envelope(robot: str, version: int, signer: Identity | None = None) -> Envelope:
    grid = OccupancyGrid(np.full((40, 60), -1, np.int8), 0.05)
    grid.data[5:35, 5:55] = 0
    grid.data[5, 5:55] = 100
    env = Envelope(
        fleet=FLEET,
        robot=robot,
        version=version,
        base_version=0,
        codec="raw",
        width=grid.width,
        height=grid.height,
        resolution=grid.resolution,
        origin=Pose2D(0.0, 0.0, 0.0),
        seq=1,
        payload=encode(grid, "raw"),
    )
    return env.signed(signer) if signer is not None else env


def forged(env: Envelope, key_holder: Identity) -> Envelope:
    """``env`` with a valid Ed25519 signature over its exact fields, made with another robot's key."""
    return dataclasses.replace(env, sig=key_holder.sign(envelope_mod._signed_blob(env._fields())))


def rogue_session(f: Fleet) -> Any:
    """A zenoh peer connected to robot0's endpoint: an outsider on the Wi-Fi (or a key holder)."""
    import zenoh

    cfg = tomllib.loads((f.run_dir / "robot0" / "config.toml").read_text())
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps(cfg["transports"]["zenoh"]["listen"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def test_forgeries_impersonation_fake_presence_and_ghosts_change_nothing(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    mallory = Identity.generate("mallory")  # on the roster: a robot of the fleet whose key leaked
    f = start_fleet(tmp_path, extra_roster={"mallory": mallory.public_text})
    robot1 = read_identity(f.run_dir / "keys" / "robot1.key", "robot1")
    try:
        snaps = fk.wait_for(
            lambda s: fk.version(s, "robot0", "robot1") > 0 and fk.version(s, "robot1", "robot0") > 0, 90, f
        )
        real = fk.version(snaps, "robot0", "robot1")
        incarnation = split(real)[0]
        top = make(incarnation, (1 << 32) - 1)  # the largest version robot1 could ever reach
        with rogue_session(f) as z:
            tokens = [z.liveliness().declare_token(f"mapd/{FLEET}/ghost{i}") for i in range(64)]
            tokens.append(z.liveliness().declare_token(f"mapd/{FLEET}/mallory"))  # on the roster, silent
            time.sleep(1.0)
            for _ in range(3):
                # as robot1, unsigned; as robot1, signed by mallory (a key holder writing as another);
                # robot1's name on mallory's key expression; made-up robots (unsigned and self-signed)
                z.put(f"mapd/{FLEET}/robot1/update", envelope("robot1", top).pack())
                z.put(f"mapd/{FLEET}/robot1/update", forged(envelope("robot1", top), mallory).pack())
                z.put(f"mapd/{FLEET}/mallory/update", forged(envelope("robot1", top), mallory).pack())
                for i in range(3):
                    z.put(f"mapd/{FLEET}/ghost{i}/update", envelope(f"ghost{i}", 7).pack())
                    ghost = Identity.generate(f"ghost{i}")
                    z.put(f"mapd/{FLEET}/ghost{i}/update", envelope(f"ghost{i}", 8, ghost).pack())
                time.sleep(0.3)
            # robot1's real maps keep arriving while 65 fake robots are "present": the publisher
            # waits for none of them (only robots that showed a valid signed message count)
            snaps = fk.wait_for(
                lambda s: (
                    split(fk.version(s, "robot0", "robot1"))[1] >= split(real)[1] + 3
                    and split(fk.version(s, "robot1", "robot0"))[1] >= 3
                ),
                60,
                f,
            )
            for t in tokens:
                t.undeclare()
        r0 = snaps["robot0"]
        assert split(r0["peers"]["robot1"]["version"])[0] == incarnation  # robot1's own versions only
        assert r0["links"]["zenoh"]["bad_signature"] >= 6, r0["links"]["zenoh"]
        assert r0["links"]["zenoh"]["peers"] == ["robot1"]  # the publisher waits for robot1 alone
        assert set(r0["peers"]) <= {"robot1", "mallory"}, r0["peers"]  # no ghost is tracked
        assert not any(p.startswith("ghost") for p in os.listdir(f.run_dir / "robot0" / "state" / "peers"))
        # robot0 restarts: robot1's next versions are still taken (nothing was locked in)
        os.kill(f.procs["robot0"].pid, signal.SIGTERM)
        assert f.procs["robot0"].wait(15) == 0
        before = fk.version(snaps, "robot0", "robot1")
        fk.restart(f, "robot0")
        fk.wait_for(lambda s: fk.version(s, "robot0", "robot1") > before, 60, f)
        # a version jump signed by robot1's own key (a bug, or the key in wrong hands) is refused,
        # and robot1's real maps still follow
        with rogue_session(f) as z:
            jump = make(incarnation, split(before)[1] + 1_000_000)
            time.sleep(1.0)
            z.put(f"mapd/{FLEET}/robot1/update", envelope("robot1", jump, robot1).pack())
            snaps = fk.wait_for(lambda s: s["robot0"]["counters"].get("refused_versions", 0) >= 1, 30, f)
        after = fk.version(snaps, "robot0", "robot1")
        assert after < jump
        fk.wait_for(lambda s: after < fk.version(s, "robot0", "robot1") < jump, 60, f)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    for name in f.names:
        log = (f.run_dir / name / "daemon.log").read_text(errors="replace")
        assert "Traceback" not in log, log[-3000:]


def test_a_robot_that_lost_its_disk_is_heard_at_once(tmp_path: Path, fk: SimpleNamespace) -> None:
    f = start_fleet(tmp_path)
    try:
        snaps = fk.wait_for(lambda s: split(fk.version(s, "robot0", "robot1"))[1] >= 5, 120, f)
        old = fk.version(snaps, "robot0", "robot1")
        os.kill(f.procs["robot1"].pid, signal.SIGKILL)
        f.procs["robot1"].wait(10)
        state = f.run_dir / "robot1" / "state"
        subprocess.run(["rm", "-rf", str(state)], check=True)  # a new SD card
        state.mkdir()
        time.sleep(1.1)  # incarnations count seconds
        fk.restart(f, "robot1")
        t0 = time.monotonic()
        # its first new map (number 1 of a new incarnation) is newer than all the old ones
        snaps = fk.wait_for(lambda s: split(fk.version(s, "robot0", "robot1"))[0] > split(old)[0], 60, f)
        took = time.monotonic() - t0
        assert split(fk.version(snaps, "robot0", "robot1"))[1] < split(old)[1]  # it counts again from 1
        assert snaps["robot0"]["counters"]["new_incarnations"] >= 1
        assert took < 45, took  # heard as soon as its first map arrives, not after passing the old count
    finally:
        codes = f.stop()
    assert codes["robot0"] == 0
