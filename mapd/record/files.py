"""Which files a recording writes and how much disk it may take (see :mod:`mapd.record.writer`).

* :class:`RecordingFiles`: the recording's files ``NAME.mcap``, ``NAME.1.mcap``, ...: the next one
  opened after the highest number there (so the numbers sort by time, also after the oldest were
  removed), the oldest removed as each new one opens until the rest fit in ``max_total_bytes``,
  and nothing opened or written while the disk has less than ``min_free_bytes`` free.
* :class:`RawFile`: an unbuffered file that a failed write can be cut back on.
"""

from __future__ import annotations

import errno
import logging
import os
from dataclasses import dataclass
from pathlib import Path

from mapd.errors import ConfigError, StateError

log = logging.getLogger("mapd.record")


class RawFile:
    """An unbuffered, write-only file for mcap's Writer, which only calls ``write`` and ``tell``.

    Not a BufferedWriter: one that failed to write (a full disk) keeps the bytes it holds and tries
    them again at every flush and at close, which would put a piece of the failed chunk after the
    point the file was taken back to. Here a write is done, or it raised and the file can be cut
    back with :meth:`truncate`.
    """

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):  # os.write may write part (up to a file size limit), then raise
            n = os.write(self._fd, view[done:])
            if n <= 0:  # (a regular file never takes nothing without an error; this loop must end)
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            done += n
            self._pos += n
        return done

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        """Nothing is held here: every write went to the OS."""

    def truncate(self, size: int) -> None:
        os.ftruncate(self._fd, size)
        os.lseek(self._fd, size, os.SEEK_SET)
        self._pos = size

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)


@dataclass(frozen=True)
class OnDisk:
    index: int  # 0 for NAME.mcap, N for NAME.N.mcap
    path: Path
    size: int
    regular: bool


class RecordingFiles:
    """The files of one recording, and the room they may take."""

    def __init__(self, path: Path, *, max_bytes: int, max_total_bytes: int, min_free_bytes: int) -> None:
        # Room for the file being written and the one just finished (each ends a little past
        # max_bytes): under that, every rotation would leave the recording with almost nothing.
        # (The config's RecordSection says the same for check-config, naming the key.)
        if max_total_bytes < 2 * max_bytes:
            raise ConfigError(
                f"record: max_total_bytes ({max_total_bytes}) is under twice max_bytes ({max_bytes})"
            )
        self.path = path
        self.max_bytes = max_bytes
        self.max_total_bytes = max_total_bytes
        self.min_free_bytes = min_free_bytes
        #: This recorder's files still on disk, oldest first.
        self.files: list[Path] = []
        #: Files of the recording removed to stay within ``max_total_bytes``.
        self.removed = 0

    def path_of(self, index: int) -> Path:
        if index == 0:
            return self.path
        return self.path.with_name(f"{self.path.stem}.{index}{self.path.suffix}")

    def index_of(self, name: str) -> int | None:
        """The number of the recording's file called ``name`` (0 for NAME.mcap), None for others."""
        if name == self.path.name:
            return 0
        head, tail = f"{self.path.stem}.", self.path.suffix
        if len(name) <= len(head) + len(tail) or not name.startswith(head) or not name.endswith(tail):
            return None
        number = name[len(head) : len(name) - len(tail)]
        # as path_of writes them: ASCII digits, no leading zero (fleet.01.mcap is someone else's)
        if not (number.isascii() and number.isdigit()) or number[0] == "0":
            return None
        return int(number)

    def on_disk(self) -> list[OnDisk]:
        """The recording's files in its folder, oldest (lowest number) first."""
        found = []
        try:
            with os.scandir(self.path.parent) as entries:
                for entry in entries:
                    index = self.index_of(entry.name)
                    if index is None:
                        continue
                    try:
                        st = entry.stat(follow_symlinks=False)
                        regular = entry.is_file(follow_symlinks=False)
                    except OSError:  # removed meanwhile
                        continue
                    found.append(OnDisk(index, Path(entry.path), st.st_size, regular))
        except OSError:  # no folder yet (or unreadable: the open says so)
            return []
        return sorted(found, key=lambda f: f.index)

    def make_room(self, on_disk: list[OnDisk]) -> None:
        """Remove the oldest files until the rest and a new file of ``max_bytes`` fit in
        ``max_total_bytes``. Only regular files named as the recording's are removed, never the
        newest of them (the file just finished: a file ends a chunk and a summary past
        ``max_bytes``, so with a tight cap it never fit, and right after each rotation the
        recording held almost nothing); none is open (this runs before the next file is opened)."""
        kept = [f for f in on_disk if f.regular]
        total = sum(f.size for f in kept)
        for f in kept[:-1]:
            if total + self.max_bytes <= self.max_total_bytes:
                break
            try:
                f.path.unlink()
            except FileNotFoundError:
                pass
            except OSError as exc:  # not ours to remove after all (permissions): try the next
                log.warning("record: cannot remove %s: %s", f.path, exc.strerror)
                continue
            else:
                self.removed += 1
                log.info(
                    "record: removed %s (%.1f MiB), the oldest file, to keep the recording within "
                    "max_total_bytes (%.1f MiB)",
                    f.path, f.size / (1 << 20), self.max_total_bytes / (1 << 20),
                )  # fmt: skip
            total -= f.size
            if f.path in self.files:
                self.files.remove(f.path)

    def check_space(self) -> None:
        """StateError while the filesystem has less than ``min_free_bytes`` free."""
        if self.min_free_bytes <= 0:
            return
        try:
            st = os.statvfs(self.path.parent)
        except OSError:  # no folder yet, or none at all: opening the file says what is wrong
            return
        free = st.f_bavail * st.f_frsize
        if free < self.min_free_bytes:
            raise StateError(
                f"record: {free / (1 << 20):.0f} MiB free on the disk of {self.path.parent}, under "
                f"min_free_bytes ({self.min_free_bytes / (1 << 20):.0f} MiB): nothing is recorded until "
                "there is room"
            )

    def open_next(self, index: int | None) -> tuple[int, Path, int]:
        """Make room, check the free space, then create the file numbered ``index`` or the next free
        one after it (``None``: after the highest number there). Returns its number, path and fd."""
        on_disk = self.on_disk()
        if index is None:
            # After the highest number there, never into a gap: a gap is where the oldest files
            # were removed, and a file there would sort as the oldest while being the newest.
            index = max((f.index for f in on_disk), default=-1) + 1
        self.make_room(on_disk)
        self.check_space()
        path = self.path_of(index)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
            while True:
                # O_EXCL, never O_TRUNC: a daemon restarted after a crash (systemd, 2 s later) must
                # not truncate the recording of that crash; it goes on with the next number.
                try:
                    fd = os.open(path, flags, 0o666)
                    break
                except FileExistsError:
                    index += 1
                    path = self.path_of(index)
        except OSError as exc:
            raise StateError(f"record: cannot write {path}: {exc.strerror}") from None
        self.files.append(path)
        return index, path, fd

    def forget(self, path: Path) -> None:
        """``path`` is no longer on disk (removed as empty)."""
        if path in self.files:
            self.files.remove(path)
