"""Over uwb a sender says when a peer's radio acks its maps but the peer's daemon refuses them.

Measured before (two ``mapd run`` over socat ptys and the emulated radio, robot1 with a
``limits.max_cells`` smaller than robot0's maps): robot1 said why once ("maps of robot0 refused:
... over limits.max_cells"), and robot0 said nothing; its ``mapd status`` showed robot1 as having
"acked our" newest version, as if it held it. Now robot0 reads robot1's relay summaries (the
versions robot1's daemon holds): acked at the radio, held by none, it says so once and shows it.

And not of a peer that merely restarted, holding our maps from its state directory: see
tests/daemon/test_uwb_relay_restart.py (and the restart floor's unit tests in
tests/transports/uwb/test_uwb_refused.py).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.daemon.headline import status_line


def _refused_by(s: dict[str, Any]) -> dict[str, Any]:
    return s.get("robot0", {}).get("links", {}).get("uwb", {}).get("refused_by") or {}


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("socat") is None, reason="socat is not installed")
def test_uwb_sender_says_once_that_a_peer_refuses_the_maps_its_radio_acks(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    period = 1.0  # summaries each second: judged 3 s after an ack, found a second later

    def summaries(cfg: dict[str, Any]) -> None:
        cfg["transports"]["uwb"]["summary_period_s"] = period

    def small_limits(cfg: dict[str, Any]) -> None:
        summaries(cfg)
        # robot1 maps a small building (25 600 cells), and takes no larger map: robot0's, every one
        cfg["source"]["sim"].update(width_m=6.0, height_m=6.0)
        cfg["limits"] = {"max_cells": 30000}

    f = fk.demo_fleet(tmp_path, 2, transport="uwb", edit={"robot0": summaries, "robot1": small_limits})
    logs = {n: f.run_dir / n / "daemon.log" for n in f.names}

    def lines(robot: str, *words: str) -> list[str]:
        text = logs[robot].read_text(errors="replace") if logs[robot].exists() else ""
        return [ln for ln in text.splitlines() if all(w in ln for w in words)]

    f.start()
    try:
        snaps = fk.wait_for(lambda s: "robot1" in _refused_by(s), 35, f)
        # robot1's radio acked robot0's maps (robot0's "acked our") and its daemon holds none of them
        refused = _refused_by(snaps)["robot1"]
        assert refused["acked"] > 0 and refused["holds"] == 0, refused
        assert snaps["robot0"]["peers"]["robot1"]["acked_our_version"] > 0
        assert snaps["robot0"]["links"]["uwb"]["refused_by_peers"] == 1
        # robot1 said why, on its side
        assert lines("robot1", "WARNING", "maps of robot0 refused", "limits.max_cells"), lines(
            "robot1", "robot0"
        )
        text = fk.status_text(f.run_dir / "robot0" / "run" / "mapd.sock")
        assert "1 peers ack this robot's maps at the radio but their daemons refuse them" in text, text
        assert "daemons refusing our maps their radios ack: robot1 (acked v" in text, text
        assert "FAULTS acks our maps at the radio (uwb) but its daemon refuses them" in text, text
        assert "peers ack this robot's maps at the radio" in status_line(snaps["robot0"])

        # The other way round robot0 takes robot1's maps: robot1, judging its acks as long, says nothing.
        def rx(s: dict[str, Any]) -> int:
            return int(s.get("robot1", {}).get("links", {}).get("uwb", {}).get("relay_summaries_rx", 0))

        snaps = fk.wait_for(lambda s: s["robot1"]["peers"]["robot0"].get("acked_our_version", 0) > 0, 20, f)
        acked_at = rx(snaps)
        snaps = fk.wait_for(lambda s: rx(s) >= acked_at + 6, 20, f)  # the margin (3 periods), and more
        assert snaps["robot1"]["links"]["uwb"]["refused_by"] == {}
        assert snaps["robot1"]["links"]["uwb"]["refused_by_peers"] == 0
        assert "robot1" in _refused_by(snaps)  # still so
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
    said = lines("robot0", "acks our maps at the radio")
    assert len(said) == 1, said  # once, while it lasts
    assert (
        "WARNING" in said[0] and "uwb: robot1 acks our maps at the radio but its daemon holds none" in said[0]
    )
    assert "holds none): it refuses them; its log and mapd status say why" in said[0]
    assert not lines("robot1", "acks our maps at the radio")
    for n in f.names:
        assert "Traceback" not in logs[n].read_text(errors="replace")
