"""Relative paths in a config are taken from the config's folder, wherever the daemon is started.

Before the fix, ``[state] dir``, ``runtime_dir``, ``[control] socket``, ``[output.files] dir``,
``[codec.paper] model_dir`` and a source's file were taken from the working directory: under
systemd (cwd "/") a relative state dir landed in "/", and ``mapd status`` run from another folder
looked for the control socket somewhere else than the daemon had put it.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from mapd import config as configmod
from mapd.codec.paper import PaperOptions
from mapd.grid.save import save_map
from mapd.mapping.synthetic import room_grid
from mapd.outputs.files import FilesOptions
from mapd.sources.base import SourceContext


def test_every_relative_path_in_the_main_tables_is_taken_from_the_configs_folder(tmp_path: Path) -> None:
    conf = tmp_path / "etc"
    conf.mkdir()
    (conf / "config.toml").write_text(
        '[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        '[state]\ndir = "state"\nruntime_dir = "run"\n[control]\nsocket = "run/ctl.sock"\n'
        '[record]\npath = "rec/fleet.mcap"\n'
    )
    cfg = configmod.load(conf / "config.toml")
    assert cfg.state.dir == conf / "state"
    assert cfg.state.runtime_dir == conf / "run"
    assert cfg.control_socket() == conf / "run" / "ctl.sock"
    assert cfg.record.path == conf / "rec" / "fleet.mcap"


def test_the_default_control_socket_follows_a_relative_runtime_dir(tmp_path: Path) -> None:
    (tmp_path / "config.toml").write_text(
        '[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n[state]\nruntime_dir = "run"\n'
    )
    assert configmod.load(tmp_path / "config.toml").control_socket() == tmp_path / "run" / "mapd.sock"


def test_plugin_paths_are_taken_from_the_configs_folder(tmp_path: Path) -> None:
    (tmp_path / "config.toml").write_text(
        '[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        '[output]\nuse = ["files"]\n[output.files]\ndir = "out"\n'
        '[codec]\nuse = "lossless"\n[codec.paper]\nmodel_dir = "models"\n'
    )
    cfg = configmod.load(tmp_path / "config.toml")
    files = configmod.plugin_options(cfg, "output", "files")
    paper = configmod.plugin_options(cfg, "codec", "paper")
    assert isinstance(files, FilesOptions) and files.dir == tmp_path / "out"
    assert isinstance(paper, PaperOptions) and paper.model_dir == tmp_path / "models"


def test_a_source_file_is_looked_up_in_the_data_folder_then_beside_the_config(tmp_path: Path) -> None:
    data, conf = tmp_path / "data", tmp_path / "etc"
    (data / "maps").mkdir(parents=True)
    (data / "maps" / "shared.yaml").write_text("x")
    ctx = SourceContext(robot="r0", data_dir=data, config_dir=conf)
    assert ctx.resolve(Path("maps/shared.yaml")) == data / "maps" / "shared.yaml"
    assert ctx.resolve(Path("mine.yaml")) == conf / "mine.yaml"
    assert ctx.resolve(Path("/abs/map.yaml")) == Path("/abs/map.yaml")
    # Without a config (a source built by hand) a relative path stays as written: from the cwd.
    assert SourceContext(robot="r0").resolve(Path("mine.yaml")) == Path("mine.yaml")


@pytest.mark.slow
def test_a_daemon_started_elsewhere_keeps_everything_beside_its_config(
    tmp_path: Path, dk: SimpleNamespace
) -> None:
    conf, cwd, other = tmp_path / "etc", tmp_path / "cwd", tmp_path / "elsewhere"
    for d in (conf, cwd, other):
        d.mkdir()
    save_map(room_grid(60, 80, seed=3), conf / "map.yaml")
    (conf / "config.toml").write_text(
        '[robot]\nname = "r0"\n[fleet]\nallow_unsigned = true\n'
        '[source]\nuse = "mapfile"\n[source.mapfile]\npath = "map.yaml"\npoll_s = 0.1\nsettle_s = 0.1\n'
        '[codec]\nuse = "raw"\n[state]\ndir = "state"\nruntime_dir = "run"\n'
        '[output]\nuse = ["files"]\n[output.files]\ndir = "out"\n'
    )
    log = tmp_path / "daemon.log"
    with dk.mapd_run(Path("../etc/config.toml"), log, cwd=cwd) as proc:
        deadline = time.monotonic() + 60
        status = None
        while time.monotonic() < deadline:
            assert proc.poll() is None, f"the daemon exited: {log.read_text()[-2000:]}"
            # `mapd status` from a third folder finds the socket through the same config.
            done = subprocess.run(
                [sys.executable, "-m", "mapd", "status", "--json", "--config", "../etc/config.toml"],
                cwd=other,
                capture_output=True,
                text=True,
                timeout=30,
            )
            if done.returncode == 0:
                status = json.loads(done.stdout)
                if (conf / "out" / "map.yaml").exists() and status["source"]["stats"]["versions"] == 1:
                    break
            time.sleep(0.3)
        else:
            raise AssertionError(f"no global map in {conf / 'out'}: {log.read_text()[-2000:]}")
        assert status is not None and Path(status["state_dir"]) == conf / "state"
        assert (conf / "state").is_dir() and (conf / "run" / "mapd.sock").exists()
        assert sorted(p.name for p in cwd.iterdir()) == [], "nothing is written in the daemon's cwd"
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
