"""The event loop's lateness (mapd/daemon/loop_lag.py): the meter on its own, what ``mapd status``
prints of it, and a real daemon stopped for a second and a half that says so once."""

from __future__ import annotations

import asyncio
import os
import signal
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.commands.status_text import _loop_line
from mapd.daemon.headline import loop_cause, loop_held, status_line
from mapd.daemon.loop_lag import SAY_EVERY_S, STALL_S, LagMeter, cause, watch


def test_the_meter_keeps_the_largest_lag_since_start_and_over_the_recent_window() -> None:
    m = LagMeter(period_s=0.1, recent_s=60.0)
    t = 0.0
    for lag in (0.002, 0.2, 0.004):
        t += 0.1
        assert m.tick(lag, t) is None
    s = m.stats(t)
    assert s["lag_ms_recent_max"] == 200.0 and s["lag_ms_max"] == 200.0 and s["stalls"] == 0
    for _ in range(700):  # 70 s of small lags: the 200 ms one leaves the window, not the total
        t += 0.1
        m.tick(0.001, t)
    s = m.stats(t)
    assert s["lag_ms_recent_max"] == 1.0 and s["lag_ms_max"] == 200.0
    assert m.stats(t + 120)["lag_ms_recent_max"] == 0.0  # nothing measured lately: nothing late


def test_the_recent_99th_percentile_and_a_bounded_window() -> None:
    m = LagMeter(period_s=0.1, recent_s=60.0)
    for i in range(100):  # lags 0..99 ms
        m.tick(i / 1000, 1.0 + i * 0.1)
    s = m.stats(1.0 + 99 * 0.1)
    assert s["lag_ms_recent_p99"] == 98.0 and s["lag_ms_recent_max"] == 99.0
    for i in range(20_000):  # ticks faster than the period (a clock that jumps) stay bounded too
        m.tick(0.0, 20.0 + i * 1e-4)
    assert len(m._recent) <= int(60.0 / 0.1) + 16
    assert m.tick(-0.5, 30.0) is None and m.stats(30.0)["lag_ms_recent_max"] == 0.0  # early: not late


def test_stalls_are_counted_and_the_long_ones_said_once_a_minute_with_how_many() -> None:
    m = LagMeter()
    assert m.tick(STALL_S + 0.05, 10.0) is None  # a stall, too short to say
    first = m.tick(1.52, 20.0)
    assert first is not None and "held 1.52 s" in first and "more" not in first
    assert m.tick(1.3, 30.0) is None and m.tick(2.0, 40.0) is None  # within the minute: counted only
    again = m.tick(1.1, 20.0 + SAY_EVERY_S)
    assert again is not None and "held 1.10 s (2 more of 1 s or longer since the last said)" in again
    s = m.stats(20.0 + SAY_EVERY_S + 5)
    assert s["stalls"] == 5 and s["last_stall_ms"] == 1100 and s["last_stall_ago_s"] == 5.0
    assert s["lag_ms_max"] == 2000.0


def test_status_says_a_recent_long_stall_as_a_fault_and_an_old_one_as_a_count() -> None:
    m = LagMeter()
    for i in range(50):
        m.tick(0.003, i * 0.1)
    quiet = _loop_line(m.stats(5.0), loop_held({"loop": m.stats(5.0)}))
    assert quiet.startswith("loop    late by at most 3 ms in the last 60s (p99 3 ms), 3 ms since start")
    assert quiet.endswith("no stalls of 250 ms or more") and "FAULTS" not in quiet
    m.tick(1.52, 6.0)
    doc = {"loop": m.stats(16.0)}
    assert loop_held(doc) == 1.52
    held = _loop_line(doc["loop"], loop_held(doc))
    assert held.startswith("loop    FAULTS the event loop was held 1.52 s 10s ago (1 stall in all)"), held
    doc = {"loop": m.stats(90.0)}  # out of the recent window: no fault, still counted
    assert loop_held(doc) is None
    old = _loop_line(doc["loop"], None)
    assert "FAULTS" not in old and old.endswith("1 stall of 250 ms or more, the last 1.52 s, 84s ago"), old


def test_the_systemd_status_line_puts_a_recent_hold_first_and_only_a_long_one() -> None:
    m = LagMeter()
    m.tick(0.6, 1.0)  # a stall, not a hold worth a fault
    doc: dict[str, Any] = {"source": {"version": 3}, "loop": m.stats(2.0)}
    assert not status_line(doc).startswith("FAULTS")
    m.tick(2.25, 3.0)
    doc["loop"] = m.stats(4.0)
    assert status_line(doc).startswith(
        "FAULTS event loop held 2.25 s (overloaded, swapping or stopped?) | map v3"
    )
    doc["loop"] = m.stats(3.0 + 61.0)
    assert not status_line(doc).startswith("FAULTS")


def test_a_hold_says_whether_the_loop_ran_code_or_waited() -> None:
    """The loop thread's CPU time during a hold tells the two causes apart: work on the loop (a bug
    to report) or waiting to run (an overloaded, swapping or stopped computer, or a blocking call)."""
    busy = LagMeter()
    said = busy.tick(1.5, 10.0, ran_s=1.45)
    assert said is not None and "held 1.50 s, running code on it for 1.45 s" in said and "worker" in said
    doc = {"loop": busy.stats(11.0)}
    assert doc["loop"]["last_stall_ran_ms"] == 1450 and loop_cause(doc) == "busy"
    line = _loop_line(doc["loop"], loop_held(doc))
    assert line.startswith("loop    FAULTS the event loop was held 1.50 s 1s ago (1 stall in all), running")
    assert "running code on it for 1.45 s: work that belongs in a worker thread" in line, line
    assert status_line(doc).startswith("FAULTS event loop held 1.50 s (code ran on it: a bug)")
    old = _loop_line(busy.stats(90.0), None)
    assert old.endswith("the last 1.50 s, running code on the loop, 80s ago"), old

    waited = LagMeter()
    said = waited.tick(1.5, 10.0, ran_s=0.02)
    assert said is not None and "held 1.50 s, waiting (it ran 0.02 s of it)" in said and "worker" not in said
    doc = {"loop": waited.stats(11.0)}
    assert loop_cause(doc) == "waiting"
    line = _loop_line(doc["loop"], loop_held(doc))
    assert "held 1.50 s 1s ago (1 stall in all), waiting (it ran 0.02 s of it): radio turns" in line, line
    assert status_line(doc).startswith("FAULTS event loop held 1.50 s (overloaded, swapping or stopped?)")

    # A thread's CPU time cannot pass the wall time: a wild reading is kept within the hold.
    wild = LagMeter(period_s=0.1)
    wild.tick(1.5, 10.0, ran_s=9.0)
    assert wild.stats(10.0)["last_stall_ran_ms"] == 1600
    assert cause(1000, 334) == "busy" and cause(1000, 300) == "waiting"
    assert cause(1000, None) is None and cause("1000", 5) is None and cause(0, 0) is None
    # a daemon from before the figure: the hold is said as before, without a cause
    unmeasured = LagMeter()
    assert unmeasured.tick(1.5, 10.0) is not None and unmeasured.stats(11.0)["last_stall_ran_ms"] is None
    assert loop_cause({"loop": unmeasured.stats(11.0)}) is None


def test_the_watcher_on_a_real_loop_tells_code_run_on_it_from_a_blocking_wait() -> None:
    async def main() -> tuple[Any, Any]:
        meter = LagMeter()
        task = asyncio.create_task(watch(meter))
        await asyncio.sleep(0.25)
        start = time.thread_time()
        while time.thread_time() - start < 1.2:  # a callback working on the loop for 1.2 s of CPU
            pass
        await asyncio.sleep(0.25)
        worked = meter.last_stall
        time.sleep(1.2)  # a call that blocks the loop: its thread runs nothing meanwhile
        await asyncio.sleep(0.25)
        blocked = meter.last_stall
        task.cancel()
        return worked, blocked

    worked, blocked = asyncio.run(main())
    assert worked is not None and worked[1] >= 1.1 and worked[2] >= 1.1, worked
    assert cause(worked[1] * 1000, worked[2] * 1000) == "busy"
    assert blocked is not None and blocked is not worked and blocked[1] >= 1.1 and blocked[2] < 0.3, blocked
    assert cause(blocked[1] * 1000, blocked[2] * 1000) == "waiting"


@pytest.mark.parametrize(
    "doc",
    [{}, {"stalls": "x", "last_stall_ms": None}, {"stalls": 3, "last_stall_ms": "1e9", "recent_s": []},
     {"stalls": 2, "last_stall_ms": 5000, "last_stall_ago_s": None, "lag_ms_max": float("nan")}],
)  # fmt: skip
def test_status_reads_a_loop_document_it_cannot_trust_without_failing(doc: dict[str, Any]) -> None:
    line = _loop_line(doc, loop_held({"loop": doc}))
    assert line.startswith("loop    ") and "\n" not in line and "FAULTS" not in line
    assert "FAULTS" not in status_line({"loop": doc})


@pytest.mark.slow
def test_a_daemon_stopped_for_a_second_and_a_half_says_its_loop_was_held_once(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    """Two ``mapd run`` over zenoh; robot0 gets SIGSTOP, then SIGCONT 1.5 s later (as an overloaded
    or swapping computer, or a debugger, would hold it). Before: nothing said it anywhere."""
    f = fk.demo_fleet(tmp_path, 2)
    f.start()
    try:
        fk.wait_for(lambda s: "loop" in s.get("robot0", {}) and "loop" in s.get("robot1", {}), 30, f)
        pid = f.procs["robot0"].pid
        os.kill(pid, signal.SIGSTOP)
        try:
            time.sleep(1.5)
        finally:
            os.kill(pid, signal.SIGCONT)
        snaps = fk.wait_for(
            lambda s: (s.get("robot0", {}).get("loop", {}).get("last_stall_ms") or 0) >= 1300, 20, f
        )
        lp = snaps["robot0"]["loop"]
        assert lp["stalls"] >= 1 and lp["lag_ms_max"] >= 1300 and lp["lag_ms_recent_max"] >= 1300, lp
        text = fk.status_text(f.run_dir / "robot0" / "run" / "mapd.sock")
        assert "loop    FAULTS the event loop was held 1." in text, text
        assert ", waiting (it ran 0." in text, text  # stopped: its loop ran nothing meanwhile
        # it went on: robot1 still gets its new maps
        had = fk.held(snaps, "robot1", "robot0")
        fk.wait_for(lambda s: fk.held(s, "robot1", "robot0") > had, 20, f)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    log = (f.run_dir / "robot0" / "daemon.log").read_text(errors="replace")
    said = [ln for ln in log.splitlines() if "the event loop was held" in ln]
    assert len(said) == 1 and "WARNING" in said[0] and ", waiting (it ran 0." in said[0], said
    assert "Traceback" not in log
