"""Files written so a crash never leaves half of one: the writes every part of mapd makes.

* :func:`atomic_write_bytes` / :func:`atomic_write_json`: readers see the old file or the new one,
  never half of either (temp file, fsync, rename, fsync of the directory);
  :func:`atomic_write_files`, the same for files that belong together (a map's image and its YAML).
* :func:`remove_stale_temps`: the temp files a writer killed mid-write (``kill -9``, power loss)
  left behind, removed at start-up so they never pile up.
* :func:`make_dir`: a folder made durable before a file that names it.
* :func:`write_new_secret`: a new key file, mode 0600, never over an existing one.

The rest of the package:

* :mod:`~mapd.files.reading`: files read so a huge one costs nothing (at most ``cap + 1`` bytes,
  within a deadline) and a FIFO cannot block, and anything but a regular file refused;
* :mod:`~mapd.files.outage`: a run of failed writes (a full disk) said in two log lines, and
  counted for ``mapd status``;
* :mod:`~mapd.files.folders`: whether a folder a daemon writes in is still there, mounted and
  writable, and whether a file it wrote is still the one it wrote, all seen without writing; where a
  relative name handed on as written is found.
"""

from __future__ import annotations

import contextlib
import errno
import io
import itertools
import json
import os
import re
import stat
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mapd.files.reading import NotRegularFileError

#: The names :func:`atomic_write_bytes` gives its temp files: ``.<name>.tmp<pid>.<thread id>.<n>``
#: (and, as mapd named them before, without ``.<n>``).
_TEMP_NAME = re.compile(r"\..+\.tmp\d+\.\d+(?:\.\d+)?")
#: A number of its own for every temp file: two writes of one file by one thread had the same temp
#: name, and a sweep that listed the folder between them could take the second's temp for stale.
_TEMP_SEQ = itertools.count()
#: The temp files this process is writing now: the only ones :func:`remove_stale_temps` keeps. (Not
#: "every temp file with our pid": after a power cut a daemon can get its old pid again at boot,
#: and its predecessor's temp files would then be kept until some later start.)
_ACTIVE: set[Path] = set()
_ACTIVE_LOCK = threading.Lock()


#: The start of a file's name kept in its temp file's name: a name as long as a directory allows
#: (255 bytes) is still written, with room for ``.tmp<pid>.<thread id>``.
_TEMP_STEM = 200


def atomic_write_bytes(path: Path, payload: bytes) -> None:
    """Write ``payload`` to a temp file beside ``path``, fsync it, rename it over ``path``, fsync the dir.

    A symlink is written through (its target is replaced, the link kept); a path that names no
    file (``.``, ``/``), or an existing device, FIFO, socket or directory, is refused with an
    OSError, never replaced: ``-o /dev/null`` as root once turned the system's null device into a
    regular file.
    """
    atomic_write_files([(path, payload)])


def atomic_write_via(path: Path, write: Callable[[io.BytesIO], object]) -> None:
    """:func:`atomic_write_bytes` of what ``write`` puts in a buffer (a figure's ``savefig``, a CSV
    writer): a report written again never leaves half a file where the last one was whole."""
    buf = io.BytesIO()
    write(buf)
    atomic_write_bytes(path, buf.getvalue())


def atomic_write_files(files: list[tuple[Path, bytes]], *, like: dict[Path, Path] | None = None) -> None:
    """:func:`atomic_write_bytes` of files that belong together (a map's image and the YAML naming it).

    Each file takes the mode of the file it replaces; a new one (a map image under a name of its
    own) takes the mode of the file ``like`` names for it, if that exists (the YAML beside it).

    Every file is written and fsynced to its temp file before any is renamed, so a full disk
    fails before anything changed; a rename that fails (an immutable file) puts back the files
    renamed before it. Only a crash between two renames, microseconds apart, can leave a new
    file beside an old one.
    """
    targets = [_write_target(path) for path, _ in files]
    temps: list[Path] = []
    try:
        for target, (path, payload) in zip(targets, files, strict=True):
            temps.append(_active(_temp_name(target)))
            with open(temps[-1], "wb") as fh:
                _keep_mode(fh.fileno(), target, (like or {}).get(path))
                fh.write(payload)
                fh.flush()
                os.fsync(fh.fileno())
        backups: list[tuple[Path, Path]] = []  # (the file as it was, kept under a temp name; its name)
        try:
            for target, tmp in zip(targets, temps, strict=True):
                if len(targets) > 1 and target.exists():
                    kept = _active(_temp_name(target, ".old"))
                    try:
                        os.link(target, kept)  # the old file stays whole until every rename is done
                    except OSError:
                        _done(kept)  # (a file system without hard links: written without the way back)
                    else:
                        backups.append((kept, target))
                os.replace(tmp, target)
        except BaseException:
            for kept, target in backups:
                with contextlib.suppress(OSError):
                    os.replace(kept, target)
            raise
        finally:
            for kept, _ in backups:
                with contextlib.suppress(OSError):
                    kept.unlink(missing_ok=True)
                _done(kept)
    finally:
        for tmp in temps:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            _done(tmp)
    for directory in {target.parent for target in targets}:
        _fsync_dir(directory)  # make the renames themselves durable across a power cut


def _write_target(path: Path) -> Path:
    """What writing ``path`` replaces: a symlink's target; refused when it is not a regular file."""
    if path.is_symlink():
        path = path.resolve()
    if path.name in ("", ".", ".."):
        raise IsADirectoryError(21, "names a directory, not a file", str(path))
    try:
        mode = os.stat(path).st_mode
    except OSError:
        pass  # not there yet (or unreadable: the write says what is wrong)
    else:
        if stat.S_ISDIR(mode):  # the same refusal, said as the OS says it
            raise NotRegularFileError(errno.EISDIR, "Is a directory", str(path))
        if not stat.S_ISREG(mode):
            raise NotRegularFileError(22, "not a regular file", str(path))
    return path


def _active(tmp: Path) -> Path:
    with _ACTIVE_LOCK:
        _ACTIVE.add(tmp)
    return tmp


def _done(tmp: Path) -> None:
    with _ACTIVE_LOCK:
        _ACTIVE.discard(tmp)


def _keep_mode(fd: int, target: Path, fallback: Path | None = None) -> None:
    """Give the new file the permissions (and, where allowed, the group) of the file it replaces,
    or of ``fallback`` when it replaces none.

    An operator's ``chmod o+r map.pgm`` (a map_server running as another user) or ``chgrp`` would
    otherwise be undone by the next write, the new file taking the daemon's umask. Permission bits
    only (no setuid, setgid or sticky bit), and the group only when not root: a root-run command
    writing into another user's folder must not hand its file to that user's group.
    """
    st = None
    for source in (target, fallback):
        if source is None:
            continue
        try:
            st = os.stat(source)
            break
        except OSError:
            continue
    if st is None:
        return  # a new file: the umask decides, as for any file
    with contextlib.suppress(OSError):
        os.fchmod(fd, stat.S_IMODE(st.st_mode) & 0o777)
    if os.geteuid() != 0:
        with contextlib.suppress(OSError):  # only a group the daemon's user is in
            os.fchown(fd, -1, st.st_gid)


def _temp_name(path: Path, kind: str = "") -> Path:
    stem = os.fsdecode(os.fsencode(path.name)[:_TEMP_STEM])  # bytes: a directory's limit is in bytes
    return path.with_name(f".{stem}{kind}.tmp{os.getpid()}.{threading.get_ident()}.{next(_TEMP_SEQ)}")


def make_dir(directory: Path) -> None:
    """``mkdir -p directory``, its new entry made durable: without the parent's fsync a power cut
    can lose the folder while a file written later that names it (state.json) survives."""
    if directory.is_dir():
        return
    directory.mkdir(parents=True, exist_ok=True)
    _fsync_dir(directory.parent)


def _fsync_dir(directory: Path) -> None:
    """fsync ``directory`` so a name just created or renamed in it is durable (best effort)."""
    try:
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass


def remove_stale_temps(directory: Path) -> list[Path]:
    """Remove the temp files of :func:`atomic_write_bytes` in ``directory`` that no write is using.

    A writer killed between creating its temp file and the rename leaves it behind, and the next
    run's temp files have other names (the pid is in them), so without this they pile up for ever,
    each as large as the file it was to replace. Only regular files named as this module names its
    temps are removed, and not the ones this process is writing now. Returns the paths removed; a
    directory that cannot be listed, or a file that cannot be removed, is skipped.
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    with _ACTIVE_LOCK:
        busy = {os.path.realpath(p) for p in _ACTIVE}  # after the listing: a write that began
        # since is not in it, and every temp name is new, so none listed can be a later write's
    for entry in entries:
        if _TEMP_NAME.fullmatch(entry.name) is None or os.path.realpath(entry.path) in busy:
            continue
        try:
            if not entry.is_file(follow_symlinks=False):
                continue
            os.unlink(entry.path)
        except OSError:
            continue
        removed.append(Path(entry.path))
    return removed


def atomic_write_json(path: Path, obj: Any) -> None:
    """:func:`atomic_write_bytes` of ``obj`` as indented JSON."""
    atomic_write_bytes(path, (json.dumps(obj, indent=1, sort_keys=True, default=str) + "\n").encode())


def write_new_secret(path: Path, data: bytes) -> None:
    """Write ``data`` to a new file readable by its owner only, durably.

    Raises FileExistsError when ``path`` exists (a key is never overwritten) and OSError otherwise.
    A write that fails (a full disk) removes the file it created: a half-written key left there
    would be refused as an existing key by every later attempt to write it.
    """
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        path.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)  # the new name survives a power cut too, not just the key's bytes
