"""Config validation errors name file and key; the plugin registry loads lazily with clear errors."""

from __future__ import annotations

import importlib.metadata
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from mapd import config, plugins
from mapd.data import REPO_ROOT
from mapd.errors import ConfigError, PluginError
from mapd.identity import Identity

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
    for section, kind in (
        ("source", "source"),
        ("codec", "codec"),
        ("transports", "transport"),
        ("output", "output"),
    ):
        assert set(checked[section]) >= set(plugins.names(kind)) - {"raw"}, section
    # Signed by default: it names the robot's key and the link key, which a robot makes with keygen.
    assert not cfg.fleet.allow_unsigned and cfg.robot.key_file is not None
    with pytest.raises(ConfigError, match=r"robot\.key_file: cannot read .*robot\.key"):
        config.check(cfg)


def test_example_config_passes_check_config_once_its_keys_are_made(tmp_path: Path) -> None:
    """The README's steps: keygen for the robot and the link, the printed line in the roster."""
    (tmp_path / "config.toml").write_text((REPO_ROOT / "config.toml").read_text())
    mapd = [sys.executable, "-m", "mapd"]
    run = lambda *a: subprocess.run([*mapd, *a], capture_output=True, text=True, cwd=tmp_path, timeout=60)  # noqa: E731
    refused = run("check-config", "config.toml")
    assert refused.returncode == 2 and refused.stderr.startswith("mapd: error: robot.key_file")
    made = run("keygen", "alpha", "-o", "robot.key")
    assert made.returncode == 0 and made.stdout.startswith('alpha = "ed25519:')
    assert (tmp_path / "robot.key").stat().st_mode & 0o777 == 0o600
    assert run("keygen", "--link-key", "link.key").returncode == 0
    mismatch = run("check-config", "config.toml")
    assert "fleet.roster.alpha does not match robot.key_file" in mismatch.stderr
    text = (tmp_path / "config.toml").read_text()
    start = text.index('alpha = "ed25519:')
    end = text.index("\n", start)
    (tmp_path / "config.toml").write_text(text[:start] + made.stdout.strip() + text[end:])
    ok = run("check-config", "config.toml")
    assert ok.returncode == 0, ok.stderr
    doc = json.loads(ok.stdout.split("\n", 1)[1])
    assert doc["keys"] == {"signed": True, "public_key": made.stdout.split('"')[1], "link_key": True}


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
        (
            MINIMAL + "\n[fusion.poses]\nbeta = [true, 0.0, 0.0]\n",
            r"fusion\.poses.*'beta' must be \[x, y, yaw\]",
        ),
        (
            MINIMAL + '\n[fusion.poses]\n"be ta" = [0.0, 0.0, 0.0]\n',
            r"fusion\.poses.*'be ta' is not a valid robot name",
        ),
    ],
)
def test_config_errors_name_file_and_key(tmp_path: Path, text: str, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        cfg = config.load(write(tmp_path, text))
        config.check_plugins(cfg)


def test_a_pose_of_neither_kind_is_one_line(tmp_path: Path) -> None:
    # The union said it twice, a line per member (list[float], literal['estimate']).
    with pytest.raises(ConfigError) as err:
        config.load(write(tmp_path, MINIMAL + '\n[fusion.poses]\nbeta = "nonsense"\n'))
    assert str(err.value).splitlines() == [
        f"{tmp_path / 'mapd.toml'}: fusion.poses: Value error, pose of 'beta' must be [x, y, yaw] in meters "
        "and radians, or \"estimate\" (got 'nonsense')"
    ]


def test_missing_config_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="no such config file"):
        config.load(tmp_path / "absent.toml")


def test_link_key_file(tmp_path: Path) -> None:
    (tmp_path / "link.key").write_text("ab" * 32 + "\n")
    text = MINIMAL + '\n[fleet]\nallow_unsigned = true\nlink_key_file = "link.key"\n'
    cfg = config.load(write(tmp_path, text))
    assert config.read_keys(cfg).link_key == bytes.fromhex("ab" * 32)
    (tmp_path / "link.key").write_text("abcd")
    with pytest.raises(ConfigError, match="at least 16"):
        config.read_keys(cfg)


def test_signed_by_default_and_the_roster_must_match_the_key(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"robot\.key_file: a signed fleet needs this robot's key"):
        config.read_keys(config.load(write(tmp_path, MINIMAL)))
    ident = Identity.generate("alpha")
    ident.write(tmp_path / "alpha.key")
    other = Identity.generate("alpha").public_text
    keyed = MINIMAL.replace('fleet = "lab"', 'fleet = "lab"\nkey_file = "alpha.key"')
    with pytest.raises(ConfigError, match=r"fleet\.roster: this robot 'alpha' is missing; add: alpha = "):
        config.read_keys(config.load(write(tmp_path, keyed)))
    with pytest.raises(ConfigError, match=r"does not match robot\.key_file"):
        config.read_keys(config.load(write(tmp_path, keyed + f'[fleet.roster]\nalpha = "{other}"\n')))
    with pytest.raises(ConfigError, match="uwb frames need the fleet's link key"):
        config.read_keys(
            config.load(
                write(
                    tmp_path,
                    keyed + f'[transports]\nuse = ["uwb"]\n[fleet.roster]\nalpha = "{ident.public_text}"\n',
                )
            )
        )
    keys = config.read_keys(
        config.load(write(tmp_path, keyed + f'[fleet.roster]\nalpha = "{ident.public_text}"\n'))
    )
    assert keys.signed and keys.identity is not None and keys.roster.robots == ["alpha"]
    with pytest.raises(ConfigError, match=r"fleet\.roster\.beta: expected 'ed25519:<base64>'"):
        config.read_keys(config.load(write(tmp_path, keyed + '[fleet.roster]\nbeta = "abc"\n')))
    unsigned = config.read_keys(config.load(write(tmp_path, MINIMAL + "[fleet]\nallow_unsigned = true\n")))
    assert not unsigned.signed and unsigned.identity is None


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


ZENOH_FILES = [
    ("transports", "zenoh", "config_file", '[transports]\nuse = ["zenoh"]\n'),
    ("output", "zenoh", "config_file", '[output]\nuse = ["zenoh"]\n'),
    ("output", "ros2", "zenoh_config", '[output]\nuse = ["ros2"]\n'),
    ("source", "ros2", "zenoh_config", '[source]\nuse = "ros2"\n'),
]


def _zenoh_file_config(tmp: Path, section: str, name: str, field: str, use: str, path: str) -> Path:
    text = MINIMAL.replace("[codec]", use + "\n[codec]") + "\n[fleet]\nallow_unsigned = true\n"
    return write(tmp, text + f'\n[{section}.{name}]\n{field} = "{path}"\n')


@pytest.mark.parametrize(("section", "name", "field", "use"), ZENOH_FILES)
def test_a_zenoh_config_file_is_found_beside_the_config_and_read_by_check(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, section: str, name: str, field: str, use: str
) -> None:
    # Relative to the config file, as robot.key_file is: under systemd the working directory is /.
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "zenoh.json5").write_text("{ scouting: { multicast: { enabled: false } } }\n")
    monkeypatch.chdir(tmp_path)  # a zenoh.json5 in the working directory is not the one meant
    (tmp_path / "zenoh.json5").write_text("{ not zenoh")
    path = _zenoh_file_config(tmp_path / "etc", section, name, field, use, "zenoh.json5")
    checked = config.check(config.load(path))
    assert getattr(checked.options[section][name], field) == tmp_path / "etc" / "zenoh.json5"


@pytest.mark.parametrize(("section", "name", "field", "use"), ZENOH_FILES)
def test_check_config_refuses_a_zenoh_config_file_that_mapd_run_would(
    tmp_path: Path, section: str, name: str, field: str, use: str
) -> None:
    # These were caught only by `mapd run`, after the daemon had started its other parts.
    os.mkfifo(tmp_path / "fifo.json5")
    (tmp_path / "bad.json5").write_text("{ mode: ")
    for file, says in (
        ("fifo.json5", "not a regular file"),
        ("absent.json5", "cannot read it"),
        ("bad.json5", ""),
    ):
        path = _zenoh_file_config(tmp_path, section, name, field, use, file)
        with pytest.raises(ConfigError, match=rf"mapd\.toml: {section}\.{name}\.{field}: .*{file}: {says}"):
            config.check(config.load(path))
    done = subprocess.run(
        [sys.executable, "-m", "mapd", "check-config", str(path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "bad.json5: " in done.stderr


def test_check_config_refuses_a_paper_model_that_mapd_run_could_not_load(tmp_path: Path) -> None:
    """The model was loaded at the first map: check-config said ok, and mapd run started, said READY
    and logged "paper model not found" at every map, never sending one."""
    import shutil

    models = tmp_path / "models"
    shutil.copytree(REPO_ROOT / "models" / "paper-v3", models / "mine")
    text = MINIMAL.replace('use = "zstd"', 'use = "paper"') + "[fleet]\nallow_unsigned = true\n"
    good = write(tmp_path, text + '[codec.paper]\nmodel = "mine"\nmodel_dir = "models"\n')
    config.check(config.load(good))  # the model is there: fine
    for model, says in (("no-such-model", "paper model not found.*models in .*: mine"), ("mine", ".*sha256")):
        if model == "mine":  # tampered weights
            weights = models / "mine" / "weights.npz"
            weights.write_bytes(weights.read_bytes()[:-1] + b"x")
        path = write(tmp_path, text + f'[codec.paper]\nmodel = "{model}"\nmodel_dir = "models"\n')
        with pytest.raises(ConfigError, match=rf"mapd\.toml: codec\.paper\.model: {says}"):
            config.check(config.load(path))
    done = subprocess.run(
        [sys.executable, "-m", "mapd", "check-config", str(path)], capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "sha256" in done.stderr


@pytest.mark.parametrize(
    ("uwb", "says"),
    [
        ("nodes = { beta = 2 }", r"transports\.uwb\.nodes: no link id for robot 'alpha'"),
        (
            'nodes = { alpha = 1, beta = 2 }\npeers = ["alpha"]',
            r"transports\.uwb\.peers: this robot's own link id 1",
        ),
        ('nodes = { alpha = 1 }\npeers = ["gamma"]', r"transports\.uwb\.peers: 'gamma' is not in"),
    ],
)
def test_check_config_refuses_uwb_link_ids_that_mapd_run_would(tmp_path: Path, uwb: str, says: str) -> None:
    """check-config said ok, and mapd run then stopped at start with exit 2, which the unit does not
    restart (RestartPreventExitStatus=2): the robot stayed down on a config the check passed."""
    text = (
        MINIMAL
        + '[fleet]\nallow_unsigned = true\n[transports]\nuse = ["uwb"]\n[transports.uwb]\n'
        + uwb
        + "\n"
    )
    with pytest.raises(ConfigError, match=rf"mapd\.toml: {says}"):
        config.check(config.load(write(tmp_path, text)))
    fine = (
        MINIMAL
        + '[fleet]\nallow_unsigned = true\n[transports]\nuse = ["uwb"]\n[transports.uwb]\nnodes = { alpha = 1, beta = 2 }\n'
    )
    config.check(config.load(write(tmp_path, fine)))


def _example_keys() -> dict[str, set[str]]:
    """Keys config.toml shows (set or commented out), by table; a shown sub-table counts as a key."""
    import re

    shown: dict[str, set[str]] = {"": set()}
    table = ""
    for line in (REPO_ROOT / "config.toml").read_text().splitlines():
        if m := re.match(r"^\s*#?\s*\[([A-Za-z0-9_.\-]+)\]", line):
            table = m.group(1)
            parent, _, leaf = table.rpartition(".")
            shown.setdefault(parent, set()).add(leaf)
            shown.setdefault(table, set())
        elif m := re.match(r"^\s*#?\s*([A-Za-z0-9_\-]+)\s*=", line):
            shown[table].add(m.group(1))
    return shown


def test_the_example_config_shows_every_key_the_code_takes() -> None:
    # its first line promises "Every key is shown"; four were not (uwb slots, slot_index, ...)
    from pydantic import BaseModel

    shown = _example_keys()
    missing = []
    for section, field in config.MapdConfig.model_fields.items():
        model = field.annotation
        if isinstance(model, type) and issubclass(model, BaseModel):
            missing += [f"[{section}] {k}" for k in model.model_fields if k not in shown.get(section, ())]
    for section, kind in config._KINDS.items():
        for name in plugins.names(kind):
            options = getattr(plugins.load(kind, name), "Options", None)
            if options is not None:
                table = f"{section}.{name}"
                missing += [f"[{table}] {k}" for k in options.model_fields if k not in shown.get(table, ())]
    assert not missing, f"config.toml does not show: {missing}"
    assert "slot_index" in shown["transports.uwb"] and "roster" in shown["fleet"]


def test_a_robots_ros2_output_on_its_ros2_sources_topic_is_refused_in_one_line(tmp_path: Path) -> None:
    """Both default to /map: the daemon would read its own global map back as the robot's map, and
    the robot's Nav2 would see two /map publishers in two frames (ROS 2 edge audit, finding 1)."""
    robot = '[robot]\nname = "r1"\n[fleet]\nallow_unsigned = true\n[source]\nuse = "ros2"\n[output]\nuse = ["ros2"]\n'
    path = tmp_path / "robot.toml"
    path.write_text(robot)
    with pytest.raises(ConfigError) as info:
        config.check(config.load(path))
    msg = str(info.value)
    assert msg.startswith(f"{path}: output.ros2.topic: '/map' (ROS domain 0) is where [source.ros2]")
    assert "\n" not in msg
    path.write_text(robot + '[output.ros2]\ntopic = "/fleet/map"\nframe = "fleet"\n')
    config.check(config.load(path))  # the robot-side layout
    path.write_text(robot.replace('use = ["ros2"]', "use = []") + "[output.ros2]\n")
    config.check(config.load(path))  # both tables present, only the source chosen
