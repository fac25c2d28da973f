"""A daemon restarted from its state directory is not sent again, by relay, the maps it holds.

Three ``mapd run`` on the emulated radio, robot0 and robot2 out of each other's range, robot1 between
them relaying. robot2 makes no map of its own and holds robot0's, through robot1. Killed and started
again, it holds robot0's map from its state directory, but its relay summaries listed only the
maps its daemon had taken since it started: none. So robot1 forwarded it robot0's keyframe again
(measured: one more relay, with robot0's map unchanged). On a 12.5 kb/s channel each such keyframe
takes a relay's turns for minutes, for every robot the restarted one held, after every restart.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

PERIOD = 1.0  # relay summaries each second


def _uwb(s: dict[str, Any], robot: str) -> dict[str, Any]:
    return s.get(robot, {}).get("links", {}).get("uwb", {})


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
def test_a_restarted_daemon_lists_its_restored_maps_so_no_relay_sends_them_again(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    def fast(cfg: dict[str, Any]) -> None:
        cfg["transports"]["uwb"]["summary_period_s"] = PERIOD
        cfg["source"]["sim"]["duration"] = 12.0  # sim seconds: a few maps, then none

    def receiver_only(cfg: dict[str, Any]) -> None:
        fast(cfg)
        cfg["source"] = {"use": "none"}

    f = fk.demo_fleet(
        tmp_path,
        3,
        transport="uwb",
        out_of_range=["0-2"],
        edit={"robot0": fast, "robot1": fast, "robot2": receiver_only},
    )
    f.start()
    try:
        # robot0 done mapping, and its last map at robot2 through robot1
        snaps = fk.wait_for(
            lambda s: (
                len(s) == 3
                and s["robot0"]["source"].get("finished")
                and fk.version(s, "robot2", "robot0") == s["robot0"]["source"]["version"]
            ),
            90,
            f,
        )
        final = snaps["robot0"]["source"]["version"]
        assert _uwb(snaps, "robot1")["relays_tx"] >= 1  # it came by relay
        # Settled: robot2's summaries heard for a while, no relay under way.
        heard = _uwb(snaps, "robot1")["relay_summaries_rx"]
        snaps = fk.wait_for(lambda s: _uwb(s, "robot1")["relay_summaries_rx"] >= heard + 6, 20, f)
        before = _uwb(snaps, "robot1")

        fk.kill9(f, "robot2")
        fk.restart(f, "robot2")
        snaps = fk.wait_for(lambda s: fk.version(s, "robot2", "robot0") == final, 30, f)
        assert snaps["robot2"]["peers"]["robot0"].get("restored") is True  # from its state directory
        back = _uwb(snaps, "robot1")["relay_summaries_rx"]
        # Summaries of robot2 since its restart, well past what robot1 needs to decide (it relays
        # within a relay period of a summary that shows a neighbour lacking a map).
        snaps = fk.wait_for(lambda s: _uwb(s, "robot1")["relay_summaries_rx"] >= back + 12, 30, f)
        after = _uwb(snaps, "robot1")
        assert snaps["robot0"]["source"]["version"] == final  # robot0's map did not change
        assert after["relays_tx"] == before["relays_tx"], (before["relays_tx"], after["relays_tx"])
        assert after["relay_keyframes_asked"] == before["relay_keyframes_asked"]
        # Nor is robot2 said to refuse robot1's maps, which its radio acked before the restart and
        # its daemon holds from disk (judged without refused.py's restart floor, on summaries that
        # did not list restored maps, both its peers said so 30 s after, of maps no longer changing).
        assert after["refused_by"] == {} and after["refused_by_peers"] == 0
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}
    for log in sorted(f.run_dir.glob("robot*/daemon*.log")):
        text = log.read_text(errors="replace")
        assert "acks our maps at the radio" not in text and "Traceback" not in text, log
