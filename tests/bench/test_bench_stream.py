"""``mapd bench stream`` runs end to end on a short replay and reports consistent totals."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from mapd.bench import stream


def test_stream_bench_short_replay(intel_log: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    stream.add_arguments(parser)
    args = parser.parse_args(
        ["--log", str(intel_log), "--every", "10", "--limit", "4", "--codec", "lossless", "pooled"]
    )
    args.json = True
    assert stream.run(args) == 0
    out = json.loads(capsys.readouterr().out)
    rows = {r["row"]: r for r in out["rows"]}
    assert set(rows) == {
        *(f"{c} {k}" for c in ("lossless", "pooled") for k in ("whole", "delta")),
        "zstd-19 whole",
        "zstd-19 diff",
    }
    assert out["snapshots"] == 4 and out["duration_s"] > 0
    for r in rows.values():
        assert r["snapshots"] == 4
        assert r["ratio"] == pytest.approx(out["raw_cells"] / r["bytes"])
        assert r["bps"] == pytest.approx(8 * r["bytes"] / out["duration_s"])
    assert rows["lossless whole"]["exact"] and rows["lossless delta"]["exact"]
    assert rows["lossless delta"]["bytes"] <= rows["lossless whole"]["bytes"]
    # pooled: its deltas decode on the base the receiver holds, to what the sender holds.
    assert rows["pooled whole"]["exact"] and rows["pooled delta"]["exact"]
    assert rows["pooled delta"]["deltas"] >= 1
    assert rows["pooled delta"]["bytes"] < rows["lossless delta"]["bytes"]
    assert rows["zstd-19 diff"]["vs_zstd_diff"] == pytest.approx(1.0)
