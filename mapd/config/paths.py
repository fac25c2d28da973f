"""Paths a config names, looked at without touching them: where a folder, a file or a socket goes.

``mapd run`` makes the folders it writes into (the state directory, an output's folder, the
recording's and the control socket's), so a folder that does not exist yet is fine. What no start
can get past is a path whose kind is wrong: a file where a folder goes, a folder below a file, a
socket path longer than the kernel takes. These functions find those by ``stat`` alone, so that
``mapd check-config`` creates and changes nothing. Who may write where is left to the start: the
unit runs as another user than the one who checks, and systemd makes its StateDirectory= and
RuntimeDirectory= only as the unit starts.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

#: The longest control socket path, in bytes: ``sun_path`` holds 108, and Python's bind takes 107
#: (one more was "AF_UNIX path too long" at start).
MAX_SOCKET_PATH = 107


def _mode(path: Path) -> int | None:
    """``path``'s mode (symlinks followed, as mkdir and open follow them), or None when nothing
    is there yet or it cannot be looked at (that, the start says)."""
    try:
        return os.stat(path).st_mode
    except OSError:
        return None


def folder_problem(path: Path) -> str | None:
    """Why ``path`` cannot be (or be made) a folder, or None: it, or a folder above it, is a file."""
    for here in [*reversed(path.parents), path]:
        mode = _mode(here)
        if mode is None:
            return None  # not there yet: the start makes it (and the rest below it)
        if not stat.S_ISDIR(mode):
            return f"{here} is not a folder"
    return None


def socket_problem(path: Path) -> str | None:
    """Why no unix socket can be bound at ``path``, or None (a stale socket there is replaced)."""
    if len(os.fsencode(path)) > MAX_SOCKET_PATH:
        return f"{path} is longer than the {MAX_SOCKET_PATH} bytes a socket path may have"
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        return folder_problem(path.parent)
    if not stat.S_ISSOCK(mode):
        return f"{path} exists and is not a socket"
    return None
