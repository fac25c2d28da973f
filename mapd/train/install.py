"""The model folder ``mapd train -o`` writes: checked before training, staged beside its place,
then renamed into it whole, so a failure (a full disk, a diverged run) leaves a model already
there as it was.
"""

from __future__ import annotations

import ctypes
import errno
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from mapd.codec import paper_model as pm
from mapd.errors import ConfigError

CARD_FILE = "MODEL_CARD.md"
#: What a model folder holds; an existing -o holding anything else is not replaced.
MODEL_FILES = frozenset({pm.WEIGHTS_FILE, pm.META_FILE, CARD_FILE})


def output_folder(out: Path) -> Path:
    """The model folder ``out`` as it will be written, checked before training so a bad -o fails fast.

    ``out`` may be new or an existing model folder (it is then replaced whole, at the end); its
    parent is created, and must take a new folder. Its name is the model's name, so it must be
    one ``[codec.paper] model`` accepts. Anything else is one :class:`ConfigError`.
    """
    from mapd.codec.paper import PaperOptions

    try:
        # Resolved, so "-o ." or a symlink names the real folder, whose name is the model's.
        path = Path(os.path.realpath(out))
    except (OSError, ValueError) as exc:
        raise ConfigError(f"-o {out}: {exc}") from None
    if not path.name:
        raise ConfigError(f"-o {out}: names no folder (its name is the model's name)")
    try:
        PaperOptions(model=path.name)
    except ValueError:
        raise ConfigError(
            f"-o {out}: '{path.name}' cannot name a model (up to 41 letters, digits, '.', '_' or '-',"
            " starting with a letter or digit)"
        ) from None
    try:
        if path.exists():
            if not path.is_dir():
                raise ConfigError(f"-o {out}: exists and is not a folder")
            extra = sorted(set(os.listdir(path)) - MODEL_FILES)
            if extra:
                raise ConfigError(
                    f"-o {out}: holds {', '.join(extra[:3])}{', ...' if len(extra) > 3 else ''}, not only"
                    " a model's files; not replacing it"
                )
        path.parent.mkdir(parents=True, exist_ok=True)
        # The model is staged in a new folder beside it and renamed into place: try that now.
        os.rmdir(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".train", dir=path.parent))
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(f"-o {out}: a path above it is a file, not a folder") from None
    except OSError as exc:
        raise ConfigError(f"-o {out}: cannot write a model folder there ({exc.strerror or exc})") from None
    return path


@contextmanager
def staging(out: Path) -> Iterator[Path]:
    """A new folder named like ``out`` inside a new hidden folder beside it, removed on the way out.

    The model is written and evaluated there (under its own name, which the codec's payloads
    carry), so a failure at any point leaves ``out`` as it was; beside it, so the final rename
    stays on one file system.
    """
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".train", dir=out.parent))
    try:
        folder = stage / out.name
        folder.mkdir()
        yield folder
    finally:
        shutil.rmtree(stage, ignore_errors=True)


def _fsync(path: Path) -> None:
    """fsync a file or a folder, so what was written (or renamed) there survives a power cut."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def install(folder: Path, out: Path) -> None:
    """Put the finished model ``folder`` at ``out``, replacing a model there whole.

    ``folder`` and ``out`` share a parent's file system. A new ``out`` is one rename. An existing
    one is swapped with ``folder`` in one step where the system can (Linux's RENAME_EXCHANGE), so
    readers see the old model or the new one, never a mix; elsewhere the old folder is moved aside
    first and back if the new one cannot follow. The old model is left in the staging folder.
    """
    for f in sorted(folder.iterdir()):
        _fsync(f)
    _fsync(folder)
    if not out.exists():
        os.rename(folder, out)
    elif not exchange(folder, out):
        aside = folder.with_name(folder.name + ".old")
        os.rename(out, aside)
        try:
            os.rename(folder, out)
        except OSError:
            os.rename(aside, out)
            raise
    with suppress(OSError):  # some file systems refuse to fsync a folder; the rename is done anyway
        _fsync(out.parent)


def exchange(a: Path, b: Path) -> bool:
    """Swap the paths ``a`` and ``b`` atomically; False where the system cannot (then nothing changed)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):  # a C library without renameat2 (glibc before 2.28, musl)
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    at_fdcwd, rename_exchange = -100, 2
    if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):  # a file system without the flag
        return False
    raise OSError(err, os.strerror(err), str(b))
