"""Peers' maps in this robot's own codec are decoded with its ``[codec.<use>]`` options."""

from __future__ import annotations

import asyncio
import json
import os
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from mapd import config as configmod
from mapd.codec import paper_model as pm
from mapd.codec import paper_net as pn
from mapd.codec.api import encode
from mapd.codec.paper import PaperOptions
from mapd.daemon.server import Daemon
from mapd.daemon.versions import incarnation_at, make
from mapd.envelope import Envelope
from mapd.grid import OccupancyGrid, Pose2D
from mapd.identity import read_identity
from transports.base import Received


def _model(folder: Path, seed: int) -> None:
    """A freshly initialised paper model folder, as ``mapd train`` writes one (another variant
    than the default model's: its weights' hash differs)."""
    torch.manual_seed(seed)
    net = pn.PaperNet(16)
    folder.mkdir(parents=True)
    sha = pm.write_weights(folder / pm.WEIGHTS_FILE, pm.state_arrays(net))
    meta = {
        "name": folder.name,
        "format": pm.MODEL_FORMAT,
        "levels": 16,
        "channels": 16,
        "weights_sha256": sha,
    }
    (folder / pm.META_FILE).write_text(json.dumps(meta))


def test_a_fleet_on_a_paper_model_of_its_own_takes_each_others_maps(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    """Each robot coded its maps with ``[codec.paper] model``, and every receiver decoded them with
    the default model: "payload was made with paper variant ..., but this mapd has ...", every map
    refused, in a fleet whose configs all agreed."""
    _model(tmp_path / "models" / "ours", seed=5)
    options = PaperOptions(model="ours", model_dir=tmp_path / "models")
    cfg = configmod.load(
        dk.write_config(
            tmp_path,
            "robot0",
            codec="paper",
            extra='[transports]\nuse = ["virtual"]\n',
            **{
                "transports.virtual": f'channel = "{dk.channel()}"',
                "codec.paper": f'model = "ours"\nmodel_dir = "{tmp_path / "models"}"',
            },
        )
    )
    d = Daemon(cfg, source=dk.QueueSource("robot0"))
    robot1 = read_identity(tmp_path / "keys" / "robot1.key", "robot1")
    grid = OccupancyGrid(np.where(np.arange(64 * 48).reshape(48, 64) % 7 == 0, 100, 0).astype(np.int8), 0.05)
    env = Envelope(
        fleet="default", robot="robot1", version=make(incarnation_at(time.time() - 60), 1),
        base_version=0, codec="paper", width=64, height=48, resolution=0.05,
        origin=Pose2D(0, 0, 0), payload=encode(grid, "paper", options=options),
    ).signed(robot1)  # fmt: skip

    link = dk.AckingLink()
    d.transports.append(link)

    async def main() -> None:
        await d._restore()
        await d.inbound.handle(Received("virtual", "robot1", env.pack()))

    asyncio.run(main())
    held = d.receiver.maps.get("robot1")
    assert held is not None and held.version == env.version and (held.width, held.height) == (64, 48)
    assert link.acks == [("robot1", env.version)] and d.receiver.counters.decode_errors == 0
    if d._state_lock is not None:
        os.close(d._state_lock)  # (what the stop does)
