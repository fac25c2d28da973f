"""What the file commands (encode, decode, merge, warmup) share: an output is never written over one
of the command's own inputs, ``-`` stands for stdin/stdout where a payload may come or go, and a
codec is named from the registry when the arguments are parsed.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from mapd import plugins
from mapd.errors import ConfigError

#: What ``-`` as a path argument parses to: stdin or stdout, told apart from a file called ``./-``
#: (which parses to ``Path("-")``, a Path, and so never equals this string).
STDIO = "-"


def path_or_stdio(text: str) -> Path | str:
    """argparse type: :data:`STDIO` for ``-`` exactly, else a Path (``./-`` is a file named ``-``)."""
    return STDIO if text == STDIO else Path(text)


def is_stdio(value: object) -> bool:
    """Whether an argument parsed by :func:`path_or_stdio` is ``-`` (stdin or stdout)."""
    return isinstance(value, str) and value == STDIO


def refuse_stdio(value: object, what: str) -> None:
    """Refuse ``-`` where a file is needed (a map_server map is a YAML *and* the image it names)."""
    if is_stdio(value):
        raise ConfigError(f"{what} cannot be '-' (stdin/stdout): {_WHY_NO_STDIO}")


_WHY_NO_STDIO = (
    "a map_server map is a YAML and the image file it names; give a path (./- for a file named '-')"
)


#: argparse type for ``--codec``: a codec registered under ``mapd.codecs``, checked when the
#: arguments are parsed (exit 2), not after the map was read; whether its optional dependencies are
#: installed is still found when it is loaded.
codec_name = plugins.name_type("codec")


def map_inputs(yaml_path: Path, what: str) -> list[tuple[Path, str]]:
    """A map_server map's YAML and the image it names, each with how to call it in an error.

    Reading the YAML raises :class:`~mapd.errors.MapFileError` as loading the map would, only sooner.
    """
    from mapd.grid.load import read_map_yaml

    image = Path(read_map_yaml(yaml_path)["image"])
    return [(yaml_path, f"{what} {yaml_path}"), (image, f"the image {image} of {what} {yaml_path}")]


def map_outputs(yaml_path: Path, what: str) -> list[tuple[Path, str]]:
    """The two files saving a map to ``yaml_path`` writes (see :func:`mapd.grid.save.save_map`)."""
    try:
        image = yaml_path.with_suffix(".pgm")
    except ValueError:  # "." or "": no image name; save_map says what is wrong with such a path
        return [(yaml_path, f"{what} {yaml_path}")]
    return [(yaml_path, f"{what} {yaml_path}"), (image, f"the image {image} that {what} {yaml_path} writes")]


def _same_file(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` are one file: the same inode when both exist (a hard link or a
    symlink counts), else the same path once symlinks and ``..`` are resolved."""
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):  # one of them does not exist (yet), or a NUL in a name
        pass
    try:
        return os.path.realpath(a) == os.path.realpath(b)
    except (OSError, ValueError):
        return False


def refuse_overwrite(outputs: Iterable[tuple[Path, str]], inputs: Iterable[tuple[Path, str]]) -> None:
    """Raise :class:`ConfigError` if any output would be written over any input.

    Called before anything is written: ``mapd encode in.yaml -o in.yaml`` replaced the map with a
    payload and exited 0, and a merge over its first input lost that map and its image.
    """
    sources = list(inputs)
    for out, out_what in outputs:
        for src, src_what in sources:
            if _same_file(out, src):
                raise ConfigError(
                    f"{out_what} is {src_what}: refusing to write over an input; name the output apart"
                )


def check_writable(path: Path, what: str) -> None:
    """Raise :class:`ConfigError` now if ``path`` cannot be written as a new or replaced file.

    For outputs written only after long work (a merge places maps for minutes, ``link recv`` waits
    for a whole transfer): a missing folder or a directory in the way is said before the work, and
    before any other output is written.
    """
    import tempfile

    if path.is_dir():
        raise ConfigError(f"{what} {path}: is a folder (it is a directory); give a file name")
    if path.exists() and not path.is_file():
        raise ConfigError(f"{what} {path}: not a regular file")
    folder = path.parent
    if not folder.is_dir():
        raise ConfigError(f"{what} {path}: the folder {folder} does not exist (no such directory)")
    try:
        # A real write, not os.access: it also catches a read-only file system, and root.
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{path.name}.", suffix=".probe"):
            pass
    except OSError as exc:
        raise ConfigError(f"{what} {path}: cannot write in {folder}: {exc.strerror}") from None
