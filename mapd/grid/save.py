"""Maps written as ``map_saver`` writes them, and committed so that no crash can tear them.

:func:`save_map` writes a map_server YAML and its PGM together: trinary grids as ``map_saver`` does
(254 free, 0 occupied, 205 unknown), grids with intermediate values in raw mode, one byte per cell,
so that every grid comes back exactly through :func:`mapd.grid.load.load_map`.
:func:`save_committed` is how the daemon's state maps and the fusion worker's global map are saved:
the image under a name of its own, then the YAML that names it and holds the map's version and
digest, which :func:`committed_record` reads back.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mapd.errors import MapFileError
from mapd.files import atomic_write_files
from mapd.grid import OccupancyGrid
from mapd.imaging.pixels import one_line


def save_map(
    grid: OccupancyGrid,
    yaml_path: str | os.PathLike[str],
    *,
    mode: str | None = None,
    image_name: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``grid`` as map_server YAML plus PGM next to it; returns the YAML path.

    Trinary grids are saved the way ``map_saver`` does (254 free, 0 occupied, 205 unknown). Grids
    with intermediate values are saved in raw mode, one byte per cell, so that
    :func:`~mapd.grid.load.load_map` gives back exactly the same data. Both files are written
    together (:func:`~mapd.files.atomic_write_files`). The image is ``NAME.pgm`` unless
    ``image_name`` names another file in the same folder; ``extra`` keys are written after
    map_server's own (which map_server ignores, :func:`~mapd.grid.load.read_map_yaml` returns).
    """
    path = Path(yaml_path)
    if mode is None:
        mode = "trinary" if grid.is_trinary() else "raw"
    if mode not in ("trinary", "raw"):
        raise MapFileError(f"{path}: save_map writes trinary or raw maps, not '{mode}'")
    if mode == "trinary" and not grid.is_trinary():
        raise MapFileError(f"{path}: grid has values other than -1/0/100; save it in raw mode")
    pixels = grid.to_image() if mode == "trinary" else np.flipud(grid.data.view(np.uint8))
    if path.is_dir() or path.name in ("", ".", ".."):
        # Checked first: the image would otherwise be written beside it (DIR.pgm) before the YAML fails.
        raise MapFileError(f"{path}: is a directory; name the map's YAML file")
    image_path = path.with_suffix(".pgm") if image_name is None else path.with_name(image_name)
    if image_path == path:  # the YAML would be written over the image it names: the map lost
        raise MapFileError(f"{path}: the map's image is written as NAME.pgm; name the YAML NAME.yaml")
    header = f"P5\n# CREATOR: mapd {grid.resolution:.3f} m/pix\n{grid.width} {grid.height}\n255\n".encode()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "image": image_path.name,
            "mode": mode,
            "resolution": float(grid.resolution),
            "origin": [float(v) for v in grid.origin],
            "negate": 0,
            "occupied_thresh": 0.65,
            "free_thresh": 0.196,
        }
        meta.update({k: v for k, v in (extra or {}).items() if k not in meta})
        # Together: a full disk (or an immutable YAML) left the new image beside the old YAML, a
        # map that loads with another map's size and origin.
        atomic_write_files(
            [
                (image_path, header + np.ascontiguousarray(pixels).tobytes()),
                (path, yaml.safe_dump(meta, sort_keys=False).encode()),
            ],
            # an image under a name of its own (map-<n>.pgm) is a new file each time: it takes the
            # permissions the operator gave the map's YAML
            like={image_path: path},
        )
    except OSError as exc:
        # strerror, not str(exc): that names the hidden temp file, which means nothing to the user.
        raise MapFileError(f"{path}: cannot write map: {exc.strerror or one_line(exc)}") from None
    return path


#: The YAML fields that commit a map saved by :func:`save_committed`.
VERSION_KEY = "mapd_version"
DIGEST_KEY = "mapd_digest"
_COUNT_LIMIT = 1 << 63  # versions are whole numbers below this, as envelopes carry them


def save_committed(grid: OccupancyGrid, yaml_path: Path, extra: dict[str, Any] | None = None) -> str:
    """Save ``grid`` so that no crash can tear it, and return its digest (hex).

    The daemon's state maps and the fusion worker's global map are saved this way: the image under
    a name of its own (``<stem>-<version>.pgm``), then the YAML that names it and holds the map's
    version and digest (:data:`VERSION_KEY`, :data:`DIGEST_KEY`), then the images no YAML names any
    more are removed. A kill at any point leaves the old map or the new one whole (a fixed image
    name renamed before its YAML left the old YAML's origin over the new image: a shifted map), and
    a reader that checks the digest (:func:`committed_record`) never takes a mismatched image for
    the map. :class:`MapFileError` with one line when the disk refuses.
    """
    digest = grid.digest().hex()
    image = f"{yaml_path.stem}-{grid.version}.pgm"
    try:
        save_map(
            grid,
            yaml_path,
            image_name=image,
            extra={VERSION_KEY: grid.version, DIGEST_KEY: digest, **(extra or {})},
        )
    except OSError as exc:  # what save_map looks at before it writes (a stat that fails)
        raise MapFileError(f"{yaml_path}: cannot write map: {exc.strerror or one_line(exc)}") from None
    with contextlib.suppress(OSError):  # best effort (a listing that fails): the next save removes them
        for old in [yaml_path.with_suffix(".pgm"), *yaml_path.parent.glob(f"{yaml_path.stem}-*.pgm")]:
            if old.name != image:
                with contextlib.suppress(OSError):  # one that cannot go stops none of the others
                    old.unlink(missing_ok=True)
    return digest


def committed_record(extra: dict[str, Any]) -> tuple[int, str] | None:
    """The version and digest a committed map's YAML holds (its ``extra`` fields, as
    :func:`~mapd.grid.load.read_map_yaml` gives them), or None when it holds none that could be (a
    YAML written before they were kept, or hand-edited)."""
    version, digest = extra.get(VERSION_KEY), extra.get(DIGEST_KEY)
    if type(version) is int and 0 <= version < _COUNT_LIMIT and isinstance(digest, str):
        return version, digest
    return None
