"""Start-up, said the same way whichever part meets the problem.

- Exit status: a path this robot cannot use exits 2 (no restart under systemd) whether it is the
  state directory, the files output's folder or the control socket's; before, the state
  directory's exited 1 and the unit was started again every 2 s for ever. What a retry may get
  past (another mapd holding the state directory) still exits 1.
- A relative uwb port or zenoh TLS file is looked up from the working directory by the one check
  ``mapd check-config`` and ``mapd run`` share, as the start looks it up; before, check-config
  said "ok" and the start failed (TLS) or waited for ever (the port).
- A ``sim`` source's world map is read once at a daemon's start, not once by the config's check
  and again by the source.
"""

from __future__ import annotations

import asyncio
import errno
import os
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from mapd import config as configmod
from mapd.errors import (
    ConfigError,
    DaemonError,
    DiskFullError,
    MapdError,
    StateError,
    TransportError,
    exit_code,
)

BASE = """[robot]
name = "alpha"
[fleet]
allow_unsigned = true
[state]
dir = "state"
runtime_dir = "run"
[source]
use = "none"
[codec]
use = "zstd"
"""
UWB = '[transports]\nuse = ["uwb"]\n[transports.uwb]\nport = "{port}"\nnodes = {{ alpha = 1, beta = 2 }}\n'
ZENOH_TLS = (
    '[transports]\nuse = ["zenoh"]\n[transports.zenoh]\nmulticast_scouting = false\n'
    'listen = ["tls/127.0.0.1:17961"]\nconfig_file = "conf/z.json5"\n'
)
CERT = "-----BEGIN CERTIFICATE-----\nMAA=\n-----END CERTIFICATE-----\n"
KEY = "-----BEGIN PRIVATE KEY-----\nMAA=\n-----END PRIVATE KEY-----\n"


def _mapd(cwd: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "mapd", *args], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )


def _raised(make: type[MapdError], cause: BaseException | None) -> MapdError:
    """``make`` raised as mapd raises its errors: ``from None`` inside the ``except`` of ``cause``."""
    try:
        try:
            if cause is not None:
                raise cause
            raise make("no cause")
        except OSError:
            raise make("one line") from None
    except MapdError as exc:
        return exc


# ---------------------------------------------------------------------------------- exit status


@pytest.mark.parametrize(
    ("cls", "cause", "code"),
    [
        (StateError, PermissionError(errno.EACCES, "Permission denied"), 2),
        (StateError, PermissionError(errno.EPERM, "Operation not permitted"), 2),
        (StateError, OSError(errno.EROFS, "Read-only file system"), 2),
        (StateError, FileExistsError(errno.EEXIST, "File exists"), 2),  # a file where a folder goes
        (StateError, BlockingIOError(errno.EAGAIN, "in use"), 1),  # another mapd holds the lock
        (StateError, FileNotFoundError(errno.ENOENT, "No such file"), 1),  # a mount not there yet
        (StateError, OSError(errno.ENOSPC, "No space left on device"), 1),
        (DiskFullError, OSError(errno.ENOSPC, "No space left on device"), 1),
        (ConfigError, None, 2),
        (ConfigError, PermissionError(errno.EACCES, "Permission denied"), 2),
        (ConfigError, OSError(errno.ENOSPC, "No space left on device"), 1),  # the disk may get room
        (DaemonError, PermissionError(errno.EACCES, "Permission denied"), 2),  # control socket
        (DaemonError, ConnectionRefusedError(errno.ECONNREFUSED, "refused"), 1),  # no daemon
        # a radio's device node may get its group from udev a moment after it appears: retried
        (TransportError, PermissionError(errno.EACCES, "Permission denied"), 1),
    ],
)
def test_exit_code_follows_what_went_wrong(cls: type[MapdError], cause: OSError | None, code: int) -> None:
    assert exit_code(_raised(cls, cause)) == code


def test_exit_code_looks_no_further_than_mapd_errors() -> None:
    # a StateError raised while handling an unrelated error that itself followed an EACCES: not a path
    try:
        try:
            try:
                raise PermissionError(errno.EACCES, "Permission denied")
            except OSError:
                raise KeyError("unrelated") from None
        except KeyError:
            raise StateError("one line") from None
    except StateError as exc:
        assert exit_code(exc) == 1


@pytest.fixture
def unmakeable() -> Iterator[Path]:
    """A folder path below which no one, root included, may make a folder (sysfs: EPERM or EACCES)."""
    path = Path("/sys") / f"mapd-test-{uuid.uuid4().hex[:8]}"
    try:
        path.mkdir()
    except OSError as exc:
        if exc.errno in (errno.EPERM, errno.EACCES, errno.EROFS):
            yield path
            return
    else:
        path.rmdir()
    pytest.skip("no /sys that refuses a new folder here")


@pytest.mark.parametrize(
    ("where", "says"),
    [
        ("state", "mapd: error: state directory {u}/state is not writable: "),
        ("files output", "mapd: error: output.files: cannot create {u}/out: "),
        ("control socket", "mapd: error: cannot create control socket {u}/run/mapd.sock: "),
    ],
)
def test_mapd_run_exits_2_for_any_folder_it_may_not_create(
    tmp_path: Path, unmakeable: Path, where: str, says: str
) -> None:
    """Reproduced first with the real CLI (a folder made immutable with chattr +i): the state
    directory exited 1, the files output's folder 2."""
    text = BASE
    if where == "state":
        text = text.replace('dir = "state"', f'dir = "{unmakeable}/state"')
    elif where == "files output":
        text += f'[output]\nuse = ["files"]\n[output.files]\ndir = "{unmakeable}/out"\n'
    else:
        text = text.replace('runtime_dir = "run"', f'runtime_dir = "{unmakeable}/run"')
    (tmp_path / "c.toml").write_text(text)
    checked = _mapd(tmp_path, "check-config", "c.toml")
    assert checked.returncode == 0, checked.stderr  # who may write where: the start's to find
    ran = _mapd(tmp_path, "run", "--config", "c.toml", timeout=60)
    lines = ran.stderr.splitlines()
    assert lines and lines[-1].startswith(says.format(u=unmakeable)), ran.stderr
    assert "Traceback" not in ran.stderr
    assert ran.returncode == 2


def test_mapd_run_exits_1_for_a_state_directory_another_mapd_holds(tmp_path: Path) -> None:
    """What a retry gets past (the other mapd stops) stays 1: systemd starts the unit again."""
    from mapd.daemon.state_lock import lock_state_dir

    (tmp_path / "c.toml").write_text(BASE)
    held = lock_state_dir(tmp_path / "state")
    try:
        ran = _mapd(tmp_path, "run", "--config", "c.toml", timeout=60)
    finally:
        os.close(held)
    assert "is in use by another mapd" in ran.stderr.splitlines()[-1], ran.stderr
    assert ran.returncode == 1


def test_the_unit_prevents_a_restart_on_the_code_exit_code_gives_an_unusable_path() -> None:
    unit = (Path(__file__).resolve().parents[1] / "deploy" / "mapd.service").read_text()
    code = exit_code(_raised(StateError, PermissionError(errno.EACCES, "Permission denied")))
    assert f"RestartPreventExitStatus={code}\n" in unit


# ------------------------------------------------------------- relative paths, from the cwd


def _tls_files(d: Path, key: str | None = "key.pem", cert: str | None = "cert.pem") -> None:
    """``d/conf/z.json5`` naming relative TLS files; ``key``/``cert``: those written into ``d``."""
    (d / "conf").mkdir(exist_ok=True)
    tls = (
        '{ transport: { link: { tls: { listen_private_key: "key.pem", listen_certificate: "cert.pem" } } } }'
    )
    (d / "conf" / "z.json5").write_text(tls)
    if key:
        (d / key).write_text(KEY)
    if cert:
        (d / cert).write_text(CERT)


def test_check_config_and_run_refuse_a_relative_tls_file_missing_from_the_working_directory(
    tmp_path: Path,
) -> None:
    """Reproduced: check-config said ok, and mapd run (exit 1) stopped when zenoh could not read
    the key, whose relative name zenoh takes from the process's working directory (not the
    config's folder, nor the zenoh config's)."""
    d = tmp_path.resolve()
    (d / "c.toml").write_text(BASE + ZENOH_TLS)
    _tls_files(d, key=None)
    (d / "conf" / "key.pem").write_text(KEY)  # beside the zenoh config: not where zenoh looks
    line = (
        f"mapd: error: c.toml: transports.zenoh.config_file: {d}/conf/z.json5: "
        "transport.link.tls.listen_private_key: 'key.pem' is relative, so mapd run's zenoh session "
        f"reads it from the working directory ({d}; / under systemd): {d}/key.pem: cannot read it: No such "
        "file or directory"
    )
    checked = _mapd(d, "check-config", "c.toml")
    assert (checked.returncode, checked.stderr.splitlines()) == (2, [line])
    ran = _mapd(d, "run", "--config", "c.toml", timeout=60)
    assert ran.returncode == 2 and ran.stderr.splitlines()[-1] == line, ran.stderr
    assert not (d / "state").exists()  # refused before the daemon made anything


def test_a_relative_tls_file_in_the_working_directory_passes_and_one_without_pem_does_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytest.importorskip("zenoh")
    d = tmp_path.resolve()
    (d / "c.toml").write_text(BASE + ZENOH_TLS)
    _tls_files(d)
    monkeypatch.chdir(d)
    configmod.check(configmod.load(d / "c.toml"))
    (d / "cert.pem").write_text("not a certificate\n")
    with pytest.raises(
        ConfigError, match=r"listen_certificate: 'cert.pem' is relative.*holds no PEM certificate$"
    ):
        configmod.check(configmod.load(d / "c.toml"))
    monkeypatch.chdir(d / "conf")  # the same config, checked from elsewhere: looked for there
    with pytest.raises(
        ConfigError, match=rf"\({d}/conf; / under systemd\): {d}/conf/cert.pem: cannot read it: No such file"
    ):
        configmod.check(configmod.load(d / "c.toml"))


def test_check_config_and_run_refuse_a_relative_uwb_port_that_is_not_there(tmp_path: Path) -> None:
    """Reproduced: check-config said ok, and mapd run waited for ./ttyUSB0 for ever (under systemd,
    /ttyUSB0). A relative name is no device the kernel makes late at boot: a mistake, said now."""
    d = tmp_path.resolve()
    (d / "c.toml").write_text(BASE + UWB.format(port="ttyUSB0"))
    line = (
        "mapd: error: c.toml: transports.uwb.port: 'ttyUSB0' is relative, so mapd run opens it from "
        f"the working directory ({d}; / under systemd): {d}/ttyUSB0 does not exist (name the device "
        "by its full path, such as /dev/ttyUSB0)"
    )
    checked = _mapd(d, "check-config", "c.toml")
    assert (checked.returncode, checked.stderr.splitlines()) == (2, [line])
    ran = _mapd(d, "run", "--config", "c.toml", timeout=60)
    assert ran.returncode == 2 and ran.stderr.splitlines()[-1] == line, ran.stderr


def test_a_relative_uwb_port_is_taken_when_a_pty_and_refused_when_a_plain_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    d = tmp_path.resolve()
    (d / "c.toml").write_text(BASE + UWB.format(port="radio"))
    monkeypatch.chdir(d)
    main, sub = os.openpty()
    try:
        (d / "radio").symlink_to(os.ttyname(sub))  # as socat's link=, or the demo's relay makes it
        configmod.check(configmod.load(d / "c.toml"))
    finally:
        os.close(main)
        os.close(sub)
    (d / "radio").unlink()
    (d / "radio").write_text("")
    with pytest.raises(ConfigError, match=rf"port: 'radio' .*: {d}/radio is not a serial device"):
        configmod.check(configmod.load(d / "c.toml"))


def test_an_absolute_uwb_port_not_there_yet_is_still_waited_for(tmp_path: Path) -> None:
    (tmp_path / "c.toml").write_text(BASE + UWB.format(port="/dev/mapd-test-no-such-port"))
    configmod.check(configmod.load(tmp_path / "c.toml"))


# ------------------------------------------------------------------------- the sim world


def _sim_config(tmp_path: Path, world: str | None) -> Path:
    table = "[source.sim]\nrealtime = 0\nduration = 2\nwidth_m = 8\nheight_m = 6\n"
    if world is not None:
        table += f'world = "{world}"\n'
    path = tmp_path / "c.toml"
    path.write_text(BASE.replace('use = "none"', 'use = "sim"') + table)
    return path


def _start_daemon(cfg_path: Path) -> None:
    """A daemon made from the config (which checks it) and run until its source sent a map."""
    from mapd.daemon.server import Daemon

    async def main() -> None:
        daemon = Daemon(configmod.load(cfg_path))
        task = asyncio.create_task(daemon.run())
        end = time.monotonic() + 60
        while not (daemon.source is not None and daemon.source.stats().get("versions", 0) >= 1):
            assert not task.done() and time.monotonic() < end, "the daemon's source sent no map"
            await asyncio.sleep(0.02)
        daemon.request_stop()
        await task

    asyncio.run(main())


def _count(monkeypatch: pytest.MonkeyPatch, module: Any, name: str) -> list[int]:
    calls: list[int] = []
    real = getattr(module, name)

    def counted(*args: Any, **kwargs: Any) -> Any:
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, counted)
    return calls


def test_a_sim_world_map_is_read_once_at_a_daemon_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Reproduced: the config's check (check_with_config) read the world map, then the source read
    it again when it built the robot."""
    from mapd.grid.save import save_map
    from mapd.mapping import worldgen
    from mapd.sources import sim

    save_map(worldgen.generate(3, 8.0, 6.0, 0.05, 1.0).grid, tmp_path / "w.yaml")
    loads = _count(monkeypatch, sim, "load_map")
    built = _count(monkeypatch, worldgen, "from_map")
    _start_daemon(_sim_config(tmp_path, "w.yaml"))
    assert (len(loads), len(built)) == (1, 1)


def test_a_generated_sim_world_is_generated_once_at_a_daemon_start(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from mapd.mapping import worldgen

    generated = _count(monkeypatch, worldgen, "generate")
    _start_daemon(_sim_config(tmp_path, None))
    assert len(generated) == 1


def test_a_checked_world_is_not_used_for_another_path_or_limit(tmp_path: Path) -> None:
    from mapd.grid.save import save_map
    from mapd.mapping import worldgen

    save_map(worldgen.generate(3, 8.0, 6.0, 0.05, 1.0).grid, tmp_path / "w.yaml")
    cfg = configmod.load(_sim_config(tmp_path, "w.yaml"))
    opts = configmod.check(cfg).options["source"]["sim"]
    path = tmp_path / "w.yaml"
    assert opts.take_world(path, cfg.limits.max_cells - 1) is None  # another limit: read again
    opts = configmod.check(cfg).options["source"]["sim"]
    assert opts.take_world(tmp_path / "other.yaml", cfg.limits.max_cells) is None
    opts = configmod.check(cfg).options["source"]["sim"]
    assert opts.take_world(path, cfg.limits.max_cells) is not None
    assert opts.take_world(path, cfg.limits.max_cells) is None  # handed over once, not kept
