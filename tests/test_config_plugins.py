"""Config validation errors name file and key; the plugin registry loads lazily with clear errors."""

from __future__ import annotations

import importlib.metadata
from pathlib import Path

import pytest

from mapd import config, plugins
from mapd.data import REPO_ROOT
from mapd.errors import ConfigError, PluginError

MINIMAL = """
[robot]
name = "alpha"
fleet = "lab"

[codec]
use = "zstd"
[codec.zstd]
level = 7
"""


def write(tmp: Path, text: str) -> Path:
    p = tmp / "mapd.toml"
    p.write_text(text)
    return p


def test_minimal_config_and_plugin_options(tmp_path: Path) -> None:
    cfg = config.load(write(tmp_path, MINIMAL))
    assert cfg.robot.name == "alpha" and cfg.codec.use == "zstd"
    opts = config.plugin_options(cfg, "codec", "zstd")
    assert opts.level == 7  # type: ignore[attr-defined]
    assert cfg.limits.max_cells == 1 << 26


def test_example_config_is_complete_and_valid() -> None:
    cfg = config.load(REPO_ROOT / "config.toml")
    checked = config.check_plugins(cfg)
    # The complete example carries a table for every installed plugin.
    for section, kind in (("source", "source"), ("codec", "codec"), ("transports", "transport")):
        assert set(checked[section]) >= set(plugins.names(kind)) - {"raw"}, section


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (MINIMAL + "\n[fusion]\nmdoe = 'logodds'\n", r"mapd\.toml: fusion\.mdoe: unknown key"),
        (MINIMAL.replace('name = "alpha"', "name = 5"), r"mapd\.toml: robot\.name: .*string"),
        (
            MINIMAL.replace("level = 7", "level = 99"),
            r"mapd\.toml: codec\.zstd\.level: .*less than or equal to 22",
        ),
        (MINIMAL.replace("level = 7", "levle = 7"), r"codec\.zstd\.levle: unknown key"),
        (MINIMAL.replace('use = "zstd"', 'use = "nosuch"'), r"codec\.use: no codec plugin 'nosuch'"),
        ("[robot]\nfleet = 'x'\n", r"robot\.name: required key is missing"),
        ("[robot\nname=1", r"not valid TOML"),
        (MINIMAL + "\n[fusion.poses]\nbeta = [1.0, 2.0]\n", r"fusion\.poses.*\[x, y, yaw\]"),
    ],
)
def test_config_errors_name_file_and_key(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        cfg = config.load(write(tmp_path, text))
        config.check_plugins(cfg)


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such config file"):
        config.load(tmp_path / "absent.toml")


def test_key_file(tmp_path: Path) -> None:
    (tmp_path / "fleet.key").write_text("ab" * 32 + "\n")
    cfg = config.load(
        write(tmp_path, MINIMAL.replace('fleet = "lab"', 'fleet = "lab"\nkey_file = "fleet.key"'))
    )
    assert config.read_key(cfg) == bytes.fromhex("ab" * 32)
    (tmp_path / "fleet.key").write_text("abcd")
    with pytest.raises(ConfigError, match="at least 16"):
        config.read_key(cfg)
    (tmp_path / "fleet.key").unlink()
    with pytest.raises(ConfigError, match="cannot read"):
        config.read_key(cfg)


def test_registry_lists_without_importing() -> None:
    assert {"raw", "zstd"} <= set(plugins.names("codec"))
    assert {"uwb", "zenoh"} <= set(plugins.names("transport"))
    assert {"sim", "laserlog", "mapfile"} <= set(plugins.names("source"))
    assert plugins.load("codec", "raw").name == "raw"


def test_unknown_plugin_and_missing_dependency(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(PluginError, match="no codec plugin named 'nope'"):
        plugins.load("codec", "nope")
    with pytest.raises(PluginError, match="unknown plugin kind"):
        plugins.names("widget")
    fake = importlib.metadata.EntryPoint(
        name="fancy", value="some_missing_lib_xyz.codec:Fancy", group="mapd.codecs"
    )
    monkeypatch.setattr(plugins, "_entry_points", lambda kind: {"fancy": fake})
    with pytest.raises(PluginError, match="codec plugin 'fancy' needs some_missing_lib_xyz"):
        plugins.load("codec", "fancy")
