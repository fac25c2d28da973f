"""``mapd bench fleet``: bad input is one line before any daemon starts."""

from __future__ import annotations

from pathlib import Path

import pytest

from mapd.cli import main


def test_an_unknown_codec_is_refused_before_any_daemon_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "fleet"
    rc = main(["bench", "fleet", "--codec", "nope", "--robots", "2", "--duration", "1", "--out", str(out)])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    assert rc == 1
    errors = [ln for ln in err.splitlines() if ln.startswith("mapd: error: ")]
    assert len(errors) == 1 and errors[0].startswith("mapd: error: no codec plugin named 'nope' "), errors
    assert "running" not in err  # no "fleet of 2: running ..." line
    assert not out.exists()  # no daemon's folder made


@pytest.mark.slow
def test_two_daemons_measure_latency_bytes_cpu_memory_and_their_loops(tmp_path: Path) -> None:
    """The bench end to end as the README runs it, at its smallest: two real daemons for 12 s."""
    import json
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-m", "mapd", "bench", "fleet", "--robots", "2", "--duration", "12",
         "--out", str(tmp_path / "fleet"), "--json"],
        capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    (row,) = json.loads(proc.stdout)
    assert row["robots"] == 2 and row["samples"] > 0  # each robot's maps fused by the other
    assert 0 < row["latency_p50_ms"] <= row["latency_p95_ms"] < 12_000
    assert row["payload_bps_per_robot"] > 0 and row["wire_bps_per_robot"] >= row["payload_bps_per_robot"]
    assert row["cpu_per_daemon"] > 0 and row["rss_mb_per_daemon"] > 50
    # each daemon's event loop was measured (NaN: a daemon that reported none)
    assert 0 <= row["loop_p99_ms"] <= row["loop_max_ms"], row
