"""Folders a daemon writes in, looked at without writing; where a relative name is found.

* :func:`folder_unusable`, :func:`mount_point`, :func:`file_id`: whether a folder a daemon writes in
  is still there, mounted and writable, and whether a file it wrote is still the one it wrote, all
  seen without writing (a state directory removed, unmounted or remounted read-only under it).
* :func:`from_workdir`: where a relative name that mapd hands on as written (a uwb port, a TLS
  file) is found.
"""

from __future__ import annotations

import contextlib
import os
import stat
from pathlib import Path

#: What :func:`folder_unusable` says of a folder that is not there (the disk it was on still mounted).
FOLDER_GONE = "is gone (removed, or its disk unmounted?)"


def mount_point(path: Path) -> Path | None:
    """The mount point ``path`` (symlinks followed) is on, itself or the nearest folder above it
    that is one; None for the root file system (``/``, mounted as long as the system runs)."""
    here = Path(os.path.realpath(path))
    while here != here.parent:
        with contextlib.suppress(OSError, ValueError):
            if os.path.ismount(here):
                return here
        here = here.parent
    return None


def folder_unusable(folder: Path, *, mount: Path | None = None) -> str | None:
    """Why nothing can be written in ``folder`` now, in words that follow its name, or None.

    Looked at without writing, so it is cheap enough for every save and for a look while nothing
    is written (a fleet at rest): the disk it was on unmounted (``mount``: its :func:`mount_point`
    when it was taken, a mount point no more: what is left there is a folder of another disk),
    ``folder`` gone (removed, or its disk unmounted) or not a folder, or read-only (ext4 remounts
    itself read-only after an I/O error). A full disk is not seen here: its writes say so.
    """
    with contextlib.suppress(OSError, ValueError):
        if mount is not None and not os.path.ismount(mount):
            if mount == Path(os.path.realpath(folder)):
                return "is not mounted any more (its disk unmounted?)"
            return f"is not mounted any more (the disk mounted at {mount} unmounted?)"
    try:
        st = os.stat(folder)
    except FileNotFoundError:
        return FOLDER_GONE
    except OSError as exc:
        return f"cannot be looked at: {exc.strerror or exc}"
    if not stat.S_ISDIR(st.st_mode):
        return "is not a folder any more"
    with contextlib.suppress(OSError):
        if os.statvfs(folder).f_flag & os.ST_RDONLY:
            return "is on a read-only file system (remounted read-only after disk errors?)"
    return None


def file_id(path: Path) -> tuple[int, int] | None:
    """``path``'s device and inode (the file itself, not a symlink's target), or None when there
    is none. A file replaced by :func:`~mapd.files.atomic_write_bytes` gets a new one, so a writer
    that keeps the id of what it wrote tells when that file was removed or replaced by someone else
    (a folder emptied, another disk mounted over it). OSError for a path that cannot be looked at."""
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):  # (a folder above it replaced by a file)
        return None
    return st.st_dev, st.st_ino


class Folder:
    """A folder a writer writes in, and the mount point it was on when first looked at: once that
    is not a mount point any more, its disk was unmounted, and what is left there is a folder of
    another disk, not to be written to (see :func:`folder_unusable`)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._mount: Path | None = None
        self._seen = False

    def unusable(self) -> str | None:
        """Why nothing can be written in the folder now, in words that follow its name, or None."""
        if not self._seen:
            self._mount, self._seen = mount_point(self.path), True
        return folder_unusable(self.path, mount=self._mount)


def file_ids(*paths: Path) -> list[tuple[Path, tuple[int, int]]]:
    """Each of ``paths`` that is there, with its :func:`file_id` (one that cannot be looked at is
    left out): what a writer keeps of what it just wrote, to tell later whether it was lost."""
    ids = []
    for path in paths:
        with contextlib.suppress(OSError):
            if (known := file_id(path)) is not None:
                ids.append((path, known))
    return ids


def from_workdir(name: str) -> tuple[Path | None, str]:
    """Where a relative ``name`` that mapd hands on as written (a uwb port to pyserial, a TLS file
    to zenoh) is found: from the working directory of the process, ``/`` under systemd. Returns
    the path and the words for where it was looked for; the path is None when this process has no
    working directory any more (a folder removed under it), where the start cannot find it either."""
    try:
        cwd = Path.cwd()
    except OSError:
        return None, "the working directory, which no longer exists"
    return cwd / name, f"the working directory ({cwd}; / under systemd)"
