"""deploy/: the systemd unit verifies, asks for what the daemon needs, and matches what install.sh sets up."""

from __future__ import annotations

import configparser
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def unit() -> configparser.RawConfigParser:
    # systemd units repeat keys (DeviceAllow): keep the last, which is enough for these checks
    cp = configparser.RawConfigParser(strict=False, interpolation=None)
    cp.optionxform = str  # type: ignore[assignment,method-assign]
    cp.read(DEPLOY / "mapd.service")
    return cp


def test_unit_asks_for_notify_watchdog_directories_and_hardening() -> None:
    s = unit()["Service"]
    assert s["Type"] == "notify" and int(s["WatchdogSec"]) > 0 and s["Restart"] == "on-failure"
    for key in ("StateDirectory", "RuntimeDirectory", "ConfigurationDirectory", "CacheDirectory"):
        assert s[key] == "mapd", key
    assert s["ProtectSystem"] == "strict" and s["NoNewPrivileges"] == "yes" and s["PrivateTmp"] == "yes"
    assert "dialout" in s["SupplementaryGroups"] and s["DevicePolicy"] == "closed"
    # uwb TDMA counts slots on the wall clock: start once it is synchronized, where that is waited for
    assert "time-sync.target" in unit()["Unit"]["After"].split()
    # restarted however often it fails at boot (systemd's default gives up after 5 in 10 s)...
    assert unit()["Unit"]["StartLimitIntervalSec"] == "0"
    # ...but not for a config error, which no retry heals (a start every 2 s, for ever)
    from mapd.errors import ConfigError

    assert s["RestartPreventExitStatus"] == str(ConfigError.exit_code) == "2"
    # a stop waits out one placement search, then saves the state: room for both before SIGKILL
    assert int(s["TimeoutStopSec"]) >= 30
    env = dict(kv.split("=", 1) for kv in s["Environment"].split())
    # numba may only write below CacheDirectory under ProtectSystem=strict, and install.sh warms it
    assert env["NUMBA_CACHE_DIR"].startswith("/var/cache/mapd/")
    install = (DEPLOY / "install.sh").read_text()
    assert f"NUMBA_CACHE_DIR={env['NUMBA_CACHE_DIR']}" in install and "mapd warmup" in install


def test_install_script_parses() -> None:
    out = subprocess.run(["bash", "-n", str(DEPLOY / "install.sh")], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed")
def test_unit_passes_systemd_analyze_verify(tmp_path: Path) -> None:
    # verify checks that ExecStart exists: point it at this checkout's mapd instead of /opt/mapd
    mapd = Path(sys.executable).parent / "mapd"
    text = (DEPLOY / "mapd.service").read_text().replace("/opt/mapd/venv/bin/mapd", str(mapd))
    (tmp_path / "mapd.service").write_text(text)
    out = subprocess.run(
        ["systemd-analyze", "verify", str(tmp_path / "mapd.service")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert out.returncode == 0 and not out.stderr.strip(), out.stderr


def test_warmup_command_compiles_the_lossless_kernels(tmp_path: Path) -> None:
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PATH": "/usr/bin:/bin"}
    out = subprocess.run(
        [sys.executable, "-m", "mapd", "warmup", "--codec", "lossless", "raw"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines()[0].startswith("lossless: ready in")
    assert any((tmp_path / "numba").rglob("*.nbi")), "numba wrote no cache index under NUMBA_CACHE_DIR"


def test_the_robot_config_install_writes_keeps_the_examples_folders(tmp_path: Path) -> None:
    # install.sh once rewrote every line starting "dir = ": [output.files] dir went to the state dir.
    from mapd import config as configmod

    example = DEPLOY.parent / "config.toml"
    out = subprocess.run(
        ["bash", str(DEPLOY / "robot-config.sh"), "robot7", "lab"],
        input=example.read_text(),
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert out.returncode == 0, out.stderr
    (tmp_path / "config.toml").write_text(out.stdout)
    cfg, orig = configmod.load(tmp_path / "config.toml"), configmod.load(example)
    assert cfg.robot.name == "robot7" and cfg.robot.fleet == "lab"
    assert cfg.robot.key_file == Path("/etc/mapd/robot.key")
    assert cfg.fleet.link_key_file == Path("/etc/mapd/link.key")
    assert cfg.fleet.roster == {}, "the example's placeholder keys are dropped"
    assert cfg.state == orig.state and cfg.output.table("files") == orig.output.table("files")
    # the models where install.sh puts them, for mapd in a shell too (the unit alone set
    # MAPD_MODELS, so check-config refused a paper codec config the daemon ran)
    assert cfg.codec.table("paper")["model_dir"] == "/opt/mapd/models"
    assert "/opt/mapd/models" in (DEPLOY / "install.sh").read_text()
    # what the unit lets the daemon write (ProtectSystem=strict): its state directory
    s = unit()["Service"]
    for folder in (cfg.state.dir, Path(cfg.output.table("files")["dir"])):
        assert folder.is_relative_to(Path("/var/lib") / s["StateDirectory"]), folder
    assert cfg.state.runtime_dir == Path("/run") / s["RuntimeDirectory"]
    # names go into sed and TOML: anything but a plain name is refused
    bad = subprocess.run(
        ["bash", str(DEPLOY / "robot-config.sh"), 'r"; x', "lab"], input="", capture_output=True, text=True
    )
    assert bad.returncode == 2 and "letters, digits" in bad.stderr
    # as long as mapd allows (config.NAME_PATTERN: 32), not longer
    long = subprocess.run(
        ["bash", str(DEPLOY / "robot-config.sh"), "r" * 33, "lab"], input="", capture_output=True, text=True
    )
    assert long.returncode == 2 and "1 to 32" in long.stderr
    from mapd.config import NAME_PATTERN

    assert NAME_PATTERN.endswith("{1,32}$")


def test_install_puts_mapd_on_the_path_and_writes_the_config_with_robot_config() -> None:
    install = (DEPLOY / "install.sh").read_text()
    assert "ln -sfn /opt/mapd/venv/bin/mapd /usr/local/bin/mapd" in install
    assert 'deploy/robot-config.sh "$robot" "$fleet" < config.toml > /etc/mapd/config.toml.new' in install
    assert "mv /etc/mapd/config.toml.new /etc/mapd/config.toml" in install
    # the names are checked before anything is installed
    assert install.index("< /dev/null > /dev/null") < install.index("useradd")
    # the example config names the ros2 and record plugins: a robot gets what they need
    extras = install.split("pip install", 1)[1].split("\n", 1)[0]
    assert "'.[ros2,record]'" in extras


def test_install_replaces_this_robots_roster_line_when_its_key_is_made_again(tmp_path: Path) -> None:
    """A robot whose key was made again (robot.key lost) got a second ``alpha = ...`` line beside
    the old one: TOML refuses a key given twice, and the daemon would not start. The roster lines of
    install.sh, run as it runs them, on a config with the old line."""
    import tomllib

    install = (DEPLOY / "install.sh").read_text()
    roster_lines = [
        ln.strip() for ln in install.splitlines() if ln.strip().startswith("sed -i") and "fleet.roster" in ln
    ]
    assert len(roster_lines) == 2
    config = tmp_path / "config.toml"
    config.write_text(
        '[robot]\nname = "alpha"\n\n[fleet.roster]\nalpha = "ed25519:OLD"\nbeta = "ed25519:BETA"\n\n'
        "[fleet.more]\nalpha = 1\n"
    )
    script = "robot=alpha; line='alpha = \"ed25519:NEW\"'\n" + "\n".join(roster_lines).replace(
        "/etc/mapd/config.toml", str(config)
    )
    done = subprocess.run(["bash", "-c", script], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    doc = tomllib.loads(config.read_text())
    assert doc["fleet"]["roster"] == {"alpha": "ed25519:NEW", "beta": "ed25519:BETA"}
    assert doc["fleet"]["more"] == {"alpha": 1}  # another table's "alpha" is not this robot's line


def test_install_restarts_a_running_daemon_after_an_upgrade() -> None:
    install = (DEPLOY / "install.sh").read_text()
    assert "systemctl try-restart mapd" in install  # the old code ran on until a reboot
    assert install.index("systemctl daemon-reload") < install.index("systemctl try-restart mapd")
    assert "useradd --system --user-group" in install


def _directives(path: Path) -> list[tuple[str, str]]:
    """Every ``Key=value`` line of a unit, repeated keys kept (comments left out)."""
    out = []
    for line in path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith(("#", ";", "[")) and "=" in line:
            key, _, value = line.partition("=")
            out.append((key.strip(), value.strip()))
    return out


def test_the_unit_lets_the_daemon_ask_the_clock_and_open_a_radio_plugged_in_later() -> None:
    found = _directives(DEPLOY / "mapd.service")
    keys = {k for k, _ in found}
    # ProtectClock= forbids adjtimex(2), even to read: the time-service question (mapd.wallclock)
    # came back "cannot be asked", so no robot led the radio clock and clock_wait_s never waited
    assert "ProtectClock" not in keys
    assert ("CapabilityBoundingSet", "") in found  # setting the clock stays out of reach
    # DevicePolicy=closed resolves char-ttyUSB/char-ttyACM once at start: their drivers first
    wants = " ".join(v for k, v in found if k == "Wants").split()
    after = " ".join(v for k, v in found if k == "After").split()
    for mod in ("modprobe@usbserial.service", "modprobe@cdc_acm.service"):
        assert mod in wants and mod in after, mod
    assert ("DevicePolicy", "closed") in found and ("DeviceAllow", "char-ttyUSB rw") in found


def test_install_keeps_an_edited_udev_rule_and_takes_the_link_key_from_where_it_was_typed() -> None:
    install = (DEPLOY / "install.sh").read_text()
    # the rule is the robot's own once edited: installed only where there is none, then triggered
    assert "if [ ! -f /etc/udev/rules.d/99-mapd-uwb.rules ]; then" in install
    assert "udevadm trigger --subsystem-match=tty" in install
    # --link-key: resolved before the cd into the repo; the installed key given again is no copy
    assert install.index('realpath -e -- "$link_key"') < install.index('cd "$(dirname "$0")/.."')
    assert '! [ "$link_key" -ef /etc/mapd/link.key ]' in install
    # an upgrade restarts the daemon only into a config the new code takes
    check = install.index("mapd check-config /etc/mapd/config.toml")
    assert check < install.index("systemctl try-restart mapd")
    # the shipped rule matches no bare CP210x (the chip of many lidars): a serial is needed
    rules = [ln for ln in (DEPLOY / "99-mapd-uwb.rules").read_text().splitlines() if not ln.startswith("#")]
    assert rules and all('ATTRS{idVendor}=="10c4"' not in ln or "ATTRS{serial}" in ln for ln in rules)


def test_install_sh_link_key_handling_runs_as_written(tmp_path: Path) -> None:
    # The argument part of install.sh, run for real up to its root check: a relative --link-key is
    # taken from the caller's folder, a missing one refused with one line.
    (tmp_path / "link.key").write_text("ab" * 32)
    head = (DEPLOY / "install.sh").read_text().split('cd "$(dirname "$0")/.."')[0]
    script = head + 'echo "$link_key"\n'
    ok = subprocess.run(
        ["bash", "-c", script, "install.sh", "--link-key", "link.key"],
        cwd=tmp_path, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert ok.returncode == 0 and ok.stdout.strip() == str((tmp_path / "link.key").resolve()), ok.stderr
    bad = subprocess.run(
        ["bash", "-c", script, "install.sh", "--link-key", "absent.key"],
        cwd=tmp_path, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert bad.returncode == 2 and bad.stderr.strip().splitlines()[-1] == "--link-key: no such file"


def test_uninstall_removes_what_install_puts_and_keeps_the_robots_identity_unless_purged() -> None:
    install = (DEPLOY / "install.sh").read_text()
    uninstall = (DEPLOY / "uninstall.sh").read_text()
    # every place install.sh writes to outside /etc/mapd and the state, uninstall.sh clears
    for path in (
        "/etc/systemd/system/mapd.service",
        "/usr/local/bin/mapd",
    ):
        assert path in install and path in uninstall, path
    assert "install -d -m 0755 /opt/mapd" in install and "rm -rf /opt/mapd" in uninstall
    # the key, the config and the maps go only with --purge (a later install takes them up again)
    keep, purge = uninstall.split('if [ "$purge" = yes ]; then', 1)
    # (and the udev rule, edited to this robot's radio: a reinstall would put the example back)
    for path in ("/etc/mapd", "/var/lib/mapd", "userdel mapd", "/etc/udev/rules.d/99-mapd-uwb.rules"):
        assert path not in keep.split("set -euo pipefail", 1)[1], path
        assert path in purge, path
    assert "systemctl disable --now mapd" in uninstall  # stopped (and saved) before anything goes
    bad = subprocess.run(
        ["bash", str(DEPLOY / "uninstall.sh"), "--everything"], capture_output=True, text=True
    )
    assert bad.returncode == 2 and bad.stderr.startswith("usage: ")
