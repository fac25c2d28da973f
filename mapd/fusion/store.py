"""The fusion worker's files in the state directory, so a restart loses neither map nor placements.

Written after every merge (each file atomic: temp file, fsync, rename, so a crash leaves the old
file or the new one, never half of one):

* ``global.yaml`` + ``global-<version>.pgm``: the global map, as map_server files committed by
  the YAML, as the daemon's state maps are (:func:`mapd.grid.save.save_committed`: a kill between the two
  renames leaves the old map whole, and an image that does not match is left out, never restored
  shifted);
* ``transforms.json``: the placements, per robot the "fleet frame -> robot map" transform (x, y in
  meters, yaw in radians, such that ``p_fleet = R(yaw) p_robot_map + (x, y)``) with its source,
  confidence and reason (and for one found against another robot's map, where that map was placed
  then, ``against_at``: a restored placement follows that map when it is placed anew), the global
  map's version, and the roster key each peer's map in it was taken under (``keys``: a robot
  re-keyed by the next start has the global map rebuilt without it);
* ``owner.npy`` + ``owner.json``: per cell, which robot's map weighed most (an index into the
  names in ``owner.json``; -1 where none knows), for coloured pictures.

Reading is forgiving: an unreadable or damaged file is said in one warning and left out, and the
worker starts without it (a new global map), never fails. Which restored placements to keep (the
roster) is the worker's decision, not this module's.

The state directory may lose these files under the running daemon (emptied, its disk unmounted
and mounted again): :meth:`FusionStore.look` writes the last ones saved again (the daemon's state
store runs it every few seconds, :meth:`~mapd.daemon.state.StateStore.also_check`), so a fleet at
rest, which makes no new merge, has them again before a restart needs them. A state directory that
is gone, or not mounted any more, is not made again here (it would be on the wrong disk): saves fail
until it is back.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapd.errors import MapdError, StateError
from mapd.files import atomic_write_bytes
from mapd.files.folders import Folder, file_id, file_ids
from mapd.files.outage import WriteOutage
from mapd.files.reading import read_json_capped
from mapd.fusion.merge import NO_OWNER, MergeResult
from mapd.fusion.placement import Placement
from mapd.grid import DEFAULT_MAX_CELLS, OccupancyGrid
from mapd.grid.load import map_from_yaml_fields, read_map_yaml
from mapd.grid.save import DIGEST_KEY, VERSION_KEY, committed_record, save_committed

log = logging.getLogger(__name__)

GLOBAL_YAML = "global.yaml"
TRANSFORMS_JSON = "transforms.json"
OWNER_NPY = "owner.npy"
OWNER_JSON = "owner.json"
FORMAT = 1
#: The largest ``transforms.json`` or ``owner.json`` read: a few hundred bytes a robot, robots capped.
MAX_JSON = 16 << 20


@dataclass
class Saved:
    """What a previous run left: its placements and the global map's version (0: none)."""

    placements: dict[str, Placement] = field(default_factory=dict)
    version: int = 0
    #: robot -> the roster key its map in the global map was taken under (its public key's text)
    keys: dict[str, str] = field(default_factory=dict)


class FusionStore:
    """Reads and writes the fusion files of one state directory (blocking: call from a worker)."""

    def __init__(self, directory: Path, *, robot: str, max_cells: int = DEFAULT_MAX_CELLS) -> None:
        self.directory = directory
        self.robot = robot
        self.max_cells = max_cells
        #: Saves of the global map that fail now (a full disk), for ``mapd status``. Not logged
        #: here: the worker says it once, with what it costs.
        self.outage = WriteOutage(None)
        self._owner_outage = WriteOutage(log)
        # What :meth:`look` writes again, and how it tells the files went (under ``_io``: a look
        # never writes an older map over one a merge saved meanwhile):
        self._io = threading.Lock()
        #: The last global map saved (the worker holds it anyway), with its placements' document.
        #: (Not the owner map, which only pictures use: it comes back with the next merge, and
        #: holding it would cost a byte a cell of the global map.)
        self._saved: tuple[OccupancyGrid, dict[str, Any]] | None = None
        #: "global" -> each file then written and its id (:func:`~mapd.files.folders.file_id`).
        self._ids: dict[str, list[tuple[Path, tuple[int, int]]]] = {}
        #: The state directory (this folder's parent), and the disk it was on at the first save:
        #: once that is unmounted, what is left there is not written to.
        self._parent = Folder(self.directory.parent)

    # -- reading ----------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """The global map's saves for ``mapd status --json`` (see
        :meth:`~mapd.files.outage.WriteOutage.status`)."""
        return self.outage.status()

    def load_placements(self) -> Saved:
        """The placements and version of ``transforms.json``; entries that do not parse are left out."""
        path = self.directory / TRANSFORMS_JSON
        try:
            doc = read_json_capped(path, MAX_JSON) if path.exists() else None
        except (OSError, ValueError, RecursionError) as exc:
            log.warning("fusion: ignoring unreadable %s: %s", path, exc)
            return Saved()
        if not isinstance(doc, dict) or not isinstance(doc.get("robots"), dict):
            return Saved()
        keys = doc.get("keys")
        saved = Saved(
            version=doc["version"] if type(doc.get("version")) is int else 0,
            keys={str(r): k for r, k in keys.items() if isinstance(k, str)} if isinstance(keys, dict) else {},
        )
        for name, entry in doc["robots"].items():
            try:
                saved.placements[str(name)] = Placement.from_dict(entry)
            except (KeyError, TypeError, ValueError) as exc:
                log.warning("fusion: ignoring entry '%s' of %s: %s", name, path, exc)
        return saved

    def load_global(self) -> OccupancyGrid | None:
        """The saved global map with its version, or None when there is none or it cannot be read
        or is not the map its YAML says it is (said once)."""
        path = self.directory / GLOBAL_YAML
        try:
            if not path.exists():
                return None
            meta = read_map_yaml(path)
            grid = map_from_yaml_fields(meta, path, max_cells=self.max_cells)
        except MapdError as exc:
            log.warning("fusion: ignoring unreadable %s: %s", path, exc)
            return None
        except OSError as exc:
            log.warning("fusion: ignoring unreadable %s: %s", path, exc.strerror or exc)
            return None
        extra = meta["extra"]
        if VERSION_KEY not in extra and DIGEST_KEY not in extra:
            # An earlier release's global.yaml + global.pgm: kept, or every fleet upgrading would
            # start with an empty global map. That release wrote them with a crash window of
            # microseconds between two renames, and what such a crash left is only a stand-in
            # until each robot's map comes again; from the first save on, the digest is checked.
            return grid
        record = committed_record(extra)
        if record is None or record[1] != grid.digest().hex():
            log.warning(
                "fusion: ignoring %s: its image does not match the digest in it (damaged, or an "
                "interrupted write); starting a new global map",
                path,
            )
            return None
        return grid.replace(version=record[0])

    # -- writing ----------------------------------------------------------------------------

    def save(
        self,
        result: MergeResult,
        placements: dict[str, Placement],
        *,
        stamp: float,
        fleet_frame: str | None,
        mode: str,
        keys: dict[str, str] | None = None,
    ) -> None:
        """``global.yaml``/``.pgm`` and ``transforms.json``; :class:`StateError` when they cannot be.

        ``keys``: robot -> the roster key its map was taken under, for the robots in this merge.
        """
        doc = {
            "format": FORMAT,
            "robot": self.robot,
            "fleet_frame": fleet_frame,
            "units": "x, y in meters, yaw in radians: p_fleet = R(yaw) p_robot_map + (x, y)",
            "mode": mode,
            "version": result.grid.version,
            "stamp": stamp,
            "resolution": result.grid.resolution,
            "origin": list(result.grid.origin),
            "robots": {r: p.as_dict() for r, p in sorted(placements.items())},
            "keys": dict(sorted((keys or {}).items())),
        }
        with self._io:
            self._save(result.grid, doc)

    def _save(self, grid: OccupancyGrid, doc: dict[str, Any], *, counted: bool = True) -> None:
        """Write the global map and its placements (``counted``: in :attr:`outage`, which is the
        worker's saves': a look writing an older map again must not end a newer one's outage)."""
        with self.outage.counted(MapdError) if counted else contextlib.nullcontext():
            self._folder()
            save_committed(grid, self.directory / GLOBAL_YAML)
            write_json_atomic(self.directory / TRANSFORMS_JSON, doc)
        self._saved = (grid, doc)
        self._remember(
            "global",
            self.directory / GLOBAL_YAML,
            self.directory / f"{GLOBAL_YAML.removesuffix('.yaml')}-{grid.version}.pgm",
            self.directory / TRANSFORMS_JSON,
        )

    def _folder(self) -> None:
        """Make this folder if it went (its parent, the state directory, must be there: one gone
        or unmounted is not made again here); :class:`StateError` when it cannot be."""
        if (why := self._parent.unusable()) is not None:
            raise StateError(f"state directory {self._parent.path} {why}")
        try:
            self.directory.mkdir(exist_ok=True)
        except OSError as exc:
            raise StateError(f"{self.directory}: cannot create the folder: {exc.strerror}") from None

    def _remember(self, what: str, *paths: Path) -> None:
        self._ids[what] = file_ids(*paths)

    def _lost(self, what: str) -> bool:
        """Whether a file last written for ``what`` is gone or not the one written."""
        try:
            return any(file_id(path) != known for path, known in self._ids.get(what, ()))
        except OSError as exc:
            raise StateError(f"{self.directory}: cannot look at it: {exc.strerror}") from None

    def look(self) -> list[str]:
        """Write again the last global map saved, and its placements, when their files went (see
        the module docstring); what was written, in words. :class:`StateError` when it cannot be."""
        with self._io:
            if self._saved is None or not self._lost("global"):
                return []
            self._save(*self._saved, counted=False)
            return [f"the global map v{self._saved[0].version} and its placements"]

    def save_owner(self, owner: np.ndarray, names: list[str]) -> None:
        """``owner.npy`` and the names it indexes; a failed write is an error line once per outage
        (pictures only), none while the global map's own save fails too (a full disk: the worker
        has said so, and a second line for the same disk says nothing more)."""
        buf = io.BytesIO()
        np.save(buf, _owner_names(owner, names))
        try:
            atomic_write_bytes(self.directory / OWNER_NPY, buf.getvalue())
            write_json_atomic(self.directory / OWNER_JSON, {"robots": names})
        except OSError as exc:  # naming the file (not its hidden temp)
            self._owner_failed(f"{self.directory / OWNER_NPY}: {exc.strerror or exc}")
        except StateError as exc:
            self._owner_failed(str(exc))
        else:
            self._owner_outage.recovered("fusion: writing the owner map again")

    def _owner_failed(self, why: str) -> None:
        if self.outage.failing:
            return  # the global map's save failed just before: the worker said it, once
        self._owner_outage.failed(f"fusion: cannot write owner map {why}")


def read_owner(directory: Path) -> tuple[np.ndarray, list[str]] | None:
    """``owner.npy`` and its names from a fusion state directory, or None when absent or unreadable."""
    try:
        names = read_json_capped(directory / OWNER_JSON, MAX_JSON)["robots"]
        npy = directory / OWNER_NPY
        if npy.stat().st_size > 2 * DEFAULT_MAX_CELLS + 4096:  # int16 cells and the header
            return None
        idx = np.load(npy, allow_pickle=False)
    except (OSError, ValueError, KeyError, TypeError, EOFError, RecursionError):
        return None
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        return None
    if idx.ndim != 2 or not np.issubdtype(idx.dtype, np.integer):
        return None
    return idx, names


def _owner_names(owner: np.ndarray, names: list[str]) -> np.ndarray:
    """Per cell, the index into sorted robot names of the map that weighed most (-1: none)."""
    out = np.full(owner.shape, -1, dtype=np.int16)
    valid = owner != NO_OWNER
    out[valid] = owner[valid]
    return out


def write_json_atomic(path: Path, doc: dict[str, Any]) -> None:
    """Write strict JSON (no NaN) via a temp file, fsync and rename, so readers never see half a file.

    :class:`StateError` when ``doc`` cannot be written as JSON or the file cannot be written.
    """
    try:
        payload = (json.dumps(doc, indent=2, allow_nan=False, default=_jsonable) + "\n").encode()
    except (TypeError, ValueError) as exc:
        raise StateError(f"{path}: cannot serialise: {exc}") from None
    try:
        atomic_write_bytes(path, payload)
    except OSError as exc:
        raise StateError(f"{path}: cannot write: {exc.strerror}") from None


def _jsonable(v: object) -> object:
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    raise TypeError(f"cannot serialise {type(v).__name__}")


__all__ = [
    "FORMAT",
    "GLOBAL_YAML",
    "OWNER_JSON",
    "OWNER_NPY",
    "TRANSFORMS_JSON",
    "FusionStore",
    "Saved",
    "read_owner",
    "write_json_atomic",
]
