"""``mapfile``: watch a map_server YAML (say, what ``map_saver`` rewrites every few seconds).

The YAML and its image are polled every ``poll_s``. A change is loaded only once both files have
stayed the same for ``settle_s`` (a writer mid-way through is left alone; so is a YAML that cannot
be read yet, or an image not there yet, until that fault has lasted ``settle_s``), and it is emitted only if
they were still the same after loading and the map differs from the last one sent, so a half-written
file is retried, never emitted. A file that will not load (truncated image, broken YAML) or that
vanishes is logged with the reason (one line, once per distinct fault), counted, and retried when the
files change again; the last good map stays the robot's map and the source keeps running. The
stream never ends on its own: not for a malformed file (every one is a :class:`~mapd.errors.MapdError`
from :func:`~mapd.grid.load.load_map`), and not even for a bug in loading one, which is logged with its
traceback and retried like a bad file, so that systemd does not restart the daemon into the same
crash for as long as the file stays as it is.

Each version is stamped with the newest modification time of the two files. The map is whatever
frame the writer used; give ``start_pose`` when its pose in the fleet frame is known.

Example ``config.toml`` table::

    [source.mapfile]
    path = "/var/lib/robot/map.yaml"
    poll_s = 1.0
"""

from __future__ import annotations

import asyncio
import logging
import os
import time
from collections.abc import AsyncIterator
from pathlib import Path

from pydantic import Field, field_validator

from mapd.errors import MapdError, MapFileError
from mapd.grid import MAX_GRID_SIDE, OccupancyGrid, Pose2D
from mapd.grid.load import load_map, read_map_yaml
from mapd.sources.base import MapSource, SourceContext, SourceOptions, check_start_pose

log = logging.getLogger(__name__)

Signature = tuple[tuple[int, int, int], tuple[int, int, int]]


class MapFileOptions(SourceOptions):
    """``[source.mapfile]``: the YAML to watch and how often."""

    path: Path = Field(
        description="map_server YAML to watch (relative: to the data folder, else the config's)"
    )
    poll_s: float = Field(default=1.0, gt=0.0, le=3600.0, description="seconds between checks")
    settle_s: float = Field(
        default=0.3, ge=0.0, le=60.0, description="files must be unchanged this long before loading"
    )
    start_pose: list[float] | None = Field(
        default=None, description="[x, y, yaw] of this map's frame in the fleet frame, when known"
    )

    @field_validator("start_pose")
    @classmethod
    def _check_pose(cls, v: list[float] | None) -> list[float] | None:
        return check_start_pose(v)


def _stat(p: Path) -> tuple[int, int, int]:
    st = os.stat(p)
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def _stat_or_error(p: Path, yaml_path: Path, what: str) -> tuple[int, int, int]:
    """:func:`_stat`, or one :class:`MapFileError` naming the map and ``what`` could not be read."""
    try:
        return _stat(p)
    except FileNotFoundError:
        raise MapFileError(f"{yaml_path}: {what} vanished or not written yet") from None
    except OSError as exc:
        raise MapFileError(f"{yaml_path}: cannot stat {what}: {exc.strerror}") from None


class MapFileSource(MapSource):
    """Emits a new version whenever a watched map_server map changes and loads cleanly."""

    name = "mapfile"
    Options = MapFileOptions

    def __init__(self, options: SourceOptions | None, ctx: SourceContext) -> None:
        super().__init__(options, ctx)
        assert isinstance(self.options, MapFileOptions)
        self.opts: MapFileOptions = self.options
        self._versions = 0
        self._errors = 0
        self._last_error = ""
        self._last_digest: bytes | None = None

    @property
    def path(self) -> Path:
        return self.ctx.resolve(self.opts.path)

    def start_pose(self) -> Pose2D | None:
        return Pose2D(*self.opts.start_pose) if self.opts.start_pose is not None else None

    def _fail(self, reason: str, *, trace: bool = False) -> None:
        # Count and log each new fault once, not once per poll while it lasts.
        if reason != self._last_error:
            self._errors += 1
            if trace:
                log.exception("%s (will retry when the files change)", reason)
            else:
                log.warning("%s (will retry when the files change)", reason)
        self._last_error = reason

    def _signature(self) -> Signature:
        """Stats of the YAML and its image; raises MapFileError when either is missing or unreadable."""
        path = self.path
        ystat = _stat_or_error(path, path, "map file")
        image = read_map_yaml(path)["image"]
        return (ystat, _stat_or_error(image, path, f"image '{image}'"))

    def check(self, state: dict[str, object], now: float) -> OccupancyGrid | None:
        """One poll (blocking file I/O; the stream runs it in a thread): a new map to emit, or None.

        ``state`` carries what earlier polls saw (pending signature and since when, last loaded).
        """
        try:
            sig = self._signature()
        except MapdError as exc:
            # A writer mid-way through (the YAML truncated, the image not yet there) fails here too:
            # the fault counts only once it has stayed the same for settle_s, like a change does.
            state["pending"] = None
            reason = str(exc)
            if state.get("fault") != reason:
                state["fault"], state["fault_since"] = reason, now
            since = state.get("fault_since")
            if isinstance(since, float) and now - since >= self.opts.settle_s:
                self._fail(reason)
            return None
        state["fault"] = None
        if sig == state.get("done"):
            return None
        if sig != state.get("pending"):
            # The files have been as they are since their last write (at start-up, often long ago).
            age = max(0.0, time.time() - max(sig[0][0], sig[1][0]) / 1e9)
            state["pending"], state["since"] = sig, now - age
        since = state.get("since")
        if isinstance(since, float) and now - since < self.opts.settle_s:
            return None
        try:
            grid = load_map(self.path, max_cells=self.ctx.max_cells, robot=self.ctx.robot)
            after = self._signature()
        except MapdError as exc:
            # Mark this signature done: a file that stays broken is retried once it changes.
            state["done"] = sig
            self._fail(str(exc))
            return None
        if after != sig:
            state["pending"], state["since"] = after, now
            return None
        state["done"] = sig
        if max(grid.height, grid.width) > MAX_GRID_SIDE:
            # load_map reads it, but no codec would send it: refuse it here, as a bad file.
            self._fail(f"{self.path}: map is {grid.width} x {grid.height} cells, over {MAX_GRID_SIDE} a side")
            return None
        self._last_error = ""
        digest = grid.digest()
        if digest == self._last_digest:
            return None
        self._last_digest = digest
        self._versions += 1
        stamp = max(sig[0][0], sig[1][0]) / 1e9
        return grid.replace(version=self._versions, stamp=stamp, robot=self.ctx.robot)

    async def maps(self) -> AsyncIterator[OccupancyGrid]:
        """Poll forever; yield each new map that loads cleanly. Never raises for a bad file."""
        state: dict[str, object] = {}
        while True:
            try:
                grid = await asyncio.to_thread(self.check, state, time.monotonic())
            except Exception as exc:  # a bug in loading must not end the stream (see the module doc)
                grid = None
                self._fail(
                    f"{self.path}: internal error while loading: {type(exc).__name__}: {exc}", trace=True
                )
                state["done"] = state.get("pending")
            if grid is not None:
                yield grid
            await asyncio.sleep(self.opts.poll_s)

    def stats(self) -> dict[str, int | float | str]:
        return {"versions": self._versions, "load_errors": self._errors, "last_error": self._last_error}
