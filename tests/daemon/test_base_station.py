"""A base station: `[source] use = "none"` receives, fuses and keeps the fleet's map, and sends none of its own."""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd.demo.fleet import Fleet, write_config
from mapd.grid.load import load_map

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("transport", ["zenoh", "uwb"])
def test_two_robots_and_a_base_station(tmp_path: Path, transport: str, fk: SimpleNamespace) -> None:
    args = argparse.Namespace(
        robots=3, transport=transport, codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0
    )
    f = Fleet(args)
    f.prepare()
    base = f.run_dir / "robot2" / "config.toml"
    cfg = tomllib.loads(base.read_text())
    cfg["source"] = {"use": "none"}
    cfg["fusion"].pop("poses", None)  # it knows no poses of its own
    cfg["output"] = {"use": ["files"], "files": {"dir": str(tmp_path / "served")}}  # say, for a map_server
    write_config(base, cfg)
    f.start()
    try:
        snaps = fk.wait_for(
            lambda s: (
                fk.held(s, "robot2", "robot0") >= 2
                and fk.held(s, "robot2", "robot1") >= 2
                and s.get("robot2", {}).get("fusion", {}).get("maps", 0) >= 2
                # the files output writes on a worker after the merge: its count comes a little later
                and s["robot2"].get("outputs", {}).get("files", {}).get("written", 0) >= 1
            ),
            150,
            f,
        )
        b = snaps["robot2"]
        assert fk.held(snaps, "robot2", "robot0") >= 2 and fk.held(snaps, "robot2", "robot1") >= 2, (
            json.dumps(b)[:2000]
        )
        assert b["source"]["name"] == "none" and b["source"]["version"] == 0
        assert b["codec"]["keyframes"] == 0 and b["codec"]["deltas"] == 0  # it sends no map
        fusion = b["fusion"]
        # the robots' maps carry their start poses, which place them (the base knows no poses itself)
        assert fusion["fleet_frame"] == "frame of the known poses (robot0, robot1)"
        for robot in ("robot0", "robot1"):
            assert fusion["robots"][robot]["source"] == "pose" and fusion["robots"][robot]["accepted"]
        assert fusion["maps"] >= 2
        # the robots go on as before, and hold no map of the base station
        for me, other in (("robot0", "robot1"), ("robot1", "robot0")):
            assert "robot2" not in {p for p, i in snaps[me]["peers"].items() if i.get("version")}
            assert fk.held(snaps, me, other) >= 1
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0, "robot2": 0}
    glob = load_map(f.run_dir / "robot2" / "state" / "global" / "global.yaml")
    served = load_map(tmp_path / "served" / "map.yaml")  # the files output got the fused map too
    assert served.width > 0 and int((served.data >= 0).sum()) > 0
    assert b["outputs"]["files"]["written"] >= 1
    robot0 = load_map(f.run_dir / "robot2" / "state" / "peers" / "robot0" / "map.yaml")
    # the global map holds at least robot0's known cells (its frame is the fleet frame)
    assert int((glob.data >= 0).sum()) >= int((robot0.data >= 0).sum()) * 0.9
