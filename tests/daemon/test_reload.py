"""``systemctl reload mapd`` (SIGHUP): the roster comes from the config again; the rest waits for a restart."""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd import config as configmod
from mapd.commands.status_text import render_status
from mapd.daemon import reload
from mapd.daemon.server import Daemon
from mapd.daemon.state import StateStore
from mapd.errors import ConfigError
from mapd.files import reading
from mapd.identity import Identity


def _drop_roster_line(path: Path, robot: str) -> None:
    text = path.read_text()
    kept = re.sub(rf'^{robot} = "ed25519:[^"]*"\n?', "", text, flags=re.M)
    assert kept != text, f"no roster line for {robot}"
    path.write_text(kept)


def _virtual(dk: SimpleNamespace, tmp_path: Path, robot: str, channel: str, codec: str = "lossless") -> Path:
    return dk.write_config(  # type: ignore[no-any-return]
        tmp_path,
        robot,
        codec=codec,
        extra='[transports]\nuse = ["virtual"]\n',
        **{"transports.virtual": f'channel = "{channel}"'},
    )


def test_plan_names_roster_changes_and_what_needs_a_restart(tmp_path: Path, dk: SimpleNamespace) -> None:
    path = _virtual(dk, tmp_path, "robot0", "c")
    running = configmod.load(path)
    _drop_roster_line(path, "robot1")
    text = path.read_text().replace('use = "lossless"', 'use = "zstd"')
    other = Identity.generate("robot2").public_text
    text = re.sub(r'^robot2 = "[^"]*"', f'robot2 = "{other}"', text, flags=re.M)
    added = f'robot9 = "{Identity.generate("robot9").public_text}"'
    path.write_text(text.replace("[fleet.roster]\n", f"[fleet.roster]\n{added}\n"))
    p = reload.plan(running, configmod.load(path))
    assert (p.added, p.removed, p.rekeyed) == (["robot9"], ["robot1"], ["robot2"])
    assert p.restart == ["codec.use"]
    said = p.summary()
    assert "added robot9" in said and "removed robot1" in said and "new key for robot2" in said
    assert "needs a restart to take effect: codec.use" in said


def test_read_says_when_the_keys_behind_the_same_paths_changed(tmp_path: Path, dk: SimpleNamespace) -> None:
    path = _virtual(dk, tmp_path, "robot0", "c")
    running = configmod.load(path)
    keys = configmod.check(running).keys
    _, new_keys, p = reload.read(running, keys)
    assert not p.roster_changed and p.restart == [] and new_keys.roster.robots == keys.roster.robots
    # robot0 got a new key file in place (and its roster line with it): that is a restart's job
    me = Identity.generate("robot0")
    (tmp_path / "keys" / "robot0.key").unlink()
    me.write(tmp_path / "keys" / "robot0.key")
    path.write_text(
        re.sub(r'^robot0 = "[^"]*"', f'robot0 = "{me.public_text}"', path.read_text(), flags=re.M)
    )
    _, _, p = reload.read(running, keys)
    assert p.rekeyed == ["robot0"] and p.restart == ["robot.key_file (the key in it changed)"]
    # a roster key that does not parse: the whole file is refused, in one line naming the key
    path.write_text(path.read_text().replace("[fleet.roster]\n", '[fleet.roster]\nrobot9 = "x"\n'))
    with pytest.raises(ConfigError, match=r"fleet\.roster\.robot9") as err:
        reload.read(running, keys)
    assert "\n" not in str(err.value)


def test_reload_admits_an_added_robot_revokes_a_removed_one_and_refuses_a_broken_file(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    channel = dk.channel()
    path0 = _virtual(dk, tmp_path, "robot0", channel)
    _drop_roster_line(path0, "robot2")  # robot2 joins the fleet later
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    d2, s2 = dk.virtual_daemon(tmp_path, "robot2", channel)
    # robot0 never acks robot2's refused map: robot2's offer then waits out its in-flight time
    # (at least 5 s a peer) before its next version goes
    d2.publisher.inflight_timeout_s = 1.0

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d in (d0, d2)]
        try:
            await dk.wait_for(
                lambda: bool(d2.transports) and d2.transports[0].peers() == ["robot0"], what="up"
            )
            await s2.queue.put(dk.growing_map(1).replace(robot="robot2"))
            # not on robot0's roster: refused, however often it comes
            await dk.wait_for(lambda: d0.receiver.counters.bad_signature >= 1, what="robot2 refused")
            assert "robot2" not in d0.receiver.maps

            _virtual(dk, tmp_path, "robot0", channel)  # the same config, robot2 on its roster now
            assert await d0.reload()
            st = d0.snapshot()
            assert "robot2" in st["security"]["roster"]
            assert st["reload"]["count"] == 1 and st["reload"]["last_ok"] is True
            assert st["reload"]["last"] == "roster: added robot2"
            await s2.queue.put(dk.growing_map(2).replace(robot="robot2"))
            # taken in whole: held, then saved, then merged (a revocation while it is saved is
            # another case, tested in test_fusion_worker)
            await dk.wait_for(
                lambda: "robot2" in d0.receiver.maps and "robot2" in d0.fusion.status()["robots"],
                20,
                what="robot2 admitted",
            )

            # robot2's key is revoked, and the codec changed too: the roster is taken, the codec waits
            path0.write_text(path0.read_text().replace('use = "lossless"', 'use = "zstd"'))
            _drop_roster_line(path0, "robot2")
            assert await d0.reload()
            assert "robot2" not in d0.keys.roster and d0.cfg.codec.use == "lossless"
            assert d0.snapshot()["reload"]["last"] == (
                "roster: removed robot2; needs a restart to take effect: codec.use"
            )
            # What it sent goes too: its map from the peers held, the state and the global map.
            st = d0.snapshot()
            assert "robot2" not in d0.receiver.maps and "robot2" not in st["peers"]
            assert "robot2" not in d0.store.data.peers and "robot2" not in d0.fusion.status()["robots"]
            assert d0.fusion.status()["revoked"] == 1
            refused = d0.receiver.counters.bad_signature
            await s2.queue.put(dk.growing_map(3).replace(robot="robot2"))
            await dk.wait_for(lambda: d0.receiver.counters.bad_signature > refused, 20, what="revoked")
            assert "robot2" not in d0.receiver.maps

            path0.write_text("[robot\nname = ")  # a half-written file: refused whole
            assert not await d0.reload()
            st = d0.snapshot()
            assert st["reload"]["refused"] == 1 and st["reload"]["last_ok"] is False
            assert st["reload"]["last"].startswith("refused, still running on the previous config: ")
            assert str(path0) in st["reload"]["last"] and "\n" not in st["reload"]["last"]
            assert st["security"]["roster"] == ["robot0", "robot1"]
            assert "reload  3 (1 refused)" in render_status(st)
        finally:
            for d in (d0, d2):
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())


def _rekey(path: Path, robot: str) -> Identity:
    new = Identity.generate(robot)
    text = path.read_text()
    rekeyed = re.sub(rf'^{robot} = "[^"]*"', f'{robot} = "{new.public_text}"', text, flags=re.M)
    assert rekeyed != text, f"no roster line for {robot}"
    path.write_text(rekeyed)
    return new


def test_a_rekeyed_robot_is_revoked_like_a_removed_one_and_its_new_key_heard_at_once(
    tmp_path: Path, dk: SimpleNamespace, caplog: pytest.LogCaptureFixture
) -> None:
    # robot1's key leaked: the attacker signed an all-walls map at a version 23 h ahead (inside
    # the day a clock may be ahead). Re-keying robot1 kept that map held, saved and fused, and
    # every map of the real robot1, under its new key, was dropped as not newer, silently.
    import logging

    import numpy as np

    from mapd.codec import encode
    from mapd.daemon.versions import incarnation_at, make
    from mapd.envelope import Envelope
    from mapd.grid import OccupancyGrid
    from mapd.identity import read_identity
    from transports.virtual import VirtualChannel

    caplog.set_level(logging.INFO, logger="mapd")
    channel = dk.channel()
    path0 = _virtual(dk, tmp_path, "robot0", channel)
    cfg = configmod.load(path0)
    d0 = Daemon(cfg, source=dk.QueueSource("robot0"))
    leaked = read_identity(tmp_path / "keys" / "robot1.key", "robot1")
    now = time.time()
    real = make(incarnation_at(now - 3600), 5)
    forged = make(incarnation_at(now + 23 * 3600), 1)

    def env(ident: Identity, version: int, fill: int) -> Envelope:
        grid = OccupancyGrid(np.full((60, 60), fill, np.int8), 0.05)
        return Envelope(
            fleet=cfg.robot.fleet, robot="robot1", version=version, base_version=0, codec="lossless",
            width=60, height=60, resolution=0.05, origin=grid.origin, payload=encode(grid, "lossless"),
            stamp=now,
        ).signed(ident)  # fmt: skip

    def held() -> int:
        return getattr(d0.receiver.maps.get("robot1"), "version", 0)

    async def main() -> None:
        task = asyncio.create_task(d0.run())
        try:
            await dk.wait_for(lambda: bool(d0.transports), what="up")
            link = VirtualChannel.get(channel)
            link.deliver("robot1", env(leaked, real, 0))
            await dk.wait_for(lambda: held() == real, what="the real map")
            link.deliver("robot1", env(leaked, forged, 100))
            await dk.wait_for(lambda: held() == forged, what="the forged map")
            await dk.wait_for(lambda: "robot1" in d0.fusion.status()["robots"], 20, what="fused")
            # the real robot's maps under the old key are refused as not newer, and now said so
            link.deliver("robot1", env(leaked, real + 1, 0))
            await dk.wait_for(lambda: d0.receiver.counters.duplicates == 1, what="refused")

            new = _rekey(path0, "robot1")
            assert await d0.reload()
            assert d0.snapshot()["reload"]["last"] == "roster: new key for robot1"
            # What the old key signed is gone, as for a robot removed: held, state, global map.
            assert "robot1" not in d0.receiver.maps and "robot1" not in d0.snapshot()["peers"]
            assert "robot1" not in d0.store.data.peers
            assert not (cfg.state.dir / "peers" / "robot1").exists()  # no restart brings it back
            assert "robot1" not in d0.fusion.status()["robots"] and d0.fusion.status()["revoked"] == 1
            refused = d0.receiver.counters.bad_signature
            link.deliver("robot1", env(leaked, forged + 1, 100))  # the old key: refused now
            await dk.wait_for(lambda: d0.receiver.counters.bad_signature > refused, what="old key refused")
            link.deliver("robot1", env(new, real + 2, 0))  # the real robot, new key, its own versions
            await dk.wait_for(lambda: held() == real + 2, what="the new key's map")
            await dk.wait_for(lambda: "robot1" in d0.store.data.peers, what="saved")
        finally:
            d0.request_stop()
            await task

    asyncio.run(main())
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any("ahead of this robot's clock" in m and "robot1" in m for m in warnings), warnings
    assert any(m.startswith("revoked robot1's old key") for m in warnings), warnings
    again = StateStore(cfg.state.dir)
    again.open()
    back = again.peer_map("robot1")
    assert back is not None and back.version == real + 2 and int(back.data.max()) == 0


@pytest.mark.parametrize("how", ["removed", "rekeyed"])
@pytest.mark.parametrize("stage", ["decode_envelope", "save_peer"])
def test_a_map_on_its_way_in_when_its_robot_is_revoked_is_dropped(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch, stage: str, how: str
) -> None:
    # The revocation runs on the loop while the map is decoded, or saved, on a worker thread.
    import threading

    from mapd.daemon import inbound

    channel = dk.channel()
    path0 = _virtual(dk, tmp_path, "robot0", channel)
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    d2, s2 = dk.virtual_daemon(tmp_path, "robot2", channel)
    inside, go_on, done = threading.Event(), threading.Event(), threading.Event()

    def held_up(real: Callable[..., object]) -> Callable[..., object]:
        def step(*args: object, **kw: object) -> object:
            inside.set()
            go_on.wait(20)
            try:
                return real(*args, **kw)
            finally:
                done.set()

        return step

    if stage == "decode_envelope":
        monkeypatch.setattr(inbound, "decode_envelope", held_up(inbound.decode_envelope))
    else:
        monkeypatch.setattr(d0.store, "save_peer", held_up(d0.store.save_peer))

    async def main() -> None:
        tasks = [asyncio.create_task(d.run()) for d in (d0, d2)]
        try:
            await s2.queue.put(dk.growing_map(1).replace(robot="robot2"))
            await dk.wait_for(inside.is_set, 20, what=f"robot2's map in {stage}")
            if how == "removed":
                _drop_roster_line(path0, "robot2")
            else:  # the key it was verified with is revoked; the robot itself is still admitted
                _rekey(path0, "robot2")
            assert await d0.reload()
            go_on.set()
            await dk.wait_for(done.is_set, 20, what=f"{stage} done")
            await asyncio.sleep(0.3)  # the rest of the map's way in runs on the loop, without a wait
            assert "robot2" not in d0.receiver.maps and "robot2" not in d0.store.data.peers
            assert "robot2" not in d0.fusion.status()["robots"] and "robot2" not in d0.snapshot()["peers"]
            assert not (d0.cfg.state.dir / "peers" / "robot2").exists()
        finally:
            go_on.set()
            for d in (d0, d2):
                d.request_stop()
            await asyncio.gather(*tasks)

    asyncio.run(main())


def test_a_robot_revoked_while_the_daemon_was_down_is_not_restored(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    channel = dk.channel()
    path0 = _virtual(dk, tmp_path, "robot0", channel)
    d1, s1 = dk.virtual_daemon(tmp_path, "robot1", channel)
    s1.queue.put_nowait(dk.growing_map(1).replace(robot="robot1"))

    def holds_robot1(d0: Daemon) -> bool:
        return "robot1" in d0.receiver.maps and "robot1" in d0.snapshot()["peers"]

    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, d1, until=lambda: "robot1" in d0.store.data.peers)
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, until=lambda: d0.fusion._loaded)
    assert holds_robot1(d0)  # a plain restart brings robot1's map back from the state directory

    _drop_roster_line(path0, "robot1")  # revoked in the config while robot0 was down
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, until=lambda: d0.fusion._loaded)
    assert not holds_robot1(d0) and "robot1" not in d0.store.data.peers
    assert "robot1" not in d0.fusion.status()["robots"]


def test_a_robot_rekeyed_while_the_daemon_was_down_is_not_restored(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    # The documented answer to a leaked key is a new key in every robot's roster; a robot that was
    # off meanwhile starts with the new roster, and restored what the old key signed (its map, its
    # version from the future, its cells in the global map) as if nothing had changed.
    channel = dk.channel()
    path0 = dk.write_config(
        tmp_path, "robot0", extra='[transports]\nuse = ["virtual"]\n[fusion]\nanchor = "robot1"\n',
        **{"transports.virtual": f'channel = "{channel}"'},
    )  # fmt: skip
    d1, s1 = dk.virtual_daemon(tmp_path, "robot1", channel)
    s1.queue.put_nowait(dk.growing_map(1).replace(robot="robot1"))

    def merged(d0: Daemon) -> bool:
        return "robot1" in d0.store.data.peers and bool(
            d0.fusion.status()["robots"].get("robot1", {}).get("accepted")
        )

    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, d1, until=lambda: merged(d0))
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, until=lambda: d0.fusion._loaded)
    assert "robot1" in d0.receiver.maps and d0.fusion.global_map is not None  # a plain restart keeps it

    _rekey(path0, "robot1")  # while robot0 was down
    d0 = Daemon(configmod.load(path0), source=dk.QueueSource("robot0"))
    dk.run_until(d0, until=lambda: d0.fusion._loaded)
    assert "robot1" not in d0.receiver.maps and "robot1" not in d0.store.data.peers
    assert not (d0.cfg.state.dir / "peers" / "robot1").exists()
    assert d0.fusion.global_map is None and "robot1" not in d0.fusion.status()["robots"]
    assert d0.fusion.status()["revoked"] == 1


@pytest.mark.slow
def test_sighup_to_a_running_daemon_revokes_and_readmits_a_robot(tmp_path: Path, fk: SimpleNamespace) -> None:
    import argparse

    from mapd.demo.fleet import Fleet

    f = Fleet(
        argparse.Namespace(
            robots=2, transport="zenoh", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0
        )
    )
    f.prepare()
    cfg0 = f.run_dir / "robot0" / "config.toml"
    original = cfg0.read_text()
    f.start()

    def zenoh0(s: dict[str, dict[str, object]]) -> dict[str, object]:
        return s["robot0"]["links"]["zenoh"]  # type: ignore[index,return-value]

    try:
        fk.wait_for(lambda s: len(s) == 2 and fk.held(s, "robot0", "robot1") >= 2, 90, f)
        _drop_roster_line(cfg0, "robot1")
        f.procs["robot0"].send_signal(signal.SIGHUP)
        snaps = fk.wait_for(lambda s: s.get("robot0", {}).get("reload", {}).get("count") == 1, 30, f)
        assert snaps["robot0"]["security"]["roster"] == ["robot0"]
        assert snaps["robot0"]["reload"]["last"] == "roster: removed robot1"
        # Its map left with its key: not held, not in the global map.
        assert "robot1" not in snaps["robot0"]["peers"]
        assert "robot1" not in snaps["robot0"]["fusion"]["robots"]
        refused = zenoh0(snaps)["unadmitted"]
        # robot1's next maps are refused by the running daemon (before any check: not on the
        # roster), which does not restart
        snaps = fk.wait_for(lambda s: zenoh0(s)["unadmitted"] > refused, 60, f)
        assert snaps["robot0"]["pid"] == f.procs["robot0"].pid

        cfg0.write_text(original)
        f.procs["robot0"].send_signal(signal.SIGHUP)
        snaps = fk.wait_for(lambda s: s.get("robot0", {}).get("reload", {}).get("count") == 2, 30, f)
        held = fk.held(snaps, "robot0", "robot1")
        fk.wait_for(lambda s: fk.held(s, "robot0", "robot1") > held, 60, f)  # admitted again

        cfg0.write_text(original.replace("[robot]", "[robot"))
        f.procs["robot0"].send_signal(signal.SIGHUP)
        snaps = fk.wait_for(lambda s: s.get("robot0", {}).get("reload", {}).get("count") == 3, 30, f)
        assert snaps["robot0"]["reload"]["refused"] == 1
        out = subprocess.run(
            [
                sys.executable,
                "-m",
                "mapd",
                "status",
                "--json",
                "--socket",
                str(f.run_dir / "robot0" / "run" / "mapd.sock"),
            ],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert json.loads(out.stdout)["security"]["roster"] == ["robot0", "robot1"]

        # The config replaced by a FIFO that a process holds open and never writes: the reload
        # read it for ever, and SIGTERM could not stop the daemon. It is given up after a deadline.
        cfg0.unlink()
        os.mkfifo(cfg0)
        held = os.open(cfg0, os.O_RDWR)
        try:
            f.procs["robot0"].send_signal(signal.SIGHUP)
            snaps = fk.wait_for(
                lambda s: s.get("robot0", {}).get("reload", {}).get("count") == 4,
                reading.READ_TIMEOUT_S + 30,
                f,
            )
        finally:
            os.close(held)
        assert snaps["robot0"]["reload"]["refused"] == 2
        assert "did not finish it in" in snaps["robot0"]["reload"]["last"]

        # Edited with a mistake (sudoedit, then systemctl reload): refused, and `mapd status
        # --config` with that file refused too, so the refusal could be seen only with --socket.
        cfg0.unlink()
        cfg0.write_text(original.replace("[robot]\n", "[robot]\nbogus = 1\n", 1))
        f.procs["robot0"].send_signal(signal.SIGHUP)
        fk.wait_for(lambda s: s.get("robot0", {}).get("reload", {}).get("count") == 5, 30, f)
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--config", str(cfg0)],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip
        assert out.returncode == 0, out.stderr
        (warning,) = out.stderr.splitlines()
        assert warning.startswith("mapd: warning: ") and "robot.bogus" in warning and "mapd.sock" in warning
        assert "reload  5 (3 refused)" in out.stdout, out.stdout
    finally:
        codes = f.stop(timeout=10)
    assert codes == {"robot0": 0, "robot1": 0}
    log = (f.run_dir / "robot0" / "daemon.log").read_text()
    refusals = [ln for ln in log.splitlines() if "reload refused" in ln]
    assert len(refusals) == 3 and all(str(cfg0) in line for line in refusals) and "Traceback" not in log
    assert f"did not finish it in {reading.READ_TIMEOUT_S:g} s" in refusals[1]
    assert "robot.bogus: unknown key" in refusals[2]


def test_a_reload_that_fails_unexpectedly_leaves_the_daemon_running(
    tmp_path: Path, dk: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    import mapd.daemon.server as server

    def broken(*_: object) -> None:
        raise RuntimeError("a bug")

    monkeypatch.setattr(server, "read_reload", broken)
    d, _ = dk.virtual_daemon(tmp_path, "robot0", dk.channel())

    async def main() -> None:
        task = asyncio.create_task(d.run())
        try:
            await dk.wait_for(lambda: bool(d.transports), what="up")
            d.request_reload()  # as SIGHUP does
            await dk.wait_for(lambda: d.reloads.count == 1, what="reload done")
            assert d.snapshot()["reload"]["last"].endswith("RuntimeError: a bug")
            await asyncio.sleep(0.2)
            assert not task.done()  # the daemon runs on
        finally:
            d.request_stop()
            await task

    asyncio.run(main())


def test_read_takes_a_rotated_view_token_and_refuses_an_invalid_one(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    """A leaked view token is rotated by writing a new one into its file and reloading; the reload
    said nothing of it and the old token kept working (on the same path nothing in the config
    changed). A token file that is gone, or holds too short a token, refuses the reload whole."""
    view = 'listen = "0.0.0.0:8080"\ntoken_file = "view.token"'
    path = _virtual(dk, tmp_path, "robot0", "c")
    path.write_text(path.read_text() + f"[view]\n{view}\n")
    token_file = path.parent / "view.token"
    token_file.write_text("old-token-0123456789abcdef\n")
    running = configmod.load(path)
    checked = configmod.check(running)
    old = checked.view_token
    assert old == "old-token-0123456789abcdef"
    _, _, p = reload.read(running, checked.keys, old)
    assert (p.view_token, p.view_token_changed, p.summary()) == (old, False, "roster unchanged")

    token_file.write_text("new-token-ffffffffffffffff\n")  # rotated in place
    _, _, p = reload.read(running, checked.keys, old)
    assert p.view_token == "new-token-ffffffffffffffff" and p.view_token_changed and p.restart == []
    assert p.summary() == "roster unchanged; view: new token in force"

    # another file: applied as well, not left for a restart
    (path.parent / "other.token").write_text("other-token-0123456789abcdef\n")
    path.write_text(path.read_text().replace('"view.token"', '"other.token"'))
    new, _, p = reload.read(running, checked.keys, old)
    assert p.view_token == "other-token-0123456789abcdef" and p.restart == []
    reloads = reload.Reloads(running)
    reloads.applied(new, p)
    assert reloads.config.view.token_file == path.parent / "other.token"
    path.write_text(path.read_text().replace('"other.token"', '"view.token"'))

    # broken: the reload is refused in one line, and the running token stays what it was
    for content, said in (("short\n", "must hold one token of 16"), (None, "cannot read")):
        if content is None:
            token_file.unlink()
        else:
            token_file.write_text(content)
        with pytest.raises(ConfigError, match=r"view\.token_file: .*" + said) as err:
            reload.read(running, checked.keys, old)
        assert "\n" not in str(err.value)

    # a new listen: the new token belongs to it and waits for the restart with it
    token_file.write_text("new-token-ffffffffffffffff\n")
    path.write_text(path.read_text().replace('"0.0.0.0:8080"', '"0.0.0.0:9090"'))
    _, _, p = reload.read(running, checked.keys, old)
    assert p.view_token == old and not p.view_token_changed and p.restart == ["view.listen"]


def test_a_rotated_view_token_is_in_force_after_a_reload(tmp_path: Path, dk: SimpleNamespace) -> None:
    """On a running daemon: the old token is refused from the reload on, the new one served; a reload
    with a token file gone or too short is refused and the token in force stays."""
    import aiohttp

    from mapd.demo.ports import free_port

    port = free_port()
    path = _virtual(dk, tmp_path, "robot0", dk.channel())
    path.write_text(path.read_text() + f'[view]\nlisten = "127.0.0.1:{port}"\ntoken_file = "view.token"\n')
    token_file = path.parent / "view.token"
    old, new = "old-token-0123456789abcdef", "new-token-ffffffffffffffff"
    token_file.write_text(old + "\n")
    d = Daemon(configmod.load(path), source=dk.QueueSource("robot0"))

    async def main() -> None:
        task = asyncio.create_task(d.run())
        try:
            async with aiohttp.ClientSession() as s:

                async def status(token: str) -> int:
                    try:
                        async with s.get(f"http://127.0.0.1:{port}/", params={"token": token}) as r:
                            return r.status
                    except aiohttp.ClientConnectionError:
                        return 0  # not listening yet

                for _ in range(400):
                    if await status(old) == 200:
                        break
                    await asyncio.sleep(0.05)
                assert await status(old) == 200 and await status(new) == 401
                token_file.write_text(new + "\n")
                assert await d.reload()
                assert (await status(old), await status(new)) == (401, 200)
                assert d.snapshot()["reload"]["last"] == "roster unchanged; view: new token in force"
                for broken in ("short\n", None):
                    if broken is None:
                        token_file.unlink()
                    else:
                        token_file.write_text(broken)
                    assert not await d.reload()
                    assert "view.token_file" in d.snapshot()["reload"]["last"]
                    assert (await status(old), await status(new)) == (401, 200)
        finally:
            d.request_stop()
            await task

    asyncio.run(main())
