"""A real daemon on the mapfile source survives half-written and malformed map files.

Before the fix a PGM cut after ``P5\\n100 `` made ``mapd run`` exit 1 with a traceback, and systemd
restarted it into the same crash for as long as the file stayed that way.
"""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.daemon.versions import incarnation_at, split
from mapd.grid import OccupancyGrid
from mapd.grid.save import save_map
from mapd.mapping.synthetic import room_grid

pytestmark = pytest.mark.slow


def _status(sock: Path) -> dict[str, Any] | None:
    out = subprocess.run(
        [sys.executable, "-m", "mapd", "status", "--json", "--socket", str(sock)],
        capture_output=True,
        text=True,
        timeout=30,
    )
    return json.loads(out.stdout) if out.returncode == 0 else None


def _wait(
    proc: subprocess.Popen[bytes], sock: Path, cond: Callable[[dict[str, Any]], bool], what: str
) -> dict[str, Any]:
    deadline = time.monotonic() + 60
    last: dict[str, Any] | None = None
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the daemon exited with {proc.returncode} while waiting for {what}"
        last = _status(sock)
        if last is not None and cond(last):
            return last
        time.sleep(0.3)
    raise AssertionError(f"{what} not reached: {json.dumps(last)[:1500]}")


def _map(k: int) -> OccupancyGrid:
    g = room_grid(60, 80, seed=k)
    data = g.data.copy()
    data[5 : 8 + k, 5:20] = 100
    return g.replace(data=data.astype(np.int8))


@contextlib.contextmanager
def _daemon(tmp_path: Path, path: Path) -> Iterator[tuple[subprocess.Popen[bytes], Path, Path]]:
    """``mapd run`` on the mapfile source of ``path``, state in ``tmp_path/state``: the process,
    its control socket and its log; killed on the way out if a test did not stop it."""
    run = tmp_path / "run"
    config = tmp_path / "config.toml"
    config.write_text(
        f'[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        f'[source]\nuse = "mapfile"\n[source.mapfile]\npath = "{path}"\npoll_s = 0.1\nsettle_s = 0.1\n'
        f'[codec]\nuse = "raw"\n[state]\ndir = "{tmp_path / "state"}"\nruntime_dir = "{run}"\n'
    )
    log = tmp_path / "daemon.log"
    with log.open("wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "mapd", "run", "--config", str(config)],
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        yield proc, run / "mapd.sock", log
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)


def test_daemon_keeps_its_last_good_map_through_bad_files(tmp_path: Path) -> None:
    path = tmp_path / "map.yaml"
    save_map(_map(0), path)
    whole_pgm = path.with_suffix(".pgm").read_bytes()
    whole_yaml = path.read_text()
    with _daemon(tmp_path, path) as (proc, sock, log):
        # The source counts a map on its worker; the daemon takes it (the version shown) a step later.
        first = _wait(
            proc,
            sock,
            lambda s: s["source"]["stats"]["versions"] == 1 and s["source"]["version"] > 0,
            "the first map",
        )
        version = first["source"]["version"]
        bad_files = [
            (".pgm", b"P5\n100 ", "truncated in its PNM header"),
            (".pgm", whole_pgm[: len(whole_pgm) // 2], "ends early"),
            (".pgm", b"P5\n80 60\n0\n" + whole_pgm[-4800:], "maxval 0"),
            (".yaml", whole_yaml[: whole_yaml.index("resolution") + 4], "malformed YAML (line 3)"),
            (".yaml", "origin: " + "[" * 3000, "nested too deeply"),
        ]
        for suffix, content, reason in bad_files:
            target = path.with_suffix(suffix)
            if isinstance(content, bytes):
                target.write_bytes(content)
            else:
                target.write_text(content)
            st = _wait(proc, sock, lambda s, r=reason: r in s["source"]["stats"]["last_error"], reason)
            # Still the last good map: no new version, nothing padded or half-read was published.
            assert st["source"]["version"] == version and st["source"]["stats"]["versions"] == 1
            path.write_text(whole_yaml)
            path.with_suffix(".pgm").write_bytes(whole_pgm)
        save_map(_map(4), path)  # the writer finishes a new map: it goes out as the next version
        st = _wait(
            proc,
            sock,
            lambda s: s["source"]["stats"]["versions"] == 2 and s["source"]["version"] > version,
            "the second map",
        )
        assert st["source"]["version"] > version and st["source"]["stats"]["load_errors"] == len(bad_files)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
    text = log.read_text()
    assert "Traceback" not in text, text
    warned = [line for line in text.splitlines() if "mapd.sources.mapfile" in line]
    assert len(warned) == len(bad_files), text  # one line per fault, not one per poll


def test_a_damaged_state_directory_is_warned_and_the_daemon_runs(tmp_path: Path) -> None:
    # Before: each of these stopped `mapd run` at start with a traceback (OverflowError for JSON's
    # infinity, AttributeError for a placement that is a list), and systemd restarted it into it.
    path = tmp_path / "map.yaml"
    save_map(_map(0), path)
    state = tmp_path / "state"
    (state / "global").mkdir(parents=True)
    (state / "state.json").write_text('{"own_version": 1e999, "seq": 3}')
    huge = "1" + "0" * 400  # JSON allows it; no float holds it
    (state / "global" / "transforms.json").write_text(
        f'{{"version": 3, "robots": {{"r1": [1], "r2": {{"robot": "r2", "x": {huge}, "y": 0, "yaw": 0}}}}}}'
    )
    with _daemon(tmp_path, path) as (proc, sock, log):
        st = _wait(proc, sock, lambda s: s["fusion"]["merges"] >= 1, "the first merge")
        # A new incarnation from the clock, as after a lost disk: its versions are ones peers take.
        incarnation = split(st["source"]["version"])[0]
        assert abs(incarnation - incarnation_at(time.time())) < 120
        assert set(st["fusion"]["robots"]) == {"r0"}  # the damaged placements left out
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0
    text = log.read_text()
    assert "Traceback" not in text, text
    assert "state.json unreadable (own_version inf" in text, text
    assert "ignoring entry 'r1'" in text and "ignoring entry 'r2'" in text, text
    assert json.loads((state / "state.json").read_text())["own_version"] == st["source"]["version"]
