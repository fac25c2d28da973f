"""`mapd bench merge` runs end to end on the shared maps and reports both methods."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from mapd.cli import main


def test_bench_merge_json(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        ["bench", "merge", "--pairs", "2", "--no-real", "--merge-size", "128", "--repeat", "1", "--json"]
    )
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["pairs"] == 2 and len(doc["records"]) == 2
    methods = {r["method"] for r in doc["rows"]}
    assert methods == {"mapd", "m-explore"}
    for rec in doc["records"]:
        for m in ("mapd", "baseline"):
            assert rec[m]["success"] == (
                rec[m]["accepted"] and rec[m]["err_cells"] <= 2 and rec[m]["err_deg"] <= 1
            )
    assert doc["speed"]["logodds"]["seconds"] > 0 and doc["speed"]["numpy_copy_s"] > 0
