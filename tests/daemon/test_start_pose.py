"""`mapd run` fuses by the robots' own start poses: each map carries its frame's pose in the fleet frame."""

from __future__ import annotations

import argparse
import math
import tomllib
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from mapd.demo.fleet import Fleet, write_config

pytestmark = pytest.mark.slow


def test_start_poses_from_the_sources_place_the_maps_without_configured_poses(
    tmp_path: Path, fk: SimpleNamespace
) -> None:
    args = argparse.Namespace(
        robots=2, transport="zenoh", codec="lossless", log=None, seed=7, out=tmp_path, duration=60.0
    )
    f = Fleet(args)
    f.prepare()
    truth: dict[str, list[float]] = {}
    for name in f.names:  # the demo configures the simulated start poses: take them out again
        path = f.run_dir / name / "config.toml"
        cfg = tomllib.loads(path.read_text())
        truth = cfg["fusion"].pop("poses")
        write_config(path, cfg)
    assert set(truth) == {"robot0", "robot1"}
    f.start()
    try:

        def both_placed(snaps: dict[str, dict[str, Any]]) -> bool:
            robots = [s.get("fusion", {}).get("robots", {}) for s in snaps.values()]
            return len(robots) == 2 and all(
                len(r) == 2 and all(p.get("accepted") for p in r.values()) for r in robots
            )

        snaps = fk.wait_for(both_placed, 120, f)
        for me in f.names:
            fusion = snaps[me]["fusion"]
            assert fusion["fleet_frame"] == "frame of the known poses (robot0, robot1)", fusion
            for robot, pose in truth.items():
                p = fusion["robots"][robot]
                assert p["source"] == "pose" and p["accepted"], p
                assert p["reason"].startswith("start pose reported by the robot"), p
                assert math.isclose(p["x"], pose[0], abs_tol=1e-6) and math.isclose(
                    p["y"], pose[1], abs_tol=1e-6
                )
                assert math.isclose(p["yaw"], pose[2], abs_tol=1e-6)
    finally:
        codes = f.stop()
    assert codes == {"robot0": 0, "robot1": 0}
