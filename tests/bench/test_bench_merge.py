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


def test_bench_merge_only_reruns_one_pair_alone(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["bench", "merge", "--pairs", "3", "--no-real", "--seed", "5", "--json"]
    assert main([*args, "--merge-size", "64", "--repeat", "1"]) == 0
    every = json.loads(capsys.readouterr().out)
    assert main([*args, "--only", "2"]) == 0
    alone = json.loads(capsys.readouterr().out)
    # the same pair as in the full run, numbered as there, and no speed rows
    assert [r["pair"] for r in alone["records"]] == [2] and alone["speed"] is None
    assert alone["records"][0]["label"] == every["records"][1]["label"]
    assert alone["records"][0]["overlap"] == every["records"][1]["overlap"]
    assert alone["records"][0]["mapd"]["err_cells"] == every["records"][1]["mapd"]["err_cells"]


def test_bench_merge_only_refuses_a_pair_that_is_not_there(
    data_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "merge", "--pairs", "2", "--no-real", "--only", "3", "--json"]) != 0
    assert "--only takes pair numbers from 1 to 2" in capsys.readouterr().err
