"""Files read so a huge one costs nothing and a FIFO named by mistake cannot block.

* :func:`read_capped`: at most ``cap + 1`` bytes of a file that should be small (a key, a config, a
  map's YAML), within a deadline, so ``/dev/zero``, a log or a pipe held open given by mistake is
  refused, not read for ever; :func:`read_json_capped`, the same for a JSON file of the state
  directory.
* :func:`open_for_reading`: a file opened so that a FIFO nobody writes to cannot block the open;
  :func:`open_regular`, the same refusing anything but a regular file (a FIFO, a device, a
  directory) with :class:`NotRegularFileError`, which the atomic writes raise too.
"""

from __future__ import annotations

import errno
import json
import os
import select
import stat
import time
from pathlib import Path
from typing import Any, BinaryIO


class NotRegularFileError(OSError):
    """Raised by :func:`open_regular` and :func:`~mapd.files.atomic_write_bytes` for a FIFO, a
    device or a directory (``strerror``: "not a regular file").
    """


def open_for_reading(path: Path) -> BinaryIO:
    """``path`` opened for reading (OSError as the OS raises it), without blocking on a FIFO.

    A plain ``open`` of a FIFO blocks until some process opens it for writing, which for a FIFO
    named by mistake is for ever. Opened with O_NONBLOCK, then switched back to blocking reads: a
    pipe with a writer (``--key <(...)``) is read as before, one without any writer reads as empty.
    ValueError (a NUL in the path) is raised as an OSError, so callers have one error to catch.
    """
    return _open_checked(path, regular=False)


def _open_checked(path: Path, *, regular: bool) -> BinaryIO:
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
    except ValueError:
        raise OSError(22, "the path holds a NUL character") from None
    try:
        # Checked on the descriptor, before fdopen: that refuses a directory with its own error.
        if regular and not stat.S_ISREG(os.fstat(fd).st_mode):
            raise NotRegularFileError(22, "not a regular file", str(path))
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def open_regular(path: Path) -> BinaryIO:
    """``path`` opened by :func:`open_for_reading`, refusing anything but a regular file.

    A file that must be read whole (a key, a map, a log) named as a FIFO would block or read as
    empty, ``/dev/zero`` would be read for ever, and a directory gives an error of its own: each
    raises :class:`NotRegularFileError`, an OSError, so callers keep one except clause.
    """
    return _open_checked(path, regular=True)


#: The longest :func:`read_capped` waits for a file's end: a pipe whose writer holds it open. Small
#: files (a config, a key, a token) are written at once; the daemon's stop (systemd gives it 10 s)
#: must not wait long on a reload stuck on one. Data a command reads from a pipe gets longer
#: (:data:`DATA_READ_TIMEOUT_S`).
READ_TIMEOUT_S = 5.0
#: The deadline of a payload or message a command reads (``mapd decode``, ``mapd link send``),
#: which may come through a pipe from a slow producer (``ssh robot cat ...``).
DATA_READ_TIMEOUT_S = 60.0


def read_capped(path: Path, cap: int, *, timeout_s: float | None = None) -> bytes:
    """Up to ``cap + 1`` bytes of ``path`` (OSError as the OS raises it); the caller refuses more than ``cap``.

    A FIFO without a writer reads as empty instead of hanging, and one whose writer holds it open
    without closing it (``--key <(sleep inf)``, a FIFO put where the config was) raises
    TimeoutError after ``timeout_s`` (default :data:`READ_TIMEOUT_S`): the daemon's reload thread
    blocked on it for ever, and the daemon could not exit while it did.
    """
    if timeout_s is None:
        timeout_s = READ_TIMEOUT_S
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)  # left non-blocking
    except ValueError:
        raise OSError(22, "the path holds a NUL character") from None
    try:
        chunks: list[bytes] = []
        got, deadline = 0, time.monotonic() + timeout_s
        while got <= cap:
            try:
                chunk = os.read(fd, min(1 << 20, cap + 1 - got))
            except BlockingIOError:  # a pipe with a writer, and nothing in it yet
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError(
                        errno.ETIMEDOUT, f"its writer did not finish it in {timeout_s:g} s", str(path)
                    ) from None
                select.select([fd], [], [], left)
                continue
            if not chunk:
                break
            chunks.append(chunk)
            got += len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def read_json_capped(path: Path, cap: int) -> Any:
    """The JSON document in ``path``, read up to ``cap`` bytes.

    Raises OSError as the OS does, ValueError for a file over ``cap`` bytes or one that is not JSON
    (JSON's and Unicode's decoding errors are ValueErrors), and RecursionError for nesting too deep
    to parse: a damaged file gives one of those three, which its reader turns into one warning.
    """
    raw = read_capped(path, cap)
    if len(raw) > cap:
        raise ValueError(f"over {cap >> 20} MiB" if cap >= 1 << 20 else f"over {cap} bytes")
    return json.loads(raw)
