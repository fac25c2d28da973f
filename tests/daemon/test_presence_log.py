"""Robots coming, going and restarting, said in the log (``mapd.daemon.presence_log``).

Found by an operator's review: after a 25 s radio outage ``mapd status`` had shown the peer gone and
back, and the journal said nothing of either; a robot killed and started again left no trace in the
others' logs.
"""

from __future__ import annotations

import time

import pytest

from mapd.daemon.presence_log import FLAP_CHANGES, FLAP_WINDOW_S, PresenceLog


def test_each_change_is_one_line_with_how_long_the_robot_was_gone() -> None:
    log = PresenceLog()
    assert log.change("robot1", "uwb", True, 0.0) == "robot1 heard on uwb"
    assert log.change("robot1", "uwb", True, 5.0) is None  # no change
    assert log.change("robot1", "uwb", False, 20.0) == "robot1 not heard on uwb any more"
    assert log.change("robot1", "uwb", True, 47.0) == "robot1 back on uwb after 27 s"
    assert log.change("robot1", "zenoh", False, 50.0) is None  # never heard there: nothing to say
    assert log.change("robot2", "uwb", True, 51.0) == "robot2 heard on uwb"


def test_a_robot_that_keeps_coming_and_going_is_said_once_then_left_to_mapd_status() -> None:
    log = PresenceLog()
    log.change("robot1", "uwb", True, 0.0)
    said = [log.change("robot1", "uwb", k % 2 == 0, 10.0 * k) for k in range(1, 40)]  # gone, back, ...
    lines = [s for s in said if s is not None]
    assert len(lines) == FLAP_CHANGES + 1, lines  # each change, then one line, then none
    assert lines[-1].startswith("robot1 comes and goes on uwb (7 changes in 60 s: at the edge of its range?)")
    assert lines[-1].endswith("go unlogged for 10 minutes (mapd status shows it)")
    # 390 s: gone. Once the window is over and it settled, a change is said again
    assert (
        log.change("robot1", "uwb", True, 70.0 + FLAP_WINDOW_S + 1000.0) == "robot1 back on uwb after 1280 s"
    )
    log.forget("robot1")
    assert log.change("robot1", "uwb", True, 5000.0) == "robot1 heard on uwb"


@pytest.mark.slow
def test_a_peer_gone_and_back_and_restarted_is_in_the_daemons_log(tmp_path, fk) -> None:  # type: ignore[no-untyped-def]
    import signal
    import subprocess
    import sys

    f = fk.demo_fleet(tmp_path, 2)
    log0 = f.run_dir / "robot0" / "daemon.log"

    def said(text: str, timeout: float) -> None:  # (robot1 is down meanwhile: no fleet check)
        end = time.monotonic() + timeout
        while text not in log0.read_text(errors="replace"):
            assert time.monotonic() < end, f"robot0 never said {text!r}"
            assert f.procs["robot0"].poll() is None
            time.sleep(0.2)

    f.start()
    try:
        fk.wait_for(lambda s: fk.held(s, "robot0", "robot1") >= 1, 60, f)
        first = f.procs["robot1"]
        first.send_signal(signal.SIGKILL)
        first.wait(10)
        said("robot1 not heard on zenoh any more", 60)
        d = f.run_dir / "robot1"
        f.procs["robot1"] = subprocess.Popen(
            [sys.executable, "-m", "mapd", "run", "--config", str(d / "config.toml")],
            stdout=open(d / "daemon2.log", "wb"),  # noqa: SIM115 - lives as long as the process
            stderr=subprocess.STDOUT,
        )
        said("robot1 back on zenoh after ", 60)
    finally:
        f.stop()
    lines = [ln for ln in log0.read_text(errors="replace").splitlines() if " robot1 " in f" {ln} "]
    assert sum("robot1 heard on zenoh" in ln for ln in lines) == 1, lines
    assert sum("not heard on zenoh any more" in ln for ln in lines) == 1, lines
    assert all(" INFO " in ln for ln in lines if "zenoh" in ln and "heard" in ln)  # (not warnings)


def test_a_restart_is_said_at_most_once_a_minute_per_robot() -> None:
    log = PresenceLog()
    line = "robot1 restarted (a new session on uwb): it gets this robot's next map whole"
    assert log.restarted("robot1", "uwb", 0.0) == line
    assert log.restarted("robot1", "uwb", 30.0) is None  # (forged HELLOs cannot fill the log)
    assert log.restarted("robot2", "uwb", 30.0) is not None
    assert log.restarted("robot1", "uwb", 61.0) == line
