"""The read-only control socket: the daemon's status as one JSON document per connection.

The socket lives in the systemd ``RuntimeDirectory`` with mode 0660. A client connects and reads
until EOF; anything it sends is ignored, so nothing on the socket can change the daemon.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import stat
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapd.errors import DaemonError

#: The most a status query reads (a status is some kilobytes, a few hundred with many robots).
MAX_STATUS_BYTES = 64 << 20

log = logging.getLogger(__name__)


class StatusServer:
    """Serves ``snapshot()`` as JSON on a Unix socket."""

    def __init__(self, path: Path, snapshot: Callable[[], dict[str, Any]]) -> None:
        self.path = path
        self.snapshot = snapshot
        self._server: asyncio.AbstractServer | None = None
        self._inode: int | None = None  # of the socket this server made

    async def start(self) -> None:
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            try:
                mode = os.lstat(self.path).st_mode
            except FileNotFoundError:
                pass
            else:
                # Only a socket (a stale one of a killed daemon) is ours to replace: a file, a FIFO
                # or a device named here by mistake was deleted (as root, even /dev/null).
                if not stat.S_ISSOCK(mode):
                    raise DaemonError(
                        f"control socket {self.path}: exists and is not a socket; not replacing it"
                    )
                if _alive(self.path):
                    raise DaemonError(f"another mapd is already serving {self.path}")
                self.path.unlink()
            self._server = await asyncio.start_unix_server(self._serve, path=str(self.path))
            os.chmod(self.path, 0o660)
            self._inode = os.lstat(self.path).st_ino
        except OSError as exc:
            raise DaemonError(f"cannot create control socket {self.path}: {exc.strerror or exc}") from None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            doc = json.dumps(self.snapshot(), default=str).encode() + b"\n"
            writer.write(doc)
            await asyncio.wait_for(writer.drain(), timeout=5)
        except (OSError, TimeoutError):
            pass
        except Exception:  # a status bug must never take the daemon down
            log.exception("status snapshot failed")
        finally:
            writer.close()

    async def close(self) -> None:
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
            self._server = None
        # Only the socket this daemon made: a second daemon that failed to start (its socket path
        # served by the first) removed the first one's, leaving it unreachable by `mapd status`.
        with contextlib.suppress(OSError):
            if self._inode is not None and os.lstat(self.path).st_ino == self._inode:
                self.path.unlink()
        self._inode = None


def _alive(path: Path) -> bool:
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(0.5)
        try:
            s.connect(str(path))
            return True
        except OSError:
            return False


def _is_socket(path: Path) -> bool:
    try:
        return stat.S_ISSOCK(os.stat(path).st_mode)
    except OSError:
        return True  # (it was there a moment ago: say what connect said)


def query(path: Path, timeout: float = 3.0) -> dict[str, Any]:
    """Read the daemon's status from ``path``; raises :class:`DaemonError` when none answers whole
    within ``timeout`` seconds (in all: a socket trickling a byte at a time is given up too)."""
    deadline = time.monotonic() + timeout
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        try:
            s.connect(str(path))
            s.shutdown(socket.SHUT_WR)
            chunks, size = [], 0
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    raise DaemonError(f"{path} sent no whole status within {timeout:g} s")
                s.settimeout(left)
                chunk = s.recv(65536)
                if not chunk:
                    break
                chunks.append(chunk)
                size += len(chunk)
                if size > MAX_STATUS_BYTES:  # a status is kilobytes: this is no mapd daemon
                    raise DaemonError(f"{path} sent over {MAX_STATUS_BYTES >> 20} MiB of status")
        except FileNotFoundError:
            raise DaemonError(f"no mapd daemon is running (no control socket at {path})") from None
        except ConnectionRefusedError:
            if not _is_socket(path):  # (a file there refuses too: "stale socket" misled)
                raise DaemonError(
                    f"{path} is not a socket: no mapd control socket (wrong --socket?)"
                ) from None
            raise DaemonError(f"no mapd daemon is running (stale control socket at {path})") from None
        except PermissionError:
            raise DaemonError(f"permission denied on {path} (are you in the mapd group?)") from None
        except TimeoutError:
            raise DaemonError(f"{path} sent no whole status within {timeout:g} s") from None
        except OSError as exc:
            raise DaemonError(f"cannot read status from {path}: {exc}") from None
    try:
        doc = json.loads(b"".join(chunks))
    except (ValueError, RecursionError):
        raise DaemonError(f"daemon at {path} sent malformed status") from None
    if not isinstance(doc, dict):
        raise DaemonError(f"daemon at {path} sent malformed status")
    return doc
