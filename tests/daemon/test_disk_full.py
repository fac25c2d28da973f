"""A real ``mapd run`` whose disk fills up, and then has room again.

The disk is a size-limited tmpfs in a user + mount namespace (``unshare -rm``, no root needed where
user namespaces are allowed): the daemon under test runs inside it with its state directory, its
``files`` output folder and its MCAP recording on that tmpfs, and a small shell in the namespace
fills it (``cat /dev/zero > filler`` until ENOSPC), empties it, and copies it out for the test to
read. A peer daemon (its state on the ordinary disk) sends it maps over zenoh. Both take their
maps from map files the test writes (``mapfile`` source), so every version is the test's to make
or withhold.

What must hold: no traceback and no crash, one log line per writer when the outage starts and one
when it ends, the fault in ``mapd status``, every file saved before the outage whole while it lasts
(each write is atomic), and writing again on its own once there is room, also while no new map
comes (a fleet at rest).

The fast tests below hold the same rules for one part at a time, with writes made to fail.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import json
import logging
import os
import select
import shutil
import signal
import struct
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.exceptions import EndOfFile
from mcap.stream_reader import StreamReader

from mapd.commands.status_text import render_status
from mapd.daemon.headline import status_line
from mapd.daemon.state import StateStore
from mapd.daemon.status_socket import query
from mapd.demo.ports import free_ports
from mapd.errors import DaemonError, StateError
from mapd.files.outage import WriteOutage
from mapd.fusion.merge import NO_OWNER, Bounds, MergeResult
from mapd.fusion.store import FusionStore
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.load import load_map
from mapd.grid.save import save_map
from mapd.identity import Identity, read_identity
from mapd.mapping.synthetic import room_grid
from mapd.outputs import files as files_output
from mapd.outputs.base import GlobalUpdate, OutputContext
from mapd.outputs.files import FilesOptions, FilesOutput

ROOT = Path(__file__).resolve().parents[2]
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

# ---------------------------------------------------------------------- the namespace and its disk

#: Runs in the namespace: mounts the tmpfs, then takes one command a line on stdin and answers one
#: line on stdout when it is done. The daemons are its children (``start NAME CONFIG LOG``), in the
#: one namespace: zenoh between a process inside a user namespace and one outside lost messages.
#: ``snap`` copies the disk while daemons write to it: a temp file renamed between cp's listing and
#: its copy fails the copy (cp: cannot stat), so it tries again, a few times. A copy is also tried
#: again until a second copy of the state directory, just after it, is the same: a save between
#: cp's copies of global.yaml and global.pgm left a copy holding one of each save, which no disk
#: ever held (seen once in a full run: "the saved global map is gone or damaged").
CONTROL = r"""
disk=$1
mount -t tmpfs -o size="$2" tmpfs "$disk" || exit 97
echo mounted
while read -r cmd a b c; do
  case $cmd in
    start) "$PY" -m mapd run --config "$b" >>"$c" 2>&1 </dev/null & eval "pid_$a=\$!"; echo "pid $!";;
    stop) eval "p=\$pid_$a"; kill -TERM "$p"; wait "$p"; echo "rc $?";;
    fill) cat /dev/zero >"$disk/filler" 2>/dev/null; echo "free $(df -k "$disk" | awk 'NR==2 {print $4}')";;
    free) rm -f "$disk/filler"; echo "free $(df -k "$disk" | awk 'NR==2 {print $4}')";;
    snap) ok=; for try in 1 2 3 4 5 6 7 8 9 10; do rm -rf "$a" "$a.state"
            cp -a "$disk/." "$a" 2>/dev/null || continue
            [ -d "$a/state" ] || { ok=1; break; }
            cp -a "$disk/state/." "$a.state" 2>/dev/null && diff -rq "$a/state" "$a.state" >/dev/null 2>&1 \
              && { ok=1; break; }; done
          rm -rf "$a.state"; [ -n "$ok" ] && echo snapped || echo "snap failed";;
    mkdir) mkdir -p "$disk/$a" && echo made;;
  esac
done
"""


def _namespace_problem(where: Path) -> str | None:
    """Why a user + mount namespace with a tmpfs cannot be made here (None: it can)."""
    if shutil.which("unshare") is None:
        return "unshare (util-linux) is not installed"
    where.mkdir(exist_ok=True)
    try:
        done = subprocess.run(
            ["unshare", "-rm", "sh", "-c", 'mount -t tmpfs -o size=1m tmpfs "$0" && touch "$0/x"', where],
            capture_output=True,
            text=True,
            timeout=30,
        )
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unshare -rm failed: {exc}"
    if done.returncode != 0:
        return f"unshare -rm cannot mount a tmpfs here (user namespaces off?): {done.stderr.strip()}"
    return None


def in_tmpfs(disk: Path, size: str, script: str) -> subprocess.CompletedProcess[str]:
    """Python ``script`` run with ``disk`` as its first argument, in a user + mount namespace where
    a tmpfs of ``size`` is mounted on ``disk``."""
    return subprocess.run(
        [
            "unshare",
            "-rm",
            "sh",
            "-c",
            f'mount -t tmpfs -o size={size} tmpfs "$0" && exec "$PY" -c "$1" "$0"',
            disk,
            script,
        ],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PY": sys.executable},
        cwd=ROOT,
    )


class FullDisk:
    """A tmpfs of ``size`` at ``disk`` in a namespace of its own, and the daemons run inside it."""

    def __init__(self, disk: Path, size: str | None, control: str = CONTROL) -> None:
        """``control``: the namespace's shell script (``size`` its second argument, if any)."""
        self.disk = disk
        self.pids: dict[str, int] = {}
        disk.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen(
            ["unshare", "-rm", "sh", "-c", control, "control", str(disk), *([size] if size else [])],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PY": sys.executable},
            cwd=ROOT,
        )
        assert self._line(30) == "mounted"

    def _line(self, timeout: float) -> str:
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        assert ready, f"the namespace's shell said nothing within {timeout} s"
        line = self.proc.stdout.readline()
        assert line, f"the namespace's shell ended (exit {self.proc.wait(5)})"
        return line.strip()

    def ask(self, command: str, timeout: float = 30.0) -> str:
        assert self.proc.stdin is not None
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()
        return self._line(timeout)

    def start(self, name: str, config: Path, log: Path) -> None:
        """``mapd run --config config`` in the namespace, its output appended to ``log``."""
        self.pids[name] = int(self.ask(f"start {name} {config} {log}").split()[1])

    def mkdir(self, name: str) -> Path:
        """A folder on the tmpfs (seen only inside the namespace); its path."""
        assert self.ask(f"mkdir {name}") == "made"
        return self.disk / name

    def alive(self, name: str) -> bool:
        return Path(f"/proc/{self.pids[name]}").exists()

    def fill(self) -> None:
        assert self.ask("fill") == "free 0"

    def free(self) -> None:
        assert self.ask("free") != "free 0"

    def snapshot(self, to: Path) -> Path:
        """A copy of the tmpfs as it is now (the daemons keep running), readable from outside."""
        assert self.ask(f"snap {to}") == "snapped"
        return to

    def stop(self, name: str) -> int:
        """SIGTERM to daemon ``name``; its exit status."""
        answer = self.ask(f"stop {name}", timeout=30)
        del self.pids[name]
        return int(answer.split()[1])

    def rss_kib(self, name: str) -> int:
        for line in Path(f"/proc/{self.pids[name]}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
        raise AssertionError("no VmRSS")

    def close(self) -> None:
        for pid in self.pids.values():  # a test that failed half-way: its daemons go too
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)


# ---------------------------------------------------------------------- two robots


def _config(
    tmp: Path,
    robot: str,
    ports: tuple[int, int],
    state: Path,
    roster: str,
    extra: str = "",
    transport: str | None = None,
    codec: str = "lossless",
) -> Path:
    """A signed config: ``robot`` takes its map from ``tmp/<robot>-map/map.yaml`` (the test writes
    it), placed by a known start pose, and talks zenoh to the other robot (or ``transport``)."""
    here = tmp / robot
    here.mkdir(exist_ok=True)
    x = 0.0 if robot == "robot0" else 6.0
    body = (
        f'[robot]\nname = "{robot}"\nkey_file = "{tmp / "keys" / robot}.key"\n'
        f'[source]\nuse = "mapfile"\n[source.mapfile]\npath = "{tmp / f"{robot}-map" / "map.yaml"}"\n'
        f"poll_s = 0.1\nsettle_s = 0.1\nstart_pose = [{x}, 0.0, 0.0]\n"
        f'[codec]\nuse = "{codec}"\n'
        f'[state]\ndir = "{state}"\nruntime_dir = "{here / "run"}"\n'
        + (
            transport
            or '[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nmode = "peer"\n'
            f'listen = ["tcp/127.0.0.1:{ports[0]}"]\nconnect = ["tcp/127.0.0.1:{ports[1]}"]\n'
            "multicast_scouting = false\n"
        )
        + "[fusion]\ndebounce_s = 0.2\n"
        + extra
        + roster
    )
    (here / "config.toml").write_text(body)
    return here / "config.toml"


def _roster(tmp: Path, robots: tuple[str, ...]) -> str:
    keys = tmp / "keys"
    keys.mkdir(exist_ok=True)
    lines = ["[fleet]", "[fleet.roster]"]
    for robot in robots:
        Identity.generate(robot).write(keys / f"{robot}.key")
        lines.append(f'{robot} = "{read_identity(keys / f"{robot}.key", robot).public_text}"')
    return "\n".join(lines) + "\n"


def _room(robot: str, n: int) -> OccupancyGrid:
    """Version ``n`` of ``robot``'s map, explored a little further each time. Random cells: each
    version then takes some 100 kB in the recording even compressed, so the recorder's 256 kB
    chunks reach the disk within a version or two (a room compresses to nothing)."""
    rng = np.random.default_rng(1 if robot == "robot0" else 2)
    data = rng.choice(np.array([0, 100, -1], np.int8), size=(500, 500), p=[0.6, 0.2, 0.2])
    data[:, 200 + 50 * n :] = -1
    return OccupancyGrid(data, 0.05)


def _publish(tmp: Path, robot: str, n: int) -> OccupancyGrid:
    folder = tmp / f"{robot}-map"
    folder.mkdir(exist_ok=True)
    grid = _room(robot, n)
    save_map(grid, folder / "map.yaml")
    return grid


def _wait(
    what: str, cond: Callable[[], Any], timeout: float = 30.0, say: Callable[[], object] = lambda: ""
) -> Any:
    """``cond()`` once it is true, polled; AssertionError with ``say()`` after ``timeout`` s."""
    end = time.monotonic() + timeout
    while True:
        got = cond()
        if got:
            return got
        if time.monotonic() > end:
            raise AssertionError(f"{what}: not within {timeout} s; {say()}")
        time.sleep(0.1)


def _status(sock: Path) -> dict[str, Any] | None:
    try:
        return query(sock)
    except DaemonError:
        return None


def _log_lines(log: Path) -> list[str]:
    return log.read_text(errors="replace").splitlines()


def _count(lines: list[str], text: str) -> int:
    return sum(text in line for line in lines)


# ---------------------------------------------------------------------- reading what was written


def _temps(root: Path) -> list[str]:
    return sorted(str(p.relative_to(root)) for p in root.rglob(".*") if ".tmp" in p.name)


def _mcap_whole(path: Path) -> int:
    """The messages of an MCAP file read as a streaming reader reads it; AssertionError when a
    record is damaged or the file ends inside one (a file cut back to its last chunk may lack
    the footer, never end mid-record)."""
    data = path.read_bytes()
    pos = 8
    while pos < len(data) and data[pos:] != b"\x89MCAP0\r\n":
        assert pos + 9 <= len(data), f"{path} ends inside a record header"
        (length,) = struct.unpack_from("<Q", data, pos + 1)
        pos += 9 + length
    assert pos <= len(data), f"{path} ends inside a record"
    messages = 0
    with open(path, "rb") as fh:
        try:
            for record in StreamReader(fh).records:
                messages += type(record).__name__ == "Message"
        except EndOfFile:
            pass
    return messages


@dataclass
class Saved:
    """What a copy of the tmpfs holds, every file read back as the daemon would read it."""

    own: OccupancyGrid
    peer: OccupancyGrid
    global_map: OccupancyGrid
    out: OccupancyGrid
    out_versions: dict[str, int]
    recorded: int
    state_json: dict[str, Any] = field(repr=False)


def _read(snap: Path) -> Saved:
    state = StateStore(snap / "state")  # (open writes its probe into the copy, not the tmpfs)
    state.open()
    own, peer = state.own_map(), state.peer_map("robot0")
    assert own is not None and peer is not None, "a state map saved before is gone or damaged"
    global_map = FusionStore(snap / "state" / "global", robot="robot1").load_global()
    assert global_map is not None, "the saved global map is gone or damaged"
    transforms = json.loads((snap / "out" / "transforms.json").read_text())
    recordings = sorted((snap / "rec").glob("fleet*.mcap"))
    assert recordings
    return Saved(
        own=own,
        peer=peer,
        global_map=global_map,
        out=load_map(snap / "out" / "map.yaml"),
        out_versions={r: t["version"] for r, t in transforms["robots"].items()},
        recorded=sum(_mcap_whole(p) for p in recordings),
        state_json=json.loads((snap / "state" / "state.json").read_text()),
    )


# ---------------------------------------------------------------------- the daemon's run


@pytest.mark.slow
def test_a_daemon_whose_disk_fills_runs_on_says_it_once_keeps_its_files_and_writes_again(
    tmp_path: Path,
) -> None:
    """robot1's state directory, files output and recording on a full disk: both robots make new
    maps meanwhile; then room again with no new map (a fleet at rest); then new maps."""
    if problem := _namespace_problem(tmp_path / "probe"):
        pytest.skip(problem)
    roster = _roster(tmp_path, ("robot0", "robot1"))
    p0, p1 = free_ports(2)
    disk = tmp_path / "disk"
    c0 = _config(tmp_path, "robot0", (p0, p1), tmp_path / "robot0" / "state", roster)
    c1 = _config(
        tmp_path,
        "robot1",
        (p1, p0),
        disk / "state",
        roster,
        extra=f'[output]\nuse = ["files"]\n[output.files]\ndir = "{disk / "out"}"\n'
        # min_free_bytes 0: the recorder writes until the disk refuses (its own floor would
        # otherwise keep it off this small disk altogether)
        f'[record]\npath = "{disk / "rec" / "fleet.mcap"}"\nmin_free_bytes = 0\nstats_every_s = 0.5\n',
    )
    sock = tmp_path / "robot1" / "run" / "mapd.sock"

    def both() -> str:
        """What each robot says, for a failed wait."""
        return json.dumps({r: _status(tmp_path / r / "run" / "mapd.sock") for r in ("robot0", "robot1")})

    log1 = tmp_path / "robot1.log"
    for robot in ("robot0", "robot1"):
        _publish(tmp_path, robot, 1)
    ns = FullDisk(disk, "8m")
    try:
        ns.start("robot0", c0, tmp_path / "robot0.log")
        ns.start("robot1", c1, log1)

        def fused() -> dict[str, Any] | None:
            """robot1's status once it holds, fuses (placed) and has sent the newest of both maps."""
            assert ns.alive("robot0"), (tmp_path / "robot0.log").read_text()[-2000:]
            s = _status(sock)
            if s is None or not s["source"]["version"] or not s["peers"].get("robot0"):
                return None
            held = {"robot0": s["peers"]["robot0"].get("version"), "robot1": s["source"]["version"]}
            merged = s["fusion"]["robots"]
            if any(
                v is None or (merged.get(r) or {}).get("version") != v or not merged[r].get("accepted")
                for r, v in held.items()
            ):
                return None
            return s if s["peers"]["robot0"].get("acked_our_version") == s["source"]["version"] else None

        def settled(
            what: str, snap: Path, after: dict[str, Any] | None = None
        ) -> tuple[dict[str, Any], Saved]:
            """Wait until both newest maps (newer than those ``after`` holds) are fused, then until
            the files hold them (read from a copy: the test cannot see into the namespace's tmpfs)."""

            def newer() -> dict[str, Any] | None:
                s = fused()
                if s is None or after is None:
                    return s
                mine, theirs = s["source"]["version"], s["peers"]["robot0"]["version"]
                ok = mine > after["source"]["version"] and theirs > after["peers"]["robot0"]["version"]
                return s if ok else None

            now = _wait(what, newer, 60)
            held = {"robot0": now["peers"]["robot0"]["version"], "robot1": now["source"]["version"]}

            def written() -> Saved | None:
                saved = _read(ns.snapshot(snap))
                ok = saved.out_versions == held and saved.own.version == held["robot1"]
                return saved if ok and saved.peer.version == held["robot0"] else None

            return now, _wait(f"{what}: written", written)

        # ---- room on the disk: everything is written
        before, snap0 = settled("robot1 holds, fuses and writes both maps", tmp_path / "snap0")
        assert snap0.own.same_map(_room("robot1", 1)) and snap0.peer.same_map(_room("robot0", 1))
        assert snap0.out_versions == {
            "robot0": before["peers"]["robot0"]["version"],
            "robot1": before["source"]["version"],
        }
        lines_before = len(_log_lines(log1))

        # ---- the disk fills: both robots make new maps, which robot1 cannot save
        ns.fill()
        rss_at_fill = ns.rss_kib("robot1")
        outage_says = (
            "new versions are not sent until one is saved",  # own map (outbound)
            "saving peers' maps and acks again every",  # peer maps, base, state.json (inbound)
            "fusion: global map not saved",
            "output.files: cannot write the global map",
            "recording failed",
        )
        prev, n = before, 1
        # New versions until every writer has met the full disk (the recorder writes 256 kB chunks:
        # it may take it two versions); each is waited for until held and fused, never for a time.
        while n < 3 or not all(_count(_log_lines(log1)[lines_before:], t) for t in outage_says):
            n += 1
            assert n <= 6, ("not every writer met the full disk", _log_lines(log1)[lines_before:])
            for robot in ("robot0", "robot1"):
                _publish(tmp_path, robot, n)

            def took(prev: dict[str, Any] = prev) -> dict[str, Any] | None:
                s = _status(sock)
                if s is None or s["peers"]["robot0"]["version"] == prev["peers"]["robot0"]["version"]:
                    return None
                held = {"robot0": s["peers"]["robot0"]["version"], "robot1": s["source"]["version"]}
                merged = s["fusion"]["robots"]
                if held["robot1"] == prev["source"]["version"]:
                    return None
                return s if all((merged.get(r) or {}).get("version") == v for r, v in held.items()) else None

            prev = _wait(f"version {n} held and fused on the full disk", took, say=both)
        during = _wait(
            "the files output's failure in status",
            lambda: (s := _status(sock)) and not s["outputs"]["files"]["writing"] and s,
        )
        assert ns.alive("robot1")
        snap1 = _read(ns.snapshot(tmp_path / "snap1"))
        rss_outage = ns.rss_kib("robot1")

        # The fault is in `mapd status`, JSON and text, as a user runs it.
        assert (
            during["outputs"]["files"]["failures"] >= 1
            and "No space left on device" in during["outputs"]["files"]["error"]
        )
        assert during["recording"]["failures"] >= 1 and during["recording"]["queued_bytes"] < 16 << 20
        assert during["recording"]["writing"] is False
        assert "recording: messages not written" in status_line(during)
        text = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--config", str(c1)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert text.returncode == 0 and "record  FAULTS" in text.stdout, text
        assert "output  files: FAULTS not writing (disk full?)" in text.stdout, text.stdout
        assert (
            "state   FAULTS state dir not writable (disk full, read-only or gone?): own maps held back"
            in text.stdout
        ), text.stdout
        assert during["state"]["writing"] is False and "No space left on device" in during["state"]["error"]
        assert during["state"]["global_map"]["writing"] is False and during["state"]["failures"] >= 2
        line = status_line(during)
        assert (
            line.startswith("FAULTS ")
            and "state dir not writable (disk full, read-only or gone?)" in line.split(" | ")[0]
        )
        assert "global map not saved" in line and "output.files not writing (disk full?)" in line
        assert "state   FAULTS" in render_status(during)  # (the text above, from the same document)
        # A version is never sent unsaved (after a restart its number could come again): robot0
        # still holds robot1's version from before the outage.
        assert during["codec"]["last_version"] == before["source"]["version"] < during["source"]["version"]
        # Everything saved before the disk filled is there and whole, as it was.
        assert snap1.own.same_map(snap0.own) and snap1.own.version == snap0.own.version
        assert snap1.peer.same_map(snap0.peer) and snap1.peer.version == snap0.peer.version
        assert snap1.global_map.same_map(snap0.global_map) and snap1.out.same_map(snap0.out)
        assert snap1.out_versions == snap0.out_versions
        assert snap1.state_json == snap0.state_json
        assert snap1.recorded >= snap0.recorded

        # ---- room again, and no new map (a fleet at rest): each writer writes on its own
        ns.free()

        def resumed() -> dict[str, Any] | None:
            s = _status(sock)
            if s is None or not (s["outputs"]["files"]["writing"] and s["state"]["writing"]):
                return None
            if not s["state"]["global_map"]["writing"]:
                return None
            return s if s["peers"]["robot0"]["acked_our_version"] == during["source"]["version"] else None

        after = _wait(
            "every writer writing again without a new map; robot0 given the unsaved map", resumed, say=both
        )
        _wait("the recording writing again", lambda: _count(_log_lines(log1), "recording again"))
        snap2 = _read(ns.snapshot(tmp_path / "snap2"))
        assert snap2.out_versions == {
            "robot0": during["peers"]["robot0"]["version"],
            "robot1": during["source"]["version"],
        }  # the global map made while the disk was full, written now
        assert after["outputs"]["files"]["written"] > during["outputs"]["files"]["written"]
        # the own version made while the disk was full: saved, then sent (robot0 acked it above)
        assert snap2.own.same_map(_room("robot1", n)) and snap2.own.version == during["source"]["version"]
        assert snap2.global_map.version > snap1.global_map.version
        line = status_line(after)
        assert not any(f in line for f in ("state dir", "global map not saved", "not writing"))
        # The recording's outage is over too: its totals stay, but no longer as a fault.
        rec = _wait(
            "the recording's status writing", lambda: (s := _status(sock)) and s["recording"]["writing"] and s
        )
        assert rec["recording"]["failures"] >= 1 and "recording" not in status_line(rec)
        assert "record  so far:" in render_status(rec) and "record  FAULTS" not in render_status(rec)

        # ---- new maps: every writer writes again
        for robot in ("robot0", "robot1"):
            _publish(tmp_path, robot, 4)
        last, _ = settled("version 4 held, fused, written and acked", tmp_path / "snap3", after)
        outage_over = (
            "own map saved again",
            "state saved again",
            "fusion: global map saved again",
            "output.files: writing to",
            "recording again",
        )
        _wait(
            "each writer's line that it writes again",
            lambda: all(_count(_log_lines(log1), t) for t in outage_over),
        )
        assert ns.stop("robot1") == 0
        final = _read(ns.snapshot(tmp_path / "final"))
        assert ns.stop("robot0") == 0
    finally:
        ns.close()

    lines = _log_lines(log1)
    assert not any("Traceback" in line for line in lines), "\n".join(lines)
    for said in outage_says + outage_over:
        assert _count(lines, said) == 1, (said, lines)  # one line each, not one per write
    assert _count(lines, "owner map") == 0  # the global map's line says it for the same disk
    errors = [line for line in lines if " ERROR " in line]
    assert len(errors) <= len(outage_says) + 2, errors  # (+ the CSV logs', when their append failed)
    assert rss_outage - rss_at_fill < 64 << 10
    # After the stop: the newest of every map, whole, and no temp file left anywhere.
    assert final.own.same_map(_room("robot1", 4)) and final.own.version == last["source"]["version"]
    assert (
        final.peer.same_map(_room("robot0", 4)) and final.peer.version == last["peers"]["robot0"]["version"]
    )
    assert final.global_map.version > snap1.global_map.version
    assert final.out_versions == {"robot0": final.peer.version, "robot1": final.own.version}
    assert final.state_json["own"]["version"] == final.own.version
    assert _temps(tmp_path / "final") == []
    assert final.recorded > snap1.recorded  # (the file opened after the outage, its footer written)


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
@pytest.mark.parametrize("full_at_start", [False, True], ids=["fills-later", "full-at-start"])
def test_a_uwb_link_whose_signing_counter_cannot_be_saved_says_so_once_and_resumes(
    tmp_path: Path, full_at_start: bool
) -> None:
    """The link's counter block (``state/links/uwb``) on the full disk, the rest of the state
    directory on one with room (a symlink): the robot keeps saving and sending its maps, so the
    link soon needs a new block it cannot save. It signs on within the block saved before, says
    so once, shows it in ``mapd status``, and saves again by itself once there is room.

    Full at start: the daemon refused to start (exit 1, "cannot write signing counter"), so under
    systemd it went down again every 2 s. It runs, sends nothing signed, and sends once there is
    room."""
    if problem := _namespace_problem(tmp_path / "probe"):
        pytest.skip(problem)
    roster = _roster(tmp_path, ("robot0", "robot1"))
    link_key = tmp_path / "keys" / "link.key"
    link_key.write_text("ab" * 32 + "\n")
    link_key.chmod(0o600)
    ptys = [tmp_path / "pty0", tmp_path / "pty1"]
    socat = subprocess.Popen(["socat", f"pty,raw,echo=0,link={ptys[0]}", f"pty,raw,echo=0,link={ptys[1]}"])
    ns = FullDisk(tmp_path / "disk", "2m")
    log1 = tmp_path / "robot1.log"
    outages = 2 if full_at_start else 1  # (each said once)
    try:
        _wait("socat's ptys", lambda: all(p.exists() for p in ptys), 10)
        configs = {}
        for i, robot in enumerate(("robot0", "robot1")):
            state = tmp_path / robot / "state"
            if robot == "robot1":
                state.mkdir(parents=True)
                (state / "links").symlink_to(ns.mkdir("links"))  # (the tmpfs, inside the namespace)
            configs[robot] = _config(
                tmp_path,
                robot,
                (0, 0),
                state,
                roster.replace("[fleet]\n", f'[fleet]\nlink_key_file = "{link_key}"\n'),
                # 128-byte frames of a map of 250 kB: some 3,000 frames, where a counter block
                # saved lasts 2,048 to 4,096 (each map needs a new block, one at least)
                transport=f'[transports]\nuse = ["uwb"]\n[transports.uwb]\nport = "{ptys[i]}"\n'
                "link_rate_bps = 2000000\nmax_frame = 128\n[transports.uwb.nodes]\nrobot0 = 1\nrobot1 = 2\n",
                codec="raw",
            )
            _publish(tmp_path, robot, 1)
        if full_at_start:
            ns.fill()
        for robot in ("robot0", "robot1"):
            ns.start(robot, configs[robot], tmp_path / f"{robot}.log")
        sock0, sock1 = (tmp_path / r / "run" / "mapd.sock" for r in ("robot0", "robot1"))

        def robot0_holds(version: int) -> dict[str, Any] | None:
            assert ns.alive("robot0") and ns.alive("robot1"), log1.read_text()[-2000:]
            s = _status(sock0)
            return s if s is not None and (s["peers"].get("robot1") or {}).get("version") == version else None

        def own_version() -> int:
            s = _status(sock1)
            return s["source"]["version"] if s is not None else 0

        v1 = _wait("robot1's first map", own_version)
        if full_at_start:
            _wait(
                "the counter's outage line", lambda: _count(_log_lines(log1), "cannot write signing counter")
            )
            s1 = _status(sock1)
            assert s1 is not None and s1["links"]["uwb"]["counter_save_errors"] >= 1
            time.sleep(3.0)  # (an absence: nothing to poll for)
            assert robot0_holds(v1) is None  # it runs, and nothing unsigned or unsaved went out
            ns.free()
        _wait("robot0 holding robot1's first map", lambda: robot0_holds(v1), 60)
        ns.fill()
        # New maps (some 3,000 frames each) need new blocks, which cannot be saved: the link signs
        # on with what is left of the block saved before (at most 4,096 counters), then waits.
        for n in (2, 3, 4):
            _publish(tmp_path, "robot1", n)
            _wait(f"robot1's version {n}", lambda n=n: own_version() >= v1 + n - 1)
        # This outage's own line (full at start, the first outage's line is there already: freeing
        # the disk before this one came made the count below one short under load).
        _wait(
            "the counter's outage line",
            lambda: _count(_log_lines(log1), "cannot write signing counter") >= outages,
        )
        s = _status(sock1)
        assert s is not None and s["links"]["uwb"]["counter_save_errors"] >= 1
        text = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--config", str(configs["robot1"])],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert "FAULTS signing counter not saved" in text.stdout, text.stdout
        newest = own_version()
        ns.free()
        _wait(
            "robot0 holding robot1's newest map, sent once the counter is saved",
            lambda: robot0_holds(newest),
            60,
        )
        assert ns.stop("robot1") == 0 and ns.stop("robot0") == 0
        final = ns.snapshot(tmp_path / "final")
    finally:
        ns.close()
        socat.terminate()
        socat.wait(10)
    lines = _log_lines(log1)
    assert not any("Traceback" in line for line in lines), lines
    assert _count(lines, "cannot write signing counter") == outages, lines
    assert _count(lines, "signing counter saved again") == outages, lines
    # The replay marks live on the same full disk: their save may fail in each outage, said once each.
    assert _count(lines, "cannot write replay marks") <= outages, lines
    assert int((final / "links" / "uwb" / "uwb-2.counter").read_text()) > 0
    assert _temps(final) == []


# ---------------------------------------------------------------------- one part at a time


CSV_ON_A_FULL_DISK = """
import csv, json, logging, sys
from pathlib import Path
from mapd.daemon.coding import CsvLog

logging.basicConfig(level=logging.INFO, format="%(message)s")
disk = Path(sys.argv[1])
log = CsvLog(disk / "fused.csv")
row = lambda i: [{"time": 1000.5 + i, "robot": "robot0", "version": 396678016907870239 + i}]
for i in range(100):
    log.write(row(i))
with open(disk / "filler", "wb", buffering=0) as fh:  # the disk fills up
    try:
        while True:
            fh.write(bytes(1 << 16))
    except OSError:
        pass
for i in range(100, 400):  # rows that do not fit: the first takes what room the last block has
    log.write(row(i))
(disk / "filler").unlink()  # room again
for i in range(400, 410):
    log.write(row(i))
with open(disk / "fused.csv", newline="") as fh:
    print(json.dumps(list(csv.reader(fh))))
"""


def test_a_csv_log_on_a_full_disk_never_leaves_a_torn_row(tmp_path: Path) -> None:
    """An append that the disk took only part of (the room in the file's last block) left half a
    row, and the first append once there was room ran into it: a row of five fields in the middle
    of ``fused.csv`` (and ``updates.csv``)."""
    if problem := _namespace_problem(tmp_path / "probe"):
        pytest.skip(problem)
    disk = tmp_path / "disk"
    disk.mkdir()
    done = in_tmpfs(disk, "1m", CSV_ON_A_FULL_DISK)
    assert done.returncode == 0, done.stderr
    rows = json.loads(done.stdout)
    assert rows[0] == ["time", "robot", "version"] and all(len(r) == 3 for r in rows), rows
    versions = [int(r[2]) - 396678016907870239 for r in rows[1:]]
    assert versions[:100] == list(range(100)) and versions[-10:] == list(range(400, 410))
    assert done.stderr.count("cannot write") == 1 and done.stderr.count("again") == 1, done.stderr


def test_a_write_outage_counts_every_failure_and_says_when_it_began(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.INFO, logger="test.outage")
    outage = WriteOutage(logging.getLogger("test.outage"))
    assert outage.status() == {"writing": True, "failures": 0, "failing_s": None, "error": None}
    outage.failed("disk full")
    outage.failed("disk still full")
    s = outage.status()
    assert s["writing"] is False and s["failures"] == 2 and s["error"] == "disk still full"
    assert isinstance(s["failing_s"], float) and 0 <= s["failing_s"] < 60
    outage.recovered("room again")
    assert outage.status() == {"writing": True, "failures": 2, "failing_s": None, "error": None}
    assert [r.getMessage() for r in caplog.records] == ["disk full", "room again"]
    quiet = WriteOutage(None)  # counted, said by another part
    quiet.failed("x")
    quiet.recovered("y")
    assert quiet.failures == 1 and not quiet.failing
    assert [r.getMessage() for r in caplog.records] == ["disk full", "room again"]


def test_the_state_directory_says_while_its_saves_fail(tmp_path: Path) -> None:
    store = StateStore(tmp_path / "state")
    store.open()
    grid = room_grid(40, 50, seed=3).replace(robot="beta", version=7)
    assert store.health() == {
        "dir": str(tmp_path / "state"),
        "writing": True,
        "failures": 0,
        "failing_s": None,
        "error": None,
    }
    blocker = tmp_path / "state" / "peers" / "beta"
    blocker.write_bytes(b"")  # the folder cannot be made (as mkdir fails on a full disk)
    with pytest.raises(StateError):
        store.save_peer(grid)
    h = store.health()
    assert h["writing"] is False and h["failures"] == 1 and "cannot create the folder" in h["error"]
    blocker.unlink()
    store.save_peer(grid)
    assert store.health()["writing"] is True and store.health()["failures"] == 1


def _merge_result(version: int) -> MergeResult:
    grid = room_grid(30, 40, seed=version).replace(version=version)
    return MergeResult(
        grid=grid, bounds=Bounds.of_grid(grid), owner=np.full(grid.data.shape, NO_OWNER, np.uint8)
    )


def test_a_full_disk_under_the_global_map_is_one_line_not_two(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """The worker says the global map was not saved; the owner map (pictures only) on the same
    full disk said so again in a line of its own, and again when it was over."""
    import mapd.fusion.store as store_mod

    store = FusionStore(tmp_path / "global", robot="a")
    full = [True]
    real_committed, real_atomic = store_mod.save_committed, store_mod.atomic_write_bytes

    def committed(*args: Any, **kw: Any) -> str:
        if full[0]:
            raise StateError(f"{tmp_path}/global/global.yaml: cannot write map: No space left on device")
        return real_committed(*args, **kw)

    def atomic(*args: Any, **kw: Any) -> None:
        if full[0]:
            raise ENOSPC
        real_atomic(*args, **kw)

    monkeypatch.setattr(store_mod, "save_committed", committed)
    monkeypatch.setattr(store_mod, "atomic_write_bytes", atomic)
    caplog.set_level(logging.INFO, logger="mapd.fusion.store")
    for version in (1, 2):
        result = _merge_result(version)
        with pytest.raises(StateError):
            store.save(result, {}, stamp=1.0, fleet_frame=None, mode="logodds")
        store.save_owner(result.owner, ["a"])
        assert store.health()["writing"] is False and store.health()["failures"] == version
    full[0] = False
    result = _merge_result(3)
    store.save(result, {}, stamp=1.0, fleet_frame=None, mode="logodds")
    store.save_owner(result.owner, ["a"])
    assert store.health()["writing"] is True and store.load_global() is not None
    assert [r.getMessage() for r in caplog.records] == []  # the worker's two lines say it all

    # The owner map alone failing (the global map fit) is still said, once, and its end.
    full[0] = True
    monkeypatch.setattr(store_mod, "save_committed", real_committed)
    monkeypatch.setattr(store_mod, "write_json_atomic", lambda *a, **k: None)
    for version in (4, 5):
        result = _merge_result(version)
        store.save(result, {}, stamp=1.0, fleet_frame=None, mode="logodds")
        store.save_owner(result.owner, ["a"])
    full[0] = False
    store.save_owner(result.owner, ["a"])
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and "cannot write owner map" in said[0] and "No space left" in said[0], said
    assert said[1] == "fusion: writing the owner map again"


def test_the_files_output_writes_its_last_map_again_once_there_is_room(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """A fleet at rest makes no new global map: the folder kept the map from before the disk
    filled until the next one came, which for a parked fleet was never."""
    monkeypatch.setattr(files_output, "WRITE_RETRY_S", 0.05)
    full = [True]
    real_save = files_output.save_map

    def save_map(*args: Any, **kw: Any) -> None:
        if full[0]:
            raise ENOSPC
        real_save(*args, **kw)

    monkeypatch.setattr(files_output, "save_map", save_map)
    caplog.set_level(logging.INFO, logger="mapd.outputs.files")
    grid = room_grid(40, 50, seed=4)
    update = GlobalUpdate(grid=grid, frames={"a": Pose2D(1.0, 2.0, 0.0)}, stamp=5.0, versions={"a": 9})

    async def main() -> None:
        out = FilesOutput(FilesOptions(dir=tmp_path / "out", name="fleet"), OutputContext("base", "f"))
        await out.start()
        try:
            await asyncio.to_thread(out.publish, update)
            stats = out.stats()
            assert stats["writing"] is False and stats["written"] == 0
            assert "No space left on device" in str(stats["error"])
            full[0] = False  # room again, and no new map comes
            end = time.monotonic() + 10
            while out.stats()["written"] == 0:
                assert time.monotonic() < end, "the last map was not written again"
                await asyncio.sleep(0.01)
            assert out.stats()["writing"] is True and "error" not in out.stats()
        finally:
            await out.close()

    asyncio.run(main())
    assert load_map(tmp_path / "out" / "fleet.yaml").same_map(grid)
    assert json.loads((tmp_path / "out" / "transforms.json").read_text())["robots"]["a"]["version"] == 9
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 2 and "trying again every" in said[0] and "writing to" in said[1], said
