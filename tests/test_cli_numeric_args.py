"""Every numeric option of a ``mapd`` command is bounded: a negative, NaN, infinite or huge value is
one error line and a non-zero exit at once, never a run of hours or a report of nothing.

Each case runs the real command (a subprocess, as a user does); ``{out}`` is a path the command
would write to, so its absence afterwards shows that nothing ran.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from mapd.cli import build_parser
from mapd.grid import OccupancyGrid
from mapd.grid.save import save_map

REPO = Path(__file__).resolve().parents[1]
#: What a refused value may take: parsing, or a check before any work. The commands it guards
#: against ran for hours; the subprocess's own limit is far above it.
FAST_S = 20.0

# (argv, what the error line must name). ``{out}``: a path the command writes; ``{file}``: an
# existing file; ``{maps}``: a folder with one map.
CASES: list[tuple[str, str]] = [
    # mapd demo
    ("demo --duration -5 --out {out}", "--duration"),
    ("demo --duration nan --out {out}", "--duration"),
    ("demo --duration 1e12 --out {out}", "--duration"),
    ("demo --robots 1 --out {out}", "--robots"),
    ("demo --robots 1000 --out {out}", "--robots"),
    ("demo --seed -1 --out {out}", "--seed"),
    ("demo --view 70000 --out {out}", "--view"),
    ("demo --drop 2 --out {out}", "--drop"),
    ("demo --flip nan --out {out}", "--flip"),
    ("demo --outage nan:1 --out {out}", "--outage"),
    ("demo --outage 0:inf --out {out}", "--outage"),
    # mapd bench fleet
    ("bench fleet --duration -1 --robots 2 --out {out}", "--duration"),
    ("bench fleet --robots 1 --duration 5 --out {out}", "--robots"),
    ("bench fleet --seed -1 --robots 2 --out {out}", "--seed"),
    # mapd bench swarm
    ("bench swarm --duration nan --robots 2 --cache {out}", "--duration"),
    ("bench swarm --duration 1e12 --robots 2 --cache {out}", "--duration"),
    ("bench swarm --robots 2 1000 --cache {out}", "--robots"),
    ("bench swarm --sim -1 --robots 2 --cache {out}", "--sim"),
    ("bench swarm --period 0 --robots 2 --cache {out}", "--period"),
    ("bench swarm --drain -1 --robots 2 --cache {out}", "--drain"),
    ("bench swarm --rate inf --robots 2 --cache {out}", "--rate"),
    ("bench swarm --loss 1.5 --robots 2 --cache {out}", "--loss"),
    ("bench swarm --wall-loss nan --robots 2 --cache {out}", "--wall-loss"),
    ("bench swarm --range nan --robots 2 --cache {out}", "--range"),
    ("bench swarm --building 1e9x20 --robots 2 --cache {out}", "--building"),
    ("bench swarm --building nanx20 --robots 2 --cache {out}", "--building"),
    ("bench swarm --scan-rate 0 --robots 2 --cache {out}", "--scan-rate"),
    ("bench swarm --guard-ms -1 --robots 2 --cache {out}", "--guard-ms"),
    ("bench swarm --clock-skew nan --robots 2 --cache {out}", "--clock-skew"),
    ("bench swarm --slot-ms 0 --robots 2 --cache {out}", "--slot-ms"),
    ("bench swarm --inflight-s inf --robots 2 --cache {out}", "--inflight-s"),
    ("bench swarm --keyframe-every 0 --robots 2 --cache {out}", "--keyframe-every"),
    ("bench swarm --seed -1 --robots 2 --cache {out}", "--seed"),
    ("bench swarm --target nan --robots 2 --cache {out}", "--target"),
    # mapd bench paper
    ("bench paper --sim 0 --duration 1e12 --out {out}", "--duration"),
    ("bench paper --sim 0 --duration nan --out {out}", "--duration"),
    ("bench paper --sim 0 --period 1e-9 --out {out}", "--period"),
    ("bench paper --sim 0 --robots 100 --out {out}", "--robots"),
    ("bench paper --sim 0 --limit 0 --out {out}", "--limit"),
    ("bench paper --log {file} --resolution inf --out {out}", "--resolution"),
    # mapd bench link, merge, codec (their output goes to the terminal: nothing to look for)
    ("bench link --size -1", "--size"),
    ("bench link --size 100000000", "--size"),
    ("bench link --rate-bps nan", "--rate-bps"),
    ("bench link --seed -1", "--seed"),
    ("bench link --outage-at inf --scenarios faulty", "--outage-at"),
    ("bench link --pose-period 0 --scenarios poses", "--pose-period"),
    ("bench link --idle nan --scenarios poses", "--idle"),
    ("bench merge --pairs 100000000 --no-real", "--pairs"),
    ("bench merge --repeat 100000000 --no-real", "--repeat"),
    ("bench merge --only -1 --no-real", "--only"),
    ("bench codec --repeat 1000000000", "--repeat"),
    # mapd link send | recv
    ("link send {file} --port /dev/null --deadline nan", "--deadline"),
    ("link send {file} --port /dev/null --peer-timeout 0", "--peer-timeout"),
    ("link send {file} --port /dev/null --node 0", "--node"),
    ("link send {file} --port /dev/null --baud -5", "--baud"),
    ("link send {file} --port /dev/null --rate-bps 1000000000000", "--rate-bps"),
    ("link send {file} --port /dev/null --max-frame 100000", "--max-frame"),
    ("link recv -o {out} --port /dev/null --timeout inf", "--timeout"),
    ("link recv -o {out} --port /dev/null --linger -1", "--linger"),
    ("link recv -o {out} --port /dev/null --peer 999", "--peer"),
    # mapd replay, train
    ("replay {file} -o {out} --max-range inf", "--max-range"),
    ("replay {file} -o {out} --max-range -1", "--max-range"),
    ("train --maps {maps} -o {out} --snapshots-sim 1 --sim-scans 1000000000000", "--sim-scans"),
    ("train --maps {maps} -o {out} --snapshots-sim -1", "--snapshots-sim"),
]


def _mapd(argv: list[str]) -> tuple[int, str]:
    """Run ``mapd argv`` in a session of its own; return its exit code and stderr. Whatever it
    started is killed afterwards: a command that ran (the fault) must not leave daemons behind."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", *argv],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        err: str | None = proc.communicate(timeout=60)[1]
    except subprocess.TimeoutExpired:
        err = None
    with contextlib.suppress(ProcessLookupError):  # else it started nothing that outlived it
        os.killpg(proc.pid, signal.SIGKILL)
    if err is None:
        proc.communicate()
        pytest.fail(f"mapd {' '.join(argv)}: still running after 60 s")
    return proc.returncode, err


def _argv(case: str, tmp_path: Path) -> list[str]:
    # a map to train on, so that only the bad number can stop mapd train
    save_map(OccupancyGrid(np.zeros((32, 32), dtype=np.int8), 0.05), tmp_path / "maps" / "room" / "room.yaml")
    (tmp_path / "input").write_text("a file the command must never get to read\n")
    paths = {"out": tmp_path / "out", "file": tmp_path / "input", "maps": tmp_path / "maps"}
    return [word.format(**paths) for word in case.split()]


@pytest.mark.parametrize(("case", "option"), CASES, ids=[c for c, _ in CASES])
def test_a_bad_number_is_one_error_line_and_nothing_runs(tmp_path: Path, case: str, option: str) -> None:
    t0 = time.monotonic()
    code, err = _mapd(_argv(case, tmp_path))
    elapsed = time.monotonic() - t0
    assert code in (1, 2), (code, err)
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    errors = [line for line in lines if "error:" in line]
    # argparse's usage may come first; the error is one line, the last, naming the option
    assert errors == lines[-1:], err
    assert option in errors[0], errors[0]
    assert elapsed < FAST_S, f"{case}: {elapsed:.1f} s"
    assert not (tmp_path / "out").exists(), f"{case}: wrote its output"


def _actions(parser: argparse.ArgumentParser, prog: str) -> Iterator[tuple[str, argparse.Action]]:
    """Every option of ``parser`` and of its subcommands, with the command it belongs to."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _actions(sub, f"{prog} {name}")
        else:
            yield prog, action


def _numeric_defaults() -> list[tuple[str, argparse.Action, Any]]:
    out = []
    for prog, action in _actions(build_parser(), "mapd"):
        values = action.default if isinstance(action.default, list) else [action.default]
        for v in values:
            if action.type is not None and isinstance(v, int | float) and not isinstance(v, bool):
                out.append((prog, action, v))
    return out


NUMERIC_DEFAULTS = _numeric_defaults()


def test_the_bounded_options_are_all_found() -> None:
    # the walk below must see the options this file bounds, or it would pass on nothing
    found = {(prog, a.option_strings[-1]) for prog, a, _ in NUMERIC_DEFAULTS}
    for want in [
        ("mapd demo", "--duration"),
        ("mapd bench swarm", "--duration"),
        ("mapd bench paper", "--duration"),
        ("mapd bench fleet", "--robots"),
        ("mapd link recv", "--linger"),
        ("mapd train", "--sim-scans"),
    ]:
        assert want in found
    assert len(NUMERIC_DEFAULTS) >= 60


@pytest.mark.parametrize(
    ("prog", "action", "default"),
    NUMERIC_DEFAULTS,
    ids=[f"{p} {a.option_strings[-1]}={d}" for p, a, d in NUMERIC_DEFAULTS],
)
def test_every_default_is_within_its_own_bounds(prog: str, action: argparse.Action, default: Any) -> None:
    # argparse does not pass a number default through type=: a bound tighter than the default would
    # go unnoticed until someone typed the default. Parse it as if typed.
    assert action.type is not None and callable(action.type)
    typed = action.type(repr(default) if isinstance(default, float) else str(default))
    assert typed == default


@pytest.mark.parametrize(
    "argv",
    [
        ["demo"],
        ["bench", "fleet"],
        ["bench", "swarm"],
        ["bench", "paper", "--sim", "0", "--out", "o"],
        ["bench", "link"],
        ["bench", "merge"],
        ["bench", "codec"],
        ["link", "send", "f", "--port", "p"],
        ["link", "recv", "-o", "f", "--port", "p"],
        ["replay", "log", "-o", "o"],
        ["train", "-o", "o"],
    ],
    ids=" ".join,
)
def test_a_command_with_its_defaults_parses(argv: list[str]) -> None:
    args = build_parser().parse_args(argv)
    assert callable(args.func)


@pytest.mark.parametrize(
    ("option", "field"), [("--baud", "baud"), ("--rate-bps", "link_rate_bps"), ("--max-frame", "max_frame")]
)
def test_mapd_link_takes_what_the_uwb_config_takes(option: str, field: str) -> None:
    # The CLI's bounds are written beside the config's (the CLI does not import transports at
    # start): each end of the config's range parses, one past either end is refused.
    from transports.uwb.options import UwbOptions

    bounds = {type(m).__name__: m for m in UwbOptions.model_fields[field].metadata}
    low, high = bounds["Ge"].ge, bounds["Le"].le  # type: ignore[attr-defined]
    parser = build_parser()
    base = ["link", "send", "f", "--port", "/dev/null"]
    for ok in (low, high):
        assert getattr(parser.parse_args([*base, option, str(ok)]), field.replace("link_", "")) == ok
    for bad in (low - 1, high + 1):
        with pytest.raises(SystemExit):
            parser.parse_args([*base, option, str(bad)])
