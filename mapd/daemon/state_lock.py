"""One daemon a state directory: ``<state>/lock``, held (flock) for the life of the process.

Two daemons on one state directory numbered maps from the same counter, swept each other's
in-flight temp files and wrote each other's ``state.json``. The lock is the kernel's, so a daemon
killed with -9 releases it; the lock file holds its holder's pid, for the line that refuses a
second. A directory that loses its lock file under the running daemon has it taken again before
anything is written there (:meth:`~mapd.daemon.state_watch.StateDirWatch._relock`).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
from pathlib import Path

from mapd.errors import StateError


def lock_state_dir(root: Path) -> int:
    """Hold ``root/lock`` (flock, exclusive) for the life of the process; returns its descriptor.

    Two daemons on one state directory (a second started by mistake, or two configs with the same
    ``state.dir``) numbered maps from the same counter, swept each other's in-flight temp files and
    wrote each other's state.json. The lock is the kernel's: a daemon killed with -9 releases it.
    """
    try:
        root.mkdir(parents=True, exist_ok=True)
        fd = os.open(root / "lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
    except OSError as exc:
        raise StateError(f"state directory {root} is not writable: {exc.strerror or exc}") from None
    _flock(root, fd)
    return fd


def _flock(root: Path, fd: int, busy: str = "is in use by another mapd{}") -> None:
    """Lock ``fd`` (``root``'s lock file) for this process, or close it and raise StateError
    (``busy``: what to say when another process holds it, ``{}`` taking its pid)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        holder = os.read(fd, 32).decode("ascii", "replace").strip()
        os.close(fd)
        raise StateError(
            f"state directory {root} " + busy.format(f" (pid {holder})" if holder.isdigit() else "")
        ) from None
    except OSError as exc:
        os.close(fd)
        raise StateError(f"state directory {root}: cannot lock it: {exc.strerror or exc}") from None
    with contextlib.suppress(OSError):  # the holder's pid, for the message above (a hint only)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
