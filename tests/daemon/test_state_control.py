"""State directory persistence, the read-only control socket, and sd_notify."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import socket
import stat
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mapd.daemon.state import StateStore
from mapd.daemon.state_lock import lock_state_dir
from mapd.daemon.state_records import MAX_STATE_JSON
from mapd.daemon.status_socket import StatusServer, query
from mapd.daemon.systemd import JournalFormatter, notify, watchdog_interval
from mapd.errors import DaemonError, StateError
from mapd.grid import OccupancyGrid, Pose2D
from mapd.grid.save import save_map


def test_state_round_trip(tmp_path: Path, room_grid: OccupancyGrid) -> None:
    store = StateStore(tmp_path / "s")
    store.open()
    own = room_grid.replace(version=4, robot="alpha")
    peer = room_grid.replace(version=9, robot="beta")
    store.save_own(own)
    store.save_base(own)
    store.save_peer(peer)
    assert store.set_acked("beta", 4) and not store.set_acked("beta", 3)
    store.flush()
    again = StateStore(tmp_path / "s")
    data = again.open()
    assert (data.own_version, data.acked) == (4, {"beta": 4})
    assert again.own_map() is not None and again.own_map().same_map(own)  # type: ignore[union-attr]
    assert again.base_map().version == 4  # type: ignore[union-attr]
    back = again.peer_map("beta")
    assert back is not None and back.same_map(peer) and back.version == 9


def test_map_not_matching_state_json_is_ignored(tmp_path: Path, room_grid: OccupancyGrid) -> None:
    store = StateStore(tmp_path)
    store.open()
    store.save_peer(room_grid.replace(version=2, robot="beta"))
    # A map without its version in its YAML (as mapd wrote them before), replaced by another:
    # state.json alone says which map it should be, and this is not it.
    changed = room_grid.data.copy()
    changed[0, 0] = 100
    save_map(room_grid.replace(data=changed), tmp_path / "peers" / "beta" / "map.yaml")
    again = StateStore(tmp_path)
    again.open()
    assert again.peer_map("beta") is None


def test_a_state_directory_from_before_versions_in_the_yaml_is_read(
    tmp_path: Path, room_grid: OccupancyGrid
) -> None:
    own = room_grid.replace(version=4, robot="alpha")
    save_map(own, tmp_path / "own" / "map.yaml")  # map.yaml + map.pgm, as earlier releases wrote them
    (tmp_path / "state.json").write_text(
        json.dumps({"own_version": 4, "own": {"version": 4, "digest": own.digest().hex()}})
    )
    store = StateStore(tmp_path)
    store.open()
    back = store.own_map()
    assert back is not None and back.same_map(own) and back.version == 4
    store.save_own(own.replace(version=5))
    assert sorted(p.name for p in (tmp_path / "own").iterdir()) == ["map-5.pgm", "map.yaml"]


def test_corrupt_state_json_starts_empty(tmp_path: Path) -> None:
    (tmp_path / "state.json").write_text("{not json")
    assert StateStore(tmp_path).open().own_version == 0


@pytest.mark.parametrize(
    "doc",
    [
        '{"own_version": 1e999}',  # json reads it as inf, which int() cannot take
        '{"seq": 1e999}',
        "[" * 100_000,  # nested past the recursion limit
        '{"own_version": -7}',  # versions are never negative: every peer would refuse them
        f'{{"own_version": {1 << 63}}}',  # past what an envelope carries: nothing could be sent
        '{"own_version": true}',
        '{"own_version": 5, "peers": [1]}',
        "7",
    ],
)
def test_a_damaged_state_json_starts_a_new_incarnation(tmp_path: Path, doc: str) -> None:
    (tmp_path / "state.json").write_text(doc)
    store = StateStore(tmp_path)
    assert store.open().own_version == 0  # so the next version is a new incarnation from the clock
    assert 0 < store.next_own_version(1.8e9) < 1 << 63


def test_an_oversized_state_json_is_not_read(tmp_path: Path) -> None:
    with open(tmp_path / "state.json", "w") as fh:
        fh.write('{"own_version": 9, "pad": "')
        fh.write("x" * MAX_STATE_JSON)
        fh.write('"}')
    assert StateStore(tmp_path).open().own_version == 0


def test_bad_records_and_acks_are_left_out_and_the_rest_kept(tmp_path: Path) -> None:
    doc = {
        "own_version": 12,
        "seq": 40,
        "peers": {"beta": {"version": -1, "digest": "x"}, "gamma": {"version": 3, "digest": "d"}},
        "acked": {"beta": 1e999, "gamma": 1 << 64, "delta": 11},
    }
    (tmp_path / "state.json").write_text(json.dumps(doc))
    data = StateStore(tmp_path).open()
    assert (data.own_version, data.seq, list(data.peers), data.acked) == (12, 40, ["gamma"], {"delta": 11})


_VALUES = st.none() | st.booleans() | st.integers(-(1 << 70), 1 << 70) | st.floats() | st.text(max_size=6)
_RECORD = st.fixed_dictionaries({}, optional={"version": _VALUES, "digest": _VALUES})


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    doc=st.fixed_dictionaries(
        {},
        optional={
            "own_version": _VALUES,
            "seq": _VALUES,
            "own": _RECORD | _VALUES,
            "base": _RECORD | _VALUES,
            "peers": st.dictionaries(st.text(max_size=4), _RECORD | _VALUES, max_size=3) | _VALUES,
            "acked": st.dictionaries(st.text(max_size=4), _VALUES, max_size=3) | _VALUES,
        },
    )
    | _VALUES
)
def test_any_state_json_opens_with_counters_an_envelope_can_carry(tmp_path: Path, doc: object) -> None:
    (tmp_path / "state.json").write_text(json.dumps(doc))
    data = StateStore(tmp_path).open()
    counts = [data.own_version, data.seq, *data.acked.values()]
    counts += [r.version for r in (data.own, data.base, *data.peers.values()) if r is not None]
    assert all(type(c) is int and 0 <= c < 1 << 63 for c in counts)


@pytest.mark.parametrize("where", ["proc", "under-a-file"])
def test_unwritable_state_dir_is_one_clear_error(tmp_path: Path, where: str) -> None:
    # /proc refuses new directories even to root; a path below a regular file can never exist.
    if where == "proc":
        target = Path("/proc/mapd-state")
    else:
        (tmp_path / "file").write_text("x")
        target = tmp_path / "file" / "state"
    with pytest.raises(StateError, match="is not writable"):
        StateStore(target).open()


def test_unsafe_peer_names_never_become_paths(tmp_path: Path, room_grid: OccupancyGrid) -> None:
    store = StateStore(tmp_path)
    store.open()
    with pytest.raises(StateError, match="unsafe"):
        store.save_peer(room_grid.replace(robot="../../etc"))


@pytest.mark.parametrize("pose", ["[1, 2]", "[.nan, 0, 0]", f"[{'9' * 400}, 0, 0]", "[0, 0, -1e400]"])
def test_a_damaged_reported_pose_in_a_peer_map_is_one_warning_and_the_map_kept(
    tmp_path: Path, room_grid: OccupancyGrid, caplog: pytest.LogCaptureFixture, pose: str
) -> None:
    # An integer too large for a float (YAML reads any) raised OverflowError out of the restore:
    # `mapd run` on that state directory died with a traceback at every start.
    store = StateStore(tmp_path)
    store.open()
    store.save_peer(room_grid.replace(robot="beta", version=3), frame_pose=Pose2D(1.0, 2.0, 0.0))
    yaml = tmp_path / "peers" / "beta" / "map.yaml"
    text = yaml.read_text()
    yaml.write_text(text[: text.index("mapd_frame_pose:")] + f"mapd_frame_pose: {pose}\n")
    with caplog.at_level(logging.WARNING, logger="mapd.daemon.state"):
        saved = StateStore(tmp_path).saved_peer("beta")
    assert saved is not None and saved.grid.version == 3 and saved.frame_pose is None
    (line,) = [r.getMessage() for r in caplog.records]
    assert line.startswith(f"state map {yaml}: ignoring its reported pose [")
    assert line.endswith("(not three finite numbers)")


@pytest.mark.parametrize("fault", ["file-in-its-place", "enospc", "eacces-on-stat"])
def test_a_peer_folder_that_cannot_be_made_is_one_state_error(
    tmp_path: Path, room_grid: OccupancyGrid, monkeypatch: pytest.MonkeyPatch, fault: str
) -> None:
    """A full disk (mkdir: ENOSPC), a stray file where the folder goes, or a folder that cannot be
    looked at: one :class:`StateError` line, which the daemon says once and goes on; a bare
    OSError ended the daemon."""
    import errno

    store = StateStore(tmp_path)
    store.open()
    if fault == "file-in-its-place":
        (tmp_path / "peers" / "beta").write_bytes(b"")
    elif fault == "enospc":

        def full(directory: Path) -> None:
            raise OSError(errno.ENOSPC, "No space left on device", str(directory))

        monkeypatch.setattr("mapd.daemon.state.make_dir", full)
    else:
        real = Path.is_dir

        def denied(self: Path) -> bool:  # a stat that fails with an error is_dir does not swallow
            if self.name == "beta" or self.parent.name == "beta":
                raise PermissionError(errno.EACCES, "Permission denied", str(self))
            return real(self)

        monkeypatch.setattr(Path, "is_dir", denied)
        monkeypatch.setattr("mapd.daemon.state.make_dir", lambda d: None)
    with pytest.raises(StateError) as err:
        store.save_peer(room_grid.replace(robot="beta", version=3))
    assert "beta" in str(err.value) and "\n" not in str(err.value)
    assert "beta" not in store.data.peers


def test_a_new_peer_folder_is_made_durable_before_state_json_names_it(
    tmp_path: Path, room_grid: OccupancyGrid, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A power cut must not keep state.json's record of a peer while losing the folder holding its
    map: the parent's entry for the new folder is fsynced first."""
    from mapd import files

    store = StateStore(tmp_path)
    store.open()
    synced: list[Path] = []
    real = files._fsync_dir
    monkeypatch.setattr(files, "_fsync_dir", lambda d: (synced.append(Path(d)), real(d))[1])
    store.save_peer(room_grid.replace(robot="beta", version=3))
    peers = store.root / "peers"
    beta = next(p for p in peers.iterdir() if p.is_dir())
    assert (beta / "map.yaml").exists()
    assert peers in synced and synced.index(peers) < synced.index(store.root)  # before state.json's
    synced.clear()
    store.save_peer(room_grid.replace(robot="beta", version=4))
    assert peers not in synced  # an existing folder: nothing more to make durable


def test_control_socket_serves_json_and_ignores_input(tmp_path: Path) -> None:
    path = tmp_path / "run" / "mapd.sock"
    calls = {"n": 0}

    def snap() -> dict[str, object]:
        calls["n"] += 1
        return {"robot": "alpha", "n": calls["n"]}

    async def main() -> None:
        server = StatusServer(path, snap)
        await server.start()
        assert stat.S_IMODE(path.stat().st_mode) == 0o660
        doc = await asyncio.to_thread(query, path)
        assert doc == {"robot": "alpha", "n": 1}
        # Writing commands changes nothing: the reply is still just the status.
        r, w = await asyncio.open_unix_connection(str(path))
        w.write(b'{"cmd": "shutdown"}\n' * 100)
        await w.drain()
        reply = json.loads(await r.read())
        assert reply["robot"] == "alpha"
        w.close()
        with pytest.raises(DaemonError, match="already serving"):
            await StatusServer(path, snap).start()
        await server.close()
        assert not path.exists()

    asyncio.run(main())


def test_status_watch_keeps_watching_while_no_daemon_answers(tmp_path: Path) -> None:
    """``mapd status --watch`` exited at the first failed query: watching through a restart ended
    with the restart."""
    path = tmp_path / "mapd.sock"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mapd", "status", "--socket", str(path), "--watch", "0.1", "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        first = proc.stdout.readline()
        assert "no mapd daemon is running" in first and "watching" in first
        assert proc.poll() is None  # still watching

        async def serve() -> str:
            server = StatusServer(path, lambda: {"robot": "alpha"})
            await server.start()
            try:
                while True:  # until a status document comes through
                    line = await asyncio.to_thread(proc.stdout.readline)  # type: ignore[union-attr]
                    if not line or '"robot": "alpha"' in line:
                        return line
            finally:
                await server.close()

        assert '"robot": "alpha"' in asyncio.run(asyncio.wait_for(serve(), 60))
    finally:
        proc.kill()
        proc.wait(30)


def test_the_control_socket_replaces_only_a_stale_socket_and_removes_only_its_own(tmp_path: Path) -> None:
    """A file, a FIFO or a device at the socket path was deleted (as root, /dev/null would be), and
    a second daemon refused at start removed the first one's socket on its way out."""
    note, fifo = tmp_path / "note.txt", tmp_path / "fifo"
    note.write_text("keep me")
    os.mkfifo(fifo)

    async def main() -> None:
        for path in (note, fifo):
            with pytest.raises(DaemonError, match="exists and is not a socket"):
                await StatusServer(path, dict).start()
        path = tmp_path / "mapd.sock"
        first = StatusServer(path, lambda: {"robot": "first"})
        await first.start()
        second = StatusServer(path, lambda: {"robot": "second"})
        with pytest.raises(DaemonError, match="already serving"):
            await second.start()
        await second.close()  # as a daemon that failed to start closes everything
        assert (await asyncio.to_thread(query, path))["robot"] == "first"
        await first.close()
        assert not path.exists()
        stale = socket.socket(socket.AF_UNIX)  # a killed daemon's socket: nobody listens
        stale.bind(str(path))
        stale.close()
        third = StatusServer(path, lambda: {"robot": "third"})
        await third.start()
        assert (await asyncio.to_thread(query, path))["robot"] == "third"
        await third.close()

    asyncio.run(main())
    assert note.read_text() == "keep me" and fifo.is_fifo()


def test_a_state_directory_is_held_by_one_daemon_at_a_time(tmp_path: Path) -> None:
    """Two daemons on one state directory numbered maps from one counter and wrote one state.json."""
    fd = lock_state_dir(tmp_path / "s")
    try:
        with pytest.raises(StateError, match=f"in use by another mapd \\(pid {os.getpid()}\\)"):
            lock_state_dir(tmp_path / "s")
        # another process too (flock is the kernel's)
        code = f"from pathlib import Path; from mapd.daemon.state_lock import lock_state_dir; lock_state_dir(Path({str(tmp_path / 's')!r}))"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert out.returncode != 0 and "in use by another mapd" in out.stderr
    finally:
        os.close(fd)
    os.close(lock_state_dir(tmp_path / "s"))  # free once the holder lets go
    holder = subprocess.Popen(  # a daemon killed with -9 frees it too (the kernel drops the lock)
        [sys.executable, "-c", code + "; print('held', flush=True); import time; time.sleep(60)"],
        stdout=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(StateError, match="in use by another mapd"):
            lock_state_dir(tmp_path / "s")
        holder.kill()
        holder.wait(10)
    finally:
        holder.kill()
    os.close(lock_state_dir(tmp_path / "s"))


def test_query_without_daemon_is_clear(tmp_path: Path) -> None:
    with pytest.raises(DaemonError, match="no mapd daemon is running"):
        query(tmp_path / "none.sock")
    # a stale socket (a killed daemon's) is not a file given as --socket by mistake
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(tmp_path / "stale.sock"))
    stale.close()
    with pytest.raises(DaemonError, match=r"stale control socket at .*stale\.sock\)$"):
        query(tmp_path / "stale.sock")
    (tmp_path / "status.json").write_text("{}")  # before: "stale control socket" for it too
    with pytest.raises(
        DaemonError, match=r"status\.json is not a socket: no mapd control socket \(wrong --socket\?\)$"
    ):
        query(tmp_path / "status.json")


def test_a_socket_that_trickles_bytes_is_given_up_after_the_whole_timeout(tmp_path: Path) -> None:
    # The timeout was per read: a byte every second kept `mapd status` waiting for ever.
    path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(path))
        server.listen(1)
        stop = threading.Event()

        def trickle() -> None:
            conn, _ = server.accept()
            with conn:
                while not stop.wait(0.2):
                    try:
                        conn.sendall(b" ")
                    except OSError:
                        return

        t = threading.Thread(target=trickle)
        t.start()
        t0 = time.monotonic()
        try:
            with pytest.raises(DaemonError, match=r"sent no whole status within 1 s"):
                query(path, timeout=1.0)
        finally:
            stop.set()
            t.join()
        assert time.monotonic() - t0 < 3.0


def test_sd_notify_and_watchdog(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    sock_path = tmp_path / "notify"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as s:
        s.bind(str(sock_path))
        monkeypatch.setenv("NOTIFY_SOCKET", str(sock_path))
        assert notify("READY=1")
        assert s.recv(100) == b"READY=1"
    monkeypatch.delenv("NOTIFY_SOCKET")
    assert not notify("READY=1")
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert watchdog_interval() == 2.0
    monkeypatch.setenv("WATCHDOG_PID", "1")
    assert watchdog_interval() is None


def test_journal_formatter_priority_prefix() -> None:
    import logging

    rec = logging.LogRecord("mapd.x", logging.WARNING, __file__, 1, "link down", None, None)
    rec.fields = {"peer": "beta"}
    assert JournalFormatter(journal=True).format(rec) == "<4>mapd.x: link down peer=beta"


def test_every_line_of_a_traceback_carries_the_journal_priority() -> None:
    """journald stores each line as an entry: unprefixed lines went in at info, so
    ``journalctl -p err`` showed an error's headline without its traceback."""
    try:
        raise ZeroDivisionError("division by zero")
    except ZeroDivisionError:
        exc_info = sys.exc_info()
    import logging

    rec = logging.LogRecord("mapd.daemon", logging.ERROR, __file__, 1, "status line failed", None, exc_info)
    lines = JournalFormatter(journal=True).format(rec).split("\n")
    assert len(lines) > 3 and all(line.startswith("<3>") for line in lines)
    assert (
        lines[0] == "<3>mapd.daemon: status line failed"
        and lines[-1] == "<3>ZeroDivisionError: division by zero"
    )


@pytest.mark.parametrize("journal", [True, False])
def test_the_error_that_stops_mapd_is_at_error_priority_in_the_journal(tmp_path: Path, journal: bool) -> None:
    """``mapd: error: ...`` (why the unit stopped) went to the journal at info priority; and only a
    stderr that is the journal stream (device and inode of ``$JOURNAL_STREAM``) gets the prefix."""
    err = tmp_path / "stderr"
    with err.open("wb") as fh:
        st = os.fstat(fh.fileno())
        env = dict(os.environ, JOURNAL_STREAM=f"{st.st_dev}:{st.st_ino}" if journal else "1:1")
        subprocess.run(
            [sys.executable, "-m", "mapd", "check-config", str(tmp_path / "none.toml")],
            stderr=fh, stdout=subprocess.DEVNULL, env=env, timeout=60, check=False,
        )  # fmt: skip
    line = err.read_text().strip().splitlines()[-1]
    assert "none.toml" in line and "error" in line
    assert line.startswith("<3>mapd: error: ") == journal


@pytest.mark.parametrize(
    ("doc", "said"),
    [({"security": []}, "AttributeError"), ({"source": {"size": [1]}}, "IndexError")],
)
def test_a_status_mapd_cannot_show_is_one_error_line(
    tmp_path: Path, doc: dict[str, object], said: str
) -> None:
    # A daemon of another mapd version may send a status of another shape: `mapd status` said it
    # with a traceback.
    path = tmp_path / "s.sock"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as server:
        server.bind(str(path))
        server.listen(1)

        def answer() -> None:
            conn, _ = server.accept()
            with conn:
                conn.sendall(json.dumps(doc).encode())

        thread = threading.Thread(target=answer, daemon=True)
        thread.start()
        out = subprocess.run(
            [sys.executable, "-m", "mapd", "status", "--socket", str(path)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        thread.join(10)
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "sent a status this mapd cannot show" in lines[0] and said in lines[0], lines


@pytest.mark.parametrize("period", ["-1", "nan", "inf", "1e-9"])
def test_status_watch_takes_a_sane_period_in_one_usage_line(tmp_path: Path, period: str) -> None:
    """-1 and nan were a ValueError traceback, inf an OverflowError; 1e-9 polled the daemon in a spin."""
    out = subprocess.run(
        [sys.executable, "-m", "mapd", "status", "--socket", str(tmp_path / "s"), "--watch", period],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert "not within 0.1..3600 seconds" in out.stderr.splitlines()[-1]


def test_status_outside_group_mapd_is_not_a_traceback(monkeypatch: pytest.MonkeyPatch) -> None:
    """/etc/mapd is 0750 root:mapd: for a user outside group mapd, Path.exists() raised
    PermissionError (Python 3.11) before the socket could say who may ask."""
    import argparse

    from mapd.commands import daemon as cmd

    class Locked(type(Path())):  # type: ignore[misc]
        def exists(self, *args: object, **kw: object) -> bool:
            raise PermissionError(13, "Permission denied", str(self))

    monkeypatch.setattr(cmd, "DEFAULT_CONFIG", Locked("/etc/mapd/config.toml"))
    args = argparse.Namespace(socket=None, config=None)
    assert cmd._socket_path(args) == Path("/run/mapd/mapd.sock")
