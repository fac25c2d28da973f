"""``mapd check-config`` refuses what ``mapd run``'s start would refuse, in the same one line.

Each config below passed ``check-config`` ("ok") and then stopped ``mapd run`` at start, some with
a traceback, some after the daemon had started its other parts: a path where a folder or a socket
goes is a file, a file it names is missing or not what it must be, an address no socket can take,
two parts of the config listening on one port. Now ``config.check`` (which both commands run)
refuses each, naming the file and the key, and ``mapd run`` stops with that line before it
touches anything. What only the machine decides at start (a radio not plugged in, a port another
program holds, who may write where) stays with the start.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

BASE = """[robot]
name = "alpha"
[fleet]
allow_unsigned = true
[state]
dir = "state"
runtime_dir = "run"
[source]
use = "sim"
[source.sim]
realtime = 0
duration = 5
[codec]
use = "zstd"
"""
NONE_SOURCE = {'use = "sim"': 'use = "none"', "[source.sim]\nrealtime = 0\nduration = 5\n": ""}
UWB = '[transports]\nuse = ["uwb"]\n[transports.uwb]\nport = "{port}"\nnodes = {{ alpha = 1, beta = 2 }}\n'
ZENOH = '[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nmulticast_scouting = false\n'
TOKEN = "0123456789abcdef0123456789abcdef"


def _file(rel: str, text: str = "") -> Callable[[Path], None]:
    def make(d: Path) -> None:
        (d / rel).parent.mkdir(parents=True, exist_ok=True)
        (d / rel).write_text(text)

    return make


def _folder(rel: str) -> Callable[[Path], None]:
    return lambda d: (d / rel).mkdir(parents=True)


def _tls_config(d: Path) -> None:
    tls = {"listen_private_key": str(d / "nokey.pem"), "listen_certificate": str(d / "cert.pem")}
    (d / "z.json5").write_text(json.dumps({"transport": {"link": {"tls": tls}}}))
    (d / "cert.pem").write_text("-----BEGIN CERTIFICATE-----\nMAA=\n-----END CERTIFICATE-----\n")


def _fake_mcap(d: Path) -> None:
    # an install without the [record] extra: importing mcap fails as it does when it is absent
    (d / "mods" / "mcap").mkdir(parents=True)
    (d / "mods" / "mcap" / "__init__.py").write_text(
        'raise ModuleNotFoundError("No module named \'mcap\'", name="mcap")\n'
    )


# (id, text added, replacements, setup, what the line says after "c.toml: ")
CASES: list[tuple[str, str, dict[str, str], Callable[[Path], None] | None, str]] = [
    ("state-dir-is-a-file", "", {}, _file("state"), "state.dir: {d}/state is not a folder"),
    # passed, and run's mapper then failed with exit 1 ("try again"): systemd restarted it for ever
    (
        "mapper-resolution-finer-than-a-map-file-holds",
        "",
        {"duration = 5\n": "duration = 5\nresolution = 1e-300\n"},
        None,
        "source.sim.resolution: Input should be greater than or equal to 0.0001 (got 1e-300)",
    ),
    (
        "mapper-log-odds-past-float32",
        "",
        {"duration = 5\n": "duration = 5\nclamp_max = 1e300\n"},
        None,
        "source.sim.clamp_max: Input should be less than or equal to 100 (got 1e+300)",
    ),
    (
        "state-dir-below-a-file",
        "",
        {'dir = "state"': 'dir = "afile/state"'},
        _file("afile"),
        "state.dir: {d}/afile is not a folder",
    ),
    ("runtime-dir-is-a-file", "", {}, _file("run"), "state.runtime_dir: {d}/run is not a folder"),
    (
        "socket-is-a-file",
        "",
        {},
        _file("run/mapd.sock"),
        "state.runtime_dir: {d}/run/mapd.sock exists and is not a socket",
    ),
    (
        "socket-path-too-long",
        '[control]\nsocket = "' + "s" * 120 + '/mapd.sock"\n',
        {},
        None,
        "control.socket: {d}/" + "s" * 120 + "/mapd.sock is longer than the 107 bytes a socket path may have",
    ),
    (
        "files-output-dir-is-a-file",
        '[output]\nuse = ["files"]\n[output.files]\ndir = "out"\n',
        {},
        _file("out"),
        "output.files.dir: {d}/out is not a folder",
    ),
    (
        "record-below-a-file",
        '[record]\npath = "afile/rec.mcap"\n',
        {},
        _file("afile"),
        "record.path: {d}/afile is not a folder",
    ),
    (
        "record-without-mcap",
        '[record]\npath = "rec.mcap"\n',
        {},
        _fake_mcap,
        "record.path: recording needs mcap (pip install 'mapd[record]')",
    ),
    (
        "view-host-no-address",
        '[view]\nlisten = "127.0.0.300:18080"\ntoken_file = "tok"\n',
        {},
        _file("tok", TOKEN),
        "view.listen: Value error, '127.0.0.300' is not an IP address",
    ),
    (
        "view-host-no-name",
        '[view]\nlisten = "no such host:18080"\ntoken_file = "tok"\n',
        {},
        _file("tok", TOKEN),
        "view.listen: Value error, 'no such host' is neither an IP address nor a host name",
    ),
    (
        "view-and-zenoh-on-one-port",
        '[view]\nlisten = "127.0.0.1:17447"\n' + ZENOH + 'listen = ["tcp/127.0.0.1:17447"]\n',
        {},
        None,
        "view.listen: 127.0.0.1:17447 is also where transports.zenoh listens (tcp/127.0.0.1:17447)",
    ),
    (
        "view-beside-a-zenoh-router",
        '[view]\nlisten = "127.0.0.1:7447"\n' + ZENOH + 'mode = "router"\n',
        {},
        None,
        "view.listen: 127.0.0.1:7447 is also where transports.zenoh listens (tcp/[::]:7447 (a router's default))",
    ),
    (
        "zenoh-output-and-transport-on-one-port",
        ZENOH
        + 'listen = ["tcp/0.0.0.0:17450"]\n[output]\nuse = ["zenoh"]\n[output.zenoh]\n'
        + 'listen = ["tcp/127.0.0.1:17450"]\nmulticast_scouting = false\n',
        {},
        None,
        "output.zenoh.listen: tcp/127.0.0.1:17450 is also where transports.zenoh listens (tcp/0.0.0.0:17450)",
    ),
    (
        "two-zenoh-routers",
        ZENOH + 'mode = "router"\n[output]\nuse = ["zenoh"]\n[output.zenoh]\nmode = "router"\n',
        {},
        None,
        "output.zenoh.listen: tcp/[::]:7447 (a router's default) is also where transports.zenoh "
        "listens (tcp/[::]:7447 (a router's default))",
    ),
    (
        "sim-world-missing",
        "",
        {"[codec]": 'world = "nosuch.yaml"\n[codec]'},
        None,
        "source.sim.world: {d}/nosuch.yaml: no such map file",
    ),
    (
        "sim-world-not-a-map",
        "",
        {"[codec]": 'world = "w.yaml"\n[codec]'},
        _file("w.yaml", "image: nosuch.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n"),
        "source.sim.world: {d}/w.yaml: image '{d}/nosuch.pgm' does not exist",
    ),
    (
        "sim-building-over-max-cells",
        "[limits]\nmax_cells = 100000\n",
        {},
        None,
        "source.sim.width_m: a 30.0 x 20.0 m building at 0.05 m/cell has 281599 cells, over "
        "limits.max_cells (100000)",
    ),
    (
        "laserlog-missing",
        "",
        {
            'use = "sim"': 'use = "laserlog"',
            "[source.sim]\nrealtime = 0\nduration = 5\n": '[source.laserlog]\nlog = "nosuch.log"\n',
        },
        None,
        "source.laserlog.log: {d}/nosuch.log: no such log file",
    ),
    (
        "uwb-port-is-a-file",
        UWB.format(port="{d}/plainfile"),
        {},
        _file("plainfile"),
        "transports.uwb.port: {d}/plainfile is not a serial device (it exists, and is no character device)",
    ),
    (
        "zenoh-endpoint-without-port",
        ZENOH + 'listen = ["tcp/notanaddress"]\n',
        {},
        None,
        "transports.zenoh.listen: Value error, 'tcp/notanaddress': tcp needs HOST:PORT with a port 0-65535",
    ),
    (
        "zenoh-endpoint-unknown-protocol",
        ZENOH + 'listen = ["foo/127.0.0.1:17448"]\n',
        {},
        None,
        "transports.zenoh.listen: Value error, 'foo/127.0.0.1:17448': zenoh has no link protocol 'foo' (it has tcp, udp, tls, "
        "quic, ws, unixsock-stream, unixpipe, serial, vsock)",
    ),
    (
        "zenoh-tls-key-missing",
        ZENOH + 'listen = ["tls/127.0.0.1:17449"]\nconfig_file = "z.json5"\n',
        {},
        _tls_config,
        "transports.zenoh.config_file: {d}/z.json5: transport.link.tls.listen_private_key: "
        "{d}/nokey.pem: cannot read it: No such file or directory",
    ),
    (
        "zenoh-tls-listener-without-key",
        ZENOH + 'listen = ["tls/127.0.0.1:17451"]\n',
        {},
        None,
        "transports.zenoh.listen: tls/127.0.0.1:17451: a tls listener needs transport.link.tls."
        "listen_private_key and listen_certificate in a zenoh config (config_file)",
    ),
    (
        "zenoh-output-endpoint",
        '[output]\nuse = ["zenoh"]\n[output.zenoh]\nlisten = ["garbage"]\n',
        {},
        None,
        "output.zenoh.listen: Value error, 'garbage' is not a zenoh endpoint (<protocol>/<address>, "
        "e.g. tcp/127.0.0.1:7447)",
    ),
    (
        "ros2-output-endpoint",
        '[output]\nuse = ["ros2"]\n[output.ros2]\nconnect = []\nlisten = ["tcp/notanaddress"]\n',
        NONE_SOURCE,
        None,
        "output.ros2.listen: Value error, 'tcp/notanaddress': tcp needs HOST:PORT with a port 0-65535",
    ),
    (
        "ros2-source-endpoint",
        "",
        {
            'use = "sim"': 'use = "ros2"',
            "[source.sim]\nrealtime = 0\nduration = 5\n": '[source.ros2]\nconnect = []\nlisten = ["garbage"]\n',
        },
        None,
        "source.ros2.listen: Value error, 'garbage' is not a zenoh endpoint (<protocol>/<address>, "
        "e.g. tcp/127.0.0.1:7447)",
    ),
]


def _mapd(d: Path, *args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    if (d / "mods").is_dir():
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(d / "mods"), env.get("PYTHONPATH")]))
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], cwd=d, env=env, capture_output=True, text=True, timeout=timeout
    )


def _tree(d: Path) -> set[Path]:
    return {p.relative_to(d) for p in d.rglob("*")}


@pytest.mark.parametrize(
    ("extra", "replace", "setup", "says"), [c[1:] for c in CASES], ids=[c[0] for c in CASES]
)
def test_check_config_refuses_what_mapd_run_would_and_run_says_the_same_line(
    tmp_path: Path,
    extra: str,
    replace: dict[str, str],
    setup: Callable[[Path], None] | None,
    says: str,
) -> None:
    d = tmp_path.resolve()
    text = BASE
    for old, new in replace.items():
        text = text.replace(old, new)
    (d / "c.toml").write_text((text + extra).replace("{d}", str(d)))
    if setup is not None:
        setup(d)
    before = _tree(d)
    checked = _mapd(d, "check-config", "c.toml", timeout=120)
    line = f"mapd: error: c.toml: {says.format(d=d)}"
    assert (checked.returncode, checked.stderr.splitlines()) == (2, [line]), checked.stdout[:300]
    assert _tree(d) == before, "check-config made or removed something"
    try:
        ran = _mapd(d, "run", "--config", "c.toml", timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("mapd run started with a config check-config refuses")
    assert ran.returncode == 2
    assert ran.stderr.splitlines()[-1] == line


def test_check_config_takes_what_only_the_start_decides_and_creates_nothing(tmp_path: Path) -> None:
    """A serial port not plugged in yet, a map file not written yet, folders not made yet, a view on
    a host name: the start waits for them or makes them; check-config says ok and touches nothing."""
    d = tmp_path.resolve()
    (d / "c.toml").write_text(
        BASE.replace('dir = "state"', 'dir = "new/state"').replace(
            'runtime_dir = "run"', 'runtime_dir = "new/run"'
        )
        + UWB.format(port="/dev/mapd-test-no-such-port")
        + '[output]\nuse = ["files"]\n[output.files]\ndir = "new/out"\n'
        + '[record]\npath = "new/rec/fleet.mcap"\n'
        + '[view]\nlisten = "localhost:18080"\n'
    )
    checked = _mapd(d, "check-config", "c.toml", timeout=120)
    assert checked.returncode == 0, checked.stderr
    assert _tree(d) == {Path("c.toml")}


@pytest.mark.parametrize(
    "endpoint",
    [
        "tcp/localhost:7447",
        "tcp/[::1]:7447",
        "tcp/[fe80::1%eth0]:7447",
        "tls/router_1.lab:7447",
        "udp/224.0.0.224:7446#iface=eth0",
        "ws/0.0.0.0:0",
        "quic/10.0.0.2:7447?prio=1",
        "unixsock-stream//run/zenoh.sock",
        "serial//dev/ttyACM0#baudrate=115200",
    ],
)
def test_endpoints_zenoh_takes_are_not_refused(endpoint: str) -> None:
    from mapd.config.endpoints import check_endpoints

    assert check_endpoints([endpoint]) == [endpoint]


@pytest.mark.parametrize(
    ("view", "zenoh"),
    [
        ("127.0.0.1:17447", "tcp/127.0.0.1:17448"),  # another port
        ("127.0.0.1:17447", "udp/127.0.0.1:17447"),  # udp beside tcp
        ("[::]:17447", "tcp/127.0.0.1:17447"),  # the view's IPv6 wildcard is IPv6 only
        ("127.0.0.1:17447", "tcp/127.0.0.2:17447"),  # another address
        ("localhost:17447", "tcp/127.0.0.1:0"),  # port 0: any free port
    ],
)
def test_listeners_on_other_sockets_are_not_refused(tmp_path: Path, view: str, zenoh: str) -> None:
    from mapd import config

    (tmp_path / "tok").write_text(TOKEN)
    view_table = f'[view]\nlisten = "{view}"\ntoken_file = "tok"\n'
    (tmp_path / "c.toml").write_text(BASE + view_table + ZENOH + f'listen = ["{zenoh}"]\n')
    config.check(config.load(tmp_path / "c.toml"))
