"""``[output.files]``: the global map as map_server files in a folder (for map_server, nav2, a viewer).

Each update writes ``<dir>/<name>.yaml``, the image it names, and ``<dir>/transforms.json``
atomically, so a reader never sees half a map. Each map's image has a name of its own,
``<name>-<n>.pgm`` (n counts up, also across restarts), and the one before it is kept: a reader
(map_server, a web viewer) reads the YAML and then the image it names, and with one fixed image
name an update between those two reads (about one a second) gave it the new image at the old
origin and size. Older images are removed. The daemon's own state directory keeps its copy
regardless (``state/global``); this output is for another place, say where a ``map_server`` on the
same robot or a web server looks.

A map that cannot be written (a full or read-only disk) leaves the files before it whole (each is
atomic), is said once per outage and shown in ``mapd status`` (``writing`` false), and is tried
again every :data:`~mapd.files.outage.WRITE_RETRY_S` until it or a newer one is written: a fleet at rest makes no new global
map, and the folder kept the one from before the disk filled.

The folder may also lose the files under the running daemon (emptied, removed, its disk unmounted
and mounted again): looked at every :data:`~mapd.files.outage.WRITE_RETRY_S` as well, the last map written
is written again once the files it wrote are gone (said once), the folder made again if its parent
is there. A folder that was a mount point is not written to once it is not one any more (its disk
unmounted: what is left is the folder under it, on another disk).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import re
import threading
from pathlib import Path
from typing import Any, ClassVar

from pydantic import Field, field_validator

from mapd.config.paths import folder_problem
from mapd.errors import ConfigError, MapdError, MapFileError
from mapd.files import atomic_write_json, remove_stale_temps
from mapd.files.folders import FOLDER_GONE, Folder, file_id
from mapd.files.outage import WRITE_RETRY_S, WriteOutage
from mapd.grid.save import save_map
from mapd.outputs.base import GlobalUpdate, Output, OutputContext, OutputOptions
from mapd.ros2.tf import check_robot_frame, robot_frame

log = logging.getLogger("mapd.outputs.files")


class FilesOptions(OutputOptions):
    #: A relative ``dir`` is taken from the config's folder (the daemon's cwd is "/" under systemd).
    beside_config: ClassVar[tuple[str, ...]] = ("dir",)

    dir: Path = Field(
        description="folder to write the map_server files and transforms.json into (relative: to the config's)"
    )
    name: str = Field(default="map", pattern=r"^[A-Za-z0-9_\-]{1,64}$", description="file name stem")
    frame_id: str = Field(default="map", description="the fleet frame's name (REP-105), in transforms.json")
    robot_map_frame: str = Field(
        default="{robot}/map",
        description="each robot's map frame in transforms.json ({robot} is its name), as the ros2 "
        "output's robot_map_frame names it",
    )

    @field_validator("robot_map_frame")
    @classmethod
    def _check_robot_frame(cls, v: str) -> str:
        return check_robot_frame(v)

    def check_files(self) -> None:
        """ValueError when ``dir`` could not be a folder (a file there, or above it): start could
        not make it. Looked at only; a folder not there yet is made by the start."""
        if problem := folder_problem(self.dir):
            raise ValueError(f"dir: {problem}")


class FilesOutput(Output):
    """Writes map_server files of every global map."""

    name = "files"
    Options = FilesOptions

    def __init__(self, options: OutputOptions | None, ctx: OutputContext) -> None:
        super().__init__(options, ctx)
        if not isinstance(self.options, FilesOptions):
            raise TypeError("files output needs FilesOptions")
        self.opts: FilesOptions = self.options
        self.written = 0
        #: Writes that failed (a full or read-only disk, a path that is a folder), tries again included.
        self.failures = 0
        self._outage = WriteOutage(log)
        #: The newest map while it is not written yet; publish (the outputs' thread) and the retry
        #: (a worker thread) write it in turn, under ``_lock``.
        self._unwritten: GlobalUpdate | None = None
        self._lock = threading.Lock()
        self._retry: asyncio.Task[None] | None = None
        # as _write names them (no leading zero: "fleet-007.pgm" is someone else's file)
        self._image = re.compile(re.escape(self.opts.name) + r"-([1-9]\d{0,17})\.pgm")
        self._seq = 1  # the next image's number; set past those in the folder at start
        #: The last map written, and the ids of the files it wrote (:func:`~mapd.files.folders.file_id`):
        #: written again when they go (see the module docstring).
        self._written: GlobalUpdate | None = None
        self._ids: list[tuple[Path, tuple[int, int]]] = []
        #: The folder, and the disk it was on when the output started.
        self._dir = Folder(self.opts.dir)
        #: The map to write is one whose files went (said when it is written again).
        self._lost_files = False

    async def start(self) -> None:
        try:
            self.opts.dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"output.files: cannot create {self.opts.dir}: {exc.strerror}") from None
        self._dir.unusable()  # (the disk it is on now: the one it must stay on)
        # what a write killed mid-way (kill -9, power loss) left there would otherwise pile up
        await asyncio.to_thread(remove_stale_temps, self.opts.dir)
        # Numbers go on from the last run's: a reader may still hold its YAML, naming its image.
        # What an earlier run left beyond the last two images (and the one fixed name of mapd
        # before) goes now; from here on each write removes the one image it makes too old.
        images = await asyncio.to_thread(self._images)
        self._seq = max(images, default=0) + 1
        for n in sorted(images)[:-2]:
            self._unlink(self._image_path(n))
        self._unlink(self.opts.dir / f"{self.opts.name}.pgm")
        self._retry = asyncio.create_task(self._retry_unwritten(), name="output.files retry")

    async def close(self) -> None:
        if self._retry is not None:
            self._retry.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._retry
            self._retry = None

    async def _retry_unwritten(self) -> None:
        """Every :data:`~mapd.files.outage.WRITE_RETRY_S`, write the newest map again if it could not be written."""
        while True:
            await asyncio.sleep(WRITE_RETRY_S)
            try:
                if self._unwritten is None and not await asyncio.to_thread(self._lost):
                    continue
                await asyncio.to_thread(self._write_unwritten)
            except Exception as exc:  # a bug: one line, and the output still takes new maps
                log.error("output.files: writing the map again failed: %s: %s", type(exc).__name__, exc)

    def _images(self) -> list[int]:
        """The numbers of the ``<name>-<n>.pgm`` images in the folder."""
        try:
            names = [p.name for p in self.opts.dir.iterdir()]
        except OSError:
            return []
        return [int(m.group(1)) for n in names if (m := self._image.fullmatch(n))]

    def _image_path(self, n: int) -> Path:
        return self.opts.dir / f"{self.opts.name}-{n}.pgm"

    @staticmethod
    def _unlink(path: Path) -> None:
        with contextlib.suppress(OSError):
            path.unlink(missing_ok=True)

    def _lost(self) -> bool:
        """Whether the files of the last map written are gone or replaced: then it is to be
        written again (said once it is; a write that fails says why, once)."""
        with self._lock:
            try:
                if self._unwritten is not None or not any(file_id(p) != i for p, i in self._ids):
                    return False
            except OSError:
                return False  # (cannot be looked at: the write says why)
            self._unwritten, self._lost_files = self._written, True
        return True

    def publish(self, update: GlobalUpdate) -> None:
        with self._lock:
            self._unwritten = update  # (one not written before is older: this one replaces it)
        self._write_unwritten()

    def _write_unwritten(self) -> None:
        with self._lock:
            update = self._unwritten
            if update is None:
                return  # written since the retry looked
            try:
                self._write(update)
            except (MapdError, OSError) as exc:
                # A full or read-only disk fails every update (about one a second): said once, with
                # the cause and not the hidden temp file's name, and counted; tried again.
                self.failures += 1
                why = str(exc) if isinstance(exc, MapdError) else f"{exc.filename}: {exc.strerror or exc}"
                self._outage.failed(
                    f"output.files: cannot write the global map ({why}); trying again every "
                    f"{WRITE_RETRY_S:g} s and with each new map"
                )
                return
            self._unwritten = None
            self._outage.recovered(f"output.files: writing to {self.opts.dir} again")
            self.written += 1
            if self._lost_files:
                self._lost_files = False
                log.warning(
                    "output.files: the map written in %s was gone (removed, or another disk mounted "
                    "there?): written again",
                    self.opts.dir,
                )

    def _folder(self) -> None:
        """The folder, made again if it was removed (not its parents: a folder gone with a disk
        unmounted above it is not made on the disk under it); MapFileError when it cannot be
        written (see :func:`~mapd.files.folders.folder_unusable`)."""
        folder = self.opts.dir
        why = self._dir.unusable()
        if why == FOLDER_GONE:  # (said only once its disk is seen mounted still)
            folder.mkdir()  # (OSError, its parent gone too: said with the folder's name)
            why = self._dir.unusable()
        if why is not None:
            raise MapFileError(f"output folder {folder} {why}")

    def _write(self, update: GlobalUpdate) -> None:
        self._folder()
        seq = self._seq
        yaml_path = self.opts.dir / f"{self.opts.name}.yaml"
        save_map(update.grid, yaml_path, image_name=self._image_path(seq).name)
        self._seq = seq + 1
        # Keep this image and the one before (a reader between the old YAML and its image). Numbers
        # go up by one per map written, so the one now too old is seq - 2.
        self._unlink(self._image_path(seq - 2))
        doc: dict[str, Any] = {
            "frame_id": self.opts.frame_id,
            "stamp": update.stamp,
            "robots": {
                robot: {"child_frame_id": robot_frame(self.opts.robot_map_frame, robot), "x": p.x, "y": p.y, "yaw": p.yaw,
                        "version": update.versions.get(robot)}
                for robot, p in sorted(update.frames.items())
            },
        }  # fmt: skip
        path = self.opts.dir / "transforms.json"
        try:
            atomic_write_json(path, doc)
        except OSError as exc:
            raise OSError(exc.errno, exc.strerror, str(path)) from None  # (not the temp file's name)
        self._written = update
        self._ids = [
            (p, known)
            for p in (yaml_path, self._image_path(seq), path)
            if (known := _id_or_none(p)) is not None
        ]

    def stats(self) -> dict[str, int | float | str]:
        """Maps written, writes failed, the folder, and ``writing``: False while the newest map
        cannot be written (``error`` then says why)."""
        out: dict[str, int | float | str] = {
            "written": self.written,
            "failures": self.failures,
            "dir": str(self.opts.dir),
            "writing": not self._outage.failing,
        }
        error = self._outage.error
        if error is not None:
            out["error"] = error
        return out


def _id_or_none(path: Path) -> tuple[int, int] | None:
    """:func:`~mapd.files.folders.file_id`, None also for a path that cannot be looked at."""
    try:
        return file_id(path)
    except OSError:
        return None
