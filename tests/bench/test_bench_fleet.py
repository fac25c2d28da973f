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
